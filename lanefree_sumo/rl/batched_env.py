"""K runs of LaneFree-v0 on the ring in one batched environment (the simulation as :mod:`~lanefree_sumo.sim.world`).

Run k is, bit for bit, a :class:`~lanefree_sumo.rl.env.LaneFreeEnv` of its own config whose episodes take the
traffic seeds of a training run (:func:`~lanefree_sumo.rl.models.episode_seed` (seed, 0, e) for its e-th
episode, as ``lanefree train --seed <seed>`` gives them): the same observations, rewards, reward terms, episode
ends and episode metrics (every column but the wall time). The runs may differ in seed, density (vehicle count:
the world pads and masks), reward preset, which passes earn the overtake bonus (``reward.overtake_bonus``), the
agent's top speed and its lateral speed bound; they share the step, the driver model, the agents' acceleration
bounds, the action and observation settings (the discrete action sizes among them) and the reward's constants.

Every step's work is array operations over the runs: observations, reward terms (:mod:`.rewards`,
:mod:`.fields_zones`, evaluated for all runs at once), collisions, overtakes and the episode books. A run whose
action is not finite is stopped — reported in ``info["stopped"]`` with its reason, never stepped as a learner
again — while the other runs go on. The safety shield and the on-ramp are not batched
(:class:`~lanefree_sumo.rl.env.LaneFreeEnv` has them).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig, ResolvedConfig, config_to_dict
from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.env import (
    DISCRETE_ACTIONS,
    METRIC_TERMS,
    NEIGHBOUR_FEATURES,
    feature_scales,
    resolve_config,
)
from lanefree_sumo.rl.fields_zones import field_terms, zone_targets
from lanefree_sumo.rl.models import episode_seed
from lanefree_sumo.rl.rewards import (
    OVERTAKE_BONUS_MODES,
    get_preset,
    lateral_cost,
    longitudinal_cost,
    pass_events,
    reciprocal_reward,
)
from lanefree_sumo.sim.spawn import spawn
from lanefree_sumo.sim.state import row_sum, take_rows
from lanefree_sumo.sim.world import World, WorldParams, replace_runs, step_world, world_of, world_to
from lanefree_sumo.sim.xp import NUMPY, torch_namespace

SHARED_SECTIONS = ("action", "observation", "sim", "episode", "shield")
"""Config sections every run of a batch must have alike (the reward may differ in its preset and overtake bonus)."""

PER_RUN_REWARD = ("preset", "overtake_bonus")
"""The reward's keys the runs of one batch may differ in."""


BOOKS = ("return", "return_bonus", "return_collision", "collisions", "collision_steps", "background_collisions",
         "speed_dev_sum", "speed_error_sum", "speed_sum", "overtakes", "boundary_contacts",
         *(f"sum_{t}" for t in METRIC_TERMS))


@dataclass
class Rewards:
    """One step's reward terms of every run (``[K]``; costs –, y_d m, v_d_eff m/s), as ``info`` reports them."""

    c_x: np.ndarray
    c_y: np.ndarray
    c_f: np.ndarray
    y_d: np.ndarray
    v_d_eff: np.ndarray
    blocked: np.ndarray
    collided: np.ndarray
    overtook: np.ndarray
    reward: np.ndarray


def _resolve(configs: Sequence[LaneFreeConfig | Mapping[str, Any]]) -> list[ResolvedConfig]:
    """The runs' full configs; ConfigError for what the batch cannot run together."""
    cfgs = [resolve_config(c) for c in configs]
    if not cfgs:
        raise ConfigError("a batched environment needs at least one run")
    first = config_to_dict(cfgs[0])
    for k, cfg in enumerate(cfgs):
        if cfg.road.kind != "ring" or cfg.scenario.agents != 1:
            raise ConfigError(f"run {k}: the batched environment runs one agent on the ring "
                              f"(road.kind = ring, scenario.agents = 1); use LaneFree-v0 for the others")
        if cfg.shield.enabled:
            raise ConfigError(f"run {k}: the batched environment has no safety shield; "
                              "use LaneFree-v0 with shield.enabled")
        if cfg.reward.overtake_bonus not in OVERTAKE_BONUS_MODES:
            raise ConfigError(f"run {k}: reward.overtake_bonus = {cfg.reward.overtake_bonus!r} is not one of "
                              f"{', '.join(OVERTAKE_BONUS_MODES)}")
        mine = config_to_dict(cfg)
        differ = [s for s in SHARED_SECTIONS if mine[s] != first[s]]
        unshared = dict.fromkeys(PER_RUN_REWARD)
        differ += ["reward"] if {**mine["reward"], **unshared} != {**first["reward"], **unshared} else []
        if differ:
            raise ConfigError(f"run {k} differs from run 0 in {', '.join(differ)}: the runs of one batch may differ in "
                              "seed, density, reward preset, overtake bonus and the agent's top speed and lateral "
                              "bound only")
    WorldParams.of(cfgs)  # the physics' shared parts (driver model, agents' acceleration bounds)
    return cfgs


