"""The simulation core: spawn, driver forces, dynamics, a backend that executes, collisions.

Each step the state is read from the backend, the force model computes the background
vehicles' accelerations from it (the agent's come from outside), the dynamics turn them into
commands, the backend executes them, and collisions are counted on the new state.

Backends: ``libsumo`` (default) and ``traci`` execute in SUMO (:mod:`.backends.sumo`);
``numpy`` executes the same dynamics with no SUMO at all — the reference and the fast path.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from tqdm import tqdm

from lanefree_sumo.config import AccelerationBounds, ConfigError, LaneFreeConfig, validate_config
from lanefree_sumo.sim.backends.numpy import Backend, NumpyBackend
from lanefree_sumo.sim.collisions import CollisionTracker, overlap_matrix
from lanefree_sumo.sim.dynamics import plan_step
from lanefree_sumo.sim.forces import driver_accelerations
from lanefree_sumo.sim.spawn import spawn
from lanefree_sumo.sim.state import VehicleState, pairwise_offsets


def make_backend(cfg: LaneFreeConfig) -> Backend:
    """The backend named by ``cfg.backend`` (``cfg.gui`` implies TraCI)."""
    validate_config(cfg)
    if cfg.backend == "numpy":
        if cfg.gui:
            raise ConfigError("the numpy backend has no GUI; use --backend traci (or libsumo) with --gui")
        return NumpyBackend(cfg)
    from lanefree_sumo.sim.backends.sumo import SumoBackend

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
    """Background traffic (and optionally externally controlled agents) on the ring.

    The backend (and so SUMO) starts at the first ``reset``, not at construction, and
    ``close`` stops it; a later ``reset`` starts a new one."""

    def __init__(self, cfg: LaneFreeConfig, backend: Backend | None = None, diagnostics: bool = False) -> None:
        """``diagnostics``: keep the driver model's per-vehicle details of each step in
        ``force_details`` (see :func:`~lanefree_sumo.sim.forces.driver_accelerations`)."""
        self.cfg = cfg
        self.force_details: dict[str, np.ndarray] | None = {} if diagnostics else None
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
        return self.place(spawn(self.cfg, rng))

    def place(self, state: VehicleState) -> VehicleState:
        """Start an episode from ``state`` as given (the vehicles at its positions and speeds); ``reset``
        places a spawned state, tests and scenarios may place their own."""
        if self.backend is None:
            self.backend = make_backend(self.cfg)
        self.backend.reset(state)
        self.state = state
        self.steps = 0
        self._tracker.reset(state.n)
        self.offsets = pairwise_offsets(state, self.cfg.road.length_m)
        self._tracker.update(overlap_matrix(state, self.cfg.road.length_m, self.offsets))
        return state

    def current(self) -> tuple[VehicleState, tuple[np.ndarray, np.ndarray]]:
        """The current state and its (dx, dy) offset matrices (m); RuntimeError before ``reset``."""
        if self.state is None or self.offsets is None:
            raise RuntimeError("call reset() before reading the state")
        return self.state, self.offsets

    def step(self, agent_accel: tuple[float, float] | np.ndarray | None = None) -> StepResult:
        """Advance one step. ``agent_accel`` = (ax, ay) in m/s² for the agent — with several agents
        one row (ax, ay) per agent, in the order of their rows in the state — each clipped to its
        bounds; required when the scenario has agents."""
        state = self.state
        if state is None or self.backend is None:
            raise RuntimeError("call reset() before step()")
        cfg = self.cfg
        ax, ay = driver_accelerations(
            state, cfg.scenario.driver, cfg.road.length_m, cfg.road.width_m, cfg.sim.step_s,
            cfg.sim.edge_clearance_m, self.offsets, self.force_details,
        )
        if not state.controlled.all():
            agents = np.flatnonzero(~state.controlled)
            if agent_accel is None:
                raise ValueError("this scenario has an agent: pass agent_accel=(ax, ay)")
            commands = np.asarray(agent_accel, dtype=float).reshape(-1, 2)
            if len(commands) != len(agents):
                raise ValueError(f"this scenario has {len(agents)} agents: pass one (ax, ay) row each, "
                                 f"got {len(commands)}")
            for agent, (agent_ax, agent_ay) in zip(agents, commands):
                ax[agent], ay[agent] = clip_acceleration(
                    float(agent_ax), float(agent_ay), cfg.scenario.agent_bounds, float(state.vx[agent]),
                    cfg.scenario.agent_max_speed_mps, cfg.sim.step_s,
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
    width = cfg.road.width_m
    collisions = boundary_contacts = done = 0
    speed_sum = 0.0
    min_margin = float(np.min(np.minimum(state.y - 0.5 * state.width, width - state.y - 0.5 * state.width)))
    interrupted = False
    try:
        for k in tqdm(range(steps), disable=not progress or not sys.stderr.isatty(), unit="step", desc="simulate"):
            result = sim.step()
            done = k + 1
            collisions += len(result.new_collisions)
            boundary_contacts += int(result.boundary_contact.sum())
            speed_sum += float(state.vx.mean())
            margin = np.minimum(state.y - 0.5 * state.width, width - state.y - 0.5 * state.width)
            min_margin = min(min_margin, float(margin.min()))
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
        "mean_desired_speed_mps": float(state.v_desired.mean()),
        "min_lateral_margin_m": min_margin,
        "wall_s": wall,
        "steps_per_s": done / wall if wall > 0 else float("nan"),
        "interrupted": interrupted,
    }
