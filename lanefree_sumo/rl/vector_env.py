"""``LaneFree-v0`` as a gymnasium vector environment: K rings in one process, one array program.

``gymnasium.make_vec("LaneFree-v0", num_envs=K, vectorization_mode="vector_entry_point", config={...})`` gives a
:class:`LaneFreeVectorEnv`: the K environments are the runs of one
:class:`~lanefree_sumo.rl.batched_env.BatchedRingEnv` (the world of :mod:`~lanefree_sumo.sim.world`), so a step
is one set of array operations over every ring instead of K Python environments. Sub-environment k is, bit for
bit, ``gymnasium.make("LaneFree-v0", config=...)`` reset with the same seed and given the same actions, across
its episode ends: the same observations, rewards, ends, ``info`` values and episode metrics (every column but the
wall time).

The gymnasium conventions: ``single_observation_space`` / ``single_action_space`` are LaneFree-v0's;
``reset(seed=s)`` seeds sub-environment k with ``s + k`` (or ``seed=[s0, s1, …]`` one each; None: fresh
entropy), each keeping its own generator for the traffic seeds of its later episodes as LaneFree-v0 does;
``reset(options={"reset_mask": mask})`` restarts the masked ones only; autoreset is gymnasium's ``NEXT_STEP``
(``metadata["autoreset_mode"]``): the step after an episode's end returns that sub-environment's first
observation of the next episode, reward 0 and neither end, its action unused. ``info`` is in gymnasium's vector
form: every key an array over the sub-environments with its ``_key`` mask — the step's reward terms where a step
was taken, ``episode_seed`` where an episode began, and ``episode_metrics`` (a dict of arrays) where one ended.
Actions are validated whole (shape, finiteness, discrete range): a bad one raises ValueError and steps nothing.

What runs batched: one learning vehicle on the ring, without the safety shield, on the numpy backend; the runs
share their config (the traffic differs by seed). Anything else is refused in one line; LaneFree-v0 under
``vectorization_mode="sync"`` runs it (a SUMO backend, the on-ramp, several agents, the shield).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from gymnasium.spaces import Box, Discrete
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.batched_env import BatchedRingEnv
from lanefree_sumo.rl.env import (
    DISCRETE_ACTIONS,
    RENDER_FPS,
    action_space,
    as_seed,
    face_config,
    observation_space,
    resolve_config,
)
from lanefree_sumo.rl.rewards import REWARD_TERMS
from lanefree_sumo.sim.road import road_kind

SEED_BOUND = 2**31 - 1
"""Episode seeds drawn by a sub-environment's generator lie in [0, SEED_BOUND) (as LaneFree-v0 draws them)."""


def _refusal(cfg: LaneFreeConfig) -> str | None:
    """Why the vector entry point cannot run ``cfg`` (None: it can)."""
    if cfg.gui or cfg.backend != "numpy":
        return (f"backend {'sumo-gui' if cfg.gui else cfg.backend!r}: the vector entry point runs its worlds as "
                "numpy arrays (the same episodes as libsumo)")
    if not road_kind(cfg).batched_world:
        return f"road.kind = {cfg.road.kind!r}: the vector entry point runs the ring"
    if cfg.scenario.agents != 1:
        return f"scenario.agents = {cfg.scenario.agents}: the vector entry point runs one learning vehicle per world"
    if cfg.shield.enabled:
        return "shield.enabled: the vector entry point has no safety shield yet"
    return None


