"""Many runs of the ring in one set of arrays: the simulation core over a leading run axis K.

A :class:`World` holds K rings as arrays ``[K, N]`` (one row per vehicle; runs with fewer vehicles are padded
to the batch's N and masked by ``present``) and per-run scalars ``[K]``. :func:`step_world` advances every run
by one step with the same physics as one simulation — :mod:`.forces` for the background rows, the agents'
commands clipped as :func:`~lanefree_sumo.sim.dynamics.clip_accelerations` does, :mod:`.dynamics`, the road
edges, the ring's wrap, :mod:`.collisions` — these modules computing over ``[..., N]``: one copy of the physics.
Positions are kept the way SUMO keeps them (edge index, position on the edge, lateral offset from the lane
centre) and advanced with SUMO's arithmetic, so that a run gives bit for bit what SUMO gives from the same
commands. The ring's :class:`~lanefree_sumo.sim.simulation.Simulation` on the ``numpy`` backend is a world
with K = 1; a run of a batch gives, bit for bit, what that simulation gives alone with the same seed
(padding included: sums over neighbours round as they would without it, :func:`~lanefree_sumo.sim.state.row_sum`).

The step is written once against an array namespace (:mod:`.xp`): on numpy arrays it runs as numpy, on torch
tensors (:func:`world_to`) as torch on their device, float64 either way — no loop over vehicles and no branch
on the state's values except result-preserving shortcuts taken on numpy. The open road (the on-ramp), whose
vehicles come and go, keeps its own path in :class:`~lanefree_sumo.sim.simulation.Simulation`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from lanefree_sumo.config import AccelerationBounds, ConfigError, DriverConfig, LaneFreeConfig
from lanefree_sumo.sim.collisions import overlap_matrix, started_overlaps
from lanefree_sumo.sim.dynamics import ballistic_distance, clip_accelerations, plan_step
from lanefree_sumo.sim.forces import driver_accelerations
from lanefree_sumo.sim.network import EDGES, edge_length, edge_to_ring, ring_to_edge
from lanefree_sumo.sim.road import road_kind
from lanefree_sumo.sim.spawn import spawn
from lanefree_sumo.sim.state import VehicleState, pairwise_offsets, take_rows
from lanefree_sumo.sim.xp import array_namespace, namespace

PER_RUN_LIMITS = ("agent_max_speed_mps", "agent_lateral_ratio", "agent_lateral_bounded")
"""The :class:`WorldParams` the runs of one batch may differ in (then arrays ``[K, 1]``, one row per run)."""


@dataclass(frozen=True)
class WorldParams:
    """The physics' parameters of a batch (SI units): the driver model, the step and the agents' acceleration
    bounds, which every run shares, and the agents' top speed and lateral bound, which may differ per run."""

    driver: DriverConfig
    step_s: float
    clearance_m: float
    """The dynamics clip bodies this far inside the road edges (m)."""
    contact_tolerance_m: float
    agent_bounds: AccelerationBounds
    agent_max_speed_mps: Any
    """The agents' top speed (m/s): one number, or ``[K, 1]`` where the runs differ."""
    agent_lateral_ratio: Any
    """The agents' |vy| ≤ r·vx bound: r, None (no bound), or ``[K, 1]`` where the runs differ."""
    min_lateral_move_m: float
    """Lateral moves shorter than this are set rather than driven, as SUMO does (m)."""
    agent_lateral_bounded: Any = None
    """Where some runs have a lateral bound and some none: ``[K, 1]`` True for the bounded runs (their r in
    :attr:`agent_lateral_ratio`, 0 for the others); else None."""

    @classmethod
    def of(cls, cfgs: Sequence[LaneFreeConfig]) -> WorldParams:
        """The parameters of the runs ``cfgs``; ConfigError when two runs differ in a shared one."""
        made = [cls._of(cfg) for cfg in cfgs]
        if not made:
            raise ConfigError("a batch needs at least one run")
        differ = [f.name for f in fields(cls) if f.name not in PER_RUN_LIMITS
                  and any(getattr(p, f.name) != getattr(made[0], f.name) for p in made)]
        if differ:
            raise ConfigError(f"the runs of one batch must share the driver model, the step and the agents' "
                              f"acceleration bounds; these differ: {', '.join(differ)}")
        per_run: dict[str, Any] = {}
        speeds = [p.agent_max_speed_mps for p in made]
        if len(set(speeds)) > 1:
            per_run["agent_max_speed_mps"] = np.array(speeds, dtype=float)[:, None]
        ratios = [p.agent_lateral_ratio for p in made]
        if len(set(ratios)) > 1:
            per_run["agent_lateral_ratio"] = np.array([0.0 if r is None else r for r in ratios], dtype=float)[:, None]
            if None in ratios:
                per_run["agent_lateral_bounded"] = np.array([r is not None for r in ratios])[:, None]
        return replace(made[0], **per_run)

    def on(self, xp: Any) -> WorldParams:
        """These parameters with their per-run arrays in the array namespace ``xp`` (a torch device's)."""
        return replace(self, **{name: xp.asarray(getattr(self, name)) for name in PER_RUN_LIMITS
                                if isinstance(getattr(self, name), np.ndarray)})

    @classmethod
    def _of(cls, cfg: LaneFreeConfig) -> WorldParams:
        if not road_kind(cfg).batched_world:
            raise ConfigError(f"the batched simulation runs the ring, not road.kind = {cfg.road.kind}")
        return cls(cfg.scenario.driver, cfg.sim.step_s, cfg.sim.edge_clearance_m, cfg.sim.edge_contact_tolerance_m,
                   cfg.scenario.agent_bounds, cfg.scenario.agent_max_speed_mps, cfg.scenario.agent_lateral_speed_ratio,
                   cfg.sim.sumo_min_lateral_speed_mps * cfg.sim.step_s)


