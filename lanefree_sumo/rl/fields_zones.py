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
from lanefree_sumo.sim.xp import namespace

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
    e_c, e_b = field_terms(dx_, dy_, dvx_, dvy_, agent_len, agent_wid, lens_, wids_, magnitude=magnitude,
                           critical_exponents=critical_exponents, broad_exponents=broad_exponents, k_r=k_r, e_v=e_v,
                           stretch=stretch)
    return min(1.0, float(e_c.sum() + e_b.sum()))


def field_terms(
    dx: np.ndarray,
    dy: np.ndarray,
    dvx: np.ndarray,
    dvy: np.ndarray,
    agent_len: np.ndarray | float,
    agent_wid: np.ndarray | float,
    lens: np.ndarray,
    wids: np.ndarray,
    *,
    magnitude: float,
    critical_exponents: tuple[float, float, float],
    broad_exponents: tuple[float, float, float],
    k_r: float,
    e_v: float,
    stretch: str,
) -> tuple[np.ndarray, np.ndarray]:
    """Each neighbour's critical and broad field values (E_c, E_b), element-wise over arrays of any shape (the
    agent's dimensions broadcast against them); :func:`field_cost` sums them. Arguments as there."""
    xp = namespace(dx)
    a_c = 0.5 * (agent_len + lens)
    b_c = 0.5 * (agent_wid + wids)
    rx = xp.abs(dx) / a_c
    ry = xp.abs(dy) / b_c
    if stretch == "absolute":
        ux, uy = xp.abs(dvx), xp.abs(dvy)
    elif stretch == "closing":
        ux = xp.maximum(0.0, xp.sign(dx) * dvx)
        uy = xp.maximum(0.0, xp.sign(dy) * dvy)
    else:
        raise ValueError(f"stretch must be 'closing' or 'absolute', got {stretch!r}")
    pcx, pcy, pct = critical_exponents
    pbx, pby, pbt = broad_exponents
    # the ellipsoid() formula, on |dx|/a and |dy|/b computed once
    pw = xp.power
    # xp.divide, not ``number / array``: torch's number / tensor multiplies by a reciprocal
    e_c = xp.divide(magnitude, pw(pw(rx, pcx) + pw(ry, pcy) + 1.0, pct))
    e_b = xp.divide(magnitude, pw(pw(rx / (1.0 + k_r * ux), pbx) + pw(ry / (1.0 + e_v * uy), pby) + 1.0, pbt))
    return e_c, e_b


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
    y_d, v_d_eff, blocked = zone_targets(
        dx_[None], dy_[None], vx_[None], lens_[None], wids_[None], np.array([agent_y]), np.array([agent_vx]),
        agent_len, agent_wid, np.array([v_desired], dtype=float), np.array([road_width], dtype=float),
        time_gap=time_gap, margin=margin,
    )
    return float(y_d[0]), float(v_d_eff[0]), bool(blocked[0])


def zone_targets(
    dx: np.ndarray,
    dy: np.ndarray,
    vxs: np.ndarray,
    lens: np.ndarray,
    wids: np.ndarray,
    agent_y: np.ndarray,
    agent_vx: np.ndarray,
    agent_len: ArrayLike,
    agent_wid: ArrayLike,
    v_desired: np.ndarray,
    road_width: np.ndarray,
    *,
    time_gap: float,
    margin: float,
    present: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`zone_target` of many agents at once: vehicle rows ``[..., M]`` (in array order; non-finite or not
    ``present`` rows are absent), the agents' values ``[...]``; returns ``(y_d, v_d_eff, blocked)`` ``[...]``,
    each agent's bit for bit as :func:`zone_target` gives it from its present rows alone.

    The free intervals are found as there, with the absent rows sorted last as empty extents (lower end +∞,
    upper end −∞): they leave the running maximum alone and their intervals are not candidates."""
    xp = namespace(dx)
    shape = tuple(dx.shape[:-1])
    if dx.shape[-1] == 0:  # no vehicle at all: one absent row keeps the reductions below defined
        dx, dy, vxs, lens, wids = (xp.full(shape + (1,), xp.nan) for _ in range(5))
        present = None

    def row(value: ArrayLike) -> np.ndarray:
        a: np.ndarray = xp.asarray(value, dtype=float)
        return (a if tuple(a.shape) == shape else xp.broadcast_to(a, shape))[..., None]

    y_a, vx_a, len_a, wid_a, width = row(agent_y), row(agent_vx), row(agent_len), row(agent_wid), row(road_width)
    v_desired = row(v_desired)[..., 0]
    half_len = 0.5 * (len_a + lens)
    d_o = vx_a * time_gap
    with xp.errstate(invalid="ignore"):
        is_blocker = xp.isfinite(dx) & xp.isfinite(dy) & xp.isfinite(vxs) & (dx > -half_len) & (dx - half_len <= d_o)
    if present is not None:
        is_blocker = is_blocker & present
    any_blocker = xp.any(is_blocker, axis=-1)
    if xp.is_numpy and not any_blocker.any():  # a shortcut with the same result: no blocker anywhere
        return 0.5 * width[..., 0], v_desired.copy(), any_blocker

    y_j = y_a + dy
    half_w = 0.5 * wids
    # clipped to the road: minimum(maximum(·)), numpy's clip without its wrapper's cost
    lo = xp.where(is_blocker, xp.minimum(xp.maximum(y_j - half_w, 0.0), width), xp.inf)
    hi = xp.where(is_blocker, xp.minimum(xp.maximum(y_j + half_w, 0.0), width), -xp.inf)
    order = xp.argsort_stable(lo, axis=-1)
    lo, hi = xp.take_along_axis(lo, order, -1), xp.take_along_axis(hi, order, -1)
    # Free intervals: gaps between the running maximum of occupied upper ends and the next lower end.
    starts = xp.concatenate((xp.zeros(shape + (1,)), xp.accumulate_max(hi, axis=-1)), axis=-1)
    ends = xp.concatenate((lo, width), axis=-1)
    real = xp.concatenate((xp.take_along_axis(is_blocker, order, -1), xp.ones(shape + (1,), dtype=bool)), axis=-1)
    with xp.errstate(invalid="ignore"):
        fits = real & ((ends - starts) >= wid_a + 2.0 * margin)
        dist = xp.maximum(0.0, xp.maximum(starts - y_a, y_a - ends))
    nearest = xp.min(xp.where(fits, dist, xp.inf), axis=-1, keepdims=True)
    candidates = fits & (dist <= nearest + _TIE_TOL_M)
    k = xp.argmax(xp.where(candidates, starts, -xp.inf), axis=-1)[..., None]  # tie -> the leftmost (largest y)
    y_zone = (0.5 * (xp.take_along_axis(starts, k, -1) + xp.take_along_axis(ends, k, -1)))[..., 0]
    any_fit = xp.any(fits, axis=-1)

    # no zone fits: the fastest blocker (the first in array order among equally fast ones)
    fastest = xp.argmax(xp.where(is_blocker, vxs, -xp.inf), axis=-1)[..., None]
    y_fast = (y_a + xp.take_along_axis(dy, fastest, -1))[..., 0]
    slowest = xp.min(xp.where(is_blocker, vxs, xp.inf), axis=-1)
    blocked = any_blocker & ~any_fit
    y_d = xp.where(any_blocker, xp.where(any_fit, y_zone, y_fast), 0.5 * width[..., 0])
    return y_d, xp.where(blocked, xp.minimum(v_desired, slowest), v_desired), blocked
