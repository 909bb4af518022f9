"""The simulation core: spawn, driver forces, dynamics, a backend that executes, collisions.

Each step the state is read from the backend, the force model computes the background
vehicles' accelerations from it (the agent's come from outside), the dynamics turn them into
commands, the backend executes them, and collisions are counted on the new state.

Backends: ``libsumo`` (default) and ``traci`` execute in SUMO (:mod:`.backends.sumo`);
``numpy`` executes the same dynamics with no SUMO at all — the reference and the fast path. On the ring the
``numpy`` simulation is the batched core (:mod:`.world`) with one run; on the open road it keeps its own path
(:class:`~lanefree_sumo.sim.backends.numpy.OpenRoadNumpyBackend`).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from tqdm import tqdm

from lanefree_sumo.config import ConfigError, LaneFreeConfig, ResolvedConfig, validate_config
from lanefree_sumo.sim.backends.numpy import Backend, OpenRoadNumpyBackend
from lanefree_sumo.sim.collisions import CollisionTracker, overlap_matrix
from lanefree_sumo.sim.dynamics import ballistic_distance, clip_acceleration, plan_step
from lanefree_sumo.sim.forces import driver_accelerations
from lanefree_sumo.sim.open_road import OpenRoadTraffic, append_rows, keep_rows
from lanefree_sumo.sim.road import Road, road_kind, road_of
from lanefree_sumo.sim.spawn import spawn, without_agents
from lanefree_sumo.sim.state import VehicleState, pairwise_offsets
from lanefree_sumo.sim.world import World, WorldParams, step_world, world_of


def make_backend(cfg: LaneFreeConfig) -> Backend | None:
    """The backend named by ``cfg.backend`` (``cfg.gui`` implies TraCI); None for the ring on ``numpy``, which
    the batched core executes (:mod:`.world`). A config not resolved (:class:`~lanefree_sumo.config.ResolvedConfig`)
    is validated first."""
    if not isinstance(cfg, ResolvedConfig):
        validate_config(cfg)
    if cfg.backend == "numpy":
        if cfg.gui:
            raise ConfigError("the numpy backend has no GUI; use --backend traci (or libsumo) with --gui")
        if cfg.net_file:
            raise ConfigError(f"the numpy backend uses no SUMO network (net_file {cfg.net_file}); drop it, or use "
                              "--backend libsumo (or traci)")
        return None if road_kind(cfg).batched_world else OpenRoadNumpyBackend(cfg)
    from lanefree_sumo.sim.backends.sumo import sumo_backend

    return sumo_backend(cfg)(cfg, kind=cfg.backend, gui=cfg.gui)


@dataclass
class StepResult:
    """What happened in one step."""

    ax: np.ndarray
    """Realised longitudinal acceleration of each vehicle (m/s²)."""
    ay: np.ndarray
    """Realised lateral acceleration of each vehicle (m/s²)."""
    boundary_contact: np.ndarray
    """True where a lateral move was clipped at a road edge."""
    overlap: np.ndarray
    """Pairwise overlap matrix after the step."""
    new_collisions: np.ndarray
    """(k, 2) index pairs (i < j) whose overlap started this step."""
    entered: VehicleState | None = None
    """Open road: the vehicles that entered at the start of this step, as they were placed (before they
    moved in it; their rows are also the last rows of the state after the step); None when none did."""
    departed: Departure | None = None
    """Open road: the vehicles taken off the road after this step (:meth:`Simulation.remove`, e.g. learning
    vehicles whose episode ended), with their state and values of this step; the fields above then
    describe the remaining rows only. None when none were."""


@dataclass
class Departure:
    """Vehicles taken off the road right after a step: their state after it and what happened to them in it."""

    state: VehicleState
    ax: np.ndarray
    ay: np.ndarray
    overlapping: np.ndarray
    """True where the vehicle's body overlapped another's after the step."""


class Simulation:
    """Background traffic (and optionally externally controlled agents) on the road (:mod:`.road`).

    The backend (and so SUMO) starts at the first ``reset``, not at construction, and
    ``close`` stops it; a later ``reset`` starts a new one. On an open road (the on-ramp) vehicles
    enter and leave (:mod:`.open_road`): at the start of each step the vehicles past the end are
    removed and the arrivals that fit are appended (and move in that step), so the state's rows change
    between steps; ``last_result`` refers to the rows of the state after the step it describes."""

    def __init__(self, cfg: LaneFreeConfig, backend: Backend | None = None, diagnostics: bool = False) -> None:
        """``diagnostics``: keep the driver model's per-vehicle details of each step in
        ``force_details`` (see :func:`~lanefree_sumo.sim.forces.driver_accelerations`)."""
        self.cfg = cfg
        self.force_details: dict[str, np.ndarray] | None = {} if diagnostics else None
        self.backend: Backend | None = backend
        self.world: World | None = None
        """The ring on ``numpy``: the batched core's world with this one run (None with a backend)."""
        self._world_params: WorldParams | None = None
        self.state: VehicleState | None = None
        self.last_result: StepResult | None = None
        """What happened in the latest step (for recorders)."""
        self.offsets: tuple[np.ndarray, np.ndarray] | None = None
        """(dx, dy) matrices of the current state, shared by collisions, forces, observations."""
        self.steps = 0
        self.backend_seconds = 0.0
        """Wall time spent inside ``backend.step`` (s), for profiling (0 for the ring on ``numpy``: no backend)."""
        self._tracker = CollisionTracker(0)
        self.road: Road = road_of(cfg)
        self._wrap = self.road.wrap_length
        self.traffic = None if self.road.periodic else OpenRoadTraffic(cfg, self.road)
        """Arrivals, removal and merging on an open road (None on the ring)."""
        self.on_ramp = np.zeros(0, dtype=bool)
        """True for the ramp vehicles not merged yet (one per row; all False on the ring)."""

    def reset(self, seed: int | None = None) -> VehicleState:
        """Spawn a new random traffic state (reproducible for a seed) and place it."""
        seed = self.cfg.seed if seed is None else seed
        rng = np.random.default_rng(seed)
        if self.traffic is None:
            return self.place(spawn(self.cfg, rng))
        self.traffic.reset(seed)
        background = spawn(without_agents(self.cfg), rng)
        if not self.cfg.scenario.with_agent:
            return self.place(background)
        agents, on_ramp = self.traffic.agent_start(background)
        state = self.place(append_rows(background, agents))
        self.on_ramp[background.n:] = on_ramp
        return state

    def remove(self, ids: list[str]) -> None:
        """Take the vehicles ``ids`` off an open road now (a learning vehicle whose episode ended there)."""
        state, backend = self.state, self.backend
        if state is None or backend is None or not ids:
            return
        keep = np.array([vid not in ids for vid in state.ids])
        if self.last_result is not None and len(self.last_result.ax) == state.n:
            self.last_result = _without(self.last_result, keep, state)
        self.state = state = keep_rows(state, keep)
        backend.remove(keep)  # type: ignore[attr-defined]
        self.on_ramp = self.on_ramp[keep]
        self._tracker.keep(keep)
        self.offsets = pairwise_offsets(state, self._wrap)

    def place(self, state: VehicleState) -> VehicleState:
        """Start an episode from ``state`` as given (the vehicles at its positions and speeds); ``reset``
        places a spawned state, tests and scenarios may place their own."""
        if self.backend is None:
            self.backend = make_backend(self.cfg)
        if self.backend is None:
            self.world = world_of([state], [self.cfg.road.length_m], [self.cfg.road.width_m])
            self._world_params = WorldParams.of([self.cfg])
        else:
            self.backend.reset(state)
        self.state = state
        self.steps = 0
        self.on_ramp = np.zeros(state.n, dtype=bool)
        self._tracker.reset(state.n)
        self.offsets = pairwise_offsets(state, self._wrap)
        self._tracker.update(overlap_matrix(state, self._wrap, self.offsets))
        return state

    def _leave_and_enter(self) -> VehicleState | None:
        """Open road, before a step: remove the vehicles past the end and append the arrivals that fit, in
        the state, the backend and the books; the new vehicles take part in the step. Returns them as
        placed (None when none entered)."""
        state, backend, traffic = self.state, self.backend, self.traffic
        assert state is not None and backend is not None and traffic is not None
        leaving = traffic.leaving(state) & state.controlled  # an agent's episode ends when it leaves
        if leaving.any():
            keep = ~leaving
            traffic.counts.left += int(leaving.sum())
            state = keep_rows(state, keep)
            backend.remove(keep)  # type: ignore[attr-defined]
            self.on_ramp = self.on_ramp[keep]
            self._tracker.keep(keep)
        rows, ramp = traffic.arrivals(state)
        if rows.n:
            state = append_rows(state, rows)
            backend.add(rows)  # type: ignore[attr-defined]
            self.on_ramp = np.concatenate([self.on_ramp, ramp])
            self._tracker.add(rows.n)
        if state is not self.state:
            self.state = state
            self.offsets = pairwise_offsets(state, self._wrap)
        return rows if rows.n else None

    def current(self) -> tuple[VehicleState, tuple[np.ndarray, np.ndarray]]:
        """The current state and its (dx, dy) offset matrices (m); RuntimeError before ``reset``."""
        if self.state is None or self.offsets is None:
            raise RuntimeError("call reset() before reading the state")
        return self.state, self.offsets

    def step(self, agent_accel: tuple[float, float] | np.ndarray | None = None) -> StepResult:
        """Advance one step. ``agent_accel`` = (ax, ay) in m/s² for the agent — with several agents
        one row (ax, ay) per agent, in the order of their rows in the state — each clipped to its
        bounds; required when the scenario has agents."""
        if self.state is None or (self.backend is None and self.world is None):
            raise RuntimeError("call reset() before step()")
        if self.world is not None:
            return self._step_world(agent_accel)
        assert self.backend is not None
        entered = self._leave_and_enter() if self.traffic is not None else None
        state = self.state
        cfg = self.cfg
        commands = self._agent_commands(state, agent_accel)
        bounds = self.road.bounds(state.x + 0.5 * state.length, self.on_ramp)  # at the front
        ax, ay = driver_accelerations(
            state, cfg.scenario.driver, self._wrap, cfg.road.width_m, cfg.sim.step_s,
            cfg.sim.edge_clearance_m, self.offsets, self.force_details, bounds=bounds,
            lateral_target=0.0 if self.traffic is None else self.traffic.lateral_target(state, self.on_ramp),
        )
        for agent, (agent_ax, agent_ay) in zip(np.flatnonzero(~state.controlled), commands):
            ax[agent], ay[agent] = clip_acceleration(
                float(agent_ax), float(agent_ay), cfg.scenario.agent_bounds, float(state.vx[agent]),
                cfg.scenario.agent_max_speed_mps, cfg.sim.step_s, float(state.vy[agent]),
                cfg.scenario.agent_lateral_speed_ratio,
            )
        if self.traffic is not None:
            ax = self.traffic.end_wall(state, self.on_ramp, ax)  # the ramp's lane ends: for agents too
            # the dynamics clip at the boundaries where each front will be
            front = state.x + 0.5 * state.length
            travel = ballistic_distance(state.vx, np.maximum(state.vx + ax * cfg.sim.step_s, 0.0), cfg.sim.step_s)
            bounds = self.road.bounds(front + travel, self.on_ramp)
        cmd = plan_step(
            state.x, state.y, state.vx, state.vy, state.width, ax, ay,
            cfg.sim.step_s, cfg.road.width_m, cfg.sim.edge_clearance_m, cfg.sim.edge_contact_tolerance_m,
            bounds=bounds,
        )
        t0 = time.perf_counter()
        state.x, state.y, state.vx = self.backend.step(cmd)
        self.backend_seconds += time.perf_counter() - t0
        state.vy = cmd.vy_next
        self.steps += 1
        self.offsets = pairwise_offsets(state, self._wrap)
        overlap = overlap_matrix(state, self._wrap, self.offsets)
        if self.traffic is not None:
            self.on_ramp = self.traffic.merge(state, self.on_ramp)
        new = self._tracker.update(overlap)
        self.last_result = StepResult(cmd.ax, cmd.ay, cmd.boundary_contact, overlap, new, entered)
        return self.last_result

    @staticmethod
    def _agent_commands(state: VehicleState, agent_accel: tuple[float, float] | np.ndarray | None) -> np.ndarray:
        """The agents' (ax, ay) rows (m/s²), one per agent in row order; ValueError when they do not match."""
        agents = int(np.count_nonzero(~state.controlled))
        if not agents:
            return np.zeros((0, 2))
        if agent_accel is None:
            raise ValueError("this scenario has an agent: pass agent_accel=(ax, ay)")
        commands = np.asarray(agent_accel, dtype=float).reshape(-1, 2)
        if len(commands) != agents:
            raise ValueError(f"this scenario has {agents} agents: pass one (ax, ay) row each, got {len(commands)}")
        return commands

    def _step_world(self, agent_accel: tuple[float, float] | np.ndarray | None) -> StepResult:
        """One step of the ring on ``numpy``: the batched core with this one run."""
        state, world = self.state, self.world
        assert state is not None and world is not None
        commands = self._agent_commands(state, agent_accel)
        details: dict[str, np.ndarray] | None = None if self.force_details is None else {}
        assert self._world_params is not None
        self.world, out = step_world(world, self._world_params, commands[None], details)
        world = self.world
        state.x, state.y, state.vx, state.vy = world.x[0], world.y[0], world.vx[0], world.vy[0]
        if self.force_details is not None and details is not None:
            self.force_details.update({k: v[0] for k, v in details.items()})
        self.steps += 1
        self.offsets = (world.dx[0], world.dy[0])
        self.last_result = StepResult(out.ax[0], out.ay[0], out.boundary_contact[0], out.overlap[0],
                                      np.argwhere(out.new_collisions[0]))
        return self.last_result

    def close(self) -> None:
        """Stop the backend (idempotent)."""
        self.world = None
        if self.backend is not None:
            self.backend.close()
            self.backend = None


