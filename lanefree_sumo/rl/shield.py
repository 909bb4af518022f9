"""A safety shield for the agent: the closest action it can certify, by worst-case reasoning on
the double integrator. Pure numpy on the state arrays: no SUMO, no gym.

**Model.** Every vehicle moves by the ballistic update of specification §2 with step T and vx ≥ 0. The
agent's command is clipped to its bounds and top speed (``clip_acceleration``) and its lateral
move at the road edges as in :func:`~lanefree_sumo.sim.dynamics.plan_step`; the shield predicts
the agent's next state with exactly these functions. A background vehicle j may do anything
within its bounds (specification §3: F_x ∈ [−b_L, a_L] = [−4, 2], |F_y| ≤ 1 m/s²).

**Braking distance.** Braking at b from speed v under the ballistic update with the v ≥ 0 floor
covers ``S_b(v) = v²/(2b) + r·(bT − r)/(2b)``, r = v mod bT (at most bT²/8 more than v²/(2b)).
Two vehicles braking at the same b keep a bumper gap of at least ``g − max(0, S_b(v_rear) −
S_b(v_front))`` at every step (the rear one is the faster one at every step, or never).

**Rule.** Let the agent's *committed lateral interval* after a candidate action be the lateral
band its body sweeps if from the next step on it brakes laterally at its bound (ay_b = 1.8)
until vy = 0: [y', y' + sign(vy')·S_ay_b(|vy'|)] ± w/2, inside the road. Let vehicle j's *reach*
be the band its body can cover within the horizon H at its lateral bound from its current y, vy
(``|vy|·H + ½·H²`` towards either side, inside the road), widened by ``margin_y``. j is *in the
corridor* of a candidate when the two bands intersect. With dx the ring offset of j and
``len = (l_a + l_j)/2``, a candidate (ax, ay) is **certified** when, for every vehicle j:

1. *ahead* (dx ≥ len, bumper gap g = dx − len) and in the corridor: after the step, with j braking
   at b_L (its worst case), the gap is at least ``max(0, S_b(vx'_a) − S_bL(vx'_j)) + margin_x``
   with b = min(agent's brake, b_L). This is an upper bound on the agent's next speed, in closed
   form (``S_b(u) + u·T/2`` is piecewise linear in u): :func:`max_speed_behind`;
2. *alongside* (|dx| < len): j is not in the corridor — no lateral move into the lateral extent,
   or reach, of a vehicle overlapping longitudinally; and *behind but able to come alongside
   within the horizon* (bumper gap ≤ (vx_j − vx_a)⁺·H + ½·(a_L + b_L)·H² + margin_x): the
   candidate's band reaches no deeper into j's reach than the current band does — no lateral move
   towards a vehicle that can overlap longitudinally within the horizon;
3. *behind* (dx ≤ −len) and in the corridor although not in the corridor of the agent's current
   state (the agent's own lateral move would put it in front of j): after the step, with j
   accelerating at a_L, the gap leaves j its braking distance, ``g ≥ max(0, S_bL(vx'_j) −
   S_bL(vx'_a)) + margin_x`` — a lower bound on the agent's next speed: :func:`min_speed_ahead`;
4. follower rule: when a vehicle behind in the corridor is within its own braking distance
   S_bL(vx_j) + margin_x, ax ≥ −b_L (the agent never brakes harder than its followers can),
   unless only harder braking satisfies rule 1.

For a given ay the certified ax form one interval, so the shield returns, over the policy's ay,
the ay that stops lateral motion in one step and ``lateral_candidates`` evenly spaced values, the
certified (ax, ay) closest to the policy's clipped action (Euclidean, m/s²); the policy's action
itself whenever it is certified. When no candidate is certified it falls back to the candidate
(on a grid of ax too, braking at the bounds included) that minimises the largest violation in
metres, ties going to the closest (with ``shield.fallback_steers_clear``, first to those whose committed band
reaches least deep into the reach of the vehicles ahead they are too close to).

**Invariant.** I(s): no overlap; the gap of rule 1 to every vehicle ahead in the corridor of the
agent's *current* committed interval; no vehicle alongside in that corridor.

**Guarantee** (assumptions: A1 every background acceleration within its bounds — true of the
force model, whose last regulation steps clip to them; A2 H ≥ T. A background vehicle clipped at
a road edge stays inside its reach, which is clipped there too):

* *one step*: a certified action leaves the agent, for EVERY background acceleration within the
  bounds, not overlapping any vehicle at the next step, except a vehicle behind that was already in
  the corridor of the agent's current state (a follower closing in on the agent: the follower's
  responsibility; rule 4 makes the agent never brake harder than that follower can);
* *recursion*: after a certified step, braking at b with the lateral brake is certified again with
  respect to every vehicle that was in the corridor (with b = b_L, as here, the margin of rule 1
  is exactly conserved when both brake, and the committed interval only shrinks). So a certified
  action fails to exist only when another vehicle's reach newly meets the agent's committed
  interval — it moved laterally towards the agent (a cut-in ahead, a side drift) — or a follower
  already in the corridor came alongside: not caused by the agent; then the fallback minimises
  the violation.

So the agent causes no overlap: it never runs into a vehicle ahead that stays within its bounds,
never moves laterally into a vehicle beside it (or towards one about to come alongside), never
cuts in front of a follower without leaving that follower its braking distance, and never brakes
harder than a close follower can. What is left — followers that do not brake enough, lateral
drifts into the agent — is measured (``lanefree rollout --shield``, README "Safety shield").
``tests/rl/test_shield.py`` checks both parts over random scenes. This is Responsibility-Sensitive
Safety (Shalev-Shwartz et al. 2017) in discrete time with a one-step response.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lanefree_sumo.config import AccelerationBounds, ConfigError, LaneFreeConfig, ShieldConfig
from lanefree_sumo.sim.dynamics import clip_acceleration, plan_step
from lanefree_sumo.sim.road import road_of
from lanefree_sumo.sim.state import VehicleState, wrap

Bounds = tuple[np.ndarray | float, np.ndarray | float]
"""(lowest, highest) lateral position of each vehicle's body (m): arrays over the state's rows, or scalars."""
_SAME = 1e-9
"""Actions closer than this (m/s²) are the same action: no intervention."""
_ROUNDING = 1e-9
"""A speed bound this far below 0 (m/s) is 0: floating-point rounding of a gap kept exactly at
rule 1's bound in the previous step (it costs at most 2.5e-10 m)."""
_FALLBACK_AX = 13
"""Evenly spaced ax values of the fallback grid (besides the policy's ax and −b_L)."""


