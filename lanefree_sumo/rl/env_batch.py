"""K runs of LaneFree-v0 with one learning agent each, stepped one after another, behind the interface of
:class:`~lanefree_sumo.rl.batched_env.BatchedRingEnv`: how the one trainer trains the runs the ring's batched world
does not hold — the safety shield, the on-ramp.

Run k is a :class:`~lanefree_sumo.rl.env.LaneFreeEnv` of its config (on the numpy backend) whose e-th episode takes
the traffic seed :func:`~lanefree_sumo.rl.models.episode_seed` (seed, 0, e), as a training run's single environment
does; each step is its own ``step`` (the learning problem of :mod:`.problem` with K = 1), so the batch loop of
:mod:`lanefree_sumo.experiments.runners.batch` trains it as SB3's loop did. A run whose action is not finite is
stopped (``info["stopped"]``) while the others go on; a stopped run is never stepped again.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.env import LaneFreeEnv, resolve_config
from lanefree_sumo.rl.models import episode_seed


class EnvBatch:
    """K LaneFree-v0 runs (module docstring): ``reset(runs)``, ``step(actions)`` and the episode books as
    :class:`~lanefree_sumo.rl.batched_env.BatchedRingEnv` has them; ``first_episodes``: each run's next episode
    number (1 for a new run); ``device`` must be None (these runs are simulated on the CPU)."""

    device = None

    def __init__(self, configs: Sequence[LaneFreeConfig | Mapping[str, Any]],
                 first_episodes: Sequence[int] | None = None, device: Any = None) -> None:
        if device is not None:
            raise ConfigError("runs with the shield or off the ring are simulated on the CPU; leave --device out")
        self.cfgs = [resolve_config(c) for c in configs]
        if not self.cfgs:
            raise ConfigError("a batch needs at least one run")
        for k, cfg in enumerate(self.cfgs):
            if cfg.scenario.agents != 1 or cfg.train.backend != "numpy":
                raise ConfigError(f"run {k}: a batch runs one agent on the numpy backend (scenario.agents = 1, "
                                  "train.backend = numpy)")
        self.runs = len(self.cfgs)
        self.envs = [LaneFreeEnv(c) for c in self.cfgs]
        self.episode = np.array([e - 1 for e in (first_episodes or [1] * self.runs)], dtype=int)
        self.episode_seeds = np.zeros(self.runs, dtype=np.int64)
        self.stopped = np.zeros(self.runs, dtype=bool)
        """Runs stopped for a non-finite action; they are never reset nor stepped again."""
        self.terminate_on_collision = np.array([c.episode.terminate_on_collision for c in self.cfgs])
        self._steps = np.zeros(self.runs, dtype=int)
        self._obs: list[Any] = [None] * self.runs

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
        if isinstance(self._obs[0], dict):
            return {name: np.stack([o[name] for o in self._obs]) for name in self._obs[0]}
        return np.stack(self._obs)

    def reset(self, runs: Sequence[int] | None = None, seeds: Sequence[int] | None = None) -> Any:
        """Start the next episode of ``runs`` (None: every run not stopped); returns every run's observation.
        ``seeds``: those episodes' traffic seeds (None: each run's training schedule)."""
        listed = list(range(self.runs) if runs is None else runs)
        if any(isinstance(k, bool) or not isinstance(k, int | np.integer) or not 0 <= k < self.runs
               for k in listed) or len(set(listed)) != len(listed):
            raise ValueError(f"reset: runs are distinct indices 0 … {self.runs - 1} of this batch, got {runs!r}")
        chosen = [int(k) for k in listed if not self.stopped[k]]
        if seeds is not None and len(seeds) != len(chosen):
            raise ValueError(f"reset: {len(seeds)} seed(s) for {len(chosen)} run(s); give one seed per run")
        given = dict(zip(chosen, seeds)) if seeds is not None else {}
        for k in chosen:
            self.episode[k] += 1
            self.episode_seeds[k] = given[k] if k in given else episode_seed(self.cfgs[k].seed, 0,
                                                                             int(self.episode[k]))
            self._obs[k], _ = self.envs[k].reset(seed=int(self.episode_seeds[k]))
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
        for k, env in enumerate(self.envs):
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
        return {**self.envs[k].episode_metrics(), "episode": int(self.episode[k])}

    def close(self) -> None:
        """Close every run's environment."""
        for env in self.envs:
            env.close()
