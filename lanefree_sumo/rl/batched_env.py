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
again — while the other runs go on. The learning problem is :mod:`~lanefree_sumo.rl.problem`'s over the world's
agent rows. The safety shield and the on-ramp are not in this world (:class:`~lanefree_sumo.rl.env.LaneFreeEnv`
has them; :class:`~lanefree_sumo.rl.env_batch.EnvBatch` trains them as a batch).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig, ResolvedConfig, config_to_dict
from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.env import DISCRETE_ACTIONS, resolve_config
from lanefree_sumo.rl.models import episode_seed
from lanefree_sumo.rl.problem import BOOKS, AgentView, Problem, ProblemState, episode_row
from lanefree_sumo.rl.rewards import Rewards
from lanefree_sumo.sim.road import road_kind
from lanefree_sumo.sim.spawn import spawn
from lanefree_sumo.sim.world import World, WorldParams, replace_runs, step_world, world_of, world_to
from lanefree_sumo.sim.xp import array_namespace, device_name

SHARED_SECTIONS = ("action", "observation", "sim", "episode", "shield")
"""Config sections every run of a batch must have alike (the reward may differ in its preset and overtake bonus)."""

PER_RUN_REWARD = ("preset", "overtake_bonus")
"""The reward's keys the runs of one batch may differ in."""


