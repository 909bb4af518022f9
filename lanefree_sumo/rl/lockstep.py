"""K runs' lockstep iterations on a torch device with no host read inside one; on a GPU, each held as a CUDA graph.

An iteration: every run acts (:meth:`~.algorithms.batched.learner.BatchedLearner.act_on_device`), the batched
ring steps (:meth:`~.batched_env.BatchedRingEnv.step_on_device`), the transition is stored and, past
``learning_starts``, every run takes one gradient step on a minibatch drawn on the device
(:meth:`~.algorithms.batched.learner.BatchedLearner.sample_on_device`). Nothing in it reads the device from the
host: the random numbers come from the device's generator and the step counts live there too. On CUDA the
iteration of each phase (random actions; acting; acting and updating) runs once eagerly, is then captured as one
CUDA graph and replayed from then on; on the CPU the same functions run eagerly (the tests run them there).

A graph removes the launch cost of the iteration's ~870 small kernels, not their own cost. So on CUDA the ring's
step and the gradient step are also compiled (``torch.compile``, each as one graph: its elementwise work fused into
a few kernels) before the capture; the acting and storing, which draw random numbers, stay as they are.

The host keeps its own counts (steps, the replay position, the update count) in step with the device's. Episodes
end by the time limit only, all runs of a batch together (they share the episode length); between episodes the
host reads the books once (:meth:`Lockstep.take_flagged`, the env's books), resets the rings (spawning is host
work) and :meth:`Lockstep.start` copies the new state into the iteration's buffers.

What differs from the exact path (:mod:`lanefree_sumo.experiments.runners.batch` on the CPU): run k draws from the
device's generator, not from its own numpy streams, so it agrees with ``lanefree train --seed k`` in distribution,
not bit for bit; prioritised replay keeps its priorities on the device (sampled through their running sum rather than
the host's sum tree: the same distribution); ``episode.terminate_on_collision`` is not run here.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import fields, replace
from typing import Any

import numpy as np
import torch as th

from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.algorithms.batched.learner import flat_observations
from lanefree_sumo.sim.world import World
from lanefree_sumo.sim.xp import torch_device


def lockstep_refusal(env: Any, learner: Any) -> str | None:
    """Why the lockstep loop cannot run ``env`` with ``learner`` (None: it can)."""
    if env.xp.is_numpy:
        return "the lockstep loop runs the torch simulation (train.device = torch-cpu or cuda)"
    if bool(np.any(env.terminate_on_collision)):
        return "episode.terminate_on_collision ends episodes at different steps"
    host = None if learner is None else learner.host_draws
    if host is not None:
        return f"{host} is drawn on the host: it is trained in the exact loop"
    return None


class Lockstep:
    """The lockstep loop of a :class:`~.batched_env.BatchedRingEnv` (on a torch device) and a batched learner
    on the same device (module docstring).

    :param learner: None: every run drives uniformly random actions and nothing learns (the environment
        alone, as the GPU benchmark times it).
    :param seed: seeds the device's random numbers (on CUDA the device's default generator, which a graph holds).
    :param graphs: capture each phase's iteration as a CUDA graph (default: on CUDA).
    :param compile: the ``torch.compile`` backend the ring's step and the gradient step are compiled with
        (``"inductor"``: fused kernels; ``"aot_eager"``: traced but the same operations, as the CPU tests use it);
        None: not compiled. Default: ``"inductor"`` on CUDA, None elsewhere."""

    def __init__(self, env: Any, learner: Any, seed: int, graphs: bool | None = None,
                 compile: str | None | bool = True) -> None:
        why = lockstep_refusal(env, learner)
        if why is not None:
            raise ConfigError(f"the lockstep loop cannot run this batch: {why}")
        self.env, self.learner = env, learner
        device = torch_device(env.device) if learner is None else learner.device
        self.cuda = device.type == "cuda"
        self.graphs = self.cuda if graphs is None else graphs
        if self.graphs and not self.cuda:
            raise ValueError("CUDA graphs need a CUDA device")
        if self.cuda:
            with th.cuda.device(device):
                th.cuda.manual_seed(seed)
            generator = None
        else:
            generator = th.Generator(device=device).manual_seed(seed)
        self.generator = generator
        if learner is not None:
            learner.use_device_streams(generator)
        backend = ("inductor" if self.cuda else None) if compile is True else compile or None
        self.compiled = backend
        """The backend the ring's step and the gradient step are compiled with (None: run as written)."""
        self._step = self._compiled(env.step_on_device)
        self._learn = None if learner is None else self._compiled(learner._learn)  # the gradient step on indices
        self.active = th.zeros(env.runs, dtype=th.bool, device=device)
        """The runs scored (not stopped, not finished), on the device; :meth:`start` sets it."""
        self.flagged = th.zeros(env.runs, dtype=th.bool, device=device)
        """Runs whose action was not finite since :meth:`take_flagged`."""
        self.obs: th.Tensor | None = None
        self._static: dict[str, th.Tensor] | None = None
        self._world: World | None = None
        self._graphs: dict[tuple[bool, bool], Any] = {}
        self._pool: Any = None

    def _compiled(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        """``fn`` compiled with :attr:`compiled`'s backend as one graph. Where its first call fails (a machine
        without the compiler's tools), a warning, and every function of the loop runs as written from then on
        (an error of ``fn`` itself then shows as it does uncompiled)."""
        if self.compiled is None:
            return fn
        compiled = th.compile(fn, backend=self.compiled, fullgraph=True)
        tried = [False]

        def call(*args: Any) -> Any:
            if self.compiled is None:
                return fn(*args)
            if tried[0]:
                return compiled(*args)
            try:
                out = compiled(*args)
            except Exception as exc:  # noqa: BLE001 - any failure of the compiler's tool chain
                cause = getattr(exc, "inner_exception", None) or exc.__cause__ or exc
                warnings.warn(f"torch.compile ({self.compiled}) failed, so the lockstep loop runs uncompiled: "
                              f"{type(cause).__name__}: {(str(cause).splitlines() or [''])[0]}",
                              RuntimeWarning, stacklevel=2)
                self.compiled = None
                return fn(*args)
            tried[0] = True
            return out

        return call

    # -- the iteration's buffers ------------------------------------------------------------------------------
    def _current(self) -> dict[str, th.Tensor]:
        env = self.env
        state = {f"world.{f.name}": getattr(env.world, f.name) for f in fields(World)}
        state.update(env.state.tensors())
        state["obs"] = self.obs
        return state

    def _pin(self) -> None:
        """Copy the state the last step or reset left into the iteration's buffers (the first call makes them)
        and point the env and the loop at them again."""
        current = self._current()
        if self._static is None:
            self._static = {name: value.clone() for name, value in current.items()}
        else:
            for name, value in current.items():
                target = self._static[name]
                if value is not target:
                    if value.shape != target.shape or value.dtype != target.dtype:
                        raise RuntimeError(f"the lockstep state {name} changed from {tuple(target.shape)} "
                                           f"{target.dtype} to {tuple(value.shape)} {value.dtype}")
                    target.copy_(value)
        static, env = self._static, self.env
        if self._world is None:
            self._world = replace(env.world, **{f.name: static[f"world.{f.name}"] for f in fields(World)})
        env.world = self._world
        env.state.point_at(static)
        self.obs = static["obs"]

    def start(self, obs: Any) -> None:
        """Take the observations ``[K, obs]`` (the set observation's dict flattened) and the env's state after a
        reset (of every run or some) as the next iteration's, and the env's stopped runs as not scored."""
        self.obs = flat_observations(obs)
        self._pin()
        self.active.copy_(th.as_tensor(~self.env.stopped).to(self.active.device))

    # -- one iteration ----------------------------------------------------------------------------------------
    def _iteration(self, random: bool, update: bool) -> None:
        """The device's work of one iteration (what a graph holds)."""
        learner, env = self.learner, self.env
        assert self.obs is not None
        if learner is None:
            draws = th.rand((env.runs, 2), generator=self.generator, dtype=th.float64, device=self.active.device)
            obs, reward, bad = self._step(draws * 2.0 - 1.0, self.active)
            obs = flat_observations(obs)
        else:
            actions, stored = learner.act_on_device(self.obs, random)
            obs, reward, bad = self._step(actions, self.active)
            obs = flat_observations(obs)
            learner.store_on_device(self.obs, stored, reward.to(th.float32), obs)
            if update:
                assert self._learn is not None
                self._learn(*learner.sample_on_device())
        self.flagged |= bad
        self.obs = obs
        self._pin()

    def iterate(self, update: bool = True) -> None:
        """One lockstep iteration of every run (``update`` False: no gradient step even past ``learning_starts``,
        as for the last step of a batch's last episode, whose final models are taken before it). The host's counts
        and SB3's ``_on_step`` (DQN's target copy) come first: in SB3 they follow storing the transition and precede
        the update, and storing changes no network."""
        if self.obs is None:
            raise RuntimeError("call start() with the observations of a reset first")
        learner = self.learner
        t = learner.num_timesteps if learner is not None else 0
        key = (True, False) if learner is None else (t < learner.random_steps,
                                                     update and t + 1 > learner.learning_starts)
        if learner is not None:
            learner.stepped_on_device(key[1])
        if not self.graphs:
            self._iteration(*key)
        elif key in self._graphs:
            self._graphs[key].replay()
        else:
            self._capture(key)
        self.env.count_step()

    def _capture(self, key: tuple[bool, bool]) -> None:
        """Run the phase's iteration once for real (on a side stream, as capture wants its first use there), then
        capture it as a graph (the capture runs nothing)."""
        side = th.cuda.Stream()
        side.wait_stream(th.cuda.current_stream())
        with th.cuda.stream(side):
            self._iteration(*key)
        th.cuda.current_stream().wait_stream(side)
        if self._pool is None:
            self._pool = th.cuda.graph_pool_handle()
        graph = th.cuda.CUDAGraph()
        with th.cuda.graph(graph, pool=self._pool):
            self._iteration(*key)
        self._graphs[key] = graph

    # -- between episodes -------------------------------------------------------------------------------------
    def episode_over(self) -> bool:
        """Whether the runs' episodes reached their time limit (a host count)."""
        live = ~self.env.stopped
        return bool(live.any()) and bool((self.env.steps[live] >= self.env.cfg.sim.episode_steps).all())

    def take_flagged(self) -> np.ndarray:
        """The runs whose action was not finite since the last call (bool ``[K]``, read from the device), and
        clear them."""
        flagged = self.flagged.cpu().numpy().copy()
        self.flagged.zero_()
        return flagged

    def state_dict(self) -> dict[str, Any]:
        """The device streams' state (the generator, the learner's device counts and noise)."""
        rng = th.cuda.get_rng_state(self.active.device) if self.cuda else self.generator.get_state()  # type: ignore[union-attr]
        return {"rng": rng, "flagged": self.flagged.cpu(),
                "learner": None if self.learner is None else self.learner.device_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if self.cuda:
            th.cuda.set_rng_state(state["rng"], self.active.device)
        else:
            self.generator.set_state(state["rng"])  # type: ignore[union-attr]
        self.flagged.copy_(state["flagged"])
        if self.learner is not None:
            self.learner.load_device_state(state["learner"])
