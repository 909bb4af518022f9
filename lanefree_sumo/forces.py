"""The force-based lane-free background driver (SPEC §3), vectorised over all vehicles.

Pure numpy: ``driver_accelerations`` maps a :class:`~lanefree_sumo.state.VehicleState` to the
longitudinal and lateral accelerations (m/s²) that every vehicle would choose.  The environment
uses the rows of background vehicles; the agent's row is ignored there.

Interpretation choices where SPEC §3 leaves room (documented here and in the README):

* A neighbour with ``dx ≥ 0`` is *ahead*; its force has ``f_x ≤ 0`` and counts as a repulsion.
  A neighbour with ``dx < 0`` is *behind*; its ``f_x > 0`` is a nudge.
* "The 6 largest repulsions" are the 6 with the largest ``|f_x|``; their ``f_y`` is summed
  with them.  Nudges likewise by the largest ``f_x``.
* The x-wall (regulation step 1) applies only when at least one summed repulsion is non-zero.
* A ramp of zero width is a step: value 1 on the plateau side of the edge, 0 beyond it.
"""

from __future__ import annotations

import numpy as np
from scipy.special import erfc

from .config import DriverConfig
from .state import VehicleState, wrap


def _ratio(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num/den where den > 0; ±inf (or 0 for num = 0) where den = 0, so ramps become steps."""
    num, den = np.broadcast_arrays(np.asarray(num, float), np.asarray(den, float))
    out = np.where(num > 0, np.inf, np.where(num < 0, -np.inf, 0.0))
    np.divide(num, den, out=out, where=den > 0)
    return out


def ramp_g(t: np.ndarray, w: np.ndarray, l: np.ndarray, c: np.ndarray) -> np.ndarray:
    """G(t, w, l, c) = max(0, min(1, t/w, 1 − (t − w − l)/c)): rise over [0, w], plateau of
    length l, fall over c.  Zero-width rises/falls are steps."""
    rise = _ratio(t, w)
    fall = 1.0 - _ratio(np.asarray(t, float) - w - l, c)
    return np.clip(np.minimum(rise, fall), 0.0, 1.0)


def trapezoid_h(t: np.ndarray, w: np.ndarray, l: np.ndarray, c: np.ndarray) -> np.ndarray:
    """H(t, w, l, c) = G(t + w + l, w, 2l, c): plateau on [−l, l], rise w before, fall c after."""
    return ramp_g(np.asarray(t, float) + w + l, w, 2.0 * np.asarray(l, float), c)


def edge_bound(v: np.ndarray, d: np.ndarray, step_s: float, decel: float) -> np.ndarray:
    """U(v, d, ū): the largest acceleration now (m/s²) after which braking at ``decel`` (ū < 0)
    still stops a body moving at ``v`` (m/s) towards an edge ``d`` (m) away before reaching it.
    Where the root is not real, U = ū."""
    t = step_s
    disc = t * t * decel * decel - 4.0 * t * decel * v + 8.0 * decel * (t * v - d)
    root = np.sqrt(np.maximum(disc, 0.0))
    return np.where(disc >= 0.0, (t * decel - 2.0 * v + root) / (2.0 * t), decel)


def _top_k_sum(
    values: np.ndarray, other: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row, the k entries of ``values`` with the largest magnitude (values are all ≤ 0 or
    all ≥ 0 per entry), summed, with the matching entries of ``other`` summed, and the column of
    the largest one.  k ≥ number of columns takes all."""
    n_cols = values.shape[1]
    mag = np.abs(values)
    if k < n_cols:
        idx = np.argpartition(-mag, k - 1, axis=1)[:, :k]
        sel = np.take_along_axis(values, idx, axis=1)
        sel_other = np.take_along_axis(other, idx, axis=1)
    else:
        sel, sel_other = values, other
    strongest = np.argmax(mag, axis=1)
    return sel.sum(axis=1), sel_other.sum(axis=1), strongest


def driver_accelerations(
    state: VehicleState,
    cfg: DriverConfig,
    ring_length: float,
    road_width: float,
    step_s: float,
    edge_clearance: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Accelerations (ax, ay) in m/s² for every vehicle from the forces of its neighbours.

    Implements SPEC §3 in order: target-speed forces, pairwise trapezoid forces, the sums of the
    strongest repulsions (and nudges when ``cfg.nudging``), then the regulation steps 1–5.
    The road-edge bound (step 2) treats the edges as ``edge_clearance`` (m) inside the road, the
    line the dynamics clip at, so a driver that obeys it never touches the clip.
    """
    x, y, vx, vy = state.x, state.y, state.vx, state.vy
    length, width, vd = state.length, state.width, state.v_desired
    n = state.n
    t = step_s

    dx = wrap(x[None, :] - x[:, None], ring_length)  # dx[i, j] = x_j − x_i
    dy = y[None, :] - y[:, None]
    vx_i = vx[:, None]
    vx_j = vx[None, :]
    ahead = dx >= 0.0

    # approach speeds and ramp sizes (m/s, m)
    ux = np.where(ahead, np.maximum(0.0, vx_i - (1.0 - cfg.speed_share_ahead) * vx_j), vx_j)
    uy = np.abs(vy[:, None] - vy[None, :])
    half_len = 0.5 * (length[:, None] + length[None, :])
    half_wid = 0.5 * (width[:, None] + width[None, :])
    lx_half = 0.5 * vx * cfg.time_headway_x_s  # L_x / 2, per vehicle i
    dist_x = ux * ux / (2.0 * cfg.braking_decel_mps2) + half_len
    lx = lx_half[:, None]
    mag_x = trapezoid_h(dx, lx, lx + dist_x + cfg.longitudinal_margin_m, lx)
    ly = uy * cfg.time_headway_y_s + cfg.lateral_ramp_offset_m
    mag_y = trapezoid_h(dy, ly, half_wid + cfg.lateral_margin_m, ly)
    mag = mag_x * mag_y

    in_range = np.abs(dx) <= cfg.neighbour_range_m
    np.fill_diagonal(in_range, False)
    mag = np.where(in_range, mag, 0.0)
    dist = np.hypot(dx, dy)
    safe = np.where(dist > 0.0, dist, 1.0)
    fx = np.where(dist > 0.0, -dx / safe, 0.0) * mag  # −cos θ · mag
    fy = np.where(dist > 0.0, -dy / safe, 0.0) * mag  # −sin θ · mag

    rep_fx = np.where(ahead, fx, 0.0)
    rep_fy = np.where(ahead, fy, 0.0)
    sum_fx, sum_fy, leader = _top_k_sum(rep_fx, rep_fy, cfg.max_repulsions)
    if cfg.nudging:
        nud_fx = np.where(ahead, 0.0, fx)
        nud_fy = np.where(ahead, 0.0, fy)
        nfx, nfy, _ = _top_k_sum(nud_fx, nud_fy, cfg.max_nudges)
        sum_fx = sum_fx + cfg.nudge_scale_x * nfx
        sum_fy = sum_fy + cfg.nudge_scale_y * nfy

    fts_x = erfc(vx - vd) - 1.0
    fts_y = erfc(vy) - 1.0
    ax = cfg.coef_fx * sum_fx + fts_x
    ay = cfg.coef_fy * sum_fy + fts_y

    # 1. x-wall towards the strongest summed repulsion
    rows = np.arange(n)
    lead_fx = rep_fx[rows, leader]
    has_leader = lead_fx < 0.0
    degree = np.abs(np.clip(lead_fx, -1.0, 1.0)) ** cfg.wall_exponent
    gap = wrap(
        (x[leader] - 0.5 * length[leader]) - (x + 0.5 * length), ring_length
    )
    v_safe = np.minimum(gap / cfg.wall_time_gap_s, vx[leader] - cfg.wall_speed_margin_mps)
    wall = ((1.0 - degree) * (vd - vx) + degree * (v_safe - vx)) / t
    ax = np.where(has_leader, np.minimum(ax, wall), ax)

    # 2. road edges
    ubar = cfg.edge_decel_mps2
    k = cfg.edge_speed_factor
    room_left = np.maximum(0.0, road_width - edge_clearance - y - 0.5 * width)
    room_right = np.maximum(0.0, y - edge_clearance - 0.5 * width)
    ay = np.minimum(ay, edge_bound(k * vy, room_left, t, ubar))
    ay = np.maximum(ay, -edge_bound(-k * vy, room_right, t, ubar))

    # 3. hard bounds
    b = cfg.bounds
    ax = np.clip(ax, b.ax_min, b.ax_max)
    ay = np.clip(ay, b.ay_min, b.ay_max)

    # 4. no reversing, no excessive speed
    ax = np.maximum(ax, -vx / t)
    ax = np.minimum(ax, (cfg.overspeed_factor * vd - vx) / t)

    # 5. lateral speed at most a share of the longitudinal speed
    r = cfg.lateral_speed_ratio
    ay = np.minimum(ay, (r * vx - vy) / t)
    ay = np.maximum(ay, -(r * vx + vy) / t)
    return ax, ay