class BatchedRingEnv:
    """K runs of the ring, each one learning agent (module docstring).

    ``reset()`` starts every run's next episode and returns the observations ``[K, obs_dim]`` (the set observation:
    a dict of ``ego`` ``[K, E]`` and ``others`` ``[K, rows, 5]``); ``reset(runs)`` restarts those runs only (their
    episodes ended) and returns every run's current observation. ``step(actions)`` takes ``[K, 2]`` continuous or
    ``[K]`` discrete actions and returns ``(obs, reward [K], terminated [K], truncated [K], info)``; a run whose
    episode ended has its episode-metrics row in ``info["episode_metrics"][k]`` (None for the others).
    ``first_episodes``: each run's next episode number (1 for a new run; a resumed run continues its schedule).

    ``device`` (None: numpy): a torch device the simulation, observations, rewards and episode books live on
    (float64, the same functions through :mod:`~lanefree_sumo.sim.xp`); ``step`` then returns the observations
    and rewards as tensors there, and ``terminated``/``truncated`` as host arrays (the episode ends are known on
    the host from the step count; only ``episode.terminate_on_collision`` reads the device each step). The
    actions are taken on the host (the learners draw them there) and the books leave the device at episode ends."""

    def __init__(self, configs: Sequence[LaneFreeConfig | Mapping[str, Any]],
                 first_episodes: Sequence[int] | None = None, device: Any = None) -> None:
        self.cfgs = _resolve(configs)
        cfg = self.cfgs[0]
        self.device = None if device is None else str(device)
        xp = self.xp
        self.runs = len(self.cfgs)
        self.params = WorldParams.of(self.cfgs).on(xp)
        self.episode = np.array([e - 1 for e in (first_episodes or [1] * self.runs)], dtype=int)
        self.episode_seeds = np.zeros(self.runs, dtype=np.int64)
        self.stopped = np.zeros(self.runs, dtype=bool)
        """Runs stopped for a non-finite action; they are never reset nor scored again."""
        self.world: World | None = None
        self._vehicles = [c.background_vehicles + 1 for c in self.cfgs]
        presets = [get_preset(c.reward.preset) for c in self.cfgs]
        self._w = {name: xp.asarray(np.array([getattr(p, name) for p in presets])) for name in
                   ("w_x", "w_y", "w_f", "use_collision", "use_overtake")}
        self._ego_scale, self._neighbour_scale = (xp.asarray(np.array(s))
                                                  for s in zip(*(feature_scales(c) for c in self.cfgs)))
        self._terminate = np.array([c.episode.terminate_on_collision for c in self.cfgs])
        self._discrete_accel = xp.asarray(DISCRETE_ACTIONS * np.array([cfg.action.discrete_ax_mps2,
                                                                      cfg.action.discrete_ay_mps2]))
        """The discrete actions' (ax, ay) in m/s², on the device (:meth:`device_accelerations`)."""
        self._range = cfg.observation.range_m
        self._books = {name: xp.zeros(self.runs) for name in BOOKS}
        self._t0 = np.zeros(self.runs)
        self._active: tuple[np.ndarray, Any] | None = None
        """The runs not stopped, on the host and as the simulation's array."""
        self._steps = np.zeros(self.runs, dtype=int)
        """Each run's steps since its reset (the world's ``steps``, kept on the host)."""
        self._prev_dx = xp.zeros((self.runs, 0))
        self._order = xp.zeros((self.runs, 0), dtype=int)
        self._in_range = xp.zeros((self.runs, 0), dtype=bool)
        bonus = np.array([c.reward.overtake_bonus for c in self.cfgs])
        self._once = xp.asarray(bonus == "once_per_vehicle")
        self._net_passes = xp.asarray(bonus == "net_passes")
        rows = max(self._vehicles)
        self._net = xp.zeros((self.runs, rows), dtype=int)
        """Per vehicle row: the agent's passes of it minus its passes of the agent this episode."""
        self._best = xp.zeros((self.runs, rows), dtype=int)
        """Per vehicle row: the highest ``_net`` a pass gave it this episode (0 before any)."""
        self._ever = xp.zeros((self.runs, rows), dtype=bool)
        """Per vehicle row: passed at least once this episode."""

    @property
    def xp(self) -> Any:
        """The array namespace of the simulation (:mod:`~lanefree_sumo.sim.xp`)."""
        return NUMPY if self.device is None else torch_namespace(self.device)

    @property
    def steps(self) -> np.ndarray:
        """``[K]``: each run's steps since its episode began (a copy)."""
        return self._steps.copy()

    @property
    def cfg(self) -> LaneFreeConfig:
        """Run 0's config (the action and observation settings are every run's)."""
        return self.cfgs[0]

    # -- episodes -----------------------------------------------------------------------------
    def reset(self, runs: Sequence[int] | None = None, seeds: Sequence[int] | None = None) -> Any:
        """Start the next episode of ``runs`` (None: every run not stopped); returns every run's observation.
        ``seeds``: the traffic seeds of those episodes, one per run of ``runs`` (None: each run's training
        schedule, :func:`~lanefree_sumo.rl.models.episode_seed`)."""
        if runs is not None:
            listed = list(runs)
            if any(isinstance(k, bool) or not isinstance(k, int | np.integer) or not 0 <= k < self.runs
                   for k in listed) or len(set(listed)) != len(listed):
                raise ValueError(f"reset: runs are distinct indices 0 … {self.runs - 1} of this batch, got {runs!r}")
        chosen = [int(k) for k in (range(self.runs) if runs is None else runs) if not self.stopped[k]]
        if seeds is not None and len(seeds) != len(chosen):
            raise ValueError(f"reset: {len(seeds)} seed(s) for {len(chosen)} run(s); give one seed per run")
        given = dict(zip(chosen, seeds)) if seeds is not None else {}
        states = []
        for k in chosen:
            self.episode[k] += 1
            self.episode_seeds[k] = given[k] if k in given else episode_seed(self.cfgs[k].seed, 0,
                                                                             int(self.episode[k]))
            states.append(spawn(self.cfgs[k], np.random.default_rng(int(self.episode_seeds[k]))))
            self._t0[k] = time.perf_counter()
            self._steps[k] = 0
        if not chosen and self.world is not None:
            return self._observe()
        index = self.xp.asarray(chosen, dtype=int)
        for book in self._books.values():
            book[index] = 0.0
        self._net[index], self._best[index], self._ever[index] = 0, 0, False
        if self.world is None or len(chosen) == self.runs:
            if len(chosen) != self.runs:
                raise RuntimeError("the first reset starts every run")
            world = world_of(states, [c.road.length_m for c in self.cfgs], [c.road.width_m for c in self.cfgs],
                             rows=max(self._vehicles))
            self.world = world if self.device is None else world_to(world, self.device)
        else:
            self.world = replace_runs(self.world, chosen, states)
        obs = self._observe()
        dx_row = self._agent_row(self.world.dx)
        if self._prev_dx.shape != dx_row.shape:
            self._prev_dx = dx_row
        self._prev_dx[index] = dx_row[index]
        return obs

    def episode_metrics(self, k: int, books: Mapping[str, np.ndarray] | None = None) -> dict[str, Any]:
        """Run k's episode metrics so far: the row :meth:`~lanefree_sumo.rl.env.LaneFreeEnv.episode_metrics` gives
        (``books``: the books on the host, :meth:`host_books`, when several runs are read at once)."""
        assert self.world is not None
        books = self.host_books() if books is None else books
        b, steps = {name: books[name][k] for name in BOOKS}, int(self._steps[k])
        per = max(steps, 1)
        cfg = self.cfgs[k]
        return {
            "episode": int(self.episode[k]),
            "steps": steps,
            "return": float(b["return"]),
            "return_bonus": float(b["return_bonus"]),
            "return_collision": float(b["return_collision"]),
            "return_reciprocal": float(b["return"] - b["return_bonus"] - b["return_collision"]),
            "collisions": int(b["collisions"]),
            "collision_steps": int(b["collision_steps"]),
            "background_collisions": int(b["background_collisions"]),
            "speed_dev_mps": float(b["speed_dev_sum"] / per),
            "speed_dev_episode_mps": float(abs(b["speed_error_sum"]) / per),
            "speed_error_mps": float(b["speed_error_sum"] / per),
            "mean_speed_mps": float(b["speed_sum"] / per),
            "overtakes": int(b["overtakes"]),
            "boundary_contacts": int(b["boundary_contacts"]),
            "shield_interventions": 0,
            "shield_fallbacks": 0,
            **{f"mean_{t}": float(b[f"sum_{t}"] / per) for t in METRIC_TERMS},
            "density": cfg.scenario.density_veh_per_km,
            "seed": int(self.episode_seeds[k]),
            "reward_preset": cfg.reward.preset,
            "wall_s": time.perf_counter() - self._t0[k],
        }

    def host_books(self) -> dict[str, np.ndarray]:
        """Every run's episode books so far as host arrays (from the device: one copy)."""
        xp = self.xp
        if xp.is_numpy:
            return self._books
        stacked = xp.to_numpy(xp.stack([self._books[name] for name in BOOKS]))
        return dict(zip(BOOKS, stacked))

    # -- one step -----------------------------------------------------------------------------
    def accelerations(self, actions: Any) -> tuple[np.ndarray, np.ndarray]:
        """(ax, ay) ``[K]`` in m/s² for the runs' actions (specification §6, as
        :func:`~lanefree_sumo.rl.env.action_to_acceleration`), and ``[K]`` True where a run's action is not finite
        (its acceleration is then 0)."""
        cfg = self.cfg
        values = np.asarray(NUMPY.to_numpy(actions) if isinstance(actions, np.ndarray)
                            else self.xp.to_numpy(actions), dtype=float)
        want = ((self.runs,), (self.runs, 1)) if cfg.action.kind == "discrete" else ((self.runs, 2),)
        if values.shape not in want:
            raise ValueError(f"step: actions of shape {' or '.join(str(w) for w in want)} expected (one row per run "
                             f"of the batch's {self.runs}), got shape {values.shape}")
        values = values.reshape(self.runs, -1)
        bad = ~np.isfinite(values).all(axis=1)
        values = np.where(bad[:, None], 0.0, values)
        if cfg.action.kind == "discrete":
            index = values[:, 0].astype(int)
            if values.shape[1] != 1 or (values[:, 0] != index).any() or (index < 0).any() or \
                    (index >= len(DISCRETE_ACTIONS)).any():
                raise ValueError(f"a discrete action is one whole number 0 … {len(DISCRETE_ACTIONS) - 1} per run, "
                                 f"got {actions!r}")
            signs = DISCRETE_ACTIONS[index]
            accel = np.column_stack([signs[:, 0] * cfg.action.discrete_ax_mps2,
                                     signs[:, 1] * cfg.action.discrete_ay_mps2])
        else:
            if values.shape[1] != 2:
                raise ValueError(f"a continuous action has 2 components (ax, ay in [-1, 1]) per run, got {actions!r}")
            bounds = cfg.scenario.agent_bounds
            a = np.minimum(1.0, np.maximum(-1.0, values))
            accel = np.column_stack([np.where(a[:, 0] >= 0.0, a[:, 0] * bounds.ax_max, -a[:, 0] * bounds.ax_min),
                                     a[:, 1] * bounds.ay_max])
        return np.where(bad[:, None], 0.0, accel), bad

    def device_accelerations(self, actions: Any) -> tuple[Any, Any]:
        """:meth:`accelerations` for actions already on the simulation's device, with no host read: (ax, ay)
        ``[K, 1, 2]`` in m/s² (0 where an action is not finite) and ``[K]`` True where it is not finite. A discrete
        action must be a valid index (it is not checked here)."""
        xp, cfg = self.xp, self.cfg
        if cfg.action.kind == "discrete":
            accel = self._discrete_accel[xp.astype(actions, int).reshape(self.runs)]
            return accel[:, None, :], xp.zeros(self.runs, dtype=bool)
        values = xp.astype(actions, float).reshape(self.runs, 2)
        bad = ~xp.all(xp.isfinite(values), axis=1)
        a = xp.minimum(1.0, xp.maximum(-1.0, xp.where(bad[:, None], 0.0, values)))
        bounds = cfg.scenario.agent_bounds
        accel = xp.column_stack([xp.where(a[:, 0] >= 0.0, a[:, 0] * bounds.ax_max, -a[:, 0] * bounds.ax_min),
                                 a[:, 1] * bounds.ay_max])
        return xp.where(bad[:, None], 0.0, accel)[:, None, :], bad

    def step_on_device(self, actions: Any, active: Any) -> tuple[Any, Any, Any]:
        """One step of every run with no host read (a CUDA graph can hold it): ``actions`` a tensor on the device,
        ``active`` ``[K]`` bool, the runs scored. Returns (observation, reward, ``[K]`` True where the action was not
        finite). The host's books — :attr:`stopped`, the steps since the reset, the episode ends — are the
        caller's (:class:`~lanefree_sumo.rl.lockstep.Lockstep`); the episode books are kept as :meth:`step` keeps
        them."""
        if self.world is None:
            raise RuntimeError("call reset() before step_on_device()")
        accel, bad = self.device_accelerations(actions)
        obs, reward, *_ = self._advance(accel, active & ~bad)
        return obs, reward, bad

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """One step of every run (class docstring). Stopped runs report reward 0 and no episode end."""
        if self.world is None:
            raise RuntimeError("call reset() before step()")
        xp = self.xp
        accel, bad = self.accelerations(actions)
        newly = bad & ~self.stopped
        stopped_now = {int(k): f"run {k}: action {np.asarray(xp.to_numpy(actions))[k]!r} at step "
                       f"{int(self._steps[k]) + 1} of episode {int(self.episode[k])} is not finite; a diverged policy "
                       "must not drive the car" for k in np.flatnonzero(newly)}
        self.stopped |= bad
        active_host = ~self.stopped
        if self._active is None or not np.array_equal(self._active[0], active_host):  # copied when it changes
            self._active = (active_host, xp.asarray(active_host))
        obs, reward, terms, overtakes, agent_events, contact, collided = self._advance(
            xp.asarray(accel[:, None, :]), self._active[1])
        self._steps += 1
        if self._terminate.any():  # the one value read from the device every step, where collisions end episodes
            terminated = active_host & self._terminate & np.asarray(xp.to_numpy(collided), dtype=bool)
        else:
            terminated = np.zeros(self.runs, dtype=bool)
        truncated = active_host & (self._steps >= self.cfg.sim.episode_steps)
        ended = np.flatnonzero(terminated | truncated)
        books = self.host_books() if len(ended) else {}
        metrics: list[dict[str, Any] | None] = [None] * self.runs
        for k in ended:
            metrics[k] = self.episode_metrics(int(k), books)
        info = {**{name: getattr(terms, name) for name in Rewards.__dataclass_fields__},
                "overtakes": overtakes, "collision_events": agent_events, "boundary_contact": contact,
                "ax": accel[:, 0], "ay": accel[:, 1], "episode_metrics": metrics, "stopped": stopped_now}
        return obs, reward, terminated, truncated, info

    def _advance(self, accel: Any, active: Any) -> tuple[Any, Any, Rewards, Any, Any, Any, Any]:
        """The array part of a step, on the simulation's device with no host read: the world advanced with the
        agents' accelerations ``accel`` ``[K, 1, 2]`` (m/s²), the observation, the reward terms and the books of the
        ``active`` runs (``[K]`` bool); returns (the observation, the reward — 0 where not active —, the reward terms,
        overtakes, the agent's collision events, its boundary contact, whether it overlaps another vehicle), each
        ``[K]`` but the observation."""
        xp = self.xp
        assert self.world is not None
        before = self.world
        self.world, out = step_world(before, self.params, accel)
        world = self.world
        a = world.agent_rows[:, :1]
        collided = xp.any(xp.take_along_axis(out.overlap, a[..., None], 1)[:, 0], axis=1)
        new = out.new_collisions
        agent_events = (xp.sum(xp.take_along_axis(new, a[..., None], 1)[:, 0], axis=1)
                        + xp.sum(xp.take_along_axis(new, a[:, None, :], 2)[..., 0], axis=1))
        background_only = xp.sum(new, axis=(1, 2)) - agent_events
        obs = self._observe()
        dx_row = self._agent_row(world.dx)
        passed, passed_by = pass_events(self._prev_dx, dx_row, self._range, world.road_length[:, None])
        passed, passed_by = passed & self._in_range, passed_by & self._in_range
        overtakes = xp.count_nonzero(passed, axis=1)
        self._prev_dx = dx_row
        terms = self._rewards(collided, self._earned(passed, passed_by) > 0)

        vx_a = self._agent(world.vx)
        error = vx_a - self._agent(world.v_desired)
        contact = self._agent(out.boundary_contact)
        r, w = self.cfg.reward, self._w
        bonus = xp.where(w["use_overtake"] & terms.overtook & ~collided, r.overtake_reward, 0.0)
        b = self._books
        for name, value in (("return", terms.reward), ("return_bonus", bonus),
                            ("return_collision", xp.where(w["use_collision"] & collided, r.collision_reward, 0.0)),
                            ("collisions", agent_events), ("collision_steps", collided),
                            ("background_collisions", background_only), ("speed_dev_sum", xp.abs(error)),
                            ("speed_error_sum", error), ("speed_sum", vx_a),
                            ("overtakes", overtakes), ("boundary_contacts", contact), ("sum_c_x", terms.c_x),
                            ("sum_c_y", terms.c_y), ("sum_c_f", terms.c_f), ("sum_reward", terms.reward)):
            b[name] = xp.where(active, b[name] + value, b[name])
        return obs, xp.where(active, terms.reward, 0.0), terms, overtakes, agent_events, contact, collided

    def _earned(self, passed: np.ndarray, passed_by: np.ndarray) -> np.ndarray:
        """How many of this step's passes ``[K, N]`` earn the bonus ``[K]``, each run by its ``overtake_bonus``
        (:class:`~lanefree_sumo.rl.rewards.OvertakeLedger`, with a vehicle's row as its id: on the ring the rows
        keep their vehicles through an episode)."""
        xp = self.xp
        self._net += xp.astype(passed, int) - xp.astype(passed_by, int)  # never passed and passing at once
        first = passed & ~self._ever
        gained = passed & (self._net > self._best)
        paid = xp.where(self._once[:, None], first, xp.where(self._net_passes[:, None], gained, passed))
        self._ever |= passed
        self._best = xp.where(gained, self._net, self._best)
        return xp.count_nonzero(paid, axis=1)

    # -- the agent's view -----------------------------------------------------------------------
    def _agent(self, a: np.ndarray) -> np.ndarray:
        """Each run's agent value of a ``[K, N]`` array: ``[K]``."""
        assert self.world is not None
        return take_rows(a, self.world.agent_rows[:, :1])[:, 0]

    def _agent_row(self, pairs: np.ndarray) -> np.ndarray:
        """Each run's agent row of a ``[K, N, N]`` array: ``[K, N]``."""
        assert self.world is not None
        return pairs[self.xp.arange(self.runs), self.world.agent_rows[:, 0]]

    def _observe(self) -> Any:
        """Every run's observation (:meth:`~lanefree_sumo.rl.env.LearningVehicle.observe`); keeps the vehicles in
        range and their order by distance for the reward."""
        world, o, xp = self.world, self.cfg.observation, self.xp
        assert world is not None
        dx, dy = self._agent_row(world.dx), self._agent_row(world.dy)
        in_range = (xp.abs(dx) <= o.range_m) & world.present
        xp.put_along_axis(in_range, world.agent_rows[:, :1], False, 1)
        order = xp.argsort_stable(xp.where(in_range, xp.hypot(dx, dy), xp.inf), axis=1)
        self._in_range, self._order = in_range, order
        seen = xp.sum(in_range, axis=1)
        y_a, vx_a, vy_a = self._agent(world.y), self._agent(world.vx), self._agent(world.vy)
        ego = xp.column_stack([y_a, vx_a, vy_a, self._agent(world.v_desired)]) / self._ego_scale

        def neighbours(rows: int, fill: np.ndarray) -> np.ndarray:
            """``[K, rows, 4]``: the nearest ``rows`` vehicles in range (dx, dy, vx, vy), ``fill`` beyond them."""
            shown = order[:, :rows]
            if shown.shape[1] < rows:  # fewer vehicles on the road than rows: the rest is fill (the last row's)
                last = xp.broadcast_to(shown[:, -1:], (self.runs, rows - shown.shape[1]))
                shown = xp.concatenate([shown, last], axis=1)
            table = xp.stack([take_rows(a, shown) for a in (dx, dy, world.vx, world.vy)], axis=-1)
            return xp.where((xp.arange(rows) < seen[:, None])[..., None], table, fill)

        if o.kind == "vector":
            fill = xp.stack([xp.full(self.runs, o.range_m), xp.zeros(self.runs), vx_a, vy_a], axis=-1)[:, None, :]
            rows = neighbours(o.n_neighbours, fill) / self._neighbour_scale[:, None, :]
            return xp.astype(xp.concatenate([ego, rows.reshape(self.runs, -1)], axis=1), np.float32)
        table = xp.zeros((self.runs, o.max_rows, NEIGHBOUR_FEATURES + 1), dtype=np.float32)
        shown = xp.arange(o.max_rows) < seen[:, None]
        scaled = neighbours(o.max_rows, xp.zeros(1)) / self._neighbour_scale[:, None, :]
        table[..., :NEIGHBOUR_FEATURES] = xp.astype(xp.where(shown[..., None], scaled, 0.0), np.float32)
        table[..., NEIGHBOUR_FEATURES] = xp.astype(shown, np.float32)
        return {"ego": xp.astype(ego, np.float32), "others": table}

    def _rewards(self, collided: Any, overtook: Any) -> Rewards:
        """Every run's reward terms (:func:`~lanefree_sumo.rl.rewards.compute_reward`, over the runs at once)."""
        world, r, xp = self.world, self.cfg.reward, self.xp
        assert world is not None
        dx, dy = self._agent_row(world.dx), self._agent_row(world.dy)
        y_a, vx_a, vy_a = self._agent(world.y), self._agent(world.vx), self._agent(world.vy)
        len_a, wid_a, vd_a = self._agent(world.length), self._agent(world.width), self._agent(world.v_desired)
        width = world.road_width
        w = self._w

        zones = w["w_y"] > 0.0
        y_d, v_d_eff, blocked = zone_targets(dx, dy, world.vx, world.length, world.width, y_a, vx_a, len_a, wid_a,
                                             vd_a, width, time_gap=r.zone_time_gap_s, margin=r.zone_margin_m,
                                             present=self._in_range)
        y_d = xp.where(zones, y_d, 0.5 * width)
        v_d_eff = xp.where(zones, v_d_eff, vd_a)
        blocked = zones & blocked
        c_y = xp.where(zones, lateral_cost(y_a, y_d, width), 0.0)
        c_x = longitudinal_cost(vx_a, v_d_eff, min_desired_speed=r.min_desired_speed_mps)

        n = self.cfg.observation.n_neighbours
        seen = xp.minimum(xp.sum(self._in_range, axis=1), n)
        observed = self._order[:, :n]

        def of(a: np.ndarray) -> np.ndarray:
            return take_rows(a, observed)

        e_c, e_b = field_terms(of(dx), of(dy), vx_a[:, None] - of(world.vx), vy_a[:, None] - of(world.vy),
                               len_a[:, None], wid_a[:, None], of(world.length), of(world.width),
                               magnitude=r.field_magnitude, critical_exponents=r.critical_exponents,
                               broad_exponents=r.broad_exponents, k_r=r.k_r_s_per_m, e_v=r.e_v_s_per_m,
                               stretch=r.broad_stretch)
        valid = xp.arange(observed.shape[1]) < seen[:, None]
        c_f = xp.minimum(1.0, row_sum(xp.where(valid, e_c, 0.0), seen) + row_sum(xp.where(valid, e_b, 0.0), seen))
        reward = reciprocal_reward(c_x, c_y, c_f, collided, overtook, w["w_x"], w["w_y"], w["w_f"],
                                   epsilon_r=r.epsilon_r, collision_reward=r.collision_reward,
                                   overtake_reward=r.overtake_reward, use_collision=w["use_collision"],
                                   use_overtake=w["use_overtake"])
        return Rewards(c_x, c_y, c_f, y_d, v_d_eff, blocked, collided, overtook, xp.asarray(reward))

