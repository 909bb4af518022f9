"""Reward components of the lane-free agent (SPEC §7; Karalakou et al., Systems 2023, Eq. 16).

Pure numpy: no SUMO, no gym.  Units are SI throughout (m, s, m/s).  Coordinates follow SPEC §1:
``dx_j = wrap(x_j − x_agent)`` in [−L/2, L/2) on the ring, ``dy_j = y_j − y_agent`` with ``y``
measured from the right road edge (0 ≤ y ≤ W).

Every default comes from :class:`lanefree_sumo.config.RewardConfig` (``_DEFAULTS`` below); the
preset weights are the paper's Table 4 (SPEC §7 table).

Conventions shared by the functions taking neighbour arrays (``field_cost``, ``zone_target``,
``agent_overlaps``): arrays are aligned by vehicle and broadcast against each other (so ``lens``
may be a scalar); a row with a non-finite (NaN) position or speed is treated as *absent*, so
padded arrays can be passed directly.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from lanefree_sumo.config import RewardConfig

__all__ = [
    "ellipsoid",
    "field_cost",
    "zone_target",
    "reciprocal_reward",
    "longitudinal_cost",
    "lateral_cost",
    "detect_overtakes",
    "agent_overlaps",
    "RewardWeights",
    "PRESETS",
    "get_preset",
    "RewardTerms",
    "compute_reward",
]

_DEFAULTS = RewardConfig()

# Two candidate zones whose distances to the agent differ by less than this are a tie (m).
# Geometry like 5.1 − 4.2 vs 6.0 − 5.1 differs by ~1e-15 m in floating point.
_TIE_TOL_M = 1e-9


def _rows(*arrays: ArrayLike) -> list[np.ndarray]:
    """The arrays as aligned 1-D float arrays (broadcast only when they are not already)."""
    flat = [np.atleast_1d(np.asarray(a, dtype=float)) for a in arrays]
    n = flat[0].shape
    if all(f.ndim == 1 and f.shape == n for f in flat):
        return flat
    return list(np.broadcast_arrays(*flat))


# --------------------------------------------------------------------------------------------
# Ellipsoid fields
# --------------------------------------------------------------------------------------------


def ellipsoid(
    dx: ArrayLike,
    dy: ArrayLike,
    a: ArrayLike,
    b: ArrayLike,
    px: float,
    py: float,
    pt: float,
    m: float,
) -> float | np.ndarray:
    """Ellipsoid field ``E = m / ((|dx|/a)^px + (|dy|/b)^py + 1)^pt`` element-wise.

    dx, dy: offsets (m); a, b: semi-axes (m, > 0); px, py, pt: exponents (–); m: peak value (–),
    reached at dx = dy = 0.  All array arguments broadcast; a scalar result is a ``float``.
    """
    dx_ = np.asarray(dx, dtype=float)
    dy_ = np.asarray(dy, dtype=float)
    a_ = np.asarray(a, dtype=float)
    b_ = np.asarray(b, dtype=float)
    base = (np.abs(dx_) / a_) ** px + (np.abs(dy_) / b_) ** py + 1.0
    out = m / base**pt
    return float(out) if np.ndim(out) == 0 else out


def field_cost(
    dx: ArrayLike,
    dy: ArrayLike,
    dvx: ArrayLike,
    dvy: ArrayLike,
    agent_len: float,
    agent_wid: float,
    lens: ArrayLike,
    wids: ArrayLike,
    *,
    magnitude: float = _DEFAULTS.field_magnitude,
    critical_exponents: tuple[float, float, float] = _DEFAULTS.critical_exponents,
    broad_exponents: tuple[float, float, float] = _DEFAULTS.broad_exponents,
    k_r: float = _DEFAULTS.k_r_s_per_m,
    e_v: float = _DEFAULTS.e_v_s_per_m,
) -> float:
    """Potential-field cost ``c_f = min(1, Σ_j (E_c,j + E_b,j))`` over the given neighbours (–).

    dx, dy: neighbour offsets from the agent (m); dvx = vx_agent − vx_j, dvy = vy_agent − vy_j
    (m/s); agent_len/agent_wid and lens/wids: vehicle dimensions (m).

    Critical region: semi-axes ``a_c = (agent_len + len_j)/2``, ``b_c = (agent_wid + wid_j)/2``,
    exponents ``critical_exponents`` (4, 4, 1).  Broad region: exponents ``broad_exponents``
    (2, 2, 1) with semi-axes stretched by the closing speeds
    ``ux = max(0, sign(dx)·dvx)``, ``uy = max(0, sign(dy)·dvy)`` (m/s):
    ``a_b = a_c·(1 + k_r·ux)``, ``b_b = b_c·(1 + e_v·uy)``.  A positive ``sign(dx)·dvx`` means
    the gap closes (agent faster than a vehicle ahead, or slower than one behind); a receding or
    exactly aligned (dx = 0) neighbour does not stretch the region.  Both regions peak at
    ``magnitude`` (m_f = 0.5).

    k_r (s/m) and e_v (s/m) are THE PROJECT'S INTERPRETATION: the paper lists k_r = 0.5 and
    e_v = 0.4 without defining them; here they stretch the broad region per m/s of closing speed,
    in the spirit of its sources where the broad region grows with speed deviation.

    Empty neighbour arrays (or only NaN rows) give 0.0.
    """
    dx_, dy_, dvx_, dvy_, lens_, wids_ = _rows(dx, dy, dvx, dvy, lens, wids)
    ok = np.isfinite(dx_ + dy_ + dvx_ + dvy_)  # NaN/inf in any of them propagates
    if not ok.all():
        if not ok.any():
            return 0.0
        dx_, dy_, dvx_, dvy_, lens_, wids_ = dx_[ok], dy_[ok], dvx_[ok], dvy_[ok], lens_[ok], wids_[ok]
    a_c = 0.5 * (agent_len + lens_)
    b_c = 0.5 * (agent_wid + wids_)
    rx = np.abs(dx_) / a_c
    ry = np.abs(dy_) / b_c
    ux = np.maximum(0.0, np.sign(dx_) * dvx_)
    uy = np.maximum(0.0, np.sign(dy_) * dvy_)
    pcx, pcy, pct = critical_exponents
    pbx, pby, pbt = broad_exponents
    # the ellipsoid() formula, on |dx|/a and |dy|/b computed once
    e_c = magnitude / (rx**pcx + ry**pcy + 1.0) ** pct
    e_b = magnitude / ((rx / (1.0 + k_r * ux)) ** pbx + (ry / (1.0 + e_v * uy)) ** pby + 1.0) ** pbt
    return min(1.0, float(e_c.sum() + e_b.sum()))


# --------------------------------------------------------------------------------------------
# Zones (lateral target)
# --------------------------------------------------------------------------------------------


def zone_target(
    dx: ArrayLike,
    dy: ArrayLike,
    vxs: ArrayLike,
    lens: ArrayLike,
    wids: ArrayLike,
    agent_y: float,
    agent_vx: float,
    agent_len: float,
    agent_wid: float,
    v_desired: float,
    road_width: float,
    *,
    time_gap: float = _DEFAULTS.zone_time_gap_s,
    margin: float = _DEFAULTS.zone_margin_m,
) -> tuple[float, float, bool]:
    """Lateral target and effective desired speed from the overtaking zones (SPEC §7 "Zones").

    dx, dy, vxs, lens, wids: the vehicles in range (m, m, m/s, m, m); agent_y (m), agent_vx
    (m/s), agent dimensions (m), v_desired (m/s), road_width W (m).  Returns
    ``(y_d [m], v_d_eff [m/s], blocked)``:

    1. scan distance ``d_o = agent_vx · time_gap``;
    2. blockers: ``dx_j > −(agent_len + len_j)/2`` (not entirely behind) and bumper gap
       ``dx_j − (agent_len + len_j)/2 ≤ d_o``;
    3. no blocker: ``(W/2, v_desired, False)``;
    4. else the blockers' lateral extents ``[y_j − w_j/2, y_j + w_j/2]`` (``y_j = agent_y + dy_j``,
       clipped to the road) are removed from ``[0, W]``; zones narrower than
       ``agent_wid + 2·margin`` are dropped; the zone nearest to ``agent_y`` (distance 0 when
       inside) is chosen: ``(its centre, v_desired, False)``.  Ties (distances within 1e-9 m) go
       to the zone on the LEFT (larger y), the conventional overtaking side in right-hand
       traffic;
    5. no zone fits: ``(y of the fastest blocker, min(v_desired, min blocker vx), True)``; among
       equally fast blockers the first in array order.
    """
    dx_, dy_, vx_, lens_, wids_ = _rows(dx, dy, vxs, lens, wids)
    half_len = 0.5 * (agent_len + lens_)
    d_o = agent_vx * time_gap
    with np.errstate(invalid="ignore"):
        is_blocker = (
            np.isfinite(dx_) & np.isfinite(dy_) & np.isfinite(vx_)
            & (dx_ > -half_len) & (dx_ - half_len <= d_o)
        )
    if not is_blocker.any():
        return 0.5 * road_width, float(v_desired), False

    y_j = agent_y + dy_[is_blocker]
    half_w = 0.5 * wids_[is_blocker]
    lo = np.clip(y_j - half_w, 0.0, road_width)
    hi = np.clip(y_j + half_w, 0.0, road_width)
    order = np.argsort(lo, kind="stable")
    lo, hi = lo[order], hi[order]
    # Free intervals: gaps between the running maximum of occupied upper ends and the next lower end.
    starts = np.concatenate(([0.0], np.maximum.accumulate(hi)))
    ends = np.concatenate((lo, [road_width]))
    fits = (ends - starts) >= agent_wid + 2.0 * margin
    if fits.any():
        starts, ends = starts[fits], ends[fits]
        dist = np.maximum(0.0, np.maximum(starts - agent_y, agent_y - ends))
        candidates = np.flatnonzero(dist <= dist.min() + _TIE_TOL_M)
        k = candidates[np.argmax(starts[candidates])]  # tie -> the leftmost (largest y) zone
        return float(0.5 * (starts[k] + ends[k])), float(v_desired), False

    vx_b = vx_[is_blocker]
    fastest = int(np.argmax(vx_b))
    return float(agent_y + dy_[is_blocker][fastest]), float(min(v_desired, vx_b.min())), True


# --------------------------------------------------------------------------------------------
# Costs, events, combination
# --------------------------------------------------------------------------------------------


def longitudinal_cost(
    vx: float,
    v_d_eff: float,
    *,
    min_desired_speed: float = _DEFAULTS.min_desired_speed_mps,
) -> float:
    """``c_x = min(1, |vx − v_d,eff| / max(v_d,eff, min_desired_speed))`` (–); speeds in m/s."""
    return float(min(1.0, abs(vx - v_d_eff) / max(v_d_eff, min_desired_speed)))


def lateral_cost(y: float, y_d: float, road_width: float) -> float:
    """``c_y = |y − y_d| / W`` (–); y, y_d and road_width W in m."""
    return float(abs(y - y_d) / road_width)


def reciprocal_reward(
    c_x: ArrayLike,
    c_y: ArrayLike,
    c_f: ArrayLike,
    collided: ArrayLike,
    overtook: ArrayLike,
    w_x: float,
    w_y: float,
    w_f: float,
    *,
    epsilon_r: float = _DEFAULTS.epsilon_r,
    collision_reward: float = _DEFAULTS.collision_reward,
    overtake_reward: float = _DEFAULTS.overtake_reward,
    use_collision: bool = True,
    use_overtake: bool = True,
) -> float | np.ndarray:
    """Paper Eq. 16: ``ε_r/(ε_r + w_x c_x + w_y c_y + w_f c_f) + r_c·[collided]
    + r_o·[overtook and not collided]`` (–).

    ``overtook`` is an indicator (a count > 0 counts once: the bonus is per step, not per
    vehicle).  ``use_collision`` / ``use_overtake`` switch the r_c / r_o terms off (presets).
    Arrays broadcast; scalar inputs give a ``float``.
    """
    if all(np.ndim(v) == 0 for v in (c_x, c_y, c_f, collided, overtook)):  # one step: plain floats
        r0 = epsilon_r / (epsilon_r + w_x * float(c_x) + w_y * float(c_y) + w_f * float(c_f))  # type: ignore[arg-type]
        hit, passed = bool(collided), bool(overtook)
        return (r0 + (collision_reward if use_collision and hit else 0.0)
                + (overtake_reward if use_overtake and passed and not hit else 0.0))
    col = np.asarray(collided).astype(bool)
    ovt = np.asarray(overtook).astype(bool)
    denom = epsilon_r + w_x * np.asarray(c_x, float) + w_y * np.asarray(c_y, float) \
        + w_f * np.asarray(c_f, float)
    r = epsilon_r / denom
    if use_collision:
        r = r + np.where(col, collision_reward, 0.0)
    if use_overtake:
        r = r + np.where(ovt & ~col, overtake_reward, 0.0)
    return float(r) if np.ndim(r) == 0 else r


def detect_overtakes(
    prev_dx: ArrayLike,
    dx: ArrayLike,
    range_m: float,
    ring_length: float,
) -> int:
    """Number of vehicles the agent passed between two steps.

    prev_dx, dx: wrapped offsets (m) of the same vehicles (aligned by index) at the previous and
    the current step; NaN = not present / not in range.  A pass is ``prev_dx > 0`` and
    ``dx ≤ 0`` for a vehicle with ``|dx| ≤ range_m`` at both steps and ``|dx| < ring_length/4``
    at both steps, so a jump across the ring seam (dx ≈ ±L/2) is never a pass, nor is a vehicle
    entering or leaving range.
    """
    p, c = _rows(prev_dx, dx)
    quarter = 0.25 * ring_length
    with np.errstate(invalid="ignore"):
        valid = (
            np.isfinite(p) & np.isfinite(c)
            & (np.abs(p) <= range_m) & (np.abs(c) <= range_m)
            & (np.abs(p) < quarter) & (np.abs(c) < quarter)
        )
        passed = valid & (p > 0.0) & (c <= 0.0)
    return int(np.count_nonzero(passed))


def agent_overlaps(
    dx: ArrayLike,
    dy: ArrayLike,
    agent_len: float,
    agent_wid: float,
    lens: ArrayLike,
    wids: ArrayLike,
) -> bool:
    """Whether the agent's rectangle overlaps any vehicle's (SPEC §4).

    Overlap: ``|dx| < (agent_len + len_j)/2`` and ``|dy| < (agent_wid + wid_j)/2`` (m); touching
    edges do not overlap.
    """
    dx_, dy_, lens_, wids_ = _rows(dx, dy, lens, wids)
    with np.errstate(invalid="ignore"):
        hit = (np.abs(dx_) < 0.5 * (agent_len + lens_)) & (np.abs(dy_) < 0.5 * (agent_wid + wids_))
    return bool(hit.any())


# --------------------------------------------------------------------------------------------
# Presets
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RewardWeights:
    """Weights of one reward preset (paper Table 4): w_x, w_y, w_f (–) and the r_c / r_o switches."""

    w_x: float
    w_y: float
    w_f: float
    use_collision: bool
    use_overtake: bool

    @property
    def uses_zones(self) -> bool:
        """Zones (the lateral target) are evaluated only when w_y > 0."""
        return self.w_y > 0.0


# w_x = 0.35 when zones are on (w_y = 0.65), else 0.65 (SPEC §7 table).
PRESETS: dict[str, RewardWeights] = {
    "collision": RewardWeights(0.65, 0.0, 0.0, True, False),
    "overtake_collision": RewardWeights(0.65, 0.0, 0.0, True, True),
    "fields": RewardWeights(0.65, 0.0, 1.0, False, False),
    "fields_collision": RewardWeights(0.65, 0.0, 1.0, True, False),
    "fields_overtake_collision": RewardWeights(0.65, 0.0, 1.0, True, True),
    "zones_overtake_collision": RewardWeights(0.35, 0.65, 0.0, True, True),
    "fields_zones_overtake_collision": RewardWeights(0.35, 0.65, 1.0, True, True),
}


def get_preset(name: str) -> RewardWeights:
    """The weights of preset ``name``; ``ValueError`` listing the valid names if unknown."""
    try:
        return PRESETS[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown reward preset {name!r}; valid presets: {', '.join(PRESETS)}"
        ) from None


# --------------------------------------------------------------------------------------------
# One step
# --------------------------------------------------------------------------------------------


@dataclass
class RewardTerms:
    """Every term of one step's reward, for ``info`` (costs –, y_d m, v_d_eff m/s)."""

    c_x: float
    c_y: float
    c_f: float
    y_d: float
    v_d_eff: float
    blocked: bool
    collided: bool
    overtook: bool
    reward: float

    def as_dict(self) -> dict[str, Any]:
        """Plain dict of the terms."""
        return dict(self.__dict__)