class LaneFreeVectorEnv(VectorEnv):
    """K LaneFree-v0 environments as one batched world (module docstring).

    ``num_envs``: K ≥ 1. ``config``: LaneFree-v0's (a dict of overrides or a
    :class:`~lanefree_sumo.config.LaneFreeConfig`), the same for every sub-environment. ``render_mode``:
    ``"rgb_array"`` (``render()`` gives one ``H × W × 3`` frame per sub-environment) or None."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": RENDER_FPS, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, config: LaneFreeConfig | Mapping[str, Any] | None = None,
                 render_mode: str | None = None) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int | np.integer) or num_envs < 1:
            raise ValueError(f"num_envs must be a whole number ≥ 1, got {num_envs!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode {render_mode!r}: the vector entry point renders 'rgb_array' frames "
                             "(sumo-gui, 'human', runs under vectorization_mode='sync')")
        cfg = resolve_config(face_config(config))
        reason = _refusal(cfg)
        if reason:
            raise ConfigError(f"{reason}; use gymnasium.make_vec('LaneFree-v0', num_envs, vectorization_mode='sync', "
                              "config=...) for it")
        self.cfg = cfg
        self.num_envs = int(num_envs)
        self.render_mode = render_mode
        self.batch = BatchedRingEnv([cfg] * self.num_envs)
        self.single_observation_space = observation_space(cfg)
        self.single_action_space = action_space(cfg)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._rngs: list[np.random.Generator | None] = [None] * self.num_envs
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self._started = False

    # -- seeds --------------------------------------------------------------------------------------------
    def _seeds(self, seed: int | Sequence[int | None] | None) -> list[int | None]:
        """One reset seed per sub-environment (module docstring)."""
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, Sequence) and not isinstance(seed, str):
            if len(seed) != self.num_envs:
                raise ValueError(f"reset: {len(seed)} seed(s) for {self.num_envs} environments; give one seed "
                                 "per environment or one int")
            return [as_seed(s) for s in seed]
        first = as_seed(seed)
        assert first is not None
        return [first + k for k in range(self.num_envs)]

    def _episode_seed(self, k: int, seed: int | None) -> int:
        """The traffic seed of sub-environment k's next episode, as LaneFree-v0's ``reset(seed=seed)`` takes it."""
        if seed is not None:
            self._rngs[k] = seeding.np_random(seed)[0]
            return seed
        rng = self._rngs[k]
        if rng is None:
            rng = self._rngs[k] = seeding.np_random()[0]
        return int(rng.integers(SEED_BOUND))

    # -- gymnasium API ------------------------------------------------------------------------------------
    def reset(self, *, seed: int | Sequence[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        """Start an episode in every sub-environment (or those of ``options["reset_mask"]``); returns the
        observations and ``info`` with ``episode_seed``."""
        seeds = self._seeds(seed)
        mask = np.ones(self.num_envs, dtype=bool)
        if options and "reset_mask" in options:
            mask = np.asarray(options["reset_mask"])
            if mask.dtype != np.bool_ or mask.shape != (self.num_envs,):
                raise ValueError(f"reset: options['reset_mask'] must be {self.num_envs} booleans, got {mask!r}")
            if not self._started and not mask.all():
                raise ValueError("reset: the first reset starts every environment (reset_mask all True)")
        runs = np.flatnonzero(mask)
        episode_seeds = [self._episode_seed(int(k), seeds[k]) for k in runs]
        obs = self.batch.reset(runs=[int(k) for k in runs], seeds=episode_seeds)
        self._started = True
        self._autoreset[runs] = False
        info = {"episode_seed": np.zeros(self.num_envs, dtype=np.int64), "_episode_seed": mask.copy()}
        info["episode_seed"][runs] = episode_seeds
        return obs, info

    def _checked(self, actions: Any) -> np.ndarray:
        """The actions as a host array the batched world takes; ValueError naming what is wrong."""
        values = np.asarray(actions)
        space = self.single_action_space
        if isinstance(space, Discrete):
            if values.shape != (self.num_envs,):
                raise ValueError(f"step: {self.num_envs} discrete actions expected (shape ({self.num_envs},)), "
                                 f"got shape {values.shape}")
            as_float = values.astype(float)
            if not np.isfinite(as_float).all() or (as_float != np.round(as_float)).any() or \
                    (as_float < 0).any() or (as_float >= len(DISCRETE_ACTIONS)).any():
                raise ValueError(f"step: a discrete action is one whole number 0 … {len(DISCRETE_ACTIONS) - 1} per "
                                 f"environment, got {values!r}")
            return as_float
        assert isinstance(space, Box)
        if values.shape != (self.num_envs, 2):
            raise ValueError(f"step: actions of shape ({self.num_envs}, 2) expected (ax, ay in [-1, 1] per "
                             f"environment), got shape {values.shape}")
        values = values.astype(float)
        if not np.isfinite(values).all():
            bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
            raise ValueError(f"step: the actions of environment(s) {', '.join(map(str, bad))} are not finite; a "
                             "diverged policy must not drive the car")
        return values

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One step of every sub-environment (module docstring: NEXT_STEP autoreset, vector ``info``)."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        values = self._checked(actions)
        restart = self._autoreset.copy()
        values[restart] = 0.0
        obs, reward, terminated, truncated, step_info = self.batch.step(values)
        stepped = ~restart
        info: dict[str, Any] = {}
        for key in (*REWARD_TERMS, "overtakes", "collision_events", "boundary_contact", "ax", "ay"):
            value = np.asarray(step_info[key])
            info[key] = value.astype(np.int64) if value.dtype.kind in "iu" else value
            info[f"_{key}"] = stepped
        info["shield_intervened"] = np.zeros(self.num_envs, dtype=bool)
        info["_shield_intervened"] = stepped
        info["shield_correction"] = np.zeros(self.num_envs)
        info["_shield_correction"] = stepped
        reward = np.asarray(reward, dtype=np.float64).copy()
        terminated = terminated & stepped
        truncated = truncated & stepped
        for k in np.flatnonzero(terminated | truncated):
            info = self._add_info(info, {"episode_metrics": step_info["episode_metrics"][k]}, int(k))
        if restart.any():
            runs = np.flatnonzero(restart)
            seeds = [self._episode_seed(int(k), None) for k in runs]
            obs = self.batch.reset(runs=[int(k) for k in runs], seeds=seeds)
            reward[restart] = 0.0
            info["episode_seed"] = np.zeros(self.num_envs, dtype=np.int64)
            info["episode_seed"][runs] = seeds
            info["_episode_seed"] = restart
        self._autoreset = terminated | truncated
        return obs, reward, terminated, truncated, info

    def render(self) -> tuple[np.ndarray, ...] | None:
        """One frame per sub-environment (``render_mode="rgb_array"``, :mod:`~lanefree_sumo.rl.render`), else None."""
        if self.render_mode != "rgb_array":
            return None
        if not self._started:
            raise RuntimeError("call reset() before render()")
        from lanefree_sumo.rl.render import Scene, draw_frame
        from lanefree_sumo.sim.road import road_of

        world, road = self.batch.world, road_of(self.cfg)
        assert world is not None
        frames = []
        for k in range(self.num_envs):
            rows = world.present[k]
            scene = Scene(world.x[k, rows], world.y[k, rows], world.vx[k, rows], world.vy[k, rows],
                          world.length[k, rows], world.width[k, rows], ~world.controlled[k, rows],
                          world.overlap[k][np.ix_(rows, rows)].any(axis=1), road,
                          int(self.batch.steps[k]) * self.cfg.sim.step_s)
            frames.append(draw_frame(scene))
        return tuple(frames)

    def close_extras(self, **kwargs: Any) -> None:
        """Nothing to release: the worlds are arrays."""
