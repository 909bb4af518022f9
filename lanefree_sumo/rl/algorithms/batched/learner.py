"""What the batched learners share: K runs' seeds, streams, replay, step counts and the store/update cycle.

The cycle per environment step is SB3's (``collect_rollouts`` then ``train``): :meth:`act` for every run,
the env steps, :meth:`store` (the step count, the transition, the per-step schedule: SB3's ``_on_step``), then
:meth:`update` (one gradient step per run once the step count is past ``learning_starts``).
"""

from __future__ import annotations

import random
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
import torch as th
from gymnasium import spaces

from lanefree_sumo.rl.algorithms.batched.replay import BatchedReplay, RunStreams
from lanefree_sumo.rl.algorithms.batched.stack import Products, StackedAdam
from lanefree_sumo.sim.xp import torch_device


def per_run(value: float | Sequence[float], runs: int, name: str) -> list[float]:
    """``value`` for each of ``runs`` runs: one number for all, or one per run."""
    if isinstance(value, (int, float)):
        return [float(value)] * runs
    values = [float(v) for v in value]
    if len(values) != runs:
        raise ValueError(f"{name}: {len(values)} values for {runs} runs; give one value or one per run")
    return values


@contextmanager
def kept_random_state() -> Iterator[None]:
    """Python's, numpy's and torch's global random states as they were before the block (building an SB3
    model reseeds them all)."""
    python, numpy = random.getstate(), np.random.get_state()
    with th.random.fork_rng(devices=[]):
        yield
    random.setstate(python)
    np.random.set_state(numpy)


def observation_size(space: spaces.Space) -> int:
    """The length of one run's observation as the batched replay stores it: a flat float32 Box (the vector
    observation), or the set observation's Dict of ``ego`` ``(E,)`` and ``others`` ``(rows, width)``, flattened
    (:func:`flat_observations`); ValueError for another space."""
    if isinstance(space, spaces.Box) and len(space.shape) == 1 and space.dtype == np.float32:
        return int(space.shape[0])
    if isinstance(space, spaces.Dict) and set(space.spaces) == {"ego", "others"}:
        ego, others = space["ego"], space["others"]
        if len(ego.shape) == 1 and len(others.shape) == 2:  # type: ignore[arg-type]
            return int(ego.shape[0]) + int(others.shape[0]) * int(others.shape[1])  # type: ignore[index]
    raise ValueError("batched learners take a flat float32 Box observation or the set observation's "
                     "Dict of ego and others")


def flat_observations(obs: Any) -> Any:
    """The set observation's dict ``{"ego": [K, E], "others": [K, rows, width]}`` (arrays or tensors) as one
    ``[K, E + rows·width]`` (ego, then the table row by row); anything else unchanged."""
    if not isinstance(obs, dict):
        return obs
    ego, others = obs["ego"], obs["others"]
    if isinstance(ego, th.Tensor):
        return th.cat([ego, others.reshape(others.shape[0], -1)], dim=1)
    ego, others = np.asarray(ego), np.asarray(others)
    return np.concatenate([ego, others.reshape(others.shape[0], -1)], axis=1)


class SpacesEnv(gym.Env):
    """An environment that only declares its spaces: what SB3 needs to build a model to export weights into."""

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space) -> None:
        self.observation_space, self.action_space = observation_space, action_space

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        raise NotImplementedError("an export-only environment does not run")

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        raise NotImplementedError("an export-only environment does not run")