@dataclass
class World:
    """K rings: vehicle arrays ``[K, N]`` (padded rows: ``present`` False, at rest, zero size), pair arrays
    ``[K, N, N]``, per-run values ``[K]``. Positions in m, speeds in m/s (:mod:`.state`)."""

    x: np.ndarray
    y: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    length: np.ndarray
    width: np.ndarray
    v_desired: np.ndarray
    controlled: np.ndarray
    """True for the background rows the driver model controls."""
    present: np.ndarray
    """True for real vehicles, False for padding."""
    edge: np.ndarray
    """The ring edge each vehicle is on (SUMO's way of keeping positions, :mod:`.network`)."""
    pos: np.ndarray
    """Position on that edge (m)."""
    lat: np.ndarray
    """Lateral offset from the lane centre (m)."""
    dx: np.ndarray
    """``[K, N, N]``: wrapped x_j − x_i now (m)."""
    dy: np.ndarray
    """``[K, N, N]``: y_j − y_i now (m)."""
    overlap: np.ndarray
    """``[K, N, N]``: the pairs overlapping now (a collision event starts where a pair was not)."""
    agent_rows: np.ndarray
    """``[K, A]``: the rows of each run's agents, in row order."""
    road_length: np.ndarray
    """``[K]``: ring circumference (m)."""
    road_width: np.ndarray
    """``[K]``: road width (m)."""
    steps: np.ndarray
    """``[K]``: steps since the run's reset."""

    @property
    def runs(self) -> int:
        return int(self.x.shape[0])

    @property
    def counts(self) -> np.ndarray:
        """``[K]``: vehicles per run."""
        return self.present.sum(axis=1)


@dataclass
class StepOutcome:
    """What happened in one step of every run (``[K, N]`` / ``[K, N, N]``)."""

    ax: np.ndarray
    """Realised longitudinal accelerations (m/s²)."""
    ay: np.ndarray
    """Realised lateral accelerations (m/s²)."""
    boundary_contact: np.ndarray
    """True where a lateral move was clipped at a road edge."""
    overlap: np.ndarray
    """The pairs overlapping after the step."""
    new_collisions: np.ndarray
    """The pairs (i < j) whose overlap started in this step."""


