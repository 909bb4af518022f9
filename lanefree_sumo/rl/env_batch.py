"""K runs of LaneFree-v0 with one learning agent each, stepped one after another, behind the interface of
:class:`~lanefree_sumo.rl.batched_env.BatchedRingEnv`: how the one trainer trains the runs the ring's batched world
does not hold — the safety shield, the on-ramp, a run inside SUMO; and :class:`SlotBatch`, K runs of several
agents or environments each (SB3's ``n_envs``), one row per slot.

Run k is a :class:`~lanefree_sumo.rl.env.LaneFreeEnv` of its config (its backend) whose e-th episode takes
the traffic seed :func:`~lanefree_sumo.rl.models.episode_seed` (seed, 0, e), as a training run's single environment
does; each step is its own ``step`` (the learning problem of :mod:`.problem` with K = 1), so the batch loop of
:mod:`lanefree_sumo.experiments.runners.batch` trains it as SB3's loop did. A run whose action is not finite is
stopped (``info["stopped"]``) while the others go on; a stopped run is never stepped again.

A run inside SUMO (``train.backend`` libsumo or traci; one run: libsumo holds one simulation per process) is
checkpointed between episodes only (:attr:`EnvBatch.saves_mid_episode`): a checkpoint holds its episode counts and
seeds, not SUMO's state, and its simulation is started again — on the first use after unpickling — from the
seed of the episode it had just begun, which gives that episode's start again (SUMO's episodes are a function of
their seed, as the numpy backend's are: ``tests/experiments/test_golden_runs.py``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.errors import ConfigError, RunError
from lanefree_sumo.rl.env import LaneFreeEnv, resolve_config
from lanefree_sumo.rl.models import episode_seed, slots
from lanefree_sumo.sim.xp import NUMPY


def _same(a: Any, b: Any) -> bool:
    """Whether two observations (arrays, or dicts of arrays) hold the same bits."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[name], b[name]) for name in a)
    return bool(np.array_equal(a, b)) and np.asarray(a).dtype == np.asarray(b).dtype


def _stacked(observations: list[Any]) -> Any:
    """Observations (arrays, or dicts of arrays) stacked row by row: ``[rows, obs]`` or a dict of ``[rows, …]``."""
    if isinstance(observations[0], dict):
        return {name: np.stack([o[name] for o in observations]) for name in observations[0]}
    return np.stack(observations)


def _runs_listed(runs: Sequence[int] | None, count: int) -> list[int]:
    """``reset``'s runs as a list (None: all ``count``); ValueError unless they are distinct indices of the batch."""
    listed = list(range(count) if runs is None else runs)
    if any(isinstance(k, bool) or not isinstance(k, int | np.integer) or not 0 <= k < count
           for k in listed) or len(set(listed)) != len(listed):
        raise ValueError(f"reset: runs are distinct indices 0 … {count - 1} of this batch, got {runs!r}")
    return listed