def compute_reward(
    dx: ArrayLike,
    dy: ArrayLike,
    vx: ArrayLike,
    vy: ArrayLike,
    lens: ArrayLike,
    wids: ArrayLike,
    agent_y: float,
    agent_vx: float,
    agent_vy: float,
    agent_len: float,
    agent_wid: float,
    v_desired: float,
    road_width: float,
    weights: RewardWeights | str,
    *,
    observed: ArrayLike | None = None,
    collided: bool | None = None,
    overtook: bool | int = False,
    config: RewardConfig | None = None,
) -> RewardTerms:
    """Combine all terms for one step (paper Eq. 16) and return them.

    dx, dy, vx, vy, lens, wids: the vehicles in observation range (m, m, m/s, m/s, m, m) — the
    zones use all of them; the fields use the rows selected by ``observed`` (boolean mask or
    index array of the n observed neighbours; ``None`` = all rows).  Agent state: agent_y (m),
    agent_vx, agent_vy (m/s), dimensions (m), nominal ``v_desired`` (m/s); road_width W (m).
    ``weights``: a :class:`RewardWeights` or a preset name.

    ``collided``: ``None`` computes the overlap from the given rows (pass every vehicle within a
    few metres, or the env's own result).  ``overtook``: a bool or the count from
    :func:`detect_overtakes` (the env keeps the vehicle identities across steps).
    ``config``: the :class:`RewardConfig` whose constants are used (default: the defaults).

    When ``weights.w_y == 0`` zones are not evaluated: ``y_d = W/2``, ``v_d_eff = v_desired``,
    ``blocked = False``, ``c_y = 0``.  ``c_f`` is always computed (reported even when w_f = 0).
    """
    cfg = _DEFAULTS if config is None else config
    w = get_preset(weights) if isinstance(weights, str) else weights
    dx_, dy_, vx_, vy_, lens_, wids_ = _rows(dx, dy, vx, vy, lens, wids)

    if w.w_y > 0.0:
        y_d, v_d_eff, blocked = zone_target(
            dx_, dy_, vx_, lens_, wids_, agent_y, agent_vx, agent_len, agent_wid, v_desired,
            road_width, time_gap=cfg.zone_time_gap_s, margin=cfg.zone_margin_m,
        )
        c_y = lateral_cost(agent_y, y_d, road_width)
    else:
        y_d, v_d_eff, blocked, c_y = 0.5 * road_width, float(v_desired), False, 0.0

    c_x = longitudinal_cost(agent_vx, v_d_eff, min_desired_speed=cfg.min_desired_speed_mps)

    if observed is None:
        sel: Any = slice(None)
    else:
        sel = np.asarray(observed)
        if sel.dtype != bool:
            sel = sel.astype(int)  # an empty list would otherwise be a float index
    c_f = field_cost(
        dx_[sel], dy_[sel], agent_vx - vx_[sel], agent_vy - vy_[sel], agent_len, agent_wid,
        lens_[sel], wids_[sel],
        magnitude=cfg.field_magnitude, critical_exponents=cfg.critical_exponents,
        broad_exponents=cfg.broad_exponents, k_r=cfg.k_r_s_per_m, e_v=cfg.e_v_s_per_m,
    )

    if collided is None:
        collided = agent_overlaps(dx_, dy_, agent_len, agent_wid, lens_, wids_)
    collided = bool(collided)
    overtook = bool(overtook)

    reward = reciprocal_reward(
        c_x, c_y, c_f, collided, overtook, w.w_x, w.w_y, w.w_f,
        epsilon_r=cfg.epsilon_r, collision_reward=cfg.collision_reward,
        overtake_reward=cfg.overtake_reward,
        use_collision=w.use_collision, use_overtake=w.use_overtake,
    )
    return RewardTerms(c_x, c_y, c_f, float(y_d), float(v_d_eff), bool(blocked), collided,
                       overtook, float(reward))