def world_of(states: Sequence[VehicleState], road_lengths: Sequence[float] | np.ndarray,
             road_widths: Sequence[float] | np.ndarray,
             rows: int | None = None) -> World:
    """Place the vehicles of ``states`` (one per run, on rings of the given lengths and widths in m) in one world
    padded to ``rows`` vehicles per run (None: the most vehicles of a run). Agents are the rows not controlled."""
    n = max(s.n for s in states) if rows is None else rows
    if any(s.n > n for s in states):
        raise ValueError(f"a run has more vehicles than the world's {n} rows")
    agents = {int((~s.controlled).sum()) for s in states}
    if len(agents) != 1:
        raise ConfigError("the runs of one batch must have the same number of agents")
    k = len(states)
    length = np.asarray(road_lengths, dtype=float)
    width = np.asarray(road_widths, dtype=float)

    def stack(name: str, fill: float | bool) -> np.ndarray:
        first = getattr(states[0], name)
        out = np.full((k, n), fill, dtype=first.dtype)
        for run, s in enumerate(states):
            out[run, :s.n] = getattr(s, name)
        return out

    present = np.arange(n)[None, :] < np.array([s.n for s in states])[:, None]
    x = stack("x", 0.0)
    y = np.where(present, stack("y", 0.0), 0.5 * width[:, None])
    edge, pos = ring_to_edge(x, length[:, None])
    world = World(
        x=x, y=y, vx=stack("vx", 0.0), vy=stack("vy", 0.0), length=stack("length", 0.0), width=stack("width", 0.0),
        v_desired=stack("v_desired", 0.0), controlled=stack("controlled", False), present=present,
        edge=edge, pos=pos, lat=y - 0.5 * width[:, None], dx=np.zeros(0), dy=np.zeros(0), overlap=np.zeros(0),
        agent_rows=np.array([np.flatnonzero(~s.controlled) for s in states], dtype=int).reshape(k, -1),
        road_length=length, road_width=width, steps=np.zeros(k, dtype=int),
    )
    world.dx, world.dy = pairwise_offsets(world, length[:, None])
    world.overlap = overlap_matrix(world, length[:, None], (world.dx, world.dy), present)
    return world


def reset_world(cfgs: Sequence[LaneFreeConfig], seeds: Sequence[int]) -> World:
    """K rings, run k spawned as a single simulation of ``cfgs[k]`` spawns it with ``seeds[k]``
    (:func:`~lanefree_sumo.sim.spawn.spawn` with ``numpy.random.default_rng(seed)``)."""
    states = [spawn(cfg, np.random.default_rng(seed)) for cfg, seed in zip(cfgs, seeds)]
    return world_of(states, [c.road.length_m for c in cfgs], [c.road.width_m for c in cfgs])


def replace_runs(world: World, runs: Sequence[int], states: Sequence[VehicleState]) -> World:
    """A new world whose runs ``runs`` start afresh from ``states`` (each run keeps its road); the other runs
    are unchanged. The states must fit the world's rows and have its number of agents."""
    if not len(runs):
        return world
    n = world.x.shape[1]
    fresh = world_of(states, world.road_length[list(runs)], world.road_width[list(runs)], rows=n)
    if fresh.agent_rows.shape[1] != world.agent_rows.shape[1]:
        raise ConfigError("the runs of one batch must have the same number of agents")
    xp = namespace(world.x)
    if not xp.is_numpy:
        fresh = world_to(fresh, xp.name)
    index = xp.asarray(list(runs), dtype=int)
    out = replace(world, **{f.name: xp.copy(getattr(world, f.name)) for f in fields(World)})
    for f in fields(World):
        if f.name not in ("road_length", "road_width"):
            getattr(out, f.name)[index] = getattr(fresh, f.name)
    return out