class BatchedLearner:
    """K runs of one off-policy algorithm: per-run seeds and random streams, replay ``[K, capacity, …]``.

    :param observation_space: a flat float32 Box (the vector observation) or the set observation's Dict, the same
        for all runs (:func:`observation_size`).
    :param seeds: run k's seed (its initial weights and random streams are the single run's with this seed).
    :param total_timesteps: the runs' SB3 ``learn`` length in steps (the progress the ε and β schedules read).
    :param device: where the networks and the replay live (CPU: batched run k equals the single run bit for bit).
    :param exact: use the batched products only where they give the single run's bits (default: on CPU).
    :param slots: the environments or learning vehicles of each run (SB3's ``n_envs``: one shared policy acts for
        each, every step stores a transition of each and counts that many timesteps; ``buffer_size`` is shared
        among them as SB3 shares it). Observations, actions and rewards are then ``[K · slots, …]``, run k's
        slots in rows k · slots …"""

    host_draws: ClassVar[str | None] = None
    """What of the update draws its random numbers on the host, so that the lockstep loop
    (:mod:`~lanefree_sumo.rl.lockstep`) cannot run it (one phrase); None: every draw is the device's."""

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space, seeds: Sequence[int], *,
                 batch_size: int, buffer_size: int, learning_starts: int, total_timesteps: int,
                 action_dim: int, action_dtype: th.dtype, device: str = "cpu",
                 exact: bool | None = None, slots: int = 1) -> None:
        self.obs_dim = observation_size(observation_space)
        if not seeds:
            raise ValueError("a batch needs at least one run")
        self.observation_space, self.action_space = observation_space, action_space
        self.seeds = [int(s) for s in seeds]
        self.runs = len(self.seeds)
        if slots < 1:
            raise ValueError(f"slots: a run has at least one environment or agent, got {slots}")
        self.slots = int(slots)
        self.rows = self.runs * self.slots
        """Rows of the observations and actions: each run's slots."""
        self.device = torch_device(device)
        """The torch device of the networks and the replay (``device`` is ``train.device``)."""
        self.mm = Products(self.device.type == "cpu" if exact is None else exact)
        self.batch_size, self.buffer_size = int(batch_size), int(buffer_size)
        self.learning_starts, self.total_timesteps = int(learning_starts), int(total_timesteps)
        self.streams = RunStreams(self.seeds, action_space)
        self.replay = BatchedReplay(self.runs, max(self.buffer_size // self.slots, 1), self.obs_dim, action_dim,
                                    action_dtype, self.device, self.slots)
        self.num_timesteps = 0
        self.n_updates = 0
        self.progress_remaining = 1.0
        self.generator: th.Generator | None = None
        self.device_streams = False
        """Whether the random numbers and counts live on the device (:meth:`use_device_streams`)."""
        self.losses: dict[str, th.Tensor] = {}
        """The last update's losses per run (``[K]`` tensors on the device; read them when logging)."""

    @property
    def dense(self) -> bool:
        """Whether a set encoder runs every row of every run at once (a GPU, the lockstep loop:
        :func:`~.set_encoder.encode`) rather than run by run."""
        return self.device.type != "cpu" or self.device_streams

    # -- the cycle ------------------------------------------------------------------------------------------

    def _obs(self, obs: Any) -> th.Tensor:
        """Observations ``[K · slots, obs]`` (host arrays, or tensors where the env runs on a device; the set
        observation's dicts flattened, :func:`flat_observations`) as the networks take them: ``[K, slots, obs]``
        float32 on the device."""
        obs = flat_observations(obs)
        values = obs if isinstance(obs, th.Tensor) else th.as_tensor(np.asarray(obs))
        return values.float().reshape(self.runs, self.slots, self.obs_dim).to(self.device)

    def store(self, obs: np.ndarray, action: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
              done: np.ndarray, truncated: np.ndarray | None = None) -> None:
        """Store every run's transitions (one per slot) and advance the step count by the slots (SB3's
        ``_store_transition`` and ``_on_step``). ``action``: what :meth:`act` returned; ``done``: the episode
        ended (terminated or truncated); ``truncated``: it ended by the time limit (SB3's ``TimeLimit.truncated``:
        no terminal value cut); ``next_obs``: the observation after the action (the terminal one where
        ``done``)."""
        done = np.asarray(done, dtype=bool).reshape(self.rows)
        timeouts = np.zeros(self.rows, dtype=bool) if truncated is None else np.asarray(truncated, dtype=bool)
        self.num_timesteps += self.slots
        pos = self.replay.add(flat_observations(obs), flat_observations(next_obs), self._buffer_actions(action),
                              np.asarray(reward), done, timeouts)
        self._stored(pos)
        self.progress_remaining = 1.0 - float(self.num_timesteps) / float(self.total_timesteps)
        self._on_step()
        if done.any():
            self._episodes_ended(done)

    def update(self) -> bool:
        """One gradient step for every run once the step count is past ``learning_starts`` (SB3's ``learn``:
        ``train_freq = gradient_steps = 1``: one per step of all slots); returns whether it stepped."""
        if not (self.num_timesteps > 0 and self.num_timesteps > self.learning_starts):
            return False
        self.n_updates += 1
        self._update()
        return True

    # -- device streams: the lockstep loop (:mod:`lanefree_sumo.rl.lockstep`) -------------------------------

    def use_device_streams(self, generator: th.Generator | None) -> None:
        """From now on draw every random number on the learner's device from ``generator`` (None: the device's
        default generator, the one a CUDA graph can hold) and keep the step counts there too, so that acting,
        storing and updating read nothing from the host (:meth:`act_on_device`, :meth:`store_on_device`,
        :meth:`sample_on_device` and the gradient step on its indices). Run k then no longer draws the single
        run's numbers: it agrees with the sequential run in distribution, not bit for bit."""
        d = self.device
        self.generator = generator
        self.device_streams = True
        self._count = th.full((), float(self.num_timesteps), dtype=th.float64, device=d)
        """The steps stored (SB3's ``num_timesteps``) on the device."""
        self._pos = th.full((), self.replay.pos, dtype=th.int64, device=d)
        self._size = th.full((), float(self.replay.size()), dtype=th.float64, device=d)
        for adam in self.optimisers():
            adam.count_on_device()

    def _rand(self, *shape: int) -> th.Tensor:
        """Uniform [0, 1) float64 numbers ``shape`` from the device stream."""
        return th.rand(shape, generator=self.generator, dtype=th.float64, device=self.device)

    def store_on_device(self, obs: th.Tensor, action: th.Tensor, reward: th.Tensor, next_obs: th.Tensor) -> None:
        """:meth:`store` with device streams, for an episode that goes on or ends by the time limit (``action``:
        the buffer's, as :meth:`act_on_device` returns it); the host's counts are :meth:`stepped_on_device`'s."""
        self.replay.add_at(self._pos, obs, next_obs, action, reward)
        self._pos.add_(1).remainder_(self.buffer_size)
        self._size.add_(1.0).clamp_(max=float(self.buffer_size))
        self._count.add_(1.0)

    def sample_on_device(self) -> tuple[th.Tensor, ...]:
        """The arguments of the gradient step (:meth:`_learn`) on each run's minibatch: ``[K, batch]`` indices drawn
        uniformly over what is stored, from the device stream."""
        return ((self._rand(self.runs, self.batch_size) * self._size).long(),)

    def stepped_on_device(self, updated: bool) -> None:
        """The host's side of a device iteration (called before its device work): what :meth:`store` and
        :meth:`update` count (the step count, the replay position, the progress, SB3's ``_on_step``; the update
        count where ``updated``)."""
        self.num_timesteps += 1
        self.replay.pos += 1
        if self.replay.pos == self.buffer_size:
            self.replay.full, self.replay.pos = True, 0
        self.progress_remaining = 1.0 - float(self.num_timesteps) / float(self.total_timesteps)
        self._on_step()
        if updated:
            self.n_updates += 1
            for adam in self.optimisers():
                adam.steps += 1

    def episodes_ended(self, done: np.ndarray) -> None:
        """Slots ``done`` (bool ``[K · slots]``) ended an episode outside :meth:`store` (the lockstep loop: noise
        reset)."""
        self._episodes_ended(np.asarray(done, dtype=bool))

    def device_state(self) -> dict[str, Any]:
        """What device streams keep beyond :meth:`state_dict` (on the host)."""
        return {"count": float(self._count), "pos": int(self._pos), "size": float(self._size)}

    def load_device_state(self, state: dict[str, Any]) -> None:
        self._count.fill_(state["count"])
        self._pos.fill_(state["pos"])
        self._size.fill_(state["size"])

    # -- what each algorithm supplies -------------------------------------------------------------------------

    @property
    def random_steps(self) -> int:
        """Steps that act uniformly at random (SB3: before ``learning_starts``)."""
        return self.learning_starts

    def optimisers(self) -> list[StackedAdam]:
        raise NotImplementedError

    def act_on_device(self, obs: th.Tensor, random: bool) -> tuple[th.Tensor, th.Tensor]:
        """(the env's actions, the buffer's) for observations on the device, from the device streams:
        uniformly random where ``random``, else the exploring policy."""
        raise NotImplementedError

    def _learn(self, indices: np.ndarray | th.Tensor) -> None:
        """One gradient step for every run on the minibatch at ``indices`` ``[K, batch]``."""
        raise NotImplementedError

    def _buffer_actions(self, action: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _stored(self, pos: int) -> None:
        """A transition was stored at ``pos`` for every run."""

    def _on_step(self) -> None:
        """SB3's ``_on_step`` (after the step count and the progress moved)."""

    def _episodes_ended(self, done: np.ndarray) -> None:
        """Slots ``done`` (bool ``[K · slots]``) ended an episode."""

    def _update(self) -> None:
        raise NotImplementedError

    # -- checkpoint -------------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Everything a resumed batch needs (networks, optimisers, replay, random streams, counters); the
        tensors are the learner's own (``torch.save`` it, or copy it before the learner goes on)."""
        return {"seeds": list(self.seeds), "num_timesteps": self.num_timesteps, "n_updates": self.n_updates,
                "progress_remaining": self.progress_remaining, "streams": self.streams.state(),
                "replay": self.replay.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if list(state["seeds"]) != self.seeds:
            raise ValueError(f"the checkpoint holds runs with seeds {state['seeds']}, this batch {self.seeds}")
        self.num_timesteps, self.n_updates = int(state["num_timesteps"]), int(state["n_updates"])
        self.progress_remaining = float(state["progress_remaining"])
        self.streams.load_state(state["streams"])
        self.replay.load_state_dict(state["replay"])
