"""The safety shield: closed-form bounds on hand-built scenes, the one-step guarantee
and recursive feasibility over random states (numpy only), and zero agent collisions in SUMO."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from lanefree_sumo.config import AccelerationBounds, ConfigError, LaneFreeConfig, merge_config
from lanefree_sumo.rl.shield import (
    ShieldDecision,
    ShieldParams,
    _depth,
    _scene,
    _travel,
    _travel_inverse,
    _violations,
    committed_band,
    invariant_holds,
    max_speed_behind,
    min_speed_ahead,
    reach_band,
    shield_action,
    stopping_distance,
)
from lanefree_sumo.sim.dynamics import clip_acceleration, plan_step
from lanefree_sumo.sim.state import VehicleState, wrap

from conftest import lanefree

CFG = LaneFreeConfig()
P = ShieldParams.from_config(CFG)
T = P.step_s  # 0.25 s
B = 4.0  # background (and certified agent) braking (m/s²)
M = P.margin_x_m
A_LEN, A_WID = 3.2, 1.6
B_LEN, B_WID = 3.5, 1.8
HALF_LEN = (A_LEN + B_LEN) / 2  # 3.35 m


def scene(*others: tuple[float, float, float, float], agent: tuple[float, float, float, float]) -> VehicleState:
    """Background vehicles (x, y, vx, vy) and the agent (last row)."""
    rows = np.array([*others, agent], dtype=float)
    n = len(rows)
    return VehicleState(
        [f"bg{i}" for i in range(n - 1)] + ["agent"], rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3],
        np.array([B_LEN] * (n - 1) + [A_LEN]), np.array([B_WID] * (n - 1) + [A_WID]), np.full(n, 20.0),
        np.array([True] * (n - 1) + [False]),
    )


def agent_next(state: VehicleState, ax: float, ay: float) -> tuple[float, float, float, float]:
    """The agent's (x, y, vx, vy) after one step, as the simulation computes it."""
    a = state.n - 1
    ax, ay = clip_acceleration(ax, ay, CFG.scenario.agent_bounds, float(state.vx[a]),
                               CFG.scenario.agent_max_speed_mps, T)
    cmd = plan_step(state.x[a:], state.y[a:], state.vx[a:], state.vy[a:], state.width[a:], np.array([ax]),
                    np.array([ay]), T, CFG.road.width_m, CFG.sim.edge_clearance_m, CFG.sim.edge_contact_tolerance_m)
    return (float(state.x[a] + (state.vx[a] + cmd.vx_next[0]) * T / 2), float(state.y[a] + cmd.dy[0]),
            float(cmd.vx_next[0]), float(cmd.vy_next[0]))


# ------------------------------------------------------------------ closed forms

def test_stopping_distance_is_the_ballistic_sum_and_at_most_bt2_over_8_above_v2_over_2b():
    for v in np.linspace(0.0, 30.0, 301):
        speeds = [v]
        while speeds[-1] > 0:
            speeds.append(max(speeds[-1] - B * T, 0.0))
        simulated = sum((a + b) * T / 2 for a, b in zip(speeds, speeds[1:]))
        assert stopping_distance(v, B, T) == pytest.approx(simulated, abs=1e-9)
        assert 0.0 <= stopping_distance(v, B, T) - v * v / (2 * B) <= B * T * T / 8 + 1e-12
    assert stopping_distance(20.0, B, T) == pytest.approx(50.0)  # 20 m/s = 20 full steps of bT


def test_travel_after_a_step_is_piecewise_linear_with_nodes_at_whole_steps_of_braking():
    # φ(u) = S_b(u) + u·T/2 is b·T²·n(n + 1)/2 at u = n·b·T (b = 4, T = 0.25: bT = 1 m/s, bT² = 0.25 m), linear between
    u = np.array([0.0, 0.5, 1.0, 1.5, 2.0, 3.0])
    assert _travel(u, B, T).tolist() == [0.0, 0.125, 0.25, 0.5, 0.75, 1.5]
    assert _travel_inverse(np.array([-1.0, 0.0, 0.125, 0.5, 1.5]), B, T).tolist() == [0.0, 0.0, 0.5, 1.5, 3.0]


def _rule1_holds(gap: float, v: float, v_leader: float, u: float) -> bool:
    """Rule 1 after a step ending at agent speed u, the leader braking at 4 m/s² (worst case)."""
    vl = max(v_leader - B * T, 0.0)
    gap_next = gap + (v_leader + vl) * T / 2 - (v + u) * T / 2
    return gap_next >= max(0.0, float(stopping_distance(u, B, T) - stopping_distance(vl, B, T))) + M - 1e-9


@pytest.mark.parametrize("gap,v,v_leader", [(40.0, 20.0, 0.0), (60.0, 20.0, 0.0), (10.0, 15.0, 15.0),
                                             (3.0, 5.0, 25.0), (80.0, 30.0, 10.0), (0.6, 0.0, 0.0),
                                             (0.2, 30.0, 30.0)])  # the last: u·T/2 ≤ c binds
def test_rule1_bound_is_the_largest_speed_that_keeps_the_braking_gap(gap, v, v_leader):
    u_star = float(max_speed_behind(gap, v, v_leader, P))
    if u_star < 0:  # no speed qualifies, not even stopping at once
        assert not _rule1_holds(gap, v, v_leader, 0.0)
        return
    assert _rule1_holds(gap, v, v_leader, u_star)
    assert not _rule1_holds(gap, v, v_leader, u_star + 1e-6)


def _rule3_holds(gap: float, v: float, v_follower: float, u: float) -> bool:
    """Rule 3 after a step ending at agent speed u, the follower accelerating at 2 m/s² (worst case)."""
    vf = v_follower + 2.0 * T
    gap_next = gap + (v + u) * T / 2 - (v_follower + vf) * T / 2
    return gap_next >= max(0.0, float(stopping_distance(vf, B, T) - stopping_distance(u, B, T))) + M - 1e-9