def world_to(world: World, device: str) -> World:
    """The world's arrays on ``device`` (``train.device``, :func:`~lanefree_sumo.sim.xp.array_namespace`): numpy
    arrays for ``cpu``, else torch tensors there (float64 positions and speeds, int64 indices); the same numbers."""
    xp = array_namespace(device)
    if xp.is_numpy:
        return replace(world, **{f.name: namespace(getattr(world, f.name)).to_numpy(getattr(world, f.name))
                                 for f in fields(World)})
    return replace(world, **{f.name: xp.asarray(getattr(world, f.name)) for f in fields(World)})


def step_world(world: World, params: WorldParams, agent_accel: np.ndarray,
               details: dict[str, np.ndarray] | None = None) -> tuple[World, StepOutcome]:
    """Advance every run one step; returns the new world (the old one is unchanged) and what happened.

    ``agent_accel``: ``[K, A, 2]`` (or ``[K, 2]`` with one agent) — each agent's (ax, ay) in m/s², clipped to
    its bounds and top speed. ``details``: the driver model's per-vehicle diagnostics, ``[K, N]``
    (:func:`~lanefree_sumo.sim.forces.driver_accelerations`)."""
    xp = namespace(world.x)
    t = params.step_s
    ring = world.road_length[:, None]
    road_width = world.road_width[:, None]
    bounds = (0.0, road_width)
    # no padding: nothing to mask (a shortcut with the same result, taken where it costs no synchronisation)
    present = None if xp.is_numpy and world.present.all() else world.present
    ax, ay = driver_accelerations(world, params.driver, ring, road_width, t, params.clearance_m,
                                  (world.dx, world.dy), details, bounds=bounds, present=present)
    commands = xp.asarray(agent_accel, dtype=float).reshape(world.runs, -1, 2)
    rows = world.agent_rows
    agent_ax, agent_ay = clip_accelerations(commands[..., 0], commands[..., 1], params.agent_bounds,
                                            take_rows(world.vx, rows), params.agent_max_speed_mps, t,
                                            take_rows(world.vy, rows), params.agent_lateral_ratio,
                                            params.agent_lateral_bounded)
    xp.put_along_axis(ax, rows, agent_ax, 1)
    xp.put_along_axis(ay, rows, agent_ay, 1)
    if present is not None:
        ax = xp.where(present, ax, 0.0)
        ay = xp.where(present, ay, 0.0)
    cmd = plan_step(world.x, world.y, world.vx, world.vy, world.width, ax, ay, t, road_width, params.clearance_m,
                    params.contact_tolerance_m, bounds=bounds)

    # the ring's executor, with SUMO's arithmetic: the ballistic distance along the edge, the hand-over to the
    # next edge, small lateral moves set rather than driven
    segment = edge_length(ring)
    half_width = 0.5 * road_width
    pos = world.pos + ballistic_distance(world.vx, cmd.vx_next, t)
    passed = pos > segment
    pos = xp.where(passed, pos - segment, pos)
    edge = xp.where(passed, (world.edge + 1) % EDGES, world.edge)
    tiny = xp.abs(cmd.dy) < params.min_lateral_move_m
    moved = xp.where(tiny, (world.y + cmd.dy) - half_width, world.lat + cmd.dy)
    lat = xp.where(cmd.dy == 0.0, world.lat, moved)

    new = replace(world, x=edge_to_ring(edge, pos, ring), y=lat + half_width, vx=cmd.vx_next, vy=cmd.vy_next,
                  edge=edge, pos=pos, lat=lat, steps=world.steps + 1)
    new.dx, new.dy = pairwise_offsets(new, ring)
    new.overlap = overlap_matrix(new, ring, (new.dx, new.dy), present)
    contact = cmd.boundary_contact if present is None else cmd.boundary_contact & present
    outcome = StepOutcome(cmd.ax, cmd.ay, contact, new.overlap,
                          started_overlaps(new.overlap, world.overlap))
    return new, outcome
