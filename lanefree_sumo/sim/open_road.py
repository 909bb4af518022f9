"""Traffic entering and leaving an open road (the on-ramp): seeded arrivals, safe insertion, removal at the
end, the merge bookkeeping, and the project's merge rule (pure numpy on state arrays).

* Arrivals: at the main road's upstream end and at the ramp's start, each step an arrival with probability
  q·T/3600 (q in veh/h, T the step in s): a Bernoulli approximation of Poisson arrivals, seeded by the
  episode. An arrival waits in its source's queue until it can enter.
* Insertion (one vehicle per source and step, the queue's first): on the main road at x = 0 at the first
  of ``LATERAL_SLOTS`` evenly spaced lateral positions (tried in a random order) where every vehicle whose
  band it would overlap keeps a bumper gap of at least ``spawn.gap_x_m`` + ``entry_headway_s`` × the entry
  speed ahead of it; on the ramp at its start, in the ramp's middle, under the same rule. Entry speed:
  the source's entry speed, or the vehicle's desired speed if lower, or lower still where a slow vehicle
  ahead in its band demands it: at most the speed from which braking at the driver's ``ax_min`` ends
  ``spawn.gap_x_m`` behind that vehicle were it to brake as hard (so an arrival behind a queue that
  reaches the entry enters slowly instead of running into it); desired speeds as the ring's background
  vehicles'.
* Removal: a vehicle whose centre passed the main road's downstream end leaves the road.
* Merging: a ramp vehicle is *merged* once its whole body is on the main road (y − w/2 ≥ 0); from then on
  it is a main-road vehicle (:meth:`~lanefree_sumo.sim.road.Road.bounds`).
* The merge rule (the smallest one that keeps every ramp vehicle from reaching the ramp's end unmerged):
  (1) in the merge zone an unmerged ramp vehicle's target-speed force aims at the lateral speed
  ``merge_lateral_speed_mps`` towards the main road instead of 0 (the neighbours' forces still hold it
  back where the main road is occupied); (2) the ramp's usable width closes in the merge zone (the
  road's boundaries at each vehicle's front, which the force model's edge bound and the dynamics' clip
  obey, push ramp vehicles onto the main road; at the ramp's end the boundary is the main road's edge);
  (3) an unmerged ramp vehicle may accelerate at most so much that braking at the driver's ``ax_min``
  still stops its front ``RAMP_END_MARGIN_M`` before the ramp's end (the force model's edge bound U,
  applied longitudinally).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lanefree_sumo.config import ConfigError, LaneFreeConfig
from lanefree_sumo.sim.forces import edge_bound
from lanefree_sumo.sim.road import Road
from lanefree_sumo.sim.spawn import agent_id
from lanefree_sumo.sim.state import VehicleState

LATERAL_SLOTS = 5
"""Lateral entry positions across the main road."""
RAMP_END_MARGIN_M = 0.0
"""An unmerged ramp vehicle's front stops at least this far before the ramp's end (m): at the end the
boundary (taken at the front) has closed, so the body is on the main road before the front gets there."""
MAIN, RAMP = 0, 1


@dataclass
class FlowCounts:
    """What entered, left and merged in an episode (vehicles)."""

    entered_main: int = 0
    entered_ramp: int = 0
    left: int = 0
    """Vehicles that passed the downstream end."""
    merged: int = 0
    """Ramp vehicles whose whole body reached the main road."""
    ramp_end_reached: int = 0
    """Ramp vehicles whose front reached the ramp's end unmerged (the merge rule should keep this 0)."""
    waiting: list[int] = field(default_factory=lambda: [0, 0])
    """Arrivals still queued at the main road and at the ramp (at the end of the episode)."""