@pytest.mark.parametrize("gap,v,v_follower", [(60.0, 15.0, 25.0), (20.0, 10.0, 20.0), (0.6, 1.0, 0.0),
                                               (0.55, 3.0, 2.0), (30.0, 20.0, 10.0), (5.0, 0.0, 12.0),
                                               (0.25, 1.0, 0.0)])  # the last: u·T/2 ≥ −G binds
def test_rule3_bound_is_the_smallest_speed_that_leaves_the_follower_its_braking_distance(gap, v, v_follower):
    u_star = float(min_speed_ahead(gap, v, v_follower, P))
    assert u_star >= 0.0 and _rule3_holds(gap, v, v_follower, u_star)
    if u_star > 0.0:  # a bound binds: any slower end speed breaks the rule
        assert not _rule3_holds(gap, v, v_follower, u_star - 1e-6)
    assert (u_star == 0.0) == _rule3_holds(gap, v, v_follower, 0.0)  # standing still qualifies: no bound


def test_a_car_stopped_ahead():
    # 55 m bumper gap is enough at 20 m/s (S(20) = 50 m): the shield caps ax at the closed-form bound
    state = scene((100 + HALF_LEN + 55.0, 5.0, 0.0, 0.0), agent=(100.0, 5.0, 20.0, 0.0))
    assert invariant_holds(1, state, P)
    d = shield_action(1, state, 2.0, 0.0, P)
    u_star = float(max_speed_behind(55.0, 20.0, 0.0, P))
    assert d.certified and d.intervened and d.ay == 0.0
    assert d.ax == pytest.approx((u_star - 20.0) / T)
    assert d.correction == pytest.approx(2.0 - d.ax)
    # a gentle policy action is left alone
    assert not shield_action(1, state, -2.0, 0.0, P).intervened
    # 40 m is not enough: no certified action, the fallback brakes at the agent's bound
    state = scene((100 + HALF_LEN + 40.0, 5.0, 0.0, 0.0), agent=(100.0, 5.0, 20.0, 0.0))
    assert not invariant_holds(1, state, P)
    d = shield_action(1, state, 2.0, 0.0, P)
    assert not d.certified and d.ax == pytest.approx(-4.5)
    # the same car 3 m to the side is outside the corridor: no constraint
    state = scene((100 + HALF_LEN + 40.0, 8.5, 0.0, 0.0), agent=(100.0, 4.0, 20.0, 0.0))
    assert not shield_action(1, state, 2.0, 0.0, P).intervened


def test_a_car_alongside():
    # 1.2 m of lateral clearance, the agent drifting towards the car at 1 m/s: its lateral stopping
    # distance (0.29 m) + the car's reach in 1 s (0.5 m) + margin (0.2 m) fit
    state = scene((100.0, 5.0 + 1.7 + 1.2, 20.0, 0.0), agent=(100.0, 5.0, 20.0, 1.0))
    assert invariant_holds(1, state, P)
    d = shield_action(1, state, 0.0, 1.8, P)  # steer into it
    assert d.certified and d.intervened and d.ax == 0.0
    _, hi = committed_band(*agent_next_band(state, d.ay), A_WID, P)
    r_lo, _ = reach_band(np.array([6.7 + 1.2]), np.array([0.0]), np.array([B_WID]), P)
    assert hi[0] <= r_lo[0]  # the committed band stays off the car's reach
    assert d.ay < 1.8 and d.ay == pytest.approx(_largest_ay_below(state, r_lo[0]), abs=0.1 + 1e-9)
    assert not shield_action(1, state, 0.0, -1.8, P).intervened  # steering away is fine