@dataclass(frozen=True)
class ShieldParams:
    """Everything the shield needs besides the state (SI units)."""

    step_s: float
    road_width_m: float
    ring_length_m: float
    agent_bounds: AccelerationBounds
    background_bounds: AccelerationBounds
    agent_max_speed_mps: float = math.inf
    horizon_s: float = ShieldConfig.horizon_s
    margin_x_m: float = ShieldConfig.margin_x_m
    margin_y_m: float = ShieldConfig.margin_y_m
    lateral_candidates: int = ShieldConfig.lateral_candidates
    edge_clearance_m: float = 1e-3
    edge_contact_tolerance_m: float = 1e-6
    fallback_steers_clear: bool = ShieldConfig.fallback_steers_clear

    def __post_init__(self) -> None:
        a, b = self.agent_bounds, self.background_bounds
        if not self.step_s > 0 or self.horizon_s < self.step_s:
            raise ConfigError(f"shield horizon {self.horizon_s:g} s must be at least one step ({self.step_s:g} s)")
        if not (a.ax_min < 0 < a.ax_max and a.ay_min < 0 < a.ay_max and b.ax_min < 0 < b.ax_max
                and b.ay_min < 0 < b.ay_max):
            raise ConfigError("the shield needs acceleration bounds with braking and accelerating on both axes")

    @classmethod
    def from_config(cls, cfg: LaneFreeConfig) -> ShieldParams:
        s = cfg.shield
        return cls(
            cfg.sim.step_s, cfg.road.width_m, road_of(cfg).wrap_length, cfg.scenario.agent_bounds,
            cfg.scenario.driver.bounds,
            cfg.scenario.agent_max_speed_mps, s.horizon_s, s.margin_x_m, s.margin_y_m, s.lateral_candidates,
            cfg.sim.edge_clearance_m, cfg.sim.edge_contact_tolerance_m, s.fallback_steers_clear,
        )

    @property
    def leader_brake(self) -> float:
        """b_L: the hardest braking of a background vehicle (m/s², > 0)."""
        return -self.background_bounds.ax_min

    @property
    def agent_brake(self) -> float:
        """b: the braking the agent's longitudinal certificate assumes, min(agent's, b_L) (m/s²)."""
        return min(-self.agent_bounds.ax_min, self.leader_brake)

    @property
    def agent_lateral_brake(self) -> float:
        """ay_b: the lateral braking of the agent's committed interval (m/s²)."""
        return min(-self.agent_bounds.ay_min, self.agent_bounds.ay_max)

    @property
    def background_lateral(self) -> float:
        """The largest lateral acceleration of a background vehicle (m/s²)."""
        return max(-self.background_bounds.ay_min, self.background_bounds.ay_max)


