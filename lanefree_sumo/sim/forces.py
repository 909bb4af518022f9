"""The force-based lane-free background driver (specification §3), vectorised over all vehicles.

Array code (numpy, or torch through :mod:`.xp`): ``driver_accelerations`` maps the vehicles' arrays (``[N]`` of one
simulation, or ``[K, N]`` of a batch of runs padded to a common N, :mod:`~lanefree_sumo.sim.world`) to the
longitudinal and lateral accelerations (m/s²) that every vehicle would choose. The environment uses the rows of
background vehicles; the agent's row is ignored there. Padded rows (``present`` False) exert and feel no force.

Interpretation choices where specification §3 leaves room (documented here and in the README):

* A neighbour with ``dx ≥ 0`` is *ahead*; its force has ``f_x ≤ 0`` and counts as a repulsion.
  A neighbour with ``dx < 0`` is *behind*; its ``f_x > 0`` is a nudge.
* The x-wall (regulation step 1) applies only when at least one summed repulsion has f_x < 0.
* A ramp of zero width is a step: value 1 on the plateau side of the edge, 0 beyond it.
"""

from __future__ import annotations

import numpy as np

from lanefree_sumo.config import DriverConfig
from lanefree_sumo.sim.state import Bodies, pair_mask, pairwise_offsets, row_sum, take_rows, wrap
from lanefree_sumo.sim.xp import namespace


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
    xp = namespace(v, d)
    t = step_s
    disc = t * t * decel * decel - 4.0 * t * decel * v + 8.0 * decel * (t * v - d)
    root = xp.sqrt(xp.maximum(disc, 0.0))
    return xp.where(disc >= 0.0, (t * decel - 2.0 * v + root) / (2.0 * t), decel)


def symmetric_trapezoid(abs_t: np.ndarray, w: np.ndarray, l: np.ndarray) -> np.ndarray:
    """H(t, w, l, w) from |t|: clip((w + l − |t|)/w, 0, 1), a step |t| ≤ l where w = 0 (w ≥ 0).

    The fast form of :func:`trapezoid_h` for equal rise and fall, as both force ramps are."""
    xp = namespace(abs_t, w, l)
    num = (w + l) - abs_t
    with xp.errstate(divide="ignore", invalid="ignore"):
        out = xp.minimum(xp.maximum(num / w, 0.0), 1.0)  # w = 0: ±inf clipped to the step's 1 or 0 ...
    return xp.where(xp.isnan(out), 1.0, out)  # ... and 0/0 (the step's edge, |t| = l) is NaN: the step's 1


def strongest_mask(mag: np.ndarray, k: int) -> np.ndarray:
    """Per row (last axis), True at the (at most) k entries of largest magnitude ``mag`` among the non-zero
    ones (specification §3: the 6 repulsions, or 3 nudges, of largest magnitude are summed)."""
    xp = namespace(mag)
    nonzero = mag > 0.0
    if mag.shape[-1] <= k or (xp.is_numpy and nonzero.sum(axis=-1).max() <= k):
        return nonzero
    idx = xp.largest_k(mag, k)
    chosen = xp.zeros_like(nonzero)
    xp.put_along_axis(chosen, idx, True, axis=-1)
    return chosen & nonzero