class OpenRoadTraffic:
    """Arrivals, insertion, removal and merging of one episode on an open road (module docstring)."""

    def __init__(self, cfg: LaneFreeConfig, road: Road) -> None:
        self.cfg, self.road = cfg, road
        o = cfg.road.onramp
        self.probability = np.array([o.main_flow_veh_per_h, o.ramp_flow_veh_per_h]) * cfg.sim.step_s / 3600.0
        self.entry_speed = (o.main_entry_speed_mps, o.ramp_entry_speed_mps)
        self.rng = np.random.default_rng(0)
        self.counts = FlowCounts()
        self.queues: tuple[list[float], list[float]] = ([], [])
        """Desired speeds (m/s) of the arrivals waiting at the main road and at the ramp."""
        self._ramp_ended: set[str] = set()

    def reset(self, seed: int) -> None:
        """A new episode whose arrivals and entries are drawn from ``seed``."""
        self.rng = np.random.default_rng([seed, 21])
        self.counts = FlowCounts()
        self.queues = ([], [])
        self._ramp_ended = set()

    def leaving(self, state: VehicleState) -> np.ndarray:
        """True for the vehicles whose centre passed the downstream end."""
        return state.x >= self.road.length_m

    def merge(self, state: VehicleState, on_ramp: np.ndarray) -> np.ndarray:
        """``on_ramp`` with the ramp vehicles whose body is now wholly on the main road merged (counted),
        and the unmerged ones whose front reached the ramp's end counted once each."""
        merged = on_ramp & (state.y - 0.5 * state.width >= 0.0)
        self.counts.merged += int(merged.sum())
        ended = on_ramp & ~merged & (state.x + 0.5 * state.length >= self.road.ramp_end_m)
        for i in np.flatnonzero(ended):
            if state.ids[i] not in self._ramp_ended:
                self._ramp_ended.add(state.ids[i])
                self.counts.ramp_end_reached += 1
        return on_ramp & ~merged

    def lateral_target(self, state: VehicleState, on_ramp: np.ndarray) -> np.ndarray | float:
        """The lateral speed each vehicle's target-speed force aims at (m/s): ``merge_lateral_speed_mps`` for
        unmerged ramp vehicles whose front is in the merge zone, else 0."""
        merging = on_ramp & (state.x + 0.5 * state.length >= self.road.merge_start_m)
        if not merging.any():
            return 0.0
        return np.where(merging, self.cfg.road.onramp.merge_lateral_speed_mps, 0.0)

    def end_wall(self, state: VehicleState, on_ramp: np.ndarray, ax: np.ndarray) -> np.ndarray:
        """``ax`` (m/s²) capped for unmerged ramp vehicles (agents too: the ramp's lane ends there, and SUMO
        stops a vehicle at a lane's end) so that they can stop before the ramp's end."""
        if not on_ramp.any():
            return ax
        room = np.maximum(0.0, self.road.ramp_end_m - RAMP_END_MARGIN_M - (state.x + 0.5 * state.length))
        cap = edge_bound(state.vx, room, self.cfg.sim.step_s, self.cfg.scenario.driver.bounds.ax_min)
        return np.where(on_ramp, np.minimum(ax, cap), ax)

    def agent_start(self, background: VehicleState) -> tuple[VehicleState, bool]:
        """The learning vehicles' rows at their start and whether they start on the ramp
        (``road.onramp.agent_start``): one behind the other, ``spawn.gap_x_m`` apart, the first at the ramp's
        start, in its middle, at the ramp's entry speed; or the first at ``agent_main_start_m`` on the main
        road, at its entry speed, each in the lateral slot farthest from every background vehicle near it.
        Background vehicles are not moved: the ramp starts empty, and on the main road the slot is chosen
        where they are not."""
        sc, o = self.cfg.scenario, self.cfg.road.onramp
        length, width, k = sc.agent.length_m, sc.agent.width_m, sc.agents
        step = length + sc.spawn.gap_x_m
        if o.agent_start == "ramp":
            xs = self.road.ramp_start_m + 0.5 * length + step * np.arange(k)[::-1]  # agent (row first) in front
            if xs.max() + 0.5 * length > self.road.merge_start_m:
                raise ConfigError(f"{k} learning vehicles do not fit one behind the other on the ramp before its merge "
                                  "zone; use fewer (scenario.agents)")
            ys = np.full(k, -0.5 * self.road.ramp_width_m)
            speed = o.ramp_entry_speed_mps
        else:
            xs = o.agent_main_start_m - step * np.arange(k)
            if xs.min() - 0.5 * length < 0.0:
                raise ConfigError(f"{k} learning vehicles do not fit one behind the other before "
                                  f"road.onramp.agent_main_start_m = {o.agent_main_start_m:g} m; use fewer or a "
                                  "later start")
            clear = self.cfg.sim.edge_clearance_m + 0.5 * sc.spawn.gap_y_m
            slots = np.linspace(0.5 * width + clear, self.road.width_m - 0.5 * width - clear, LATERAL_SLOTS)
            ys = np.empty(k)
            for i, x in enumerate(xs):
                near = np.abs(background.x - x) < 0.5 * (background.length + length) + sc.spawn.gap_x_m
                clearance = [np.min(np.abs(background.y[near] - s), initial=np.inf) for s in slots]
                ys[i] = slots[int(np.argmax(clearance))]
            speed = o.main_entry_speed_mps
        rows = VehicleState([agent_id(i) for i in range(k)], np.asarray(xs, dtype=float), ys, np.full(k, speed),
                            np.zeros(k), np.full(k, length), np.full(k, width),
                            np.full(k, sc.agent.desired_speed_min_mps), np.zeros(k, dtype=bool))
        return rows, o.agent_start == "ramp"

    def arrivals(self, state: VehicleState) -> tuple[VehicleState, np.ndarray]:
        """This step's new vehicles (at most one per source: the first in its queue, where it fits) and
        whether each is a ramp vehicle."""
        bg = self.cfg.scenario.background
        for source in (MAIN, RAMP):
            if self.rng.random() < self.probability[source]:
                self.queues[source].append(float(self.rng.uniform(bg.desired_speed_min_mps, bg.desired_speed_max_mps)))
        new: list[tuple[str, float, float, float, float]] = []
        taken = state
        for source in (MAIN, RAMP):
            if not self.queues[source]:
                continue
            vehicle = self._try_enter(taken, source, self.queues[source][0])
            if vehicle is None:
                continue
            self.queues[source].pop(0)
            if source == MAIN:
                self.counts.entered_main += 1
                vid = f"m{self.counts.entered_main}"
            else:
                self.counts.entered_ramp += 1
                vid = f"r{self.counts.entered_ramp}"
            new.append((vid, *vehicle))
            taken = append_rows(taken, _rows(self.cfg, [new[-1]]))
        self.counts.waiting = [len(queue) for queue in self.queues]
        return _rows(self.cfg, new), np.array([vid.startswith("r") for vid, *_ in new], dtype=bool)

    def _try_enter(self, state: VehicleState, source: int,
                   v_desired: float) -> tuple[float, float, float, float] | None:
        """(x, y, speed, desired speed) of a vehicle desiring ``v_desired`` (m/s) at the first place it fits
        at ``source``, else None."""
        bg = self.cfg.scenario.background
        length, width = bg.length_m, bg.width_m
        speed = min(self.entry_speed[source], v_desired)
        gap = self.cfg.scenario.spawn.gap_x_m + self.cfg.road.onramp.entry_headway_s * speed
        clear = self.cfg.sim.edge_clearance_m + 0.5 * self.cfg.scenario.spawn.gap_y_m
        if source == MAIN:
            x = 0.5 * length
            low, high = 0.5 * width + clear, self.road.width_m - 0.5 * width - clear
            slots = np.linspace(low, high, LATERAL_SLOTS)[self.rng.permutation(LATERAL_SLOTS)]
        else:
            x = self.road.ramp_start_m + 0.5 * length
            slots = np.array([-0.5 * self.road.ramp_width_m])
        for y in slots:
            beside = np.abs(state.y - y) < 0.5 * (state.width + width) + 0.5 * self.cfg.scenario.spawn.gap_y_m
            bumper = np.abs(state.x - x) - 0.5 * (state.length + length)
            if not np.any(beside & (bumper < gap)):
                return x, float(y), min(speed, self._stoppable_speed(state, x, beside, bumper)), v_desired
        return None

    def _stoppable_speed(self, state: VehicleState, x: float, beside: np.ndarray, bumper: np.ndarray) -> float:
        """The highest entry speed (m/s) from which braking at the driver's ``ax_min`` ends ``spawn.gap_x_m``
        behind every vehicle ahead in the band, should it brake as hard: √(v_l² + 2·|ax_min|·(gap − gap_x))."""
        ahead = beside & (state.x > x)
        if not ahead.any():
            return float("inf")
        room = np.maximum(bumper[ahead] - self.cfg.scenario.spawn.gap_x_m, 0.0)
        brake = -self.cfg.scenario.driver.bounds.ax_min
        return float(np.sqrt(state.vx[ahead] ** 2 + 2.0 * brake * room).min())