class EnvBatch:
    """K LaneFree-v0 runs (module docstring): ``reset(runs)``, ``step(actions)`` and the episode books as
    :class:`~lanefree_sumo.rl.batched_env.BatchedRingEnv` has them; ``first_episodes``: each run's next episode
    number (1 for a new run); ``device`` must be ``cpu`` (these runs are simulated on the CPU, their arrays numpy)."""

    device = "cpu"
    xp = NUMPY

    def __init__(self, configs: Sequence[LaneFreeConfig | Mapping[str, Any]],
                 first_episodes: Sequence[int] | None = None, device: str = "cpu") -> None:
        if device != "cpu":
            raise ConfigError("runs with the shield, off the ring or inside SUMO are simulated on the CPU "
                              "(train.device = cpu); leave --device out")
        self.cfgs = [resolve_config(c) for c in configs]
        if not self.cfgs:
            raise ConfigError("a batch needs at least one run")
        for k, cfg in enumerate(self.cfgs):
            if cfg.scenario.agents != 1:
                raise ConfigError(f"run {k}: a batch runs one agent (scenario.agents = 1)")
        self.runs = len(self.cfgs)
        self.in_sumo = any(c.backend != "numpy" for c in self.cfgs)
        """Whether the runs move SUMO's vehicles (libsumo, traci) rather than numpy's."""
        if self.in_sumo and self.runs != 1:
            raise ConfigError("a run inside SUMO (train.backend libsumo or traci) trains alone, not in a batch: "
                              "train each seed with --seed, or batch them on train.backend = numpy (the same "
                              "episodes)")
        self.envs: list[LaneFreeEnv] | None = [LaneFreeEnv(c) for c in self.cfgs]
        self.episode = np.array([e - 1 for e in (first_episodes or [1] * self.runs)], dtype=int)
        self.episode_seeds = np.zeros(self.runs, dtype=np.int64)
        self.stopped = np.zeros(self.runs, dtype=bool)
        """Runs stopped for a non-finite action; they are never reset nor stepped again."""
        self.terminate_on_collision = np.array([c.episode.terminate_on_collision for c in self.cfgs])
        self._steps = np.zeros(self.runs, dtype=int)
        self._obs: list[Any] = [None] * self.runs

    @property
    def saves_mid_episode(self) -> bool:
        """Whether a checkpoint may be taken inside an episode (not inside SUMO: module docstring)."""
        return not self.in_sumo

    def __getstate__(self) -> dict[str, Any]:
        """Pickled (a batch checkpoint holds its env); inside SUMO without the environments (module docstring)."""
        if not self.in_sumo:
            return dict(self.__dict__)
        return {**self.__dict__, "envs": None}

    def __setstate__(self, saved: dict[str, Any]) -> None:
        self.__dict__.update({"in_sumo": False, **saved})

    def _live(self) -> list[LaneFreeEnv]:
        """The runs' environments; after unpickling a run inside SUMO, started again: each run that had just
        begun an episode is reset with that episode's seed (a run checkpointed at an episode's end is reset when
        its next episode begins)."""
        if self.envs is None:
            self.envs = [LaneFreeEnv(c) for c in self.cfgs]
            for k, env in enumerate(self.envs):
                env.episode = int(self.episode[k])
                if self._steps[k] == 0 and not self.stopped[k] and self.episode[k] > 0:
                    env.episode -= 1  # reset counts it again
                    saved, (self._obs[k], _) = self._obs[k], env.reset(seed=int(self.episode_seeds[k]))
                    if not _same(saved, self._obs[k]):
                        raise RunError(f"run {k}: SUMO did not start episode {int(self.episode[k])} as it did "
                                       "before the checkpoint (its seed gave another first observation); "
                                       "resuming would not continue the same run")
        return self.envs

    @property
    def cfg(self) -> LaneFreeConfig:
        """Run 0's config (the action and observation settings are every run's)."""
        return self.cfgs[0]

    @property
    def steps(self) -> np.ndarray:
        """``[K]``: each run's steps since its episode began (a copy)."""
        return self._steps.copy()

    def _stacked(self) -> Any:
        """Every run's current observation, stacked: ``[K, obs]`` or a dict of ``[K, …]``."""
        return _stacked(self._obs)

    def reset(self, runs: Sequence[int] | None = None, seeds: Sequence[int] | None = None) -> Any:
        """Start the next episode of ``runs`` (None: every run not stopped); returns every run's observation.
        ``seeds``: those episodes' traffic seeds (None: each run's training schedule)."""
        listed = _runs_listed(runs, self.runs)
        chosen = [int(k) for k in listed if not self.stopped[k]]
        if seeds is not None and len(seeds) != len(chosen):
            raise ValueError(f"reset: {len(seeds)} seed(s) for {len(chosen)} run(s); give one seed per run")
        given = dict(zip(chosen, seeds)) if seeds is not None else {}
        for k in chosen:
            self.episode[k] += 1
            self.episode_seeds[k] = given[k] if k in given else episode_seed(self.cfgs[k].seed, 0,
                                                                             int(self.episode[k]))
            self._obs[k], _ = self._live()[k].reset(seed=int(self.episode_seeds[k]))
            self._steps[k] = 0
        if any(o is None for o in self._obs):
            raise RuntimeError("the first reset starts every run")
        return self._stacked()

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One step of every run not stopped (a stopped run reports reward 0 and no episode end); ``actions``
        ``[K, 2]`` continuous or ``[K]`` discrete."""
        values = np.asarray(actions)
        if len(values) != self.runs:
            raise ValueError(f"step: one action per run of the batch's {self.runs} expected, got shape "
                             f"{values.shape}")
        reward = np.zeros(self.runs)
        terminated = np.zeros(self.runs, dtype=bool)
        truncated = np.zeros(self.runs, dtype=bool)
        metrics: list[dict[str, Any] | None] = [None] * self.runs
        stopped: dict[int, str] = {}
        for k, env in enumerate(self._live()):
            if self.stopped[k]:
                continue
            if not np.isfinite(np.asarray(values[k], dtype=float)).all():
                stopped[k] = (f"run {k}: action {values[k]!r} at step {int(self._steps[k]) + 1} of episode "
                              f"{int(self.episode[k])} is not finite; a diverged policy must not drive the car")
                self.stopped[k] = True
                continue
            self._obs[k], reward[k], terminated[k], truncated[k], info = env.step(values[k])
            self._steps[k] += 1
            metrics[k] = info.get("episode_metrics")
        return self._stacked(), reward, terminated, truncated, {"episode_metrics": metrics, "stopped": stopped}

    def episode_metrics(self, k: int, books: Any = None) -> dict[str, Any]:
        """Run k's episode metrics so far (LaneFree-v0's row)."""
        return {**self._live()[k].episode_metrics(), "episode": int(self.episode[k])}

    def close(self) -> None:
        """Close every run's environment (inside SUMO: end its simulation)."""
        for env in self.envs or []:
            env.close()


