"""The road as the physics sees it: its length, whether its ends meet, and the lateral boundaries at x.

Two roads (``road.kind``):

* ``ring`` — the paper's closed ring of circumference L and width W: x is periodic and every vehicle
  may use [0, W] everywhere. Its boundaries are the scalars 0 and W, so the physics computes exactly
  what it computed before roads were pluggable (the same arithmetic, the same bits).
* ``onramp`` — an open, straight main road of width W (y ∈ [0, W], y measured from its right edge) from
  x = 0 to x = upstream + ramp + downstream, with an acceleration lane of width w_r beside its right
  edge (y ∈ [−w_r, 0]) for x ∈ [upstream, upstream + ramp]. Main-road vehicles keep to the main road. A
  ramp vehicle keeps to the ramp before the merge zone (the ramp's last ``merge_m``), may use the ramp
  and the main road in it, where the ramp's usable width closes linearly to 0 at the ramp's end, and is
  *merged* — a main-road vehicle from then on — once its whole body is on the main road.

Longitudinal differences on the open road are plain differences: :attr:`Road.wrap_length` is so large
that :func:`~lanefree_sumo.sim.state.wrap` returns them unchanged, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lanefree_sumo.config import ConfigError, LaneFreeConfig


@dataclass(frozen=True)
class RoadKind:
    """What the code around the physics tells one road kind (``road.kind``) by: declared once here, read
    through :func:`road_kind` (never by comparing the kind's name)."""

    name: str
    periodic: bool
    """x wraps: the vehicles stay on the road (no entries, no exits)."""
    batched_world: bool
    """The batched world of :mod:`~lanefree_sumo.sim.world` runs it (the numpy simulation, ``--seeds`` as one
    array program, the vector entry point, the GPU)."""
    tag: str
    """In run and simulation folder names (empty for the paper's ring)."""
    ego_features: tuple[str, ...]
    """The learning vehicle's extra ego features (``observation.road_features``)."""
    metrics: tuple[str, ...]
    """Its extra episode metrics (``episodes.csv`` columns)."""


ROAD_KIND_SPECS: dict[str, RoadKind] = {
    "ring": RoadKind("ring", periodic=True, batched_world=True, tag="", ego_features=(), metrics=()),
    "onramp": RoadKind("onramp", periodic=False, batched_world=False, tag="onramp",
                       ego_features=("lowest lateral position at the front (/W)",
                                     "highest lateral position at the front (/W)", "on the ramp (0/1)",
                                     "ramp end ahead (/d)"),
                       metrics=("merged", "time_to_merge_s", "left_road")),
}
"""Every road kind of :data:`~lanefree_sumo.config.ROAD_KINDS`, by name (``tests/sim/test_open_road.py`` checks
that this and each table keyed by kind cover them all)."""


def road_kind(cfg: LaneFreeConfig) -> RoadKind:
    """The :class:`RoadKind` of ``cfg``'s road."""
    return ROAD_KIND_SPECS[cfg.road.kind]


OPEN_ROAD_WRAP_M = 1e12
"""The wrap length of an open road (m): differences of positions on any road up to ~1e11 m long wrap to
themselves exactly (floor(d / 1e12 + 0.5) = 0)."""


@dataclass(frozen=True)
class Road:
    """Geometry of the road the simulation runs on (module docstring)."""

    kind: str
    length_m: float
    """Ring circumference, or the main road's length from its upstream to its downstream end (m)."""
    width_m: float
    """Width of the ring, or of the main road (m)."""
    ramp_start_m: float = 0.0
    """x where the ramp begins (m; on-ramp only)."""
    merge_start_m: float = 0.0
    """x where the merge zone begins (m)."""
    ramp_end_m: float = 0.0
    """x where the ramp ends (m)."""
    ramp_width_m: float = 0.0

    @property
    def periodic(self) -> bool:
        """x wraps (the ring)."""
        return ROAD_KIND_SPECS[self.kind].periodic

    @property
    def wrap_length(self) -> float:
        """The length :func:`~lanefree_sumo.sim.state.wrap` takes: L on the ring, a length that never wraps
        on an open road (m)."""
        return self.length_m if self.periodic else OPEN_ROAD_WRAP_M

    def bounds(self, x: np.ndarray, on_ramp: np.ndarray | None) -> tuple[np.ndarray | float, np.ndarray | float]:
        """(lowest, highest) lateral position (m) the body of each vehicle may reach at longitudinal position
        ``x`` (m; the simulation passes each vehicle's front); ``on_ramp``: True for ramp vehicles not yet
        merged. On the ring: the scalars 0 and W."""
        if self.periodic or on_ramp is None or not on_ramp.any():
            return 0.0, self.width_m
        closing = np.clip((x - self.merge_start_m) / (self.ramp_end_m - self.merge_start_m), 0.0, 1.0)
        in_merge = x >= self.merge_start_m
        lo = np.where(on_ramp, -self.ramp_width_m * (1.0 - closing), 0.0)
        hi = np.where(on_ramp & ~in_merge, 0.0, self.width_m)
        return lo, hi


def road_of(cfg: LaneFreeConfig) -> Road:
    """The :class:`Road` of a config; ConfigError when the on-ramp's parts do not fit together."""
    if road_kind(cfg).periodic:
        return Road(cfg.road.kind, cfg.road.length_m, cfg.road.width_m)
    o = cfg.road.onramp
    if o.merge_m > o.ramp_m:
        raise ConfigError(f"config 'road.onramp.merge_m' = {o.merge_m:g} is longer than the ramp "
                          f"(road.onramp.ramp_m = {o.ramp_m:g}); the merge zone is the ramp's last part")
    if o.agent_start == "main" and o.agent_main_start_m + cfg.scenario.agent.length_m >= cfg.road.main_length_m:
        raise ConfigError(f"config 'road.onramp.agent_main_start_m' = {o.agent_main_start_m:g} is not on the main road "
                          f"(it ends at {cfg.road.main_length_m:g} m)")
    start = o.upstream_m
    return Road("onramp", cfg.road.main_length_m, cfg.road.width_m, ramp_start_m=start,
                merge_start_m=start + o.ramp_m - o.merge_m, ramp_end_m=start + o.ramp_m, ramp_width_m=o.ramp_width_m)
