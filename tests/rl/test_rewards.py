"""Reward components (specification §7) against values computed by hand from the formulas."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from lanefree_sumo.config import RewardConfig
from lanefree_sumo.rl.rewards import (
    PRESETS,
    REWARD_TERMS,
    Rewards,
    RewardWeights,
    agent_overlaps,
    compute_reward,
    detect_overtakes,
    ellipsoid,
    field_cost,
    get_preset,
    lateral_cost,
    longitudinal_cost,
    reciprocal_reward,
    zone_target,
)

W = 10.2  # road width (m)
L = 500.0  # ring length (m)
A_LEN, A_WID = 3.2, 1.6  # agent (m)
B_LEN, B_WID = 3.5, 1.8  # background vehicle (m)
A_C = (A_LEN + B_LEN) / 2  # 3.35 m
B_C = (A_WID + B_WID) / 2  # 1.7 m


# ------------------------------------------------------------------ ellipsoid


def test_ellipsoid_centre_is_magnitude():
    assert ellipsoid(0.0, 0.0, 2.0, 1.0, 4, 4, 1, 0.5) == pytest.approx(0.5)
    assert ellipsoid(0.0, 0.0, 7.0, 3.0, 2, 2, 3, 0.8) == pytest.approx(0.8)


def test_ellipsoid_on_axes():
    # dx = a on the x axis: 0.5 / (1 + 0 + 1)^1 = 0.25
    assert ellipsoid(2.0, 0.0, 2.0, 1.0, 4, 4, 1, 0.5) == pytest.approx(0.25)
    # negative dx uses |dx|: (4/2)^2 = 4 -> 0.5 / 5 = 0.1
    assert ellipsoid(-4.0, 0.0, 2.0, 1.0, 2, 2, 1, 0.5) == pytest.approx(0.1)
    # dy = b on the y axis with p_t = 2: 0.5 / 2^2 = 0.125
    assert ellipsoid(0.0, 1.5, 3.0, 1.5, 2, 2, 2, 0.5) == pytest.approx(0.125)
    # off axis: (1/2)^4 + (1/1)^4 + 1 = 2.0625 -> 0.5 / 2.0625
    assert ellipsoid(1.0, -1.0, 2.0, 1.0, 4, 4, 1, 0.5) == pytest.approx(0.5 / 2.0625)


def test_ellipsoid_broadcasts():
    dx = np.array([0.0, 1.0, 2.0])
    dy = np.array([[0.0], [1.0]])
    out = ellipsoid(dx, dy, 1.0, 1.0, 2, 2, 1, 1.0)
    assert out.shape == (2, 3)
    expected = np.array(
        [
            [1 / 1, 1 / 2, 1 / 5],  # dy = 0: 1/(dx^2 + 1)
            [1 / 2, 1 / 3, 1 / 6],  # dy = 1: 1/(dx^2 + 2)
        ]
    )
    np.testing.assert_allclose(out, expected)
    # arrays of semi-axes broadcast too
    np.testing.assert_allclose(
        ellipsoid(2.0, 0.0, np.array([1.0, 2.0, 4.0]), 1.0, 2, 2, 1, 1.0),
        [1 / 5, 1 / 2, 1 / 1.25],
    )


# ------------------------------------------------------------------ fields


def _one(v):
    return np.array([v], dtype=float)


def test_field_cost_zero_relative_speed_by_hand():
    # neighbour 5 m ahead, same lateral position, same speed
    e_c = 0.5 / ((5 / A_C) ** 4 + 1)
    e_b = 0.5 / ((5 / A_C) ** 2 + 1)
    got = field_cost(_one(5.0), _one(0.0), _one(0.0), _one(0.0), A_LEN, A_WID, _one(B_LEN), _one(B_WID))
    assert got == pytest.approx(e_c + e_b)
    assert 0.0 < got < 1.0


def test_field_cost_approaching_vs_receding():
    args = (A_LEN, A_WID, _one(B_LEN), _one(B_WID))
    still = field_cost(_one(5.0), _one(0.0), _one(0.0), _one(0.0), *args)
    # agent 3 m/s slower than the vehicle ahead: gap opens, no stretch
    receding = field_cost(_one(5.0), _one(0.0), _one(-3.0), _one(0.0), *args)
    # agent 4 m/s faster than the vehicle ahead: ux = 4, a_b = 3.35 * (1 + 0.5*4) = 10.05
    approaching = field_cost(_one(5.0), _one(0.0), _one(4.0), _one(0.0), *args)
    e_c = 0.5 / ((5 / 3.35) ** 4 + 1)
    e_b = 0.5 / ((5 / 10.05) ** 2 + 1)
    assert receding == pytest.approx(still)
    assert approaching == pytest.approx(e_c + e_b)
    assert approaching > still + 0.1

    # vehicle 5 m behind and faster than the agent (dvx = -4): closing, same stretch
    behind = field_cost(_one(-5.0), _one(0.0), _one(-4.0), _one(0.0), *args)
    assert behind == pytest.approx(approaching)
    # vehicle behind and slower (dvx = +4): opening, no stretch
    behind_open = field_cost(_one(-5.0), _one(0.0), _one(4.0), _one(0.0), *args)
    assert behind_open == pytest.approx(still)


def test_field_cost_absolute_stretch_ignores_direction():
    # stretch="absolute": a receding neighbour (agent 4 m/s slower than the one ahead) stretches the
    # broad region exactly like a closing one: a_b = 3.35 * (1 + 0.5*4) = 10.05
    args = (A_LEN, A_WID, _one(B_LEN), _one(B_WID))
    closing = field_cost(_one(5.0), _one(0.0), _one(4.0), _one(0.0), *args)
    receding = field_cost(_one(5.0), _one(0.0), _one(-4.0), _one(0.0), *args, stretch="absolute")
    assert receding == pytest.approx(closing)
    assert receding > field_cost(_one(5.0), _one(0.0), _one(-4.0), _one(0.0), *args) + 0.1
    with pytest.raises(ValueError, match="stretch"):
        field_cost(_one(5.0), _one(0.0), _one(0.0), _one(0.0), *args, stretch="signed")


def test_field_cost_lateral_closing_speed():
    # neighbour 2 m to the left (dy > 0), agent drifting left 1 m/s faster: uy = 1,
    # b_b = 1.7 * (1 + 0.4*1) = 2.38; dx = 0 so the x terms vanish
    args = (A_LEN, A_WID, _one(B_LEN), _one(B_WID))
    got = field_cost(_one(0.0), _one(2.0), _one(0.0), _one(1.0), *args)
    e_c = 0.5 / ((2 / 1.7) ** 4 + 1)
    e_b = 0.5 / ((2 / 2.38) ** 2 + 1)
    assert got == pytest.approx(e_c + e_b)
    away = field_cost(_one(0.0), _one(2.0), _one(0.0), _one(-1.0), *args)
    assert away == pytest.approx(e_c + 0.5 / ((2 / 1.7) ** 2 + 1))


def test_field_cost_sums_and_respects_keywords():
    dx = np.array([5.0, -8.0])
    dy = np.array([0.0, 1.0])
    zero = np.zeros(2)
    got = field_cost(dx, dy, zero, zero, A_LEN, A_WID, B_LEN, B_WID)
    expected = (
        0.5 / ((5 / 3.35) ** 4 + 1) + 0.5 / ((5 / 3.35) ** 2 + 1)
        + 0.5 / ((8 / 3.35) ** 4 + (1 / 1.7) ** 4 + 1) + 0.5 / ((8 / 3.35) ** 2 + (1 / 1.7) ** 2 + 1)
    )
    assert got == pytest.approx(expected)
    # k_r is used: with k_r = 1, ux = 4 -> a_b = 3.35 * 5 = 16.75
    kr = field_cost(_one(5.0), _one(0.0), _one(4.0), _one(0.0), A_LEN, A_WID, B_LEN, B_WID, k_r=1.0)
    assert kr == pytest.approx(0.5 / ((5 / 3.35) ** 4 + 1) + 0.5 / ((5 / 16.75) ** 2 + 1))


def test_field_cost_capped_at_one():
    n = 6
    dx = np.full(n, 1.0)
    got = field_cost(dx, np.zeros(n), np.zeros(n), np.zeros(n), A_LEN, A_WID, np.full(n, B_LEN), np.full(n, B_WID))
    # uncapped: 6 * (0.5/((1/3.35)^4+1) + 0.5/((1/3.35)^2+1)) ≈ 5.7
    assert n * (0.5 / ((1 / 3.35) ** 4 + 1) + 0.5 / ((1 / 3.35) ** 2 + 1)) > 5.0
    assert got == 1.0


def test_field_cost_empty_and_nan_rows():
    e = np.array([])
    assert field_cost(e, e, e, e, A_LEN, A_WID, e, e) == 0.0
    nan = np.array([np.nan])
    assert field_cost(nan, nan, nan, nan, A_LEN, A_WID, _one(B_LEN), _one(B_WID)) == 0.0
    # a NaN (padding) row next to a real one contributes nothing
    got = field_cost(np.array([5.0, np.nan]), np.array([0.0, np.nan]), np.zeros(2), np.zeros(2),
                     A_LEN, A_WID, B_LEN, B_WID)
    assert got == pytest.approx(0.5 / ((5 / 3.35) ** 4 + 1) + 0.5 / ((5 / 3.35) ** 2 + 1))


# ------------------------------------------------------------------ zones

# agent at 20 m/s: d_o = 20 * 0.7 = 14 m; blockers need dx > -3.35 and dx - 3.35 <= 14
V_A = 20.0


def _zones(dx, y_j, agent_y, vxs=None, wids=None, v_desired=20.0, **kw):
    dx = np.asarray(dx, float)
    dy = np.asarray(y_j, float) - agent_y
    vxs = np.full(dx.shape, 15.0) if vxs is None else np.asarray(vxs, float)
    wids = np.full(dx.shape, B_WID) if wids is None else np.asarray(wids, float)
    return zone_target(dx, dy, vxs, np.full(dx.shape, B_LEN), wids, agent_y, V_A, A_LEN, A_WID,
                       v_desired, W, **kw)


def test_zone_empty_road_is_centre():
    e = np.array([])
    assert zone_target(e, e, e, e, e, 3.0, V_A, A_LEN, A_WID, 20.0, W) == (W / 2, 20.0, False)


def test_zone_one_blocker_middle_picks_nearest_side():
    # blocker at y = 5.1 occupies [4.2, 6.0]; zones [0, 4.2] (centre 2.1) and [6.0, 10.2] (8.1)
    # agent at y = 5.5: distance 5.5 - 4.2 = 1.3 to the right zone, 6.0 - 5.5 = 0.5 to the left
    y_d, v_d, blocked = _zones([10.0], [5.1], agent_y=5.5)
    assert y_d == pytest.approx((6.0 + 10.2) / 2)
    assert v_d == 20.0 and blocked is False
    # agent at y = 4.7: 0.5 to the right zone, 1.3 to the left -> right zone
    y_d, _, _ = _zones([10.0], [5.1], agent_y=4.7)
    assert y_d == pytest.approx(4.2 / 2)


def test_zone_tie_goes_left():
    # agent centred behind the blocker: distance 0.9 to both zones -> documented tie rule (left)
    y_d, _, _ = _zones([10.0], [5.1], agent_y=5.1)
    assert y_d == pytest.approx((6.0 + 10.2) / 2)


def test_zone_agent_already_in_free_zone():
    # agent at y = 2.0 is inside [0, 4.2]: distance 0 -> centre 2.1 (not its own y)
    y_d, v_d, blocked = _zones([10.0], [5.1], agent_y=2.0)
    assert y_d == pytest.approx(2.1)
    assert (v_d, blocked) == (20.0, False)
    # inside the left zone [6.0, 10.2] at y = 9.5 -> 8.1
    y_d, _, _ = _zones([10.0], [5.1], agent_y=9.5)
    assert y_d == pytest.approx(8.1)


def test_zone_too_narrow_is_dropped():
    # blockers at y = 2.0 ([1.1, 2.9]) and 5.5 ([4.6, 6.4]); zones [0, 1.1] (1.1 m),
    # [2.9, 4.6] (1.7 m) and [6.4, 10.2] (3.8 m).  Minimum width 1.6 + 2*0.1 = 1.8 m drops the
    # 1.7 m gap even though the agent (1.6 m) is inside it -> [6.4, 10.2], centre 8.3
    y_d, v_d, blocked = _zones([6.0, 9.0], [2.0, 5.5], agent_y=3.75)
    assert y_d == pytest.approx((6.4 + 10.2) / 2)
    assert (v_d, blocked) == (20.0, False)
    # without the margin (1.6 m minimum) the 1.7 m gap fits and contains the agent
    y_d, _, _ = _zones([6.0, 9.0], [2.0, 5.5], agent_y=3.75, margin=0.0)
    assert y_d == pytest.approx((2.9 + 4.6) / 2)


def test_zone_fully_blocked():
    # 2.5 m wide blockers at y = 1.5, 5.1, 8.7 occupy [0.25, 2.75], [3.85, 6.35], [7.45, 9.95];
    # gaps 0.25, 1.1, 1.1, 0.25 m are all < 1.8 m -> blocked
    dx, ys, vxs, wids = [5.0, 8.0, 12.0], [1.5, 5.1, 8.7], [15.0, 12.0, 17.0], [2.5, 2.5, 2.5]
    y_d, v_d, blocked = _zones(dx, ys, agent_y=5.1, vxs=vxs, wids=wids)
    assert blocked is True
    assert v_d == pytest.approx(12.0)  # slowest blocker
    assert y_d == pytest.approx(8.7)  # y of the fastest blocker (17 m/s)
    # v_d_eff never exceeds the agent's own desired speed
    _, v_d, blocked = _zones(dx, ys, agent_y=5.1, vxs=vxs, wids=wids, v_desired=10.0)
    assert (v_d, blocked) == (10.0, True)


def test_zone_non_blockers_behind_and_beyond_scan():
    # blocker in front at y = 5.1, agent at y = 4.0 -> zone [0, 4.2], centre 2.1
    assert _zones([10.0], [5.1], agent_y=4.0)[0] == pytest.approx(2.1)
    # entirely behind: dx = -3.4 <= -(3.2 + 3.5)/2 = -3.35 -> not a blocker -> W/2
    assert _zones([-3.4], [5.1], agent_y=4.0) == (W / 2, 20.0, False)
    # partly alongside (dx = -3.3 > -3.35) is a blocker
    assert _zones([-3.3], [5.1], agent_y=4.0)[0] == pytest.approx(2.1)
    # bumper gap 17.5 - 3.35 = 14.15 > d_o = 14 -> not a blocker
    assert _zones([17.5], [5.1], agent_y=4.0) == (W / 2, 20.0, False)
    # bumper gap 17.0 - 3.35 = 13.65 <= 14 -> blocker
    assert _zones([17.0], [5.1], agent_y=4.0)[0] == pytest.approx(2.1)
    # NaN (absent) rows are ignored
    assert _zones([np.nan], [5.1], agent_y=4.0) == (W / 2, 20.0, False)


def test_zone_scan_distance_scales_with_speed():
    # at 10 m/s d_o = 7 m: bumper gap 13.65 m is beyond it
    e = np.array([17.0])
    out = zone_target(e, np.array([1.1]), np.array([15.0]), np.array([B_LEN]), np.array([B_WID]),
                      4.0, 10.0, A_LEN, A_WID, 20.0, W)
    assert out == (W / 2, 20.0, False)


# ------------------------------------------------------------------ overtakes


def test_overtake_simple_pass():
    assert detect_overtakes(np.array([2.0]), np.array([-0.5]), 80.0, L) == 1
    assert detect_overtakes(np.array([1.0]), np.array([0.0]), 80.0, L) == 1  # to <= 0
    assert detect_overtakes(np.array([0.0]), np.array([-1.0]), 80.0, L) == 0  # from > 0 only
    assert detect_overtakes(np.array([-1.0]), np.array([1.0]), 80.0, L) == 0  # being passed
    assert detect_overtakes(np.array([3.0]), np.array([2.0]), 80.0, L) == 0  # still ahead
    assert detect_overtakes(np.array([2.0]), np.array([0.5]), 80.0, L) == 0  # still ahead, closer than 1 m


def test_overtake_ring_seam_is_not_a_pass():
    for prev, cur in [(-240.0, 240.0), (240.0, -240.0)]:
        assert detect_overtakes(np.array([prev]), np.array([cur]), 80.0, L) == 0
        # even with a range that covers the whole ring, |dx| < L/4 excludes the seam
        assert detect_overtakes(np.array([prev]), np.array([cur]), 300.0, L) == 0


def test_overtake_leaving_or_entering_range_is_not_a_pass():
    assert detect_overtakes(np.array([2.0]), np.array([np.nan]), 80.0, L) == 0
    assert detect_overtakes(np.array([np.nan]), np.array([-0.5]), 80.0, L) == 0
    assert detect_overtakes(np.array([5.0]), np.array([-81.0]), 80.0, L) == 0


def test_overtake_counts_several():
    prev = np.array([2.0, 0.5, 10.0, np.nan, -240.0])
    cur = np.array([-0.5, -0.1, 9.0, -1.0, 240.0])
    assert detect_overtakes(prev, cur, 80.0, L) == 2


# ------------------------------------------------------------------ costs and overlap


def test_longitudinal_and_lateral_costs():
    assert longitudinal_cost(15.0, 20.0) == pytest.approx(5.0 / 20.0)
    assert longitudinal_cost(25.0, 20.0) == pytest.approx(5.0 / 20.0)
    assert longitudinal_cost(50.0, 20.0) == 1.0  # min(1, 30/20)
    # floor: v_d_eff = 0.5 -> denominator 1.0: |1.0 - 0.5| / 1 = 0.5
    assert longitudinal_cost(1.0, 0.5) == pytest.approx(0.5)
    assert lateral_cost(3.0, 5.1, W) == pytest.approx(2.1 / 10.2)
    assert lateral_cost(8.0, 2.0, W) == pytest.approx(6.0 / 10.2)


def test_agent_overlaps():
    assert agent_overlaps(np.array([3.0]), np.array([1.5]), A_LEN, A_WID, B_LEN, B_WID)
    assert not agent_overlaps(np.array([3.4]), np.array([0.0]), A_LEN, A_WID, B_LEN, B_WID)
    assert not agent_overlaps(np.array([0.0]), np.array([1.75]), A_LEN, A_WID, B_LEN, B_WID)
    assert not agent_overlaps(np.array([]), np.array([]), A_LEN, A_WID, np.array([]), np.array([]))
    assert agent_overlaps(np.array([50.0, -1.0]), np.array([0.0, -1.0]), A_LEN, A_WID, B_LEN, B_WID)


# ------------------------------------------------------------------ reciprocal reward


def test_reciprocal_reward_by_hand():
    base = 0.1 / (0.1 + 0.35 * 0.2 + 0.65 * 0.1 + 1.0 * 0.3)
    assert reciprocal_reward(0.2, 0.1, 0.3, False, False, 0.35, 0.65, 1.0) == pytest.approx(base)
    assert reciprocal_reward(0.0, 0.0, 0.0, False, False, 0.35, 0.65, 1.0) == pytest.approx(1.0)
    assert reciprocal_reward(0.2, 0.1, 0.3, True, False, 0.35, 0.65, 1.0) == pytest.approx(base - 2.5)
    assert reciprocal_reward(0.2, 0.1, 0.3, False, True, 0.35, 0.65, 1.0) == pytest.approx(base + 2.0)


def test_overtake_bonus_not_paid_on_collision_step():
    base = 0.1 / (0.1 + 0.65 * 0.4)
    got = reciprocal_reward(0.4, 0.0, 0.0, True, True, 0.65, 0.0, 0.0)
    assert got == pytest.approx(base - 2.5)
    # with the collision term switched off, the bonus is still withheld on a collision step
    got = reciprocal_reward(0.4, 0.0, 0.0, True, True, 0.65, 0.0, 0.0, use_collision=False)
    assert got == pytest.approx(base)


def test_reciprocal_reward_switches():
    base = 0.1 / (0.1 + 0.65 * 0.4)
    assert reciprocal_reward(0.4, 0, 0, True, False, 0.65, 0, 0, use_collision=False) == pytest.approx(base)
    assert reciprocal_reward(0.4, 0, 0, False, True, 0.65, 0, 0, use_overtake=False) == pytest.approx(base)
    assert reciprocal_reward(0.4, 0, 0, True, False, 0.65, 0, 0, collision_reward=-1.0) == pytest.approx(base - 1.0)


def test_collision_term_on_every_overlapping_step():
    # the vehicle ahead is passed at 1 m/s relative speed; dx per step (m):
    steps = [5.0, 3.0, 1.0, -1.0, -3.0, -5.0]
    overlapping = [abs(d) < 3.35 for d in steps]  # by hand: steps 2..5 overlap
    assert overlapping == [False, True, True, True, True, False]
    for d, ov in zip(steps, overlapping):
        dx, dy, vx = np.array([d]), np.array([0.5]), np.array([17.0])
        terms = compute_reward(dx, dy, vx, np.zeros(1), np.array([B_LEN]), np.array([B_WID]),
                               4.0, 18.0, 0.0, A_LEN, A_WID, 20.0, W, "fields_collision")
        assert terms.collided is ov
        # by hand: c_x = |18 - 20| / 20 = 0.1; reward from the reported c_f
        base = 0.1 / (0.1 + 0.65 * 0.1 + 1.0 * terms.c_f)
        assert terms.c_x == pytest.approx(0.1)
        assert terms.reward - base == pytest.approx(-2.5 if ov else 0.0, abs=1e-12)
        # the same step without the collision term differs by exactly r_c when overlapping
        off = compute_reward(dx, dy, vx, np.zeros(1), np.array([B_LEN]), np.array([B_WID]),
                             4.0, 18.0, 0.0, A_LEN, A_WID, 20.0, W, "fields")
        assert terms.reward - off.reward == pytest.approx(-2.5 if ov else 0.0, abs=1e-12)


# ------------------------------------------------------------------ compute_reward


def test_compute_reward_fields_by_hand():
    # one neighbour 5 m ahead, same lane position, 2 m/s slower than the agent (closing)
    terms = compute_reward(np.array([5.0]), np.array([0.0]), np.array([16.0]), np.array([0.0]),
                           np.array([B_LEN]), np.array([B_WID]), 5.0, 18.0, 0.0, A_LEN, A_WID,
                           20.0, W, "fields_overtake_collision", overtook=True)
    e_c = 0.5 / ((5 / 3.35) ** 4 + 1)
    e_b = 0.5 / ((5 / (3.35 * (1 + 0.5 * 2))) ** 2 + 1)
    c_f = e_c + e_b
    assert terms.c_f == pytest.approx(c_f)
    assert terms.c_y == 0.0 and terms.y_d == pytest.approx(W / 2)  # zones off
    assert terms.collided is False and terms.overtook is True
    assert terms.reward == pytest.approx(0.1 / (0.1 + 0.65 * 0.1 + c_f) + 2.0)
    assert isinstance(terms, Rewards)
    assert tuple(terms.as_dict()) == REWARD_TERMS and {"c_x", "c_y", "c_f"} <= set(terms.as_dict())


def test_compute_reward_zones_on_blocked_changes_cx_and_cy():
    dx = np.array([5.0, 8.0, 12.0])
    ys = np.array([1.5, 5.1, 8.7])
    vxs = np.array([15.0, 12.0, 17.0])
    agent_y = 5.0
    terms = compute_reward(dx, ys - agent_y, vxs, np.zeros(3), np.full(3, B_LEN), np.full(3, 2.5),
                           agent_y, 14.0, 0.0, A_LEN, A_WID, 20.0, W,
                           "fields_zones_overtake_collision")
    # d_o = 14 * 0.7 = 9.8; bumper gaps 5-3.35, 8-3.35, 12-3.35 = 8.65 all <= 9.8 -> all block
    assert terms.blocked is True
    assert terms.v_d_eff == pytest.approx(12.0)
    assert terms.y_d == pytest.approx(8.7)
    assert terms.c_x == pytest.approx(2.0 / 12.0)
    assert terms.c_y == pytest.approx(3.7 / 10.2)
    expected = 0.1 / (0.1 + 0.35 * (2.0 / 12.0) + 0.65 * (3.7 / 10.2) + 1.0 * terms.c_f)
    assert terms.reward == pytest.approx(expected)
    # zones off for the same traffic: nominal desired speed, centre, c_y = 0
    off = compute_reward(dx, ys - agent_y, vxs, np.zeros(3), np.full(3, B_LEN), np.full(3, 2.5),
                         agent_y, 14.0, 0.0, A_LEN, A_WID, 20.0, W, "fields_overtake_collision")
    assert (off.y_d, off.v_d_eff, off.blocked, off.c_y) == (W / 2, 20.0, False, 0.0)
    assert off.c_x == pytest.approx(6.0 / 20.0)


def test_compute_reward_observed_subset_and_config():
    dx = np.array([5.0, 60.0])
    zero = np.zeros(2)
    only_near = compute_reward(dx, zero, np.full(2, 18.0), zero, B_LEN, B_WID, 5.0, 18.0, 0.0,
                               A_LEN, A_WID, 20.0, W, "fields", observed=np.array([True, False]))
    assert only_near.c_f == pytest.approx(0.5 / ((5 / 3.35) ** 4 + 1) + 0.5 / ((5 / 3.35) ** 2 + 1))
    none = compute_reward(dx, zero, np.full(2, 18.0), zero, B_LEN, B_WID, 5.0, 18.0, 0.0,
                          A_LEN, A_WID, 20.0, W, "fields", observed=[])
    assert none.c_f == 0.0
    cfg = RewardConfig(epsilon_r=0.2, field_magnitude=0.25)
    t = compute_reward(dx[:1], zero[:1], np.full(1, 18.0), zero[:1], B_LEN, B_WID, 5.0, 18.0, 0.0,
                       A_LEN, A_WID, 20.0, W, "fields", config=cfg)
    c_f = 0.25 / ((5 / 3.35) ** 4 + 1) + 0.25 / ((5 / 3.35) ** 2 + 1)
    assert t.c_f == pytest.approx(c_f)
    assert t.reward == pytest.approx(0.2 / (0.2 + 0.65 * 0.1 + c_f))


# ------------------------------------------------------------------ presets


PAPER_TABLE_4 = {
    # name: (w_x, w_y, w_f, r_c on, r_o on)
    "collision": (0.65, 0.0, 0.0, True, False),
    "overtake_collision": (0.65, 0.0, 0.0, True, True),
    "fields": (0.65, 0.0, 1.0, False, False),
    "fields_collision": (0.65, 0.0, 1.0, True, False),
    "fields_overtake_collision": (0.65, 0.0, 1.0, True, True),
    "zones_overtake_collision": (0.35, 0.65, 0.0, True, True),
    "fields_zones_overtake_collision": (0.35, 0.65, 1.0, True, True),
}


@pytest.mark.parametrize("name", sorted(PAPER_TABLE_4))
def test_presets_match_paper_table_4(name):
    p = get_preset(name)
    assert isinstance(p, RewardWeights)
    assert (p.w_x, p.w_y, p.w_f, p.use_collision, p.use_overtake) == PAPER_TABLE_4[name]


def test_preset_set_is_exactly_the_table():
    assert set(PRESETS) == set(PAPER_TABLE_4)
    assert RewardConfig().preset in PRESETS


def test_a_preset_name_with_an_unknown_component_is_refused():
    from lanefree_sumo.rl.rewards import _weights

    assert _weights("fields_zones_collision") == RewardWeights(0.35, 0.65, 1.0, True, False)
    with pytest.raises(ValueError, match="'feilds_collision': unknown component.s. feilds"):
        _weights("feilds_collision")


def test_unknown_preset_lists_names():
    with pytest.raises(ValueError) as err:
        get_preset("fieldz")
    msg = str(err.value)
    assert "fieldz" in msg and "\n" not in msg
    assert msg.endswith("valid presets: " + ", ".join(PRESETS))
    for name in PAPER_TABLE_4:
        assert name in msg
    with pytest.raises(ValueError):
        compute_reward(np.array([]), np.array([]), np.array([]), np.array([]), np.array([]),
                       np.array([]), 5.0, 20.0, 0.0, A_LEN, A_WID, 20.0, W, "nope")


def test_presets_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        get_preset("fields").w_f = 2.0  # type: ignore[misc]
    assert math.isclose(get_preset("fields").w_f, 1.0)


# ------------------------------------------------------------------ non-default weights and constants
# Weights other than the paper's, and every constant changed, so that a dropped factor, a swapped
# weight or a default used in place of the passed value changes the number.


def test_reciprocal_reward_with_non_default_weights_and_constants():
    # w_x c_x = 2 × 0.2 = 0.4, w_y c_y = 3 × 0.4 = 1.2, w_f c_f = 4 × 0.5 = 2.0; ε_r = 0.5
    # r0 = 0.5 / (0.5 + 0.4 + 1.2 + 2.0) = 0.5 / 4.1
    r0 = 0.5 / 4.1
    kw = {"epsilon_r": 0.5, "collision_reward": -7.0, "overtake_reward": 3.0}
    args = (0.2, 0.4, 0.5)
    w = (2.0, 3.0, 4.0)
    assert reciprocal_reward(*args, False, False, *w, **kw) == pytest.approx(r0)
    assert reciprocal_reward(*args, True, False, *w, **kw) == pytest.approx(r0 - 7.0)
    assert reciprocal_reward(*args, False, True, *w, **kw) == pytest.approx(r0 + 3.0)
    assert reciprocal_reward(*args, True, True, *w, **kw) == pytest.approx(r0 - 7.0)  # no bonus on a hit
    # a count of 3 vehicles passed pays the bonus once (per step, not per vehicle)
    assert reciprocal_reward(*args, False, 3, *w, **kw) == pytest.approx(r0 + 3.0)
    assert reciprocal_reward(*args, True, False, *w, **kw, use_collision=False) == pytest.approx(r0)
    assert reciprocal_reward(*args, False, True, *w, **kw, use_overtake=False) == pytest.approx(r0)
    # swapping c_x and c_y changes the weighted sum: 2 × 0.4 + 3 × 0.2 = 1.4 instead of 1.6
    assert reciprocal_reward(0.4, 0.2, 0.5, False, False, *w, **kw) == pytest.approx(0.5 / 3.9)


def test_reciprocal_reward_arrays_match_the_scalar_formula():
    # the same four steps as one array call: (collided, overtook) = (F, F), (T, F), (F, 2 passes), (T, T)
    r0 = 0.5 / 4.1
    got = reciprocal_reward(np.full(4, 0.2), np.full(4, 0.4), np.full(4, 0.5),
                            np.array([False, True, False, True]), np.array([0, 0, 2, 1]), 2.0, 3.0, 4.0,
                            epsilon_r=0.5, collision_reward=-7.0, overtake_reward=3.0)
    np.testing.assert_allclose(got, [r0, r0 - 7.0, r0 + 3.0, r0 - 7.0])
    # per-step costs differ: step 2 has c_x = 0 -> 0.5 / (0.5 + 1.2 + 2.0) = 0.5 / 3.7
    got = reciprocal_reward(np.array([0.2, 0.0]), np.full(2, 0.4), np.full(2, 0.5), np.zeros(2), np.zeros(2),
                            2.0, 3.0, 4.0, epsilon_r=0.5)
    np.testing.assert_allclose(got, [0.5 / 4.1, 0.5 / 3.7])
    off = reciprocal_reward(np.full(2, 0.2), np.full(2, 0.4), np.full(2, 0.5), np.array([True, False]),
                            np.array([False, True]), 2.0, 3.0, 4.0, epsilon_r=0.5, use_collision=False,
                            use_overtake=False)
    np.testing.assert_allclose(off, [r0, r0])


def test_longitudinal_cost_floor_is_the_passed_one():
    # v_d_eff = 0.5 below the floor 2.0: |1.0 − 0.5| / 2.0 = 0.25 (the default floor 1.0 would give 0.5)
    assert longitudinal_cost(1.0, 0.5, min_desired_speed=2.0) == pytest.approx(0.25)
    # above the floor the desired speed itself divides: |3 − 8| / 8
    assert longitudinal_cost(3.0, 8.0, min_desired_speed=2.0) == pytest.approx(5.0 / 8.0)


def _one_neighbour(weights, config, collided=None, overtook=0):
    """Agent 3.0 × 2.0 m at vx 17, vy 0.5; one vehicle 3.0 × 2.0 m at dx = 6, dy = 1, vx 15, vy 0."""
    return compute_reward(np.array([6.0]), np.array([1.0]), np.array([15.0]), np.array([0.0]), np.array([3.0]),
                          np.array([2.0]), 5.0, 17.0, 0.5, 3.0, 2.0, 20.0, 10.0, weights, config=config,
                          collided=collided, overtook=overtook)


def test_compute_reward_uses_every_constant_of_its_config():
    cfg = RewardConfig(epsilon_r=0.5, collision_reward=-7.0, overtake_reward=3.0, field_magnitude=0.25,
                       critical_exponents=(3.0, 2.0, 1.0), broad_exponents=(2.0, 1.0, 2.0), k_r_s_per_m=0.25,
                       e_v_s_per_m=2.0)
    weights = RewardWeights(2.0, 0.0, 3.0, True, True)
    # a_c = (3 + 3)/2 = 3, b_c = (2 + 2)/2 = 2: rx = 6/3 = 2, ry = 1/2 = 0.5
    # critical: 0.25 / (2^3 + 0.5^2 + 1)^1 = 0.25 / 9.25
    e_c = 0.25 / 9.25
    # closing speeds: ux = 17 − 15 = 2 (ahead, agent faster), uy = 0.5 − 0 = 0.5 (to the left, drifting left)
    # broad: rx / (1 + 0.25 × 2) = 2 / 1.5 = 4/3, ry / (1 + 2 × 0.5) = 0.25
    # 0.25 / ((4/3)^2 + 0.25^1 + 1)^2 = 0.25 / (16/9 + 1.25)^2
    e_b = 0.25 / (16 / 9 + 1.25) ** 2
    c_f = e_c + e_b
    c_x = 3.0 / 20.0  # zones off (w_y = 0): |17 − 20| / 20
    terms = _one_neighbour(weights, cfg, overtook=2)
    assert terms.c_f == pytest.approx(c_f)
    assert (terms.c_x, terms.c_y, terms.y_d, terms.v_d_eff) == (pytest.approx(c_x), 0.0, 5.0, 20.0)
    assert terms.collided is False and terms.overtook is True  # |dx| = 6 ≥ 3: no overlap
    assert terms.reward == pytest.approx(0.5 / (0.5 + 2.0 * c_x + 3.0 * c_f) + 3.0)
    hit = _one_neighbour(weights, cfg, collided=True, overtook=2)
    assert hit.reward == pytest.approx(0.5 / (0.5 + 2.0 * c_x + 3.0 * c_f) - 7.0)
    # the switches come from the weights, the amounts from the config
    quiet = _one_neighbour(RewardWeights(2.0, 0.0, 3.0, False, False), cfg, collided=True, overtook=1)
    assert quiet.reward == pytest.approx(0.5 / (0.5 + 2.0 * c_x + 3.0 * c_f))
    # r_o switched off by the preset: a pass without a collision earns nothing
    no_bonus = _one_neighbour(RewardWeights(2.0, 0.0, 3.0, True, False), cfg, overtook=1)
    assert no_bonus.overtook is True and no_bonus.reward == pytest.approx(0.5 / (0.5 + 2.0 * c_x + 3.0 * c_f))
    # w_f = 0: c_f is still reported, and the reward ignores it
    no_f = _one_neighbour(RewardWeights(2.0, 0.0, 0.0, False, False), cfg)
    assert no_f.c_f == pytest.approx(c_f) and no_f.reward == pytest.approx(0.5 / (0.5 + 2.0 * c_x))


def test_compute_reward_lateral_closing_speed_is_the_agents_minus_the_neighbours():
    # the same scene with the neighbour drifting right at 0.5 m/s: dvy = 0.5 − (−0.5) = 1 m/s, closing (dy > 0);
    # default constants: broad b_b = 2 × (1 + 0.4 × 1) = 2.8, a_b = 3 × (1 + 0.5 × 2) = 6 (ux = 2)
    terms = compute_reward(np.array([6.0]), np.array([1.0]), np.array([15.0]), np.array([-0.5]), np.array([3.0]),
                           np.array([2.0]), 5.0, 17.0, 0.5, 3.0, 2.0, 20.0, 10.0, "fields")
    e_c = 0.5 / ((6 / 3) ** 4 + (1 / 2) ** 4 + 1)
    e_b = 0.5 / ((6 / 6) ** 2 + (1 / 2.8) ** 2 + 1)
    assert terms.c_f == pytest.approx(e_c + e_b)


def test_compute_reward_floor_of_the_desired_speed_comes_from_the_config():
    # v_desired = 2 below the floor 4: c_x = |3 − 2| / 4 = 0.25 (the default floor 1 would give 0.5)
    terms = compute_reward(np.array([]), np.array([]), np.array([]), np.array([]), np.array([]), np.array([]),
                           5.0, 3.0, 0.0, 3.0, 2.0, 2.0, 10.0, RewardWeights(1.0, 0.0, 0.0, False, False),
                           config=RewardConfig(min_desired_speed_mps=4.0, epsilon_r=0.25))
    assert terms.c_x == pytest.approx(0.25) and terms.c_f == 0.0
    assert terms.reward == pytest.approx(0.25 / (0.25 + 0.25))


def test_compute_reward_zones_use_the_configs_time_gap_and_margin():
    # agent 3 × 2 m at y = 5 on a 10 m road, vx = 10; a 3 × 2 m blocker straight ahead at dx = 15, vx 15:
    # bumper gap 15 − 3 = 12 m. Time gap 2 s: d_o = 20 m ≥ 12 -> it blocks (0.7 s: d_o = 7 m, it does not)
    weights = RewardWeights(1.0, 2.0, 0.0, False, False)
    args = (np.array([15.0]), np.array([0.0]), np.array([15.0]), np.array([0.0]), np.array([3.0]), np.array([2.0]),
            5.0, 10.0, 0.0, 3.0, 2.0, 20.0, 10.0, weights)
    far = compute_reward(*args, config=RewardConfig(epsilon_r=0.1))
    assert (far.y_d, far.v_d_eff, far.blocked, far.c_y) == (5.0, 20.0, False, 0.0)
    # the blocker occupies [4, 6]: zones [0, 4] and [6, 10], 1 m from the agent's centre each: a tie,
    # the left one (centre 8): c_y = |5 − 8| / 10 = 0.3; c_x = |10 − 20| / 20 = 0.5
    near = compute_reward(*args, config=RewardConfig(zone_time_gap_s=2.0))
    assert (near.y_d, near.v_d_eff, near.blocked) == (pytest.approx(8.0), 20.0, False)
    assert (near.c_x, near.c_y) == (pytest.approx(0.5), pytest.approx(0.3))
    assert near.reward == pytest.approx(0.1 / (0.1 + 1.0 * 0.5 + 2.0 * 0.3))
    # a margin of 1.5 m asks for 2 + 2 × 1.5 = 5 m > 4 m: no zone fits -> blocked, follow the blocker
    # (y_d = its y = 5, v_d_eff = 15): c_x = |10 − 15| / 15 = 1/3, c_y = 0
    narrow = compute_reward(*args, config=RewardConfig(zone_time_gap_s=2.0, zone_margin_m=1.5))
    assert (narrow.y_d, narrow.v_d_eff, narrow.blocked, narrow.c_y) == (5.0, 15.0, True, 0.0)
    assert narrow.reward == pytest.approx(0.1 / (0.1 + 1.0 / 3.0))


# ------------------------------------------------------------------ several events in one step, exact boundaries


def test_several_overtakes_in_one_step_and_the_range_and_quarter_boundaries():
    # range 30 m on a 400 m ring (quarter 100 m)
    prev = np.array([30.0, 0.5, 12.0, 3.0, 31.0, 4.0])
    cur = np.array([-30.0, 0.0, -1.0, -29.9, -1.0, -31.0])
    # passes: 30 -> −30 (|dx| = range at both steps counts), 0.5 -> 0 (ends at 0), 12 -> −1, 3 -> −29.9;
    # not: 31 -> −1 (out of range before), 4 -> −31 (out of range after)
    assert detect_overtakes(prev, cur, 30.0, 400.0) == 4
    # the quarter of the ring is excluded exactly: ring 120 m (quarter 30 m), range 40 m
    assert detect_overtakes(np.array([30.0]), np.array([-1.0]), 40.0, 120.0) == 0
    assert detect_overtakes(np.array([29.5]), np.array([-1.0]), 40.0, 120.0) == 1
    assert detect_overtakes(np.array([1.0]), np.array([-30.0]), 40.0, 120.0) == 0
    assert detect_overtakes(np.array([1.0]), np.array([-29.5]), 40.0, 120.0) == 1
    # everyone passed at once (six vehicles) and nobody passed backwards
    assert detect_overtakes(np.arange(1.0, 7.0), -np.arange(1.0, 7.0), 80.0, 500.0) == 6
    assert detect_overtakes(-np.arange(1.0, 7.0), np.arange(1.0, 7.0), 80.0, 500.0) == 0


def test_boxes_that_touch_do_not_overlap_the_agent():
    # agent 4 × 2 m, vehicles 2 × 1 m: half sums (4 + 2)/2 = 3 m and (2 + 1)/2 = 1.5 m, exact in binary
    def hit(dx, dy):
        return agent_overlaps(np.array([dx]), np.array([dy]), 4.0, 2.0, np.array([2.0]), np.array([1.0]))

    assert not hit(3.0, 0.0) and not hit(-3.0, 0.0)  # touching ahead and behind
    assert not hit(0.0, 1.5) and not hit(0.0, -1.5)  # touching left and right
    assert hit(2.96875, 1.46875) and hit(-2.96875, -1.46875)  # 1/32 m inside on both axes
    assert not hit(2.96875, 1.5) and not hit(3.0, 1.46875)  # inside on one axis only
    # each row has its own size: a 6 m long vehicle at dx = 4.5 touches ((4 + 6)/2 = 5 > 4.5: overlaps),
    # a 2 m one at the same offset does not
    assert agent_overlaps(np.array([4.5, 50.0]), np.zeros(2), 4.0, 2.0, np.array([6.0, 2.0]), np.ones(2))
    assert not agent_overlaps(np.array([50.0, 4.5]), np.zeros(2), 4.0, 2.0, np.array([6.0, 2.0]), np.ones(2))


def test_zone_blockers_at_the_exact_scan_boundaries():
    # agent and vehicle 3 m long: half sum 3 m; agent at 10 m/s, time gap 0.5 s: d_o = 5 m (all exact in binary)
    def zones(dx):
        return zone_target(np.array([dx]), np.array([0.0]), np.array([8.0]), np.array([3.0]), np.array([2.0]), 5.0,
                           10.0, 3.0, 2.0, 20.0, 10.0, time_gap=0.5, margin=0.0)

    assert zones(-3.0) == (5.0, 20.0, False)  # touching behind: entirely behind, not a blocker
    assert zones(-2.96875)[0] == 8.0  # overlapping by 1/32 m: a blocker ([4, 6] taken, a tie -> left zone [6, 10])
    assert zones(8.0)[0] == 8.0  # bumper gap 8 − 3 = 5 m = d_o: a blocker
    assert zones(8.03125) == (5.0, 20.0, False)  # 1/32 m beyond d_o: not


def test_zone_edges_are_clipped_to_the_road():
    # a 0.8 m agent at y = 0.5 with no margin; a 2 m blocker at y = 1.5 takes [0.5, 2.5]: the zone [0, 0.5] is too
    # narrow, so [2.5, 10] (centre 6.25) is the target
    def target(y_blocker):
        return zone_target(np.array([5.0]), np.array([y_blocker - 0.5]), np.array([8.0]), np.array([3.0]),
                           np.array([2.0]), 0.5, 10.0, 3.0, 0.8, 20.0, 10.0, margin=0.0)[0]

    assert target(1.5) == pytest.approx(6.25)
    # a blocker beyond the left edge (another road part, on an open road) frees the whole road [0, 10], not more
    assert target(12.0) == pytest.approx(5.0)
    # one beyond the right edge likewise
    assert target(-2.0) == pytest.approx(5.0)


def test_zone_targets_of_many_agents_are_each_agents_zone_target_from_its_present_rows():
    """The batched scan ``[2, 12, M]`` (agents of several runs, each with its own speed, size, desired speed and
    road width; rows absent or non-finite) gives bit for bit what zone_target gives each agent alone."""
    from lanefree_sumo.rl.fields_zones import zone_targets

    rng = np.random.default_rng(7)
    shape, m = (2, 12), 7
    dx = rng.uniform(-8.0, 30.0, shape + (m,))
    dy = rng.uniform(-6.0, 6.0, shape + (m,))
    vxs = rng.uniform(8.0, 22.0, shape + (m,))
    lens = rng.uniform(3.0, 5.0, shape + (m,))
    wids = rng.uniform(1.5, 2.5, shape + (m,))
    present = rng.random(shape + (m,)) < 0.8
    dx[0, 3, 2] = dy[1, 5, 0] = vxs[1, 7, 4] = np.nan  # non-finite rows are absent too
    present[0, :2] = present[1, 4] = False  # agents alone on the road among others that are not
    agent_y, agent_vx = rng.uniform(1.0, 9.0, shape), rng.uniform(5.0, 25.0, shape)
    agent_len, agent_wid = rng.uniform(3.0, 4.5, shape), rng.uniform(1.4, 2.0, shape)
    v_desired, width = rng.uniform(14.0, 30.0, shape), np.where(rng.random(shape) < 0.5, 10.2, 8.0)
    y_d, v_d, blocked = zone_targets(dx, dy, vxs, lens, wids, agent_y, agent_vx, agent_len, agent_wid, v_desired,
                                     width, time_gap=0.8, margin=0.3, present=present)
    assert y_d.shape == v_d.shape == blocked.shape == shape
    outcomes = set()
    for i in np.ndindex(*shape):
        rows = present[i]
        alone = zone_target(dx[i][rows], dy[i][rows], vxs[i][rows], lens[i][rows], wids[i][rows], agent_y[i],
                            agent_vx[i], agent_len[i], agent_wid[i], v_desired[i], width[i], time_gap=0.8, margin=0.3)
        assert (float(y_d[i]), float(v_d[i]), bool(blocked[i])) == alone, i
        outcomes.add("alone" if not rows.any() else "blocked" if alone[2] else "zone")
    assert outcomes == {"alone", "blocked", "zone"}  # free roads, chosen zones and blocked agents were compared
    # every row absent, or no row at all: the road's centre at the desired speed
    for rows in (np.zeros(shape + (m,), dtype=bool), None):
        cut = slice(None) if rows is not None else slice(0, 0)
        y_d, v_d, blocked = zone_targets(dx[..., cut], dy[..., cut], vxs[..., cut], lens[..., cut], wids[..., cut],
                                         agent_y, agent_vx, agent_len, agent_wid, v_desired, width, time_gap=0.8,
                                         margin=0.3, present=rows)
        assert y_d.tolist() == (width / 2).tolist() and v_d.tolist() == v_desired.tolist() and not blocked.any()
    # one size, desired speed and road for every agent (numbers): each agent's values all the same
    y_d, v_d, blocked = zone_targets(dx[..., :0], dy[..., :0], vxs[..., :0], lens[..., :0], wids[..., :0], agent_y,
                                     agent_vx, 3.5, 1.8, 25.0, 10.2, time_gap=0.8, margin=0.3)
    assert y_d.shape == v_d.shape == blocked.shape == shape and (y_d == 5.1).all() and (v_d == 25.0).all()


def test_zone_targets_compute_as_torch_on_tensors():
    torch = pytest.importorskip("torch")
    from lanefree_sumo.rl.fields_zones import zone_targets

    rng = np.random.default_rng(8)
    shape, m = (3, 6), 5
    rows = [rng.uniform(-8.0, 30.0, shape + (m,)), rng.uniform(-6.0, 6.0, shape + (m,)),
            rng.choice([12.0, 15.0], shape + (m,)), rng.uniform(3.0, 5.0, shape + (m,)),
            rng.uniform(1.5, 2.5, shape + (m,))]
    agents = [rng.uniform(1.0, 9.0, shape), rng.uniform(5.0, 25.0, shape), np.full(shape, 3.5), np.full(shape, 1.8),
              rng.uniform(14.0, 30.0, shape), np.full(shape, 10.2)]
    present = rng.random(shape + (m,)) < 0.8
    for cut in (slice(None), slice(0, 0)):  # vehicles, and none at all
        args = [r[..., cut] for r in rows] + agents
        mask = present[..., cut]
        want = zone_targets(*args, time_gap=0.8, margin=0.3, present=mask)
        got = zone_targets(*(torch.from_numpy(a) for a in args), time_gap=0.8, margin=0.3,
                           present=torch.from_numpy(mask))
        for g, w in zip(got, want):
            assert isinstance(g, torch.Tensor)
            np.testing.assert_array_equal(g.numpy(), w)


def test_field_terms_compute_as_torch_on_tensors():
    """The batched environment on a device evaluates the fields on tensors: the same values, as tensors."""
    torch = pytest.importorskip("torch")
    from lanefree_sumo.rl.fields_zones import field_terms

    rng = np.random.default_rng(4)
    arrays = [rng.uniform(-20.0, 20.0, (3, 5)), rng.uniform(-4.0, 4.0, (3, 5)), rng.uniform(-5.0, 5.0, (3, 5)),
              rng.uniform(-1.0, 1.0, (3, 5))]
    sizes = (np.full((3, 1), A_LEN), np.full((3, 1), A_WID), np.full((3, 5), B_LEN), np.full((3, 5), B_WID))
    options = {"magnitude": 0.7, "critical_exponents": (4.0, 3.0, 1.5), "broad_exponents": (2.0, 2.5, 1.0),
               "k_r": 0.6, "e_v": 0.3, "stretch": "closing"}
    want = field_terms(*arrays, *sizes, **options)
    got = field_terms(*(torch.from_numpy(a) for a in (*arrays, *sizes)), **options)
    for g, w in zip(got, want):
        assert isinstance(g, torch.Tensor)
        np.testing.assert_allclose(g.numpy(), w, rtol=1e-12, atol=0.0)


def test_zone_of_exactly_the_agents_width_and_margins_fits_and_the_agents_own_zone_wins():
    # a 3 m long vehicle 5 m ahead (a blocker at 10 m/s, time gap 0.5 s); road 10 m; all exact in binary
    def zones(y_blocker, width, agent_y, agent_wid, margin):
        return zone_target(np.array([5.0]), np.array([y_blocker - agent_y]), np.array([8.0]), np.array([3.0]),
                           np.array([width]), agent_y, 10.0, 3.0, agent_wid, 20.0, 10.0, time_gap=0.5, margin=margin)

    # the blocker takes [3, 7]: both zones 3 m = 2 m + 2 × 0.5 m fit (a tie: the left one); a wider margin: none
    assert zones(5.0, 4.0, 5.0, 2.0, 0.5) == (8.5, 20.0, False)
    assert zones(5.0, 4.0, 5.0, 2.0, 0.5625) == (5.0, 8.0, True)
    # the blocker takes [4, 4.5]: the agent at 3.875 is inside [0, 4] (distance 0), 0.625 m from [4.5, 10]
    assert zones(4.25, 0.5, 3.875, 1.0, 0.0) == (2.0, 20.0, False)


# ------------------------------------------------------------------ the learning problem against compute_reward


@pytest.mark.parametrize("config", [
    {"scenario": {"density_veh_per_km": 120}},
    {"reward": {"preset": "fields_overtake_collision"}},
    {"road": {"kind": "onramp"}, "scenario": {"density_veh_per_km": 40}},
], ids=["ring", "no-zones", "onramp"])
def test_every_steps_reward_terms_are_compute_rewards_of_the_scene_bit_for_bit(config):
    """compute_reward is the scalar reference of the learning problem (rl/problem.py): each step of LaneFree-v0, its
    terms from the simulation's state — the vehicles in range, the n nearest, the lateral bounds — are info's."""
    from lanefree_sumo.rl.env import LaneFreeEnv

    env = LaneFreeEnv({"backend": "numpy", **config})
    env.reset(seed=4)
    rng = np.random.default_rng(0)
    cfg, zoned = env.cfg, 0
    for _ in range(300):
        _, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        state, (dx_all, dy_all) = env.sim.current()
        a = env.vehicle.index
        dx, dy = dx_all[a], dy_all[a]
        idx = np.flatnonzero((np.abs(dx) <= cfg.observation.range_m) & (np.arange(state.n) != a))
        nearest = idx[np.argsort(np.hypot(dx[idx], dy[idx]), kind="stable")][:cfg.observation.n_neighbours]
        lo, hi = env.vehicle.lateral_bounds()
        terms = compute_reward(dx[idx], dy[idx], state.vx[idx], state.vy[idx], state.length[idx], state.width[idx],
                               float(state.y[a]) - lo, float(state.vx[a]), float(state.vy[a]), float(state.length[a]),
                               float(state.width[a]), float(state.v_desired[a]), hi - lo, cfg.reward.preset,
                               observed=np.searchsorted(idx, nearest), collided=bool(info["collided"]),
                               overtook=bool(info["overtook"]), config=cfg.reward)
        for name, value in terms.as_dict().items():
            assert np.asarray(info[name]).tobytes() == np.asarray(value).tobytes(), name
        assert reward == terms.reward
        zoned += terms.y_d != 0.5 * (hi - lo)  # a blocker ahead moved the lateral target
        if terminated or truncated:
            break
    env.close()
    assert zoned > 0 or "reward" in config, "the scenes exercise the zones"