def _resolve(configs: Sequence[LaneFreeConfig | Mapping[str, Any]]) -> list[ResolvedConfig]:
    """The runs' full configs; ConfigError for what the batch cannot run together."""
    cfgs = [resolve_config(c) for c in configs]
    if not cfgs:
        raise ConfigError("a batched environment needs at least one run")
    first = config_to_dict(cfgs[0])
    for k, cfg in enumerate(cfgs):
        if not road_kind(cfg).batched_world or cfg.scenario.agents != 1:
            raise ConfigError(f"run {k}: the batched environment runs one agent on the ring "
                              f"(road.kind = ring, scenario.agents = 1); use LaneFree-v0 for the others")
        if cfg.shield.enabled:
            raise ConfigError(f"run {k}: the batched environment has no safety shield; "
                              "use LaneFree-v0 with shield.enabled")
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

    ``device`` (``train.device``: ``cpu``, numpy, the default; ``torch-cpu`` or ``cuda``, torch there): where the
    simulation, observations, rewards and episode books live (float64, the same functions through
    :func:`~lanefree_sumo.sim.xp.array_namespace`); on torch, ``step`` returns the observations
    and rewards as tensors there, and ``terminated``/``truncated`` as host arrays (the episode ends are known on
    the host from the step count; only ``episode.terminate_on_collision`` reads the device each step). The
    actions are taken on the host (the learners draw them there) and the books leave the device at episode ends."""

    def __init__(self, configs: Sequence[LaneFreeConfig | Mapping[str, Any]],
                 first_episodes: Sequence[int] | None = None, device: str = "cpu") -> None:
        self.cfgs = _resolve(configs)
        cfg = self.cfgs[0]
        self.xp = array_namespace(device)
        """The array namespace of the simulation (:mod:`~lanefree_sumo.sim.xp`)."""
        self.device = self.xp.name
        xp = self.xp
        self.runs = len(self.cfgs)
        self.params = WorldParams.of(self.cfgs).on(xp)
        self.episode = np.array([e - 1 for e in (first_episodes or [1] * self.runs)], dtype=int)
        self.episode_seeds = np.zeros(self.runs, dtype=np.int64)
        self.stopped = np.zeros(self.runs, dtype=bool)
        """Runs stopped for a non-finite action; they are never reset nor scored again."""
        self.world: World | None = None
        self.problem = Problem(self.cfgs, xp)
        """The learning problem's per-run constants (:mod:`~lanefree_sumo.rl.problem`)."""
        self.state = ProblemState.empty(xp, self.runs, max(c.background_vehicles + 1 for c in self.cfgs))
        """What each run's learning problem keeps from step to step: the pass book, who is in range, the books."""
        self.terminate_on_collision = np.array([c.episode.terminate_on_collision for c in self.cfgs])
        """``[K]``: the runs whose episodes end at a collision (``episode.terminate_on_collision``)."""
        self._discrete_accel = xp.asarray(DISCRETE_ACTIONS * np.array([cfg.action.discrete_ax_mps2,
                                                                      cfg.action.discrete_ay_mps2]))
        """The discrete actions' (ax, ay) in m/s², on the device (:meth:`device_accelerations`)."""
        self._t0 = np.zeros(self.runs)
        self._active: tuple[np.ndarray, Any] | None = None
        """The runs not stopped, on the host and as the simulation's array."""
        self._steps = np.zeros(self.runs, dtype=int)
        """Each run's steps since its reset (the world's ``steps``, kept on the host)."""
        self._lo = xp.zeros(self.runs)
        """The lowest lateral position of each run's agent (0 on the ring)."""
        self._seen: tuple[World, Any] | None = None
        """The world :meth:`step` left and its observation (what ``reset([])`` returns while it is the world)."""

    saves_mid_episode = True
    """A checkpoint may be taken inside an episode (the whole world is arrays; :class:`~lanefree_sumo.rl.env_batch.
    EnvBatch` inside SUMO may not)."""

    def close(self) -> None:
        """Nothing to release: the world is arrays (the interface of :class:`~lanefree_sumo.rl.env_batch.EnvBatch`,
        whose runs inside SUMO end their simulations)."""

    def __getstate__(self) -> dict[str, Any]:
        """Pickled (a batch checkpoint holds its env) without the namespace, which its device name stands for."""
        return {name: value for name, value in self.__dict__.items() if name != "xp"}

    def __setstate__(self, saved: dict[str, Any]) -> None:
        """Unpickle (a batch checkpoint); one of the layout before :mod:`~lanefree_sumo.rl.problem` (its arrays
        and books as private attributes) is taken over as it was."""
        saved["device"] = device_name(saved["device"])
        saved["xp"] = array_namespace(saved["device"])
        if "state" not in saved:
            books = saved.pop("_books")
            zeros = saved["xp"].zeros(saved["runs"])
            arrays = {name: saved.pop(f"_{name}") for name in ProblemState.ARRAYS}
            saved["state"] = ProblemState(**arrays, books={name: books.get(name, zeros) for name in BOOKS})
            saved["terminate_on_collision"] = saved.pop("_terminate")
            for name in ("_w", "_ego_scale", "_neighbour_scale", "_once", "_net_passes", "_range"):
                saved.pop(name, None)
        self.__dict__.update(saved)
        if "problem" not in saved:
            self.problem = Problem(self.cfgs, self.xp)
        if "_lo" not in saved:
            self._lo = self.xp.zeros(self.runs)

    @property
    def steps(self) -> np.ndarray:
        """``[K]``: each run's steps since its episode began (a copy)."""
        return self._steps.copy()

    def count_step(self) -> None:
        """Count one step of every run taken outside :meth:`step` (the lockstep loop steps the world on the
        device)."""
        self._steps += 1

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
        if self.world is None and len(chosen) != self.runs:
            raise RuntimeError("the first reset starts every run")
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
            seen = getattr(self, "_seen", None)  # the last step's observation, while the world is that step's
            return seen[1] if seen is not None and seen[0] is self.world else self.problem.observe(self.state,
                                                                                                  self.view())
        index = self.xp.asarray(chosen, dtype=int)
        if self.world is None or len(chosen) == self.runs:
            self.world = world_to(world_of(states, [c.road.length_m for c in self.cfgs],
                                           [c.road.width_m for c in self.cfgs]), self.device)
        else:
            self.world = replace_runs(self.world, chosen, states)
        return self.problem.begin(self.state, self.view(), index)

    def episode_metrics(self, k: int, books: Mapping[str, np.ndarray] | None = None) -> dict[str, Any]:
        """Run k's episode metrics so far: the row :meth:`~lanefree_sumo.rl.env.LaneFreeEnv.episode_metrics` gives
        (``books``: the books on the host, :meth:`host_books`, when several runs are read at once)."""
        assert self.world is not None
        books = self.host_books() if books is None else books
        return episode_row(int(self.episode[k]), int(self._steps[k]), {name: books[name][k] for name in BOOKS},
                           self.cfgs[k], int(self.episode_seeds[k]), time.perf_counter() - self._t0[k])

    def host_books(self) -> dict[str, np.ndarray]:
        """Every run's episode books so far as host arrays (from the device: one copy)."""
        xp = self.xp
        if xp.is_numpy:
            return self.state.books
        stacked = xp.to_numpy(xp.stack([self.state.books[name] for name in BOOKS]))
        return dict(zip(BOOKS, stacked))

    # -- one step -----------------------------------------------------------------------------
    def accelerations(self, actions: Any) -> tuple[np.ndarray, np.ndarray]:
        """(ax, ay) ``[K]`` in m/s² for the runs' actions (specification §6, as
        :func:`~lanefree_sumo.rl.env.action_to_acceleration`), and ``[K]`` True where a run's action is not finite
        (its acceleration is then 0)."""
        cfg = self.cfg
        values = np.asarray(self.xp.to_numpy(actions), dtype=float)
        want = ((self.runs,), (self.runs, 1)) if cfg.action.kind == "discrete" else ((self.runs, 2),)
        if values.shape not in want:
            raise ValueError(f"step: actions of shape {' or '.join(str(w) for w in want)} expected (one row per run "
                             f"of the batch's {self.runs}), got shape {values.shape}")
        values = values.reshape(self.runs, -1)
        bad = ~np.isfinite(values).all(axis=1)
        values = np.where(bad[:, None], 0.0, values)  # action 0 of either kind: no acceleration
        if cfg.action.kind == "discrete":
            index = values[:, 0].astype(int)
            if (values[:, 0] != index).any() or (index < 0).any() or (index >= len(DISCRETE_ACTIONS)).any():
                raise ValueError(f"a discrete action is one whole number 0 … {len(DISCRETE_ACTIONS) - 1} per run, "
                                 f"got {actions!r}")
            signs = DISCRETE_ACTIONS[index]
            accel = np.column_stack([signs[:, 0] * cfg.action.discrete_ax_mps2,
                                     signs[:, 1] * cfg.action.discrete_ay_mps2])
        else:
            bounds = cfg.scenario.agent_bounds
            a = np.minimum(1.0, np.maximum(-1.0, values))
            accel = np.column_stack([np.where(a[:, 0] >= 0.0, a[:, 0] * bounds.ax_max, -a[:, 0] * bounds.ax_min),
                                     a[:, 1] * bounds.ay_max])
        return accel, bad

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
        a = xp.minimum(1.0, xp.maximum(-1.0, xp.where(bad[:, None], 0.0, values)))  # 0: no acceleration
        bounds = cfg.scenario.agent_bounds
        accel = xp.column_stack([xp.where(a[:, 0] >= 0.0, a[:, 0] * bounds.ax_max, -a[:, 0] * bounds.ax_min),
                                 a[:, 1] * bounds.ay_max])
        return accel[:, None, :], bad

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
        if self.terminate_on_collision.any():  # the one value read from the device every step, where it counts
            terminated = active_host & self.terminate_on_collision & xp.to_numpy(collided)
        else:
            terminated = np.zeros(self.runs, dtype=bool)
        truncated = active_host & (self._steps >= self.cfg.sim.episode_steps)
        ended = np.flatnonzero(terminated | truncated)
        books = self.host_books() if len(ended) else {}
        metrics: list[dict[str, Any] | None] = [None] * self.runs
        for k in ended:
            metrics[k] = self.episode_metrics(int(k), books)
        self._seen = (self.world, obs)
        info = {**terms.as_dict(),
                "overtakes": overtakes, "collision_events": agent_events, "boundary_contact": contact,
                "ax": accel[:, 0], "ay": accel[:, 1], "episode_metrics": metrics, "stopped": stopped_now}
        return obs, reward, terminated, truncated, info

    def view(self) -> AgentView:
        """Each run's scene around its agent (:class:`~lanefree_sumo.rl.problem.AgentView`) in the current world."""
        xp, world = self.xp, self.world
        assert world is not None
        agent = world.agent_rows[:, 0]
        runs = xp.arange(self.runs)
        return AgentView.of(xp, world.dx[runs, agent], world.dy[runs, agent], world.vx, world.vy, world.length,
                            world.width, world.v_desired, world.y, world.present, agent, self._lo, world.road_width,
                            world.road_length)

    def _advance(self, accel: Any, active: Any) -> tuple[Any, Any, Rewards, Any, Any, Any, Any]:
        """The array part of a step, on the simulation's device with no host read: the world advanced with the
        agents' accelerations ``accel`` ``[K, 1, 2]`` (m/s²), the observation, the reward terms and the books of the
        ``active`` runs (``[K]`` bool); returns (the observation, the reward — 0 where not active —, the reward terms,
        overtakes, the agent's collision events, its boundary contact, whether it overlaps another vehicle), each
        ``[K]`` but the observation."""
        xp = self.xp
        assert self.world is not None
        self.world, out = step_world(self.world, self.params, accel)
        agent = self.world.agent_rows[:, 0]
        runs = xp.arange(self.runs)
        collided = xp.any(out.overlap[runs, agent], axis=1)
        new = out.new_collisions
        agent_events = xp.sum(new[runs, agent], axis=1) + xp.sum(new[runs, :, agent], axis=1)
        background_only = xp.sum(new, axis=(1, 2)) - agent_events
        contact = out.boundary_contact[runs, agent]
        obs, reward, terms, overtakes = self.problem.step(self.state, self.view(), collided, agent_events,
                                                          background_only, contact, active)
        return obs, xp.where(active, reward, 0.0), terms, overtakes, agent_events, contact, collided