@dataclass(frozen=True)
class ShieldDecision:
    """What the shield did with one action."""

    ax: float
    """Longitudinal acceleration to command (m/s²)."""
    ay: float
    """Lateral acceleration to command (m/s²)."""
    intervened: bool
    """The action differs from the policy's (after the clip to the agent's bounds and top speed)."""
    correction: float
    """Norm of the change, |(ax, ay) − policy's clipped (ax, ay)| (m/s²)."""
    certified: bool
    """False when no candidate was certified and this is the least-violating fallback."""


# -- closed forms on the double integrator ----------------------------------------------------

def stopping_distance(v: np.ndarray | float, decel: float, step_s: float) -> np.ndarray:
    """S_b(v): distance (m) covered from speed v (m/s) braking at ``decel`` b (m/s²) under the
    ballistic update with the v ≥ 0 floor: v²/(2b) + r·(bT − r)/(2b), r = v mod bT."""
    v = np.maximum(np.asarray(v, dtype=float), 0.0)
    bt = decel * step_s
    r = np.mod(v, bt)
    return (v * v + r * (bt - r)) / (2.0 * decel)


def _travel(u: np.ndarray, decel: float, step_s: float) -> np.ndarray:
    """φ(u) = S_b(u) + u·T/2: the braking distance after a step ending at speed u, plus that step's
    share of u (m). Piecewise linear: b·T²·n(n + 1)/2 at u = n·b·T."""
    return stopping_distance(u, decel, step_s) + 0.5 * step_s * np.asarray(u, dtype=float)


def _travel_inverse(k: np.ndarray, decel: float, step_s: float) -> np.ndarray:
    """The speed u ≥ 0 with φ(u) = k (k ≥ 0; 0 for k ≤ 0) (m/s)."""
    k = np.maximum(np.asarray(k, dtype=float), 0.0)
    bt2 = decel * step_s * step_s
    n = np.floor((np.sqrt(1.0 + 8.0 * k / bt2) - 1.0) / 2.0)
    r = (k - 0.5 * bt2 * n * (n + 1.0)) / ((n + 1.0) * step_s)
    return n * decel * step_s + np.clip(r, 0.0, decel * step_s)