def driver_accelerations(
    state: Bodies,
    cfg: DriverConfig,
    ring_length: np.ndarray | float,
    road_width: np.ndarray | float,
    step_s: float,
    edge_clearance: float = 0.0,
    offsets: tuple[np.ndarray, np.ndarray] | None = None,
    details: dict[str, np.ndarray] | None = None,
    bounds: tuple[np.ndarray | float, np.ndarray | float] | None = None,
    lateral_target: np.ndarray | float = 0.0,
    present: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Accelerations (ax, ay) in m/s² for every vehicle from the forces of its neighbours.

    Arrays are ``[..., N]`` (one simulation, or runs ``[K, N]``); ``ring_length`` and ``road_width`` are scalars
    or one per run, shape ``[..., 1]``. ``present`` (``[..., N]``, None: all): the padded rows (False) exert
    and feel no force, and every sum over neighbours rounds as it would without them (:func:`row_sum`).
    Implements specification §3 in order: target-speed forces, pairwise trapezoid forces, the sums of the
    strongest repulsions (and nudges when ``cfg.nudging``), then the regulation steps 1–5.
    The road-edge bound (step 2) treats the edges as ``edge_clearance`` (m) inside the road, the
    line the dynamics clip at, so a driver that obeys it never touches the clip.
    ``offsets`` = (dx, dy) from :func:`~lanefree_sumo.sim.state.pairwise_offsets` if already computed.
    ``bounds`` = (lowest, highest) lateral position each vehicle's body may reach (m; scalars or one per
    vehicle, :meth:`~lanefree_sumo.sim.road.Road.bounds`); None: the ring's 0 and ``road_width``.
    ``lateral_target``: the lateral speed the target-speed force aims at (m/s; specification §3: 0; a merging ramp
    vehicle's is positive, :mod:`~lanefree_sumo.sim.open_road`).
    ``details``, if given, receives per-vehicle diagnostics: ``sum_fx`` (Σ of the summed
    repulsions' f_x), ``leader_gap_m`` (bumper gap to the x-wall leader, NaN without one) and
    ``wall_binds`` (the x-wall lowered F_x).
    """
    x, y, vx, vy = state.x, state.y, state.vx, state.vy
    length, width, vd = state.length, state.width, state.v_desired
    t = step_s
    xp = namespace(x)

    if offsets is None:
        offsets = pairwise_offsets(state, ring_length)
    dx, dy = offsets  # dx[i, j] = wrap(x_j − x_i), dy[i, j] = y_j − y_i
    abs_dx = xp.abs(dx)
    vx_j = vx[..., None, :]
    ahead = dx >= 0.0

    # lateral trapezoid first: it is zero for most pairs
    uy = xp.abs(vy[..., :, None] - vy[..., None, :])
    ly = uy * cfg.time_headway_y_s + cfg.lateral_ramp_offset_m
    half_wid = 0.5 * (width[..., :, None] + width[..., None, :])
    mag_y = symmetric_trapezoid(xp.abs(dy), ly, half_wid + cfg.lateral_margin_m)
    # longitudinal trapezoid: approach speed ux, ramp L_x/2, plateau L_x/2 + D_x + margin
    ux = xp.where(ahead, xp.maximum(0.0, vx[..., :, None] - (1.0 - cfg.speed_share_ahead) * vx_j), vx_j)
    half_len = 0.5 * (length[..., :, None] + length[..., None, :])
    lx_half = (0.5 * cfg.time_headway_x_s) * vx[..., :, None]
    gain_x = cfg.effective_gain_x  # k_x = c_x
    plateau = lx_half + (ux * ux) / (2.0 * gain_x) + half_len + cfg.longitudinal_margin_m
    mag = symmetric_trapezoid(abs_dx, lx_half, plateau) * mag_y
    xp.fill_where(mag, abs_dx > cfg.neighbour_range_m, 0.0)
    if present is None:
        xp.fill_diagonal(mag, 0.0)
        count = None
    else:
        xp.fill_where(mag, ~pair_mask(present), 0.0)
        count = present.sum(axis=-1)[..., None]  # each run's vehicles: its rows' sums round as unpadded

    dist = xp.sqrt(dx * dx + dy * dy)
    scale = xp.divide_where(mag, dist, 0.0)
    fx = -dx * scale  # −cos θ · mag
    fy = -dy * scale  # −sin θ · mag

    summed = strongest_mask(xp.where(ahead, mag, 0.0), cfg.max_repulsions)
    rep_fx = xp.where(summed, fx, 0.0)
    sum_fx = row_sum(rep_fx, count)
    sum_fy = row_sum(xp.where(summed, fy, 0.0), count)
    if cfg.nudging:
        nudges = strongest_mask(xp.where(ahead, 0.0, mag), cfg.max_nudges)
        sum_fx = sum_fx + cfg.nudge_scale_x * row_sum(xp.where(nudges, fx, 0.0), count)
        sum_fy = sum_fy + cfg.nudge_scale_y * row_sum(xp.where(nudges, fy, 0.0), count)

    fts_x = xp.erfc(vx - vd) - 1.0
    fts_y = xp.erfc(vy - lateral_target) - 1.0
    ax = gain_x * sum_fx + fts_x
    ay = cfg.coef_fy * sum_fy + fts_y

    # 1. x-wall towards the summed repulsion of largest degree δ (the most negative f_x)
    leader = xp.argmin(rep_fx, axis=-1)
    lead_fx = xp.min(rep_fx, axis=-1)  # the value at the leader
    has_leader = lead_fx < 0.0
    degree = xp.power(xp.abs(xp.clip(lead_fx, -1.0, 1.0)), cfg.wall_exponent)

    def of_leader(a: np.ndarray) -> np.ndarray:
        return take_rows(a, leader)

    gap = wrap((of_leader(x) - 0.5 * of_leader(length)) - (x + 0.5 * length), ring_length)
    v_safe = xp.minimum(gap / cfg.wall_time_gap_s, of_leader(vx) - cfg.wall_speed_margin_mps)
    wall = ((1.0 - degree) * (vd - vx) + degree * (v_safe - vx)) / t
    if details is not None:
        details["sum_fx"] = row_sum(rep_fx, count)
        details["leader_gap_m"] = xp.where(has_leader, gap, xp.nan)
        details["wall_binds"] = has_leader & (wall < ax)
    ax = xp.where(has_leader, xp.minimum(ax, wall), ax)

    # 2. road edges
    ubar = cfg.edge_decel_mps2
    k = cfg.edge_speed_factor
    lo, hi = (0.0, road_width) if bounds is None else bounds
    room_left = xp.maximum(0.0, hi - edge_clearance - y - 0.5 * width)
    room_right = xp.maximum(0.0, y - lo - edge_clearance - 0.5 * width)
    ay = xp.minimum(ay, edge_bound(k * vy, room_left, t, ubar))
    ay = xp.maximum(ay, -edge_bound(-k * vy, room_right, t, ubar))

    # 3. hard bounds
    b = cfg.bounds
    ax = xp.clip(ax, b.ax_min, b.ax_max)
    ay = xp.clip(ay, b.ay_min, b.ay_max)

    # 4. no reversing, no excessive speed
    ax = xp.maximum(ax, -vx / t)
    ax = xp.minimum(ax, (cfg.overspeed_factor * vd - vx) / t)

    # 5. lateral speed at most a share of the longitudinal speed
    r = cfg.lateral_speed_ratio
    ay = xp.minimum(ay, (r * vx - vy) / t)
    ay = xp.maximum(ay, -(r * vx + vy) / t)
    ay = xp.clip(ay, b.ay_min, b.ay_max)  # the lateral hard bound again (specification §3)
    return ax, ay