def agent_next_band(state: VehicleState, ay: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The agent's lateral position and speed after one step with each lateral acceleration ``ay``."""
    a = state.n - 1
    ay = np.atleast_1d(np.asarray(ay, dtype=float))
    k = len(ay)
    cmd = plan_step(np.repeat(state.x[a:], k), np.repeat(state.y[a:], k), np.repeat(state.vx[a:], k),
                    np.repeat(state.vy[a:], k), np.repeat(state.width[a:], k), np.zeros(k), ay, T,
                    CFG.road.width_m, CFG.sim.edge_clearance_m)
    return state.y[a] + cmd.dy, cmd.vy_next


def _largest_ay_below(state: VehicleState, edge: float) -> float:
    """The largest ay (on a fine grid) whose committed band stays below ``edge``."""
    grid = np.linspace(-1.8, 1.8, 3601)
    below = committed_band(*agent_next_band(state, grid), A_WID, P)[1] <= edge
    return float(grid[below][-1]) if below.any() else -1.8


def test_a_fast_follower():
    # a follower 8 m behind at 25 m/s: the agent brakes no harder than the follower can (rule 4)
    state = scene((100 - HALF_LEN - 8.0, 5.0, 25.0, 0.0), agent=(100.0, 5.0, 20.0, 0.0))
    d = shield_action(1, state, -4.5, 0.0, P)
    assert d.certified and d.ax == pytest.approx(-B) and d.correction == pytest.approx(0.5)
    # ... unless only braking harder avoids a car stopped ahead (three vehicles)
    state = scene((100 - HALF_LEN - 8.0, 5.0, 25.0, 0.0), (100 + HALF_LEN + 40.0, 5.0, 0.0, 0.0),
                  agent=(100.0, 5.0, 20.0, 0.0))
    assert shield_action(2, state, -4.5, 0.0, P).ax == pytest.approx(-4.5)


def test_no_cut_in_before_a_fast_follower():
    # the follower drives 2.9 m to the left, 5 m behind, at 25 m/s; the agent at 15 m/s steers left
    follower = (100 - HALF_LEN - 5.0, 7.9, 25.0, 0.0)
    state = scene(follower, agent=(100.0, 5.0, 15.0, 1.0))
    d = shield_action(1, state, 0.0, 1.8, P)
    assert d.certified and d.ay < 1.8
    _, hi = committed_band(*agent_next_band(state, d.ay), A_WID, P)
    r_lo, _ = reach_band(np.array([7.9]), np.array([0.0]), np.array([B_WID]), P)
    assert hi[0] <= r_lo[0]  # it stays out of the follower's corridor
    # with a 60 m gap the follower can brake behind the agent if the agent keeps at least 14 m/s
    # (S(25.5) − S(14) ≈ 56.7 m): the lane change at constant speed is allowed
    assert float(min_speed_ahead(60.0, 15.0, 25.0, P)) == pytest.approx(14.0, abs=0.05)
    state = scene((100 - HALF_LEN - 60.0, 7.9, 25.0, 0.0), agent=(100.0, 5.0, 15.0, 1.0))
    assert not shield_action(1, state, 0.0, 1.8, P).intervened


def test_rule3_raises_the_speed_of_a_lane_change_in_front_of_a_follower():
    # 56 m ahead of a follower at 25 m/s the agent must end the step at 15.0625 m/s or more: ax ≥ 0.25 m/s²
    state = scene((100 - HALF_LEN - 56.0, 7.9, 25.0, 0.0), agent=(100.0, 5.0, 15.0, 1.0))
    d = shield_action(1, state, 0.0, 1.8, P)
    assert d.certified and d.intervened and d.ay == 1.8 and d.ax == pytest.approx(0.25, abs=1e-9)


def test_alone_on_the_road_the_policy_is_kept_up_to_its_clip():
    assert shield_action(0, scene(agent=(100.0, 5.0, 15.0, 1.0)), 0.5, 1.0, P) == ShieldDecision(0.5, 1.0, False, 0.0,
                                                                                                   True)
    # 0.25 m/s below the top speed (30 m/s) the agent may gain 1 m/s² at most; above it, it must shed the excess
    assert shield_action(0, scene(agent=(100.0, 5.0, 29.75, 0.0)), 2.0, 0.0, P) == ShieldDecision(1.0, 0.0, False,
                                                                                                    0.0, True)
    assert shield_action(0, scene(agent=(100.0, 5.0, 32.0, 0.0)), 2.0, 0.0, P) == ShieldDecision(-8.0, 0.0, False,
                                                                                                   0.0, True)


def test_stopping_exactly_at_rule_1s_gap_is_certified_and_a_shorter_gap_is_not():
    def behind_a_stopped_car(gap: float) -> VehicleState:  # 4 m bodies: bumper gaps in exact binary fractions
        return VehicleState(["bg", "agent"], np.array([104.0 + gap, 100.0]), np.full(2, 5.0), np.array([0.0, 1.0]),
                            np.zeros(2), np.full(2, 4.0), np.full(2, 2.0), np.full(2, 20.0), np.array([True, False]))

    # at 1 m/s, 0.625 m behind: stopping in this step (ax = −4) covers 0.125 m and leaves the 0.5 m margin
    d = shield_action(1, behind_a_stopped_car(0.625), 0.0, 0.0, P)
    assert (d.certified, d.ax, d.ay) == (True, -4.0, 0.0)
    assert not shield_action(1, behind_a_stopped_car(0.375), 0.0, 0.0, P).certified


def test_only_the_candidates_that_reach_a_car_ahead_are_bound_by_it():
    # a car stopped 25 m ahead in the lane to the left: steering hard left reaches it, a gentler ay does not
    state = scene((100 + HALF_LEN + 25.0, 7.45, 0.0, 0.0), agent=(100.0, 5.0, 20.0, 0.0))
    d = shield_action(1, state, 0.0, 1.8, P)
    assert (d.certified, d.ax) == (True, 0.0) and d.ay == pytest.approx(0.7)
    # the same car 5 m ahead at the agent's 20 m/s: hard left is certified braking at 0.4 m/s², 1.4 m/s² from
    # the policy's +1; a gentler ay (0.7) keeps the +1 and is closer (1.1 m/s²)
    state = scene((100 + HALF_LEN + 5.0, 7.45, 20.0, 0.0), agent=(100.0, 5.0, 20.0, 0.0))
    d = shield_action(1, state, 1.0, 1.8, P)
    assert (d.certified, d.ax) == (True, 1.0) and d.ay == pytest.approx(0.7) and d.correction == pytest.approx(1.1)
    # without a follower nothing stops the agent braking harder than a background vehicle can (rule 4)
    alone = scene((100 + HALF_LEN + 60.0, 5.0, 0.0, 0.0), agent=(100.0, 5.0, 20.0, 0.0))
    assert shield_action(1, alone, -4.5, 0.0, P) == ShieldDecision(-4.5, 0.0, False, 0.0, True)


def test_on_an_open_road_each_vehicles_own_bounds_shape_the_bands():
    # the agent on a ramp (its body within [0, 4] m) drifting left at 1.5 m/s, a main-road car (within
    # [4.4, 10.2] m) alongside at 5.5 m: neither can cross the barrier, so steering left is safe
    state = scene((100.0, 5.5, 20.0, 0.0), agent=(100.0, 3.0, 20.0, 1.5))
    hi = np.array([10.2, 4.0])
    assert shield_action(1, state, 0.0, 1.8, P, (np.array([4.4, 0.0]), hi)) == ShieldDecision(0.0, 1.8, False, 0.0,
                                                                                              True)
    # without the barrier (the ring's road) the same steer leads into the car: the fallback steers away
    assert shield_action(1, state, 0.0, 1.8, P) == ShieldDecision(0.0, -1.8, True, 3.6, False)
    assert shield_action(1, state, 0.0, 1.8, P, (0.0, 10.2)) == ShieldDecision(0.0, -1.8, True, 3.6, False)
    # the car without the barrier may come down into the agent's band: no certified candidate
    assert not shield_action(1, state, 0.0, 1.8, P, (np.array([0.0, 0.0]), hi)).certified


def test_three_vehicles_slow_car_ahead_and_car_alongside():
    # a car at 10 m/s 40 m ahead in the agent's lane (S(20) − S(10) = 37.5 m), a car alongside on
    # the left; the policy accelerates and steers left: the shield caps ax and keeps off the left car
    state = scene((100 + HALF_LEN + 40.0, 5.0, 10.0, 0.0), (100.0, 7.9, 20.0, 0.0), agent=(100.0, 5.0, 20.0, 1.0))
    assert invariant_holds(2, state, P)
    d = shield_action(2, state, 1.0, 1.8, P)
    assert d.certified and d.ay < 1.8
    assert d.ax <= float((max_speed_behind(40.0, 20.0, 10.0, P) - 20.0) / T) + 1e-9 < 1.0
    _, hi = committed_band(*agent_next_band(state, d.ay), A_WID, P)
    assert hi[0] <= reach_band(np.array([7.9]), np.array([0.0]), np.array([B_WID]), P)[0][0]


def test_params_validate():
    with pytest.raises(ConfigError, match="horizon"):
        ShieldParams(0.25, 10.2, 500.0, AccelerationBounds(), AccelerationBounds(-4, 2, -1, 1), horizon_s=0.1)
    with pytest.raises(ConfigError, match="horizon"):
        ShieldParams(0.0, 10.2, 500.0, AccelerationBounds(), AccelerationBounds(-4, 2, -1, 1))  # no step
    # a horizon of exactly one step is allowed (assumption A2: H ≥ T)
    assert ShieldParams(0.25, 10.2, 500.0, AccelerationBounds(), AccelerationBounds(-4, 2, -1, 1),
                        horizon_s=0.25).horizon_s == 0.25


def test_the_fallbacks_violations_are_the_rules_shortfalls_after_a_simulated_step():
    # agent braking (3) and background braking (4) and accelerating (2.5) differ, so that no two swap unseen
    p = ShieldParams(T, 10.2, 500.0, AccelerationBounds(-3.0, 2.0, -1.8, 1.8), AccelerationBounds(-4.0, 2.5, -1, 1),
                     horizon_s=1.5, margin_x_m=0.7, margin_y_m=0.3)
    v, vl, vf = 14.0, 6.0, 17.0
    # row 0 ahead (gap 33 m), row 1 behind in another lane (gap 18 m), row 2 alongside, row 3 close behind in the lane
    state = scene((100.0 + HALF_LEN + 33.0, 5.0, vl, 0.0), (100.0 - HALF_LEN - 18.0, 1.2, vf, 0.0),
                  (101.0, 8.5, 10.0, 0.0), (100.0 - HALF_LEN - 3.0, 5.0, 20.0, 0.0), agent=(100.0, 5.0, v, 0.0))
    sc = _scene(4, state, p)
    assert sc.ahead.tolist() == [True, False, False, False] and sc.alongside.tolist() == [False, False, True, False]
    assert sc.in_current_corridor.tolist() == [True, False, False, True]
    assert sc.soon_alongside.tolist() == [False, False, False, True]
    # reach of a car at y = 5 m: 5 ± ½·1·1.5² ± 0.9 ± 0.3 = [2.675, 7.325]; the agent's band 5 ± 0.8 = [4.2, 5.8]
    assert sc.depth_now.tolist() == pytest.approx([3.125, 0.0, 0.0, 3.125], abs=1e-12)
    ax = np.array([-3.0, -1.0, 0.0, 1.0, 2.0])
    u = np.maximum(v + ax * T, 0.0)
    s = stopping_distance

    def shortfall_ahead(u: float) -> float:
        vl_next = max(vl - 4.0 * T, 0.0)
        gap_next = 33.0 + (vl + vl_next) * T / 2 - (v + u) * T / 2
        return max(0.0, max(0.0, float(s(u, 3.0, T) - s(vl_next, 4.0, T))) + 0.7 - gap_next)

    def shortfall_behind(u: float) -> float:
        vf_next = vf + 2.5 * T
        gap_next = 18.0 + (v + u) * T / 2 - (vf + vf_next) * T / 2
        return max(0.0, max(0.0, float(s(vf_next, 4.0, T) - s(u, 4.0, T))) + 0.7 - gap_next)

    ahead = np.array([shortfall_ahead(x) for x in u])
    behind = np.array([shortfall_behind(x) for x in u])
    assert ahead.min() == 0.0 < ahead.max() and behind.min() == 0.0 < behind.max()  # both rules bind somewhere
    depth = np.zeros((5, 4))
    in_corridor = np.zeros((5, 4), bool)
    for row, expected in ((0, ahead), (1, behind)):
        corridor = in_corridor.copy()
        corridor[:, row] = True
        got = _violations(v, ax, corridor, depth, sc, p)
        assert got == pytest.approx(expected, abs=1e-12), row
    # alongside, or behind and about to come alongside: how much deeper the band reaches into the reach band
    depth[:, 2] = [0.0, 0.25, 0.5, 0.75, 1.0]
    depth[:, 3] = [0.0, 0.0, 0.0, 4.0, 0.0]
    corridor = in_corridor.copy()
    corridor[:, 2] = True
    got = _violations(v, ax, corridor, depth, sc, p)
    soon = np.maximum(depth[:, 3] - sc.depth_now[3], 0.0)
    assert got == pytest.approx(np.maximum(depth[:, 2], soon), abs=1e-12)
    # a vehicle behind already in the agent's current corridor: its rule-3 shortfall is the follower's own
    corridor = in_corridor.copy()
    corridor[:, 3] = True
    assert _violations(v, ax, corridor, np.zeros((5, 4)), sc, p).tolist() == [0.0] * 5


@pytest.mark.parametrize("kind,gap,v,v_other", [
    ("ahead", 0.25, 6.5, 8.0),  # a faster leader: hard braking owes the margin alone (the u·T/2 branch)
    ("ahead", 0.25, 0.5, 0.5),  # both nearly stopped: speeds floored at 0 after the step
    ("behind", 0.25, 6.0, 5.5),  # a slower follower: accelerating owes the margin alone
    ("behind", 2.0, 0.5, 6.0),  # the agent nearly stopped, a follower closing
])
def test_the_fallbacks_violations_in_each_branch_of_the_rules(kind, gap, v, v_other):
    p = ShieldParams(T, 10.2, 500.0, AccelerationBounds(-3.0, 2.0, -1.8, 1.8), AccelerationBounds(-4.0, 2.5, -1, 1),
                     horizon_s=1.5, margin_x_m=0.7, margin_y_m=0.3)
    ahead = kind == "ahead"
    other = (100.0 + HALF_LEN + gap, 5.0, v_other, 0.0) if ahead else (100.0 - HALF_LEN - gap, 1.2, v_other, 0.0)
    sc = _scene(1, scene(other, agent=(100.0, 5.0, v, 0.0)), p)
    ax = np.array([-3.0, -1.0, 0.0, 1.0, 2.0])
    s = stopping_distance
    expected = []
    for u in np.maximum(v + ax * T, 0.0):
        if ahead:
            vl_next = max(v_other - 4.0 * T, 0.0)
            gap_next = gap + (v_other + vl_next) * T / 2 - (v + u) * T / 2
            need = max(0.0, float(s(u, 3.0, T) - s(vl_next, 4.0, T))) + 0.7
        else:
            vf_next = v_other + 2.5 * T
            gap_next = gap + (v + u) * T / 2 - (v_other + vf_next) * T / 2
            need = max(0.0, float(s(vf_next, 4.0, T) - s(u, 4.0, T))) + 0.7
        expected.append(max(0.0, need - gap_next))
    assert max(expected) > 0.0
    got = _violations(v, ax, np.ones((5, 1), bool), np.zeros((5, 1)), sc, p)
    assert got == pytest.approx(expected, abs=1e-9)


def test_the_invariant_at_exactly_the_gap_rule_1_asks():
    def two(x_other: float, y_other: float, v: float, v_other: float) -> VehicleState:
        return VehicleState(["bg", "agent"], np.array([x_other, 100.0]), np.array([y_other, 5.0]),
                            np.array([v_other, v]), np.zeros(2), np.full(2, 4.0), np.full(2, 2.0), np.full(2, 20.0),
                            np.array([True, False]))

    # a faster leader in the lane: rule 1 asks the margin alone (0.5 m), bumper to bumper
    assert invariant_holds(1, two(104.5, 5.0, 10.0, 25.0), P)
    assert invariant_holds(1, two(104.75, 5.0, 10.0, 25.0), P)
    assert not invariant_holds(1, two(104.375, 5.0, 10.0, 25.0), P)
    # a leader as fast as the agent: S_b(v) − S_bL(v) = 0 (b = b_L = 4), again the margin
    assert invariant_holds(1, two(104.5, 5.0, 20.0, 20.0), P)
    # 0.25 m behind a stopped car in another lane, outside the corridor: nothing asked
    assert invariant_holds(1, two(104.25, 9.0, 20.0, 0.0), P)
    assert not invariant_holds(1, two(104.25, 5.0, 20.0, 0.0), P)


def test_the_scene_at_exactly_its_boundaries():
    # 4 m × 2 m bodies, H = 1.5 s, a_L = 2.5 and b_L = 4 m/s², margins 0.75 m and 0.25 m: every edge in binary fractions
    p = ShieldParams(T, 10.2, 500.0, AccelerationBounds(), AccelerationBounds(-4.0, 2.5, -1.0, 1.0), horizon_s=1.5,
                     margin_x_m=0.75, margin_y_m=0.25)
    rows = [  # (x, y, vx): the agent at x = 100, y = 5, 20 m/s
        (104.0, 5.0, 20.0),  # bumper to bumper ahead (gap 0): ahead, not alongside
        (96.0, 5.0, 20.0),  # bumper to bumper behind: behind, not alongside
        (100.0 - 4.0 - 11.0625, 5.0, 22.0),  # behind, gap = (22 − 20)·1.5 + ½·6.5·1.5² + 0.75 = 11.0625: soon alongside
        (100.0 - 4.0 - 11.125, 5.0, 22.0),  # 1/16 m further: not
        (100.0 - 4.0 - 2.75, 5.0, 4.0),  # gap = S_bL(4 m/s) + margin = 2 + 0.75: a close follower
        (100.0 - 4.0 - 2.8125, 5.0, 4.0),  # 1/16 m further: not
        (100.0 - 4.0 - 8.125, 5.0, 4.0),  # slower than the agent: 1/16 m beyond ½·6.5·1.5² + 0.75, not soon alongside
        (130.0, 8.375, 20.0),  # its reach starts at 8.375 − ½·1·1.5² − 1 − 0.25 = 6 = the agent's band's top: apart
        (130.0, 1.625, 20.0),  # its reach ends at 1.625 + 1.125 + 1.25 = 4 = the band's bottom: apart
    ]
    n = len(rows) + 1
    x, y, vx = (np.array([r[i] for r in rows] + [a]) for i, a in zip(range(3), (100.0, 5.0, 20.0)))
    state = VehicleState([f"v{i}" for i in range(n)], x, y, vx, np.zeros(n), np.full(n, 4.0), np.full(n, 2.0),
                         np.full(n, 20.0), np.array([True] * (n - 1) + [False]))
    sc = _scene(n - 1, state, p)
    assert sc.ahead.tolist() == [True] + [False] * 6 + [True, True]
    assert sc.alongside.tolist() == [False] * 9
    assert sc.behind.tolist() == [False] + [True] * 6 + [False, False]
    assert sc.soon_alongside.tolist() == [False, True, True, False, True, True, False, False, False]
    assert sc.close_follower[1:7].tolist() == [True, True, True, True, False, False]  # S_bL(22 m/s) > 60 m
    assert sc.in_current_corridor.tolist() == [True] * 7 + [False, False]


def test_reach_bands_at_other_lateral_bounds_and_horizons():
    # a = 2 m/s² (the background's larger lateral bound), H = 1.5 s: ½·a·H² = 2.25 m, vy·H = ±0.75 m
    p = ShieldParams(T, 10.2, 500.0, AccelerationBounds(), AccelerationBounds(-4.0, 2.0, -2.0, 1.5), horizon_s=1.5,
                     margin_y_m=0.25)
    lo, hi = reach_band(np.array([5.0, 5.0]), np.array([0.5, -0.5]), np.array([2.0, 2.0]), p)
    assert lo.tolist() == [2.25, 0.75] and hi.tolist() == [9.25, 7.75]
    # within its own bounds [4, 7] (the lines 5.001 and 5.999 m): it reaches no further than they let it
    lo, hi = reach_band(np.array([5.0]), np.array([0.5]), np.array([2.0]), p, (np.array([4.0]), np.array([7.0])))
    assert lo.tolist() == [3.75] and hi[0] == pytest.approx(7.249)


@pytest.mark.parametrize("which", ["agent", "background"])
@pytest.mark.parametrize("bound", ["ax_min", "ax_max", "ay_min", "ay_max"])
def test_params_need_every_acceleration_bound_strictly_off_zero(which, bound):
    asymmetric = AccelerationBounds(-4.0, 2.0, -1.0, 0.5)  # 0.5 < 1: any small non-zero bound is enough
    assert ShieldParams(0.25, 10.2, 500.0, asymmetric, asymmetric).agent_lateral_brake == 0.5
    zero = AccelerationBounds(**{**dataclasses.asdict(asymmetric), bound: 0.0})
    bounds = (zero, asymmetric) if which == "agent" else (asymmetric, zero)
    with pytest.raises(ConfigError, match="^the shield needs acceleration bounds with braking and accelerating on both"
                                          " axes$"):
        ShieldParams(0.25, 10.2, 500.0, *bounds)


def test_the_fallback_can_steer_clear_of_a_leader_it_is_too_close_to():
    """A scene met in a shielded evaluation (positions rounded): the agent closes at 5 m/s on a slower car ahead
    whose reach its committed band has just met, and no action is certified. Every lateral acceleration
    violates that car's gap by the same amount, so by default the fallback keeps the policy's steering towards it
    (it then touched the car two steps later); with ``fallback_steers_clear`` it brakes as hard and steers away,
    its committed band reaching less deep into the car's reach."""
    state = scene((264.864, 8.908, 14.737, 0.004), (257.816, 0.942, 16.153, -0.089), (260.568, 3.942, 18.919, 0.031),
                  (256.284, 6.638, 14.010, 0.100), agent=(250.0, 4.183, 19.176, 0.776))
    clear = dataclasses.replace(P, fallback_steers_clear=True)
    kept, steered = shield_action(4, state, -4.5, 1.8, P), shield_action(4, state, -4.5, 1.8, clear)
    assert not kept.certified and not steered.certified
    assert (kept.ax, kept.ay) == (-4.5, 1.8) and not kept.intervened
    assert steered.ax == kept.ax and steered.ay == CFG.scenario.agent_bounds.ay_min

    def depth_into_leader(d: ShieldDecision) -> float:
        _, y, _, vy = agent_next(state, d.ax, d.ay)
        lo, hi = committed_band(y, vy, A_WID, P)
        r_lo, r_hi = reach_band(state.y[3:4], state.vy[3:4], state.width[3:4], P)
        return float(_depth(lo, hi, r_lo, r_hi)[0])

    assert depth_into_leader(steered) < depth_into_leader(kept)


def test_params_from_a_config_take_every_setting_from_it():
    cfg = merge_config(LaneFreeConfig(), {
        "sim": {"step_s": 0.2, "edge_clearance_m": 0.01, "edge_contact_tolerance_m": 1e-4},
        "road": {"length_m": 400.0, "width_m": 9.0},
        "scenario": {"agent_bounds": {"ax_min": -5.0, "ax_max": 2.5, "ay_min": -1.5, "ay_max": 1.6},
                     "agent_max_speed_mps": 28.0,
                     "driver": {"bounds": {"ax_min": -3.5, "ax_max": 1.5, "ay_min": -0.8, "ay_max": 0.9}}},
        "shield": {"horizon_s": 1.5, "margin_x_m": 0.7, "margin_y_m": 0.3, "lateral_candidates": 11,
                   "fallback_steers_clear": True},
    })
    assert ShieldParams.from_config(cfg) == ShieldParams(
        0.2, 9.0, 400.0, AccelerationBounds(-5.0, 2.5, -1.5, 1.6), AccelerationBounds(-3.5, 1.5, -0.8, 0.9),
        28.0, 1.5, 0.7, 0.3, 11, 0.01, 1e-4, True)
    with pytest.raises(ConfigError):
        ShieldParams(0.25, 10.2, 500.0, AccelerationBounds(0.0, 2.0, -1.8, 1.8), AccelerationBounds(-4, 2, -1, 1))


# ------------------------------------------------------------------ the guarantee over random states

def _random_state(rng: np.random.Generator) -> VehicleState:
    """The agent and 1–5 vehicles within ±40 m, random lateral positions and speeds."""
    n = int(rng.integers(1, 6))
    x_a = 250.0
    others = []
    for _ in range(n):
        others.append((x_a + rng.uniform(-40.0, 40.0), rng.uniform(0.91, 9.29), rng.uniform(0.0, 25.0),
                       rng.uniform(-1.0, 1.0)))
    return scene(*others, agent=(x_a, rng.uniform(0.81, 9.39), rng.uniform(0.0, 30.0), rng.uniform(-2.0, 2.0)))


def _background_next(state: VehicleState, ax: np.ndarray, ay: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    bg = slice(0, state.n - 1)
    cmd = plan_step(state.x[bg], state.y[bg], state.vx[bg], state.vy[bg], state.width[bg], ax, ay, T,
                    CFG.road.width_m, CFG.sim.edge_clearance_m, CFG.sim.edge_contact_tolerance_m)
    return state.x[bg] + (state.vx[bg] + cmd.vx_next) * T / 2, state.y[bg] + cmd.dy


def _followers_in_corridor(state: VehicleState) -> np.ndarray:
    """Vehicles behind whose reach meets the agent's current committed band (their responsibility)."""
    a = state.n - 1
    dx = wrap(state.x[:a] - state.x[a], CFG.road.length_m)
    lo, hi = committed_band(state.y[a], state.vy[a], A_WID, P)
    r_lo, r_hi = reach_band(state.y[:a], state.vy[:a], state.width[:a], P)
    return (dx <= -HALF_LEN) & (hi > r_lo) & (lo < r_hi)


def _bands_meet(state: VehicleState, agent_y: float, agent_vy: float) -> np.ndarray:
    """Per background vehicle: its reach (from ``state``) meets the agent's committed band from
    (agent_y, agent_vy)."""
    a = state.n - 1
    lo, hi = committed_band(agent_y, agent_vy, A_WID, P)
    r_lo, r_hi = reach_band(state.y[:a], state.vy[:a], state.width[:a], P)
    return (hi > r_lo) & (lo < r_hi)


def _drive(state: VehicleState, rng: np.random.Generator, steps: int, shielded: bool) -> dict[str, int]:
    """``steps`` steps of a jumpy random policy (a new uniform action every 8 steps) among
    background vehicles whose accelerations are drawn anywhere inside F_x ∈ [−4, 2], |F_y| ≤ 1
    (corners half of the time; |vy| held below 1 m/s). Asserts the guarantee of the module
    docstring at every step; returns counts."""
    a = state.n - 1
    bounds = CFG.scenario.agent_bounds
    counts = {"steps": 0, "certified": 0, "overlaps": 0, "excused": 0, "lost": 0}
    certified_before = True
    for k in range(steps):
        if k % 8 == 0:
            policy = (rng.uniform(bounds.ax_min, bounds.ax_max), rng.uniform(bounds.ay_min, bounds.ay_max))
        if shielded:
            d = shield_action(a, state, *policy, P)
            action, certified = (d.ax, d.ay), d.certified
        else:
            action, certified = policy, False
        if shielded and certified_before and not certified:
            counts["lost"] += 1  # explained below, at the step that lost it
        corners = rng.random(a) < 0.5
        ax_bg = np.where(corners, rng.choice([-4.0, 2.0], a), rng.uniform(-4.0, 2.0, a))
        ay_bg = np.where(corners, rng.choice([-1.0, 1.0], a), rng.uniform(-1.0, 1.0, a))
        ay_bg = np.where(np.abs(state.vy[:a]) > 1.0, -np.sign(state.vy[:a]), ay_bg)
        excused = _followers_in_corridor(state)
        x_a, y_a, vx_a, vy_a = agent_next(state, *action)
        x_bg, y_bg = _background_next(state, ax_bg, ay_bg)
        nxt = state.copy()
        nxt.x[:a], nxt.y[:a] = np.mod(x_bg, CFG.road.length_m), y_bg
        nxt.vx[:a] = np.maximum(state.vx[:a] + ax_bg * T, 0.0)
        cmd = plan_step(state.x[:a], state.y[:a], state.vx[:a], state.vy[:a], state.width[:a], ax_bg, ay_bg, T,
                        CFG.road.width_m, CFG.sim.edge_clearance_m)
        nxt.vy[:a] = cmd.vy_next
        nxt.x[a], nxt.y[a], nxt.vx[a], nxt.vy[a] = x_a % CFG.road.length_m, y_a, vx_a, vy_a
        overlap = ((np.abs(wrap(x_bg - x_a, CFG.road.length_m)) < HALF_LEN)
                   & (np.abs(y_bg - y_a) < (A_WID + B_WID) / 2))
        counts["steps"] += 1
        counts["certified"] += certified
        counts["overlaps"] += int((overlap & ~excused).any())
        counts["excused"] += int((overlap & excused).any())
        if shielded and certified:
            # (1) a certified action: no overlap after the step, whatever the background did,
            # except with a follower already in the agent's corridor
            assert not (overlap & ~excused).any(), (state, policy, d, ax_bg, ay_bg)
            # (2) recursion: the next step has a certified action unless a vehicle's reach newly met
            # the agent's committed band (it moved laterally towards the agent), or a follower in the
            # corridor came alongside or ahead
            if not shield_action(a, nxt, *policy, P).certified:
                newly = _bands_meet(nxt, y_a, vy_a) & ~_bands_meet(state, y_a, vy_a)
                dx_next = wrap(nxt.x[:a] - nxt.x[a], CFG.road.length_m)
                follower_came = excused & (dx_next > -HALF_LEN)
                assert (newly | follower_came).any(), (state, policy, d, ax_bg, ay_bg)
        certified_before = certified
        state = nxt
    return counts


def test_following_the_shield_the_agent_causes_no_overlap():
    """Precisely (numpy only): 150 random scenes of 3–8 vehicles within ±30 m of the agent, each
    driven for 40 steps (10 s) by a jumpy random policy through the shield, the background
    accelerations drawn anywhere inside their bounds: (1) after every certified step the agent
    overlaps no vehicle, except a follower that was already in its corridor; (2) a certified step
    is followed by a step without a certified action only when another vehicle moved laterally so
    that its reach newly met the agent's committed band, or a follower in the corridor came
    alongside. The same scenes without the shield overlap (the check is not vacuous)."""
    totals = {True: {}, False: {}}
    for shielded in (True, False):
        rng = np.random.default_rng(2026)
        for _ in range(150):
            n = int(rng.integers(3, 9))
            others = [(250.0 + rng.uniform(-30.0, 30.0), rng.uniform(0.91, 9.29), rng.uniform(10.0, 22.0),
                       0.0) for _ in range(n)]
            state = scene(*others, agent=(250.0, rng.uniform(0.81, 9.39), rng.uniform(10.0, 22.0), 0.0))
            if not invariant_holds(n, state, P):
                continue
            for key, value in _drive(state, rng, 40, shielded).items():
                totals[shielded][key] = totals[shielded].get(key, 0) + value
    on, off = totals[True], totals[False]
    # with these deliberately erratic lateral moves (a corner of the bounds half of the time) ~10 % of
    # the shielded steps have no certified action, and the overlaps left follow those steps
    assert on["steps"] > 3000 and on["certified"] > 0.85 * on["steps"]
    assert off["overlaps"] > 100 and on["overlaps"] < off["overlaps"]


def test_longitudinal_invariant_is_kept_when_nobody_moves_laterally():
    """With every vehicle keeping its lateral position (vy = ay = 0), a certified step from I(s)
    lands in I(s') for any longitudinal background acceleration within its bounds, as long as no
    follower closes in on the agent (the invariant says nothing about followers)."""
    rng = np.random.default_rng(3)
    kept = 0
    while kept < 500:
        state = _random_state(rng)
        a = state.n - 1
        state.vy[:a] = 0.0
        if not invariant_holds(a, state, P) or _followers_in_corridor(state).any():
            continue
        d = shield_action(a, state, rng.uniform(-4.5, 2.0), rng.uniform(-1.8, 1.8), P)
        ax_bg = rng.choice([-4.0, 2.0, 0.0], a) if kept % 2 else rng.uniform(-4.0, 2.0, a)
        x_bg, y_bg = _background_next(state, ax_bg, np.zeros(a))
        nxt = state.copy()
        nxt.x[:a], nxt.y[:a] = x_bg, y_bg
        nxt.vx[:a] = np.maximum(state.vx[:a] + ax_bg * T, 0.0)
        nxt.x[a], nxt.y[a], nxt.vx[a], nxt.vy[a] = agent_next(state, d.ax, d.ay)
        if _followers_in_corridor(nxt).any():
            continue
        assert invariant_holds(a, nxt, P), (state, d)
        kept += 1


# ------------------------------------------------------------------ in SUMO

@pytest.mark.sumo
@pytest.mark.slow
def test_rollout_random_policy_at_120_collides_without_the_shield_and_never_with_it():
    """`lanefree rollout --policy random --density 120 --episodes 2 --seed 9 [--shield] --json`."""
    args = ("rollout", "--policy", "random", "--density", "120", "--episodes", "2", "--seed", "9", "--json")
    shielded = lanefree(*args, "--shield")
    plain = lanefree(*args)
    for res in (shielded, plain):
        assert res.returncode == 0, res.stderr
    on = json.loads(shielded.stdout.strip().splitlines()[-1])
    off = json.loads(plain.stdout.strip().splitlines()[-1])
    for key in ("episodes", "collisions", "collisions_per_episode", "shield_interventions_per_episode",
                "speed_dev_mps", "mean_speed_mps", "background_collisions"):
        assert key in on and key in off
    assert on["episodes"] == off["episodes"] == 2 and on["shield"] and not off["shield"]
    assert on["collisions"] == 0 and on["background_collisions"] == 0
    assert on["shield_interventions_per_episode"] > 0
    assert off["collisions"] > 0 and off["shield_interventions_per_episode"] == 0
    assert len(shielded.stdout.strip().splitlines()) == 1 + 2 + 1  # header, 2 rows, the JSON


# ------------------------------------------------------------------ the lateral margin, on both sides

def _params(margin_y: float, margin_x: float = 0.5) -> ShieldParams:
    """The default scene's parameters with a horizon of 1 s (background reach ½·1·1² = 0.5 m) and these margins."""
    return ShieldParams(T, 10.2, 500.0, CFG.scenario.agent_bounds, AccelerationBounds(-4.0, 2.0, -1.0, 1.0),
                        horizon_s=1.0, margin_x_m=margin_x, margin_y_m=margin_y)


def test_reach_band_is_widened_by_the_lateral_margin_on_both_sides():
    # y = 5, vy = 0, width 2: reach 0.5 m each way, body ± 1 m, margin 0.3 m: [5 − 1.8, 5 + 1.8]
    lo, hi = reach_band(np.array([5.0]), np.array([0.0]), np.array([2.0]), _params(0.3))
    assert (lo[0], hi[0]) == (pytest.approx(3.2), pytest.approx(6.8))
    # drifting left at 0.5 m/s: 0.5·1 + 0.5 = 1.0 m up, max(0, −0.5 + 0.5) = 0 down
    lo, hi = reach_band(np.array([5.0]), np.array([0.5]), np.array([2.0]), _params(0.3))
    assert (lo[0], hi[0]) == (pytest.approx(5.0 - 1.3), pytest.approx(6.0 + 1.3))
    # drifting right at 0.25 m/s: 0.25 m up, 0.75 m down
    lo, hi = reach_band(np.array([5.0]), np.array([-0.25]), np.array([2.0]), _params(0.0))
    assert (lo[0], hi[0]) == (pytest.approx(3.25), pytest.approx(6.25))
    # at the right edge the reach stops at the road (clearance 1 mm), the margin does not
    lo, hi = reach_band(np.array([1.2]), np.array([0.0]), np.array([2.0]), _params(0.3))
    assert (lo[0], hi[0]) == (pytest.approx(1.001 - 1.3), pytest.approx(1.7 + 1.3))


@pytest.mark.parametrize("side", [+1, -1])
def test_a_car_alongside_within_the_lateral_margin_is_avoided_on_either_side(side):
    # agent 1.6 m wide at y = 5, vy = 0: holding ay = 0 its committed band is 5 ± 0.8. A 1.8 m car alongside
    # (dx = 0) at y = 5 ± 2.37: body edge 5 ± 1.47, reach edge 5 ± 0.97 (0.5 m reach), minus the margin m
    state = scene((100.0, 5.0 + side * 2.37, 20.0, 0.0), agent=(100.0, 5.0, 20.0, 0.0))
    # m = 0.2: the reach edge at 0.77 m from the agent's centre meets its band (0.8 m): moving away is needed.
    # One step at ay moves the agent ay·T²/2 and stops there (vy' = ay·T, braked at 1.8 m/s² from the next
    # step on: the band's far edge stays at y'): ay = ∓1.0 moves 0.03125 m (0.8 − 0.03125 = 0.76875 < 0.77),
    # ∓0.9 only 0.028125 m (0.771875 > 0.77): the closest certified candidate on the 0.1 m/s² grid is ∓1.0
    d = shield_action(1, state, 0.0, 0.0, _params(0.2))
    assert d.certified and d.intervened and d.ax == 0.0
    assert d.ay == pytest.approx(-side * 1.0) and d.correction == pytest.approx(1.0)
    # m = 0.1: the reach edge at 0.87 m stays off the band: the policy's action stands
    d = shield_action(1, state, 0.0, 0.0, _params(0.1))
    assert d.certified and not d.intervened and (d.ax, d.ay) == (0.0, 0.0)