def max_speed_behind(gap: np.ndarray | float, v: float, v_leader: np.ndarray | float,
                     params: ShieldParams) -> np.ndarray:
    """Rule 1: the largest agent speed u at the end of this step (m/s) after which the bumper gap
    to a leader ``gap`` (m) ahead, moving at ``v_leader`` (m/s) and braking at b_L, still is
    ``max(0, S_b(u) − S_bL(v_L')) + margin_x``; negative when no u ≥ 0 qualifies.

    With c = g + (v_L + v_L')·T/2 − v·T/2 − margin_x the condition reads u·T/2 ≤ c and
    φ_b(u) ≤ c + S_bL(v_L'), so u* = min(2c/T, φ_b⁻¹(c + S_bL(v_L')))."""
    t, bl, b = params.step_s, params.leader_brake, params.agent_brake
    v_leader = np.asarray(v_leader, dtype=float)
    vl_next = np.maximum(v_leader - bl * t, 0.0)
    c = np.asarray(gap, dtype=float) + 0.5 * t * (v_leader + vl_next) - 0.5 * t * v - params.margin_x_m
    return np.minimum(2.0 * c / t, _travel_inverse(c + stopping_distance(vl_next, bl, t), b, t))


def _behind_terms(gap: np.ndarray, v: float, v_follower: np.ndarray, params: ShieldParams
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(G, S_bL(v_j')) of rule 3: G = g − (v_j + v_j')·T/2 − margin_x + v·T/2 with the follower
    accelerating at a_L; the rule is G + u·T/2 ≥ max(0, S_bL(v_j') − S_bL(u))."""
    t, bl = params.step_s, params.leader_brake
    vf_next = v_follower + params.background_bounds.ax_max * t
    g = gap - 0.5 * t * (v_follower + vf_next) - params.margin_x_m + 0.5 * t * v
    return g, stopping_distance(vf_next, bl, t)


def min_speed_ahead(gap: np.ndarray | float, v: float, v_follower: np.ndarray | float,
                    params: ShieldParams) -> np.ndarray:
    """Rule 3: the smallest agent speed u at the end of this step (m/s) that leaves a follower
    ``gap`` (m) behind, moving at ``v_follower`` (m/s) and accelerating at a_L during the step,
    its braking distance: u ≥ max(−2G/T, φ_bL⁻¹(S_bL(v_j') − G)); 0 when no bound binds."""
    g, s_follower = _behind_terms(np.asarray(gap, dtype=float), v, np.asarray(v_follower, dtype=float), params)
    t = params.step_s
    need = _travel_inverse(s_follower - g, params.leader_brake, t)
    return np.maximum(np.maximum(-2.0 * g / t, need), 0.0)


def _road_lines(width: np.ndarray | float, params: ShieldParams, bounds: Bounds | None
                ) -> tuple[np.ndarray | float, np.ndarray | float]:
    """The lowest and highest centre line (m) of bodies of ``width``: inside the ring's [0, W], or inside
    ``bounds`` (each vehicle's own, on an open road)."""
    if bounds is None:
        return 0.5 * width + params.edge_clearance_m, params.road_width_m - 0.5 * width - params.edge_clearance_m
    return (bounds[0] + 0.5 * width + params.edge_clearance_m,
            bounds[1] - 0.5 * width - params.edge_clearance_m)


def reach_band(y: np.ndarray, vy: np.ndarray, width: np.ndarray, params: ShieldParams,
               bounds: Bounds | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) edges (m) of the band a body of ``width`` at ``y`` moving laterally at ``vy``
    can cover within the horizon at the background's lateral bound (inside the road: [0, W], or
    ``bounds`` per vehicle), widened by ``margin_y``."""
    h, a = params.horizon_s, params.background_lateral
    up = np.maximum(0.0, vy * h + 0.5 * a * h * h)
    down = np.maximum(0.0, -vy * h + 0.5 * a * h * h)
    lo_road, hi_road = _road_lines(width, params, bounds)
    low = np.minimum(np.maximum(y - down, lo_road), y)
    high = np.maximum(np.minimum(y + up, hi_road), y)
    return low - 0.5 * width - params.margin_y_m, high + 0.5 * width + params.margin_y_m


def committed_band(y: np.ndarray, vy: np.ndarray, width: float, params: ShieldParams,
                   bounds: Bounds | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) edges (m) of the band the agent's body sweeps from ``y`` if it brakes laterally
    at ay_b until vy = 0 (inside the road: [0, W], or its own ``bounds``)."""
    y = np.asarray(y, dtype=float)
    vy = np.asarray(vy, dtype=float)
    stop = y + np.sign(vy) * stopping_distance(np.abs(vy), params.agent_lateral_brake, params.step_s)
    lo_road, hi_road = _road_lines(width, params, bounds)
    low = np.minimum(np.maximum(np.minimum(y, stop), lo_road), y)
    high = np.maximum(np.minimum(np.maximum(y, stop), hi_road), y)
    return low - 0.5 * width, high + 0.5 * width


# -- the shield -------------------------------------------------------------------------------

@dataclass
class _Scene:
    """The other vehicles' quantities that do not depend on the candidate action."""

    ahead: np.ndarray
    alongside: np.ndarray
    behind: np.ndarray
    reach_lo: np.ndarray
    reach_hi: np.ndarray
    gap_ahead: np.ndarray
    gap_behind: np.ndarray
    vx: np.ndarray
    in_current_corridor: np.ndarray
    close_follower: np.ndarray
    soon_alongside: np.ndarray
    depth_now: np.ndarray


def _own(bounds: Bounds | None, rows: np.ndarray | int) -> Bounds | None:
    """The entries of per-vehicle ``bounds`` at ``rows`` (None stays None: the ring)."""
    if bounds is None:
        return None
    lo, hi = bounds
    return (lo[rows] if isinstance(lo, np.ndarray) else lo, hi[rows] if isinstance(hi, np.ndarray) else hi)


def _scene(agent: int, state: VehicleState, params: ShieldParams, bounds: Bounds | None = None) -> _Scene:
    others = np.arange(state.n) != agent
    dx = wrap(state.x[others] - state.x[agent], params.ring_length_m)
    half_len = 0.5 * (state.length[agent] + state.length[others])
    vx = state.vx[others]
    reach_lo, reach_hi = reach_band(state.y[others], state.vy[others], state.width[others], params,
                                    _own(bounds, others))
    c_lo, c_hi = committed_band(state.y[agent], state.vy[agent], float(state.width[agent]), params,
                                _own(bounds, agent))
    corridor = (c_hi > reach_lo) & (c_lo < reach_hi)
    gap_behind = -dx - half_len
    s_follower = stopping_distance(vx, params.leader_brake, params.step_s)
    h = params.horizon_s
    closing = (np.maximum(vx - state.vx[agent], 0.0) * h
               + 0.5 * (params.background_bounds.ax_max + params.leader_brake) * h * h + params.margin_x_m)
    behind = dx <= -half_len
    return _Scene(
        ahead=dx >= half_len, alongside=np.abs(dx) < half_len, behind=behind,
        reach_lo=reach_lo, reach_hi=reach_hi, gap_ahead=dx - half_len, gap_behind=gap_behind, vx=vx,
        in_current_corridor=corridor, close_follower=gap_behind <= s_follower + params.margin_x_m,
        soon_alongside=behind & (gap_behind <= closing), depth_now=_depth(c_lo, c_hi, reach_lo, reach_hi),
    )


def _depth(lo: np.ndarray, hi: np.ndarray, reach_lo: np.ndarray, reach_hi: np.ndarray) -> np.ndarray:
    """How far (m) the band [lo, hi] reaches into each reach band (0 when they do not meet);
    ``lo``/``hi`` broadcast against the reach arrays."""
    return np.maximum(np.minimum(hi - reach_lo, reach_hi - lo), 0.0)


def _candidate_bands(agent: int, state: VehicleState, ay: np.ndarray, params: ShieldParams,
                     bounds: Bounds | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Committed bands of the agent after one step with each lateral acceleration in ``ay``."""
    k = len(ay)
    a = agent
    own = _own(bounds, a)
    cmd = plan_step(
        np.full(k, state.x[a]), np.full(k, state.y[a]), np.full(k, state.vx[a]), np.full(k, state.vy[a]),
        np.full(k, state.width[a]), np.zeros(k), ay, params.step_s, params.road_width_m,
        params.edge_clearance_m, params.edge_contact_tolerance_m, bounds=own,
    )
    return committed_band(state.y[a] + cmd.dy, cmd.vy_next, float(state.width[a]), params, own)


def _violations(v: float, ax: np.ndarray, corridor: np.ndarray, depth: np.ndarray, scene: _Scene,
                params: ShieldParams) -> np.ndarray:
    """Largest violation (m) of rules 1–3 of each candidate (rows of ``corridor``, ``ax`` per row)."""
    return _violation_table(v, ax, corridor, depth, scene, params).max(axis=1, initial=0.0)


def _violation_table(v: float, ax: np.ndarray, corridor: np.ndarray, depth: np.ndarray, scene: _Scene,
                     params: ShieldParams) -> np.ndarray:
    """Violation (m) of rules 1–3 of each candidate (rows) with respect to each vehicle (columns)."""
    t, b, bl = params.step_s, params.agent_brake, params.leader_brake
    u = np.maximum(v + ax * t, 0.0)[:, None]
    vl = scene.vx
    vl_next = np.maximum(vl - bl * t, 0.0)
    c = scene.gap_ahead + 0.5 * t * (vl + vl_next) - 0.5 * t * v - params.margin_x_m
    ahead_v = np.maximum(0.5 * t * u - c, _travel(u, b, t) - stopping_distance(vl_next, bl, t) - c)
    g, s_f = _behind_terms(scene.gap_behind, v, scene.vx, params)
    behind_v = np.maximum(-(g + 0.5 * t * u), s_f - g - _travel(u, bl, t))
    worst: np.ndarray = np.zeros(corridor.shape)
    worst = np.where(corridor & scene.ahead, np.maximum(ahead_v, 0.0), worst)
    worst = np.where(corridor & scene.behind & ~scene.in_current_corridor, np.maximum(behind_v, 0.0), worst)
    worst = np.where(corridor & scene.alongside, depth, worst)
    worst = np.where(scene.soon_alongside, np.maximum(worst, depth - scene.depth_now), worst)
    return worst


def shield_action(agent: int, state: VehicleState, ax: float, ay: float, params: ShieldParams,
                  road_bounds: Bounds | None = None) -> ShieldDecision:
    """The certified (ax, ay) closest to the policy's (m/s²) for the agent in row ``agent`` of
    ``state``, or the least-violating fallback; see the module docstring for the rules. ``road_bounds``:
    each vehicle's (lowest, highest) lateral position on an open road (None: the ring's 0 and W)."""
    a, t = agent, params.step_s
    v = float(state.vx[a])
    bounds = params.agent_bounds
    ax_p, ay_p = clip_acceleration(ax, ay, bounds, v, params.agent_max_speed_mps, t)
    ax_top = min(bounds.ax_max, (params.agent_max_speed_mps - v) / t)
    ax_min = min(bounds.ax_min, ax_top)
    stop_vy = float(np.clip(-state.vy[a] / t, bounds.ay_min, bounds.ay_max))
    ay_c = np.concatenate([[ay_p, stop_vy], np.linspace(bounds.ay_min, bounds.ay_max, params.lateral_candidates)])
    scene = _scene(a, state, params, road_bounds)
    c_lo, c_hi = _candidate_bands(a, state, ay_c, params, road_bounds)
    corridor = (c_hi[:, None] > scene.reach_lo[None, :]) & (c_lo[:, None] < scene.reach_hi[None, :])

    # rule 1: upper bounds on ax; rule 3: lower bounds; rule 2: no side conflict; rule 4: −b_L floor
    u_max = max_speed_behind(scene.gap_ahead, v, scene.vx, params)
    ax_hi_j = np.where(u_max >= -_ROUNDING, (np.maximum(u_max, 0.0) - v) / t, -np.inf)
    hi = np.min(np.where(corridor & scene.ahead, ax_hi_j, np.inf), axis=1, initial=np.inf)
    hi = np.minimum(hi, ax_top)
    u_min = min_speed_ahead(scene.gap_behind, v, scene.vx, params)
    ax_lo_j = np.where(u_min > 0.0, (u_min - v) / t, -np.inf)
    entering = corridor & scene.behind & ~scene.in_current_corridor
    lo = np.maximum(np.max(np.where(entering, ax_lo_j, -np.inf), axis=1, initial=-np.inf), ax_min)
    close = (corridor & scene.behind & scene.close_follower).any(axis=1)
    lo_pref = np.where(close, np.maximum(lo, -params.leader_brake), lo)
    lo = np.where(lo_pref <= hi, lo_pref, lo)
    depth = _depth(c_lo[:, None], c_hi[:, None], scene.reach_lo[None, :], scene.reach_hi[None, :])
    side = (corridor & scene.alongside).any(axis=1)
    side |= (scene.soon_alongside & (depth > scene.depth_now + _ROUNDING)).any(axis=1)
    certified = (lo <= hi) & ~side

    if certified.any():
        ax_c = np.clip(ax_p, lo, np.maximum(hi, lo))
        dist = np.where(certified, np.hypot(ax_c - ax_p, ay_c - ay_p), np.inf)
        k = int(np.argmin(dist))
        return _decision(float(ax_c[k]), float(ay_c[k]), ax_p, ay_p, True)

    # fallback: the least-violating candidate on an (ax, ay) grid, ties to the closest
    ax_grid = np.unique(np.concatenate([np.linspace(ax_min, ax_top, _FALLBACK_AX),
                                        [ax_p, max(-params.leader_brake, ax_min)]]))
    kk = np.repeat(np.arange(len(ay_c)), len(ax_grid))
    mm = np.tile(np.arange(len(ax_grid)), len(ay_c))
    table = _violation_table(v, ax_grid[mm], corridor[kk], depth[kk], scene, params)
    worst = table.max(axis=1, initial=0.0)
    dist = np.hypot(ax_grid[mm] - ax_p, ay_c[kk] - ay_p)
    best = np.flatnonzero(worst <= worst.min() + _SAME)
    if params.fallback_steers_clear:  # then the least deep into the reach of the leaders it is too close to
        into = np.where(corridor[kk] & scene.ahead & (table > 0.0), depth[kk], 0.0).max(axis=1, initial=0.0)
        best = best[into[best] <= into[best].min() + _SAME]
    k = int(best[np.argmin(dist[best])])
    return _decision(float(ax_grid[mm[k]]), float(ay_c[kk[k]]), ax_p, ay_p, False)


def _decision(ax: float, ay: float, ax_p: float, ay_p: float, certified: bool) -> ShieldDecision:
    correction = math.hypot(ax - ax_p, ay - ay_p)
    if correction <= _SAME:
        return ShieldDecision(ax_p, ay_p, False, 0.0, certified)
    return ShieldDecision(ax, ay, True, correction, certified)


def invariant_holds(agent: int, state: VehicleState, params: ShieldParams) -> bool:
    """Whether I(s) of the module docstring holds: no overlap; rule 1's gap (before the step) to
    every vehicle ahead in the corridor of the agent's current committed band; no vehicle alongside
    in that corridor."""
    scene = _scene(agent, state, params)
    others = np.arange(state.n) != agent
    dy = np.abs(state.y[others] - state.y[agent])
    overlap = scene.alongside & (dy < 0.5 * (state.width[agent] + state.width[others]))
    t = params.step_s
    v = float(state.vx[agent])
    need = np.maximum(0.0, stopping_distance(v, params.agent_brake, t)
                      - stopping_distance(scene.vx, params.leader_brake, t)) + params.margin_x_m
    ahead_ok = ~(scene.in_current_corridor & scene.ahead) | (scene.gap_ahead >= need)
    side_ok = ~(scene.in_current_corridor & scene.alongside)
    return bool(~overlap.any() & ahead_ok.all() & side_ok.all())
