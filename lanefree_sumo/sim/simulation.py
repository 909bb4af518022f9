"""The simulation core: spawn, driver forces, dynamics, a backend that executes, collisions.

Each step the state is read from the backend, the force model computes the background
vehicles' accelerations from it (the agent's come from outside), the dynamics turn them into
commands, the backend executes them, and collisions are counted on the new state.

Backends: ``libsumo`` (default) and ``traci`` execute in SUMO (:mod:`.sumo_backend`);
``numpy`` executes the same dynamics with no SUMO at all — the reference and the fast path.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from lanefree_sumo.sim.collisions import CollisionTracker, overlap_matrix
from lanefree_sumo.config import AccelerationBounds, ConfigError, LaneFreeConfig
from lanefree_sumo.sim.dynamics import StepCommand, ballistic_distance, plan_step
from lanefree_sumo.sim.network import EDGES
from lanefree_sumo.sim.forces import driver_accelerations
from lanefree_sumo.sim.spawn import spawn
from lanefree_sumo.sim.state import VehicleState, pairwise_offsets

BACKENDS = ("libsumo", "traci", "numpy")


class Backend(Protocol):
    """Executes steps; positions and speeds are always read back from it."""

    def reset(self, state: VehicleState) -> None: ...

    def step(self, cmd: StepCommand) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def close(self) -> None: ...


class NumpyBackend:
    """SUMO-free execution of the same commands.

    Positions are kept the way SUMO keeps them — edge index plus position on the edge, lateral
    offset from the lane centre — and updated with the same arithmetic (ballistic distance,
    edge hand-over, small lateral moves set rather than driven), so that both backends produce
    bit-identical trajectories from the same commands.
    """

    def __init__(self, cfg: LaneFreeConfig) -> None:
        self._segment = cfg.road.length_m / EDGES
        self._step = cfg.sim.step_s
        self._half_width = 0.5 * cfg.road.width_m
        self._min_lateral_move = cfg.sim.sumo_min_lateral_speed_mps * cfg.sim.step_s
        self._edge = np.zeros(0, dtype=int)
        self._pos = self._pos_lat = self._vx = self._y = np.zeros(0)

    def reset(self, state: VehicleState) -> None:
        self._edge = np.minimum((state.x // self._segment).astype(int), EDGES - 1)
        self._pos = state.x - self._edge * self._segment
        self._pos_lat = state.y - self._half_width
        self._vx = state.vx.copy()
        self._y = state.y.copy()

    def step(self, cmd: StepCommand) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        pos = self._pos + ballistic_distance(self._vx, cmd.vx_next, self._step)
        passed = pos > self._segment
        self._pos = np.where(passed, pos - self._segment, pos)
        self._edge = np.where(passed, (self._edge + 1) % EDGES, self._edge)
        tiny = np.abs(cmd.dy) < self._min_lateral_move
        moved = np.where(tiny, (self._y + cmd.dy) - self._half_width, self._pos_lat + cmd.dy)
        self._pos_lat = np.where(cmd.dy == 0.0, self._pos_lat, moved)
        self._vx = cmd.vx_next.copy()
        x = self._edge * self._segment + self._pos
        self._y = self._pos_lat + self._half_width
        return x, self._y.copy(), self._vx.copy()

    def close(self) -> None:
        pass


def make_backend(cfg: LaneFreeConfig) -> Backend:
    """The backend named by ``cfg.backend`` (``cfg.gui`` implies TraCI)."""
    if cfg.backend not in BACKENDS:
        raise ConfigError(f"unknown backend '{cfg.backend}'; choose one of {', '.join(BACKENDS)}")
    if cfg.backend == "numpy":
        if cfg.gui:
            raise ConfigError("the numpy backend has no GUI; use --backend traci (or libsumo) with --gui")
        return NumpyBackend(cfg)
    from lanefree_sumo.sim.backends.sumo import SumoBackend  # noqa: PLC0415 - SUMO only when asked for

    return SumoBackend(cfg, kind=cfg.backend, gui=cfg.gui)


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


def clip_acceleration(
    ax: float, ay: float, bounds: AccelerationBounds, vx: float, max_speed: float, step_s: float
) -> tuple[float, float]:
    """Clip an agent's acceleration (m/s²) to its bounds and so that its speed vx (m/s) does
    not exceed ``max_speed`` (m/s) at the end of the step."""
    ax_top = min(bounds.ax_max, (max_speed - vx) / step_s)
    return (
        float(min(max(ax, bounds.ax_min), ax_top)),
        float(np.clip(ay, bounds.ay_min, bounds.ay_max)),
    )


class Simulation:
    """Background traffic (and optionally one externally controlled agent) on the ring.

    The backend (and so SUMO) starts at the first ``reset``, not at construction, and
    ``close`` stops it; a later ``reset`` starts a new one."""

    def __init__(self, cfg: LaneFreeConfig, backend: Backend | None = None) -> None:
        self.cfg = cfg
        self.backend: Backend | None = backend
        self.state: VehicleState | None = None
        self.last_result: StepResult | None = None
        """What happened in the latest step (for recorders)."""
        self.offsets: tuple[np.ndarray, np.ndarray] | None = None
        """(dx, dy) matrices of the current state, shared by collisions, forces, observations."""
        self.steps = 0
        self.backend_seconds = 0.0
        """Wall time spent inside ``backend.step`` (s), for profiling."""
        self._tracker = CollisionTracker(0)

    def reset(self, seed: int | None = None) -> VehicleState:
        """Spawn a new random traffic state (reproducible for a seed) and place it."""
        rng = np.random.default_rng(self.cfg.seed if seed is None else seed)
        state = spawn(self.cfg, rng)
        if self.backend is None:
            self.backend = make_backend(self.cfg)
        self.backend.reset(state)
        self.state = state
        self.steps = 0
        self._tracker.reset(state.n)
        self.offsets = pairwise_offsets(state, self.cfg.road.length_m)
        self._tracker.update(overlap_matrix(state, self.cfg.road.length_m, self.offsets))
        return state

    def step(self, agent_accel: tuple[float, float] | None = None) -> StepResult:
        """Advance one step. ``agent_accel`` = (ax, ay) in m/s² for the agent, clipped to its
        bounds; required when the scenario has an agent."""
        state = self.state
        if state is None or self.backend is None:
            raise RuntimeError("call reset() before step()")
        cfg = self.cfg
        ax, ay = driver_accelerations(
            state, cfg.scenario.driver, cfg.road.length_m, cfg.road.width_m, cfg.sim.step_s,
            cfg.sim.edge_clearance_m, self.offsets,
        )
        if not state.controlled.all():
            if agent_accel is None:
                raise ValueError("this scenario has an agent: pass agent_accel=(ax, ay)")
            agent = np.flatnonzero(~state.controlled)[0]
            ax[agent], ay[agent] = clip_acceleration(
                *agent_accel, cfg.scenario.agent_bounds, float(state.vx[agent]), cfg.scenario.agent_max_speed_mps,
                cfg.sim.step_s,
            )
        cmd = plan_step(
            state.x, state.y, state.vx, state.vy, state.width, ax, ay,
            cfg.sim.step_s, cfg.road.width_m, cfg.sim.edge_clearance_m, cfg.sim.edge_contact_tolerance_m,
        )
        t0 = time.perf_counter()
        state.x, state.y, state.vx = self.backend.step(cmd)
        self.backend_seconds += time.perf_counter() - t0
        state.vy = cmd.vy_next
        self.steps += 1
        self.offsets = pairwise_offsets(state, cfg.road.length_m)
        overlap = overlap_matrix(state, cfg.road.length_m, self.offsets)
        new = self._tracker.update(overlap)
        self.last_result = StepResult(cmd.ax, cmd.ay, cmd.boundary_contact, overlap, new)
        return self.last_result

    def close(self) -> None:
        """Stop the backend (idempotent)."""
        if self.backend is not None:
            self.backend.close()
            self.backend = None