class SlotBatch:
    """K runs of several slots each — ``train.envs`` LaneFree-v0 environments, or the ``scenario.agents``
    learning vehicles of one :class:`~lanefree_sumo.rl.multi_agent.LaneFreeParallelEnv` — behind the interface
    of :class:`EnvBatch`, one row per slot (run k's slots in rows k · slots …), as SB3's loop steps them for one
    shared policy (its ``DummyVecEnv`` or :class:`~lanefree_sumo.rl.multi_agent.SharedPolicyVecEnv`):

    - environment r of run k takes, for its e-th episode, the traffic seed :func:`~lanefree_sumo.rl.models.
      episode_seed` (seed, r, e) and starts its next episode on its own when one ends (:meth:`reset`);
    - the agents of a run share its simulation, whose e-th episode has the traffic seed (seed, 0, e); the first
      agent whose episode ends (it left the on-ramp) ends the others' too, as truncations.

    Simulated on the CPU: with numpy (``train.backend = numpy``), where a checkpoint may be taken inside an episode;
    or, for one run of several agents, inside SUMO (libsumo or traci: one simulation), checkpointed between episodes
    only and started again from its episode's seed after unpickling, as :class:`EnvBatch` does."""

    device = "cpu"
    xp = NUMPY

    def __init__(self, configs: Sequence[LaneFreeConfig | Mapping[str, Any]], device: str = "cpu") -> None:
        from lanefree_sumo.rl.multi_agent import LaneFreeParallelEnv

        if device != "cpu":
            raise ConfigError("runs of several agents or environments are simulated on the CPU (train.device = "
                              "cpu); leave --device out")
        self.cfgs = [resolve_config(c) for c in configs]
        if not self.cfgs:
            raise ConfigError("a batch needs at least one run")
        self.slots = slots(self.cfgs[0])
        if any(slots(c) != self.slots for c in self.cfgs):
            raise ConfigError("the runs of a batch of several agents or environments share scenario.agents and "
                              "train.envs")
        self.runs = len(self.cfgs)
        self.rows = self.runs * self.slots
        self.grouped = self.cfgs[0].scenario.agents > 1
        """The slots are the agents of one simulation (their rows of one episode are that episode's)."""
        self.in_sumo = any(c.backend != "numpy" for c in self.cfgs)
        """Whether the runs move SUMO's vehicles (libsumo, traci) rather than numpy's."""
        if self.in_sumo and (self.runs != 1 or not self.grouped):
            raise ConfigError("inside SUMO (train.backend libsumo or traci) one run of several agents trains alone, "
                              "not in a batch, and several environments do not train; the numpy backend "
                              "gives the same episodes")
        self.multi: list[LaneFreeParallelEnv] | None = ([LaneFreeParallelEnv(c) for c in self.cfgs]
                                                       if self.grouped else [])
        self.envs = [] if self.grouped else [[LaneFreeEnv(c) for _ in range(self.slots)] for c in self.cfgs]
        self.episode = np.zeros(self.rows, dtype=int)
        """Each slot's episodes begun."""
        self.stopped = np.zeros(self.runs, dtype=bool)
        """Runs stopped (a non-finite action, or finished); they are never reset nor stepped again."""
        self.terminate_on_collision = np.array([c.episode.terminate_on_collision for c in self.cfgs])
        self._due = np.ones(self.rows, dtype=bool)
        """Slots whose next episode :meth:`reset` starts (each, at first)."""
        self._obs: list[Any] = [None] * self.rows
        self._steps = np.zeros(self.runs, dtype=int)
        """Each run's steps since its simulation's episode began (agents)."""

    @property
    def saves_mid_episode(self) -> bool:
        """Whether a checkpoint may be taken inside an episode (not inside SUMO)."""
        return not self.in_sumo

    def __getstate__(self) -> dict[str, Any]:
        """Pickled (a batch checkpoint holds its env); inside SUMO without the simulation."""
        return {**self.__dict__, "multi": None} if self.in_sumo else dict(self.__dict__)

    def _parallel(self) -> list[Any]:
        """The runs' multi-agent environments; after unpickling a run inside SUMO, started again: a run that had
        just begun an episode is reset with that episode's seed, which must give the observations saved."""
        from lanefree_sumo.rl.multi_agent import LaneFreeParallelEnv

        if self.multi is None:
            self.multi = [LaneFreeParallelEnv(c) for c in self.cfgs]
            m = self.slots
            for k, env in enumerate(self.multi):
                if self.stopped[k] or self._due[k * m] or self.episode[k * m] == 0:
                    continue
                if self._steps[k] != 0:
                    raise RunError(f"run {k}: a run inside SUMO is checkpointed between episodes, not at step "
                                   f"{int(self._steps[k])} of episode {int(self.episode[k * m])}")
                observations, _ = env.reset(seed=int(episode_seed(self.cfgs[k].seed, 0, int(self.episode[k * m]))))
                env.episode = int(self.episode[k * m])
                if not all(_same(observations[name], self._obs[k * m + i])
                           for i, name in enumerate(env.possible_agents)):
                    raise RunError(f"run {k}: SUMO did not start episode {int(self.episode[k * m])} as it did before "
                                   "the checkpoint (its seed gave other first observations); resuming would not "
                                   "continue the same run")
        return self.multi

    @property
    def cfg(self) -> LaneFreeConfig:
        """Run 0's config (the action and observation settings are every run's)."""
        return self.cfgs[0]

    def _stacked(self) -> Any:
        return _stacked(self._obs)

    def reset(self, runs: Sequence[int] | None = None) -> Any:
        """Start the next episode of every slot of ``runs`` (None: every run not stopped) whose episode ended (at
        first: all); returns every slot's observation ``[K · slots, …]``."""
        listed = _runs_listed(runs, self.runs)
        m = self.slots
        for k in (int(k) for k in listed if not self.stopped[k]):
            rows = range(k * m, (k + 1) * m)
            if self.grouped and self._due[k * m]:
                self.episode[rows] += 1
                env = self._parallel()[k]
                observations, _ = env.reset(seed=int(episode_seed(self.cfgs[k].seed, 0, int(self.episode[k * m]))))
                for row, name in zip(rows, env.possible_agents):
                    self._obs[row] = observations[name]
                self._due[rows] = False
                self._steps[k] = 0
            elif not self.grouped:
                for r, row in enumerate(rows):
                    if self._due[row]:
                        self.episode[row] += 1
                        seed = episode_seed(self.cfgs[k].seed, r, int(self.episode[row]))
                        self._obs[row], _ = self.envs[k][r].reset(seed=int(seed))
                        self._due[row] = False
        if any(o is None for o in self._obs):
            raise RuntimeError("the first reset starts every run")
        return self._stacked()

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One step of every slot of every run not stopped (a stopped run's slots report reward 0 and no episode
        end); ``actions`` ``[K · slots, 2]`` continuous or ``[K · slots]`` discrete. The observation of a slot
        whose episode ended is its last (SB3's terminal observation) until :meth:`reset`."""
        values = np.asarray(actions)
        if len(values) != self.rows:
            raise ValueError(f"step: one action per slot of the batch's {self.runs} run(s) × {self.slots} expected, "
                             f"got shape {values.shape}")
        m = self.slots
        reward = np.zeros(self.rows)
        terminated = np.zeros(self.rows, dtype=bool)
        truncated = np.zeros(self.rows, dtype=bool)
        metrics: list[dict[str, Any] | None] = [None] * self.rows
        stopped: dict[int, str] = {}
        for k in range(self.runs):
            if self.stopped[k]:
                continue
            rows = slice(k * m, (k + 1) * m)
            if not np.isfinite(np.asarray(values[rows], dtype=float)).all():
                stopped[k] = (f"run {k}: an action at a step of episode {int(self.episode[k * m])} is not finite; "
                              "a diverged policy must not drive the car")
                self.stopped[k] = True
                continue
            if self.grouped:
                self._step_agents(k, values[rows], reward, terminated, truncated, metrics)
                continue
            for r, env in enumerate(self.envs[k]):
                row = k * m + r
                self._obs[row], reward[row], terminated[row], truncated[row], info = env.step(values[row])
                metrics[row] = info.get("episode_metrics")
                self._due[row] = metrics[row] is not None
        return self._stacked(), reward, terminated, truncated, {"episode_metrics": metrics, "stopped": stopped}

    def _step_agents(self, k: int, actions: np.ndarray, reward: np.ndarray, terminated: np.ndarray,
                     truncated: np.ndarray, metrics: list[dict[str, Any] | None]) -> None:
        """Run k's agents' step (:class:`~lanefree_sumo.rl.multi_agent.SharedPolicyVecEnv`'s: one agent's end ends
        the episode of all, the others truncated)."""
        env = self._parallel()[k]
        names = env.possible_agents
        observations, rewards, terminations, truncations, infos = env.step(
            {name: actions[i] for i, name in enumerate(names)})
        self._steps[k] += 1
        done = [terminations[name] or truncations[name] for name in names]
        for i, name in enumerate(names):
            row = k * self.slots + i
            self._obs[row], reward[row] = observations[name], rewards[name]
            terminated[row] = terminations[name]
            truncated[row] = truncations[name] or (any(done) and not done[i])
            if any(done):
                metrics[row] = infos[name].get("episode_metrics") or env.episode_metrics(name)
        if any(done):
            self._due[k * self.slots:(k + 1) * self.slots] = True

    def close(self) -> None:
        """Close every run's environments."""
        for multi in self.multi or []:
            multi.close()
        for envs in self.envs:
            for env in envs:
                env.close()