def _rows(cfg: LaneFreeConfig, vehicles: list[tuple[str, float, float, float, float]]) -> VehicleState:
    """Background vehicles as state rows: (id, x, y, speed, desired speed) each."""
    bg = cfg.scenario.background
    n = len(vehicles)
    return VehicleState(
        ids=[v[0] for v in vehicles], x=np.array([v[1] for v in vehicles], dtype=float),
        y=np.array([v[2] for v in vehicles], dtype=float), vx=np.array([v[3] for v in vehicles], dtype=float),
        vy=np.zeros(n), length=np.full(n, bg.length_m), width=np.full(n, bg.width_m),
        v_desired=np.array([v[4] for v in vehicles], dtype=float), controlled=np.ones(n, dtype=bool),
    )


def append_rows(state: VehicleState, rows: VehicleState) -> VehicleState:
    """``state`` with ``rows`` appended at the end (new arrays)."""
    return VehicleState(
        state.ids + rows.ids, *(np.concatenate([getattr(state, k), getattr(rows, k)])
                                for k in ("x", "y", "vx", "vy", "length", "width", "v_desired", "controlled")))


def keep_rows(state: VehicleState, keep: np.ndarray) -> VehicleState:
    """The rows of ``state`` where ``keep`` is True (new arrays)."""
    return VehicleState(
        [vid for vid, k in zip(state.ids, keep) if k],
        *(getattr(state, k)[keep] for k in ("x", "y", "vx", "vy", "length", "width", "v_desired", "controlled")))