def _without(result: StepResult, keep: np.ndarray, state: VehicleState) -> StepResult:
    """``result`` for the rows where ``keep`` is True, the others (rows of ``state``) as its departure."""
    gone = ~keep
    new_index = np.cumsum(keep) - 1
    pairs = result.new_collisions
    pairs = new_index[pairs[keep[pairs].all(axis=1)]] if len(pairs) else pairs
    departed = Departure(keep_rows(state, gone), result.ax[gone], result.ay[gone], result.overlap[gone].any(axis=1))
    return StepResult(result.ax[keep], result.ay[keep], result.boundary_contact[keep],
                      result.overlap[np.ix_(keep, keep)], pairs, result.entered, departed)


def run_simulation(
    cfg: LaneFreeConfig,
    steps: int,
    on_step: Callable[[int, VehicleState, StepResult], None] | None = None,
    progress: bool = False,
    sim: Simulation | None = None,
) -> dict[str, Any]:
    """Run background traffic for ``steps`` and return its summary (speeds in m/s, margins in m).

    ``on_step(step, state, result)`` is called after every step (e.g. a trajectory writer).
    ``sim``: a prepared :class:`Simulation` of ``cfg`` (e.g. with diagnostics), else a new one.
    Ctrl-C stops early and returns what was simulated, with ``interrupted`` set."""
    sim = sim or Simulation(cfg)
    t0 = time.perf_counter()
    state = sim.reset(cfg.seed)
    n = state.n

    def smallest_margin(state: VehicleState) -> float:
        """The smallest lateral distance of a body to its boundaries now (m)."""
        if not state.n:
            return float("inf")
        lo, hi = sim.road.bounds(state.x + 0.5 * state.length, sim.on_ramp)
        return float(np.min(np.minimum(state.y - 0.5 * state.width - lo, hi - state.y - 0.5 * state.width)))

    collisions = boundary_contacts = done = 0
    speed_sum = 0.0
    min_margin = smallest_margin(state)
    interrupted = False
    try:
        for k in tqdm(range(steps), disable=not progress or not sys.stderr.isatty(), unit="step", desc="simulate"):
            result = sim.step()
            state = sim.current()[0]
            done = k + 1
            collisions += len(result.new_collisions)
            boundary_contacts += int(result.boundary_contact.sum())
            speed_sum += float(state.vx.mean()) if state.n else 0.0
            min_margin = min(min_margin, smallest_margin(state))
            if on_step is not None:
                on_step(done, state, result)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        sim.close()
    wall = time.perf_counter() - t0
    return {
        "steps": done,
        "vehicles": n,
        "density_veh_per_km": cfg.scenario.density_veh_per_km,
        "seed": cfg.seed,
        "backend": cfg.backend,
        "nudging": cfg.scenario.driver.nudging,
        "background_collisions": collisions,
        "boundary_contacts": boundary_contacts,
        "mean_speed_mps": speed_sum / done if done else float("nan"),
        "mean_desired_speed_mps": float(state.v_desired.mean()) if state.n else float("nan"),
        "min_lateral_margin_m": min_margin,
        "wall_s": wall,
        "steps_per_s": done / wall if wall > 0 else float("nan"),
        "interrupted": interrupted,
        **({} if sim.traffic is None else {"onramp": _flow_summary(sim, state, done)}),
    }


def _flow_summary(sim: Simulation, state: VehicleState, steps: int) -> dict[str, Any]:
    """The open road's books: what entered, left, merged and waits, in vehicles and veh/h."""
    assert sim.traffic is not None
    c = sim.traffic.counts
    hours = steps * sim.cfg.sim.step_s / 3600.0
    return {
        "started_on_road": sim.cfg.background_vehicles,
        "entered_main": c.entered_main, "entered_ramp": c.entered_ramp, "left": c.left, "on_road": state.n,
        "merged": c.merged, "ramp_on_road_unmerged": int(sim.on_ramp.sum()),
        "ramp_end_reached_unmerged": c.ramp_end_reached, "waiting_main": c.waiting[0], "waiting_ramp": c.waiting[1],
        "inflow_veh_per_h": (c.entered_main + c.entered_ramp) / hours if hours else float("nan"),
        "outflow_veh_per_h": c.left / hours if hours else float("nan"),
    }
