"""Potential fields and overtaking zones of the reward (specification §7; Karalakou et al. 2023).

Pure numpy, SI units. ``ellipsoid``/``field_cost`` give the fields cost c_f from the observed
neighbours; ``zone_target`` the lateral target y_d and the effective desired speed. Re-exported by
:mod:`lanefree_sumo.rl.rewards`, whose
docstring states the conventions shared by these functions.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from lanefree_sumo.config import RewardConfig

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
    stretch: str = _DEFAULTS.broad_stretch,
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
    exactly aligned (dx = 0) neighbour does not stretch the region.  ``stretch="absolute"`` uses
    ``ux = |dvx|``, ``uy = |dvy|`` instead (any speed difference stretches).  Both regions peak at
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
    if stretch == "absolute":
        ux, uy = np.abs(dvx_), np.abs(dvy_)
    elif stretch == "closing":
        ux = np.maximum(0.0, np.sign(dx_) * dvx_)
        uy = np.maximum(0.0, np.sign(dy_) * dvy_)
    else:
        raise ValueError(f"stretch must be 'closing' or 'absolute', got {stretch!r}")
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
    """Lateral target and effective desired speed from the overtaking zones (specification §7 "Zones").

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
