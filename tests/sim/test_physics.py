"""The physics without SUMO: forces on hand-built cases, ramps, edge bounds, ring wrap,
dynamics, collisions counted once per contact, spawning."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.special import erfc

from lanefree_sumo.config import AccelerationBounds, ConfigError, DriverConfig, LaneFreeConfig, merge_config
from lanefree_sumo.sim.collisions import CollisionTracker, count_events, overlap_matrix
from lanefree_sumo.sim.dynamics import ballistic_distance, clip_acceleration, clip_accelerations, plan_step
from lanefree_sumo.sim.forces import (
    driver_accelerations,
    edge_bound,
    ramp_g,
    strongest_mask,
    symmetric_trapezoid,
    trapezoid_h,
)
from lanefree_sumo.sim.network import EDGES, edge_to_ring, ring_to_edge
from lanefree_sumo.sim.simulation import Simulation
from lanefree_sumo.sim.spawn import check_fits, max_density, spawn
from lanefree_sumo.sim.state import VehicleState, wrap

T = 0.25
L = 500.0
W = 10.2


def make_state(x, y, vx, vd, vy=None, length=3.5, width=1.8) -> VehicleState:
    n = len(x)
    return VehicleState(
        ids=[f"v{i}" for i in range(n)],
        x=np.asarray(x, float),
        y=np.asarray(y, float),
        vx=np.asarray(vx, float),
        vy=np.zeros(n) if vy is None else np.asarray(vy, float),
        length=np.full(n, length),
        width=np.full(n, width),
        v_desired=np.asarray(vd, float),
        controlled=np.ones(n, bool),
    )


def accel(state: VehicleState, **driver) -> tuple[np.ndarray, np.ndarray]:
    cfg = merge_config(DriverConfig(), driver)
    return driver_accelerations(state, cfg, L, W, T)


# -- ramps and bounds ------------------------------------------------------------------------

def test_ramp_g_rises_plateaus_falls():
    # w = 2, l = 3, c = 4: rise on [0, 2], plateau [2, 5], fall [5, 9]
    t = np.array([-1.0, 0.0, 1.0, 2.0, 4.0, 5.0, 7.0, 9.0, 10.0])
    expected = [0.0, 0.0, 0.5, 1.0, 1.0, 1.0, 1 - 2 / 4, 0.0, 0.0]
    assert ramp_g(t, 2.0, 3.0, 4.0) == pytest.approx(expected)


def test_zero_width_ramps_at_exactly_their_edges():
    # w = 0, l = 2, c = 0: 0 before and at the rise's edge (t = 0), 1 on the plateau up to and at its end (t = 2)
    g = ramp_g(np.array([-1.0, 0.0, 1.0, 2.0, 3.0]), 0.0, 2.0, 0.0)
    assert g.tolist() == [0.0, 0.0, 1.0, 1.0, 0.0]


def test_a_neighbour_exactly_alongside_repels_as_one_ahead():
    # dx = 0 counts as ahead (specification §3 as read here): its repulsion is summed without nudging
    state = make_state([100.0, 100.0], [5.0, 6.5], [20.0, 20.0], [20.0, 20.0])
    _, ay = accel(state)
    assert ay[0] < 0.0 < ay[1]  # pushed apart


def test_a_leader_exactly_at_the_neighbour_range_still_counts():
    # 30 m apart at 30 m/s: the plateau (9.75 + 13.5 + 3.5 + 2.5 = 29.25 m) and its 9.75 m fall reach past 30 m
    state = make_state([100.0, 130.0], [5.0, 5.0], [30.0, 30.0], [30.0, 30.0])
    ax, _ = accel(state, neighbour_range_m=30.0)
    assert ax[0] < 0.0  # braking for it
    ax, _ = accel(state, neighbour_range_m=29.875)
    assert ax[0] == 0.0  # just beyond the range: ignored


def test_trapezoid_h_is_symmetric_around_zero():
    # H(t, w, l, c) = G(t + w + l, w, 2l, c): plateau |t| <= l, ramps of w before and c after
    t = np.array([-7.0, -5.5, -4.0, 0.0, 4.0, 5.5, 7.0])
    assert trapezoid_h(t, 3.0, 4.0, 3.0) == pytest.approx([0.0, 0.5, 1.0, 1.0, 1.0, 0.5, 0.0])


def test_zero_width_ramp_is_a_step_without_nan():
    with np.errstate(all="raise"):
        h = trapezoid_h(np.array([-2.1, -1.9, 0.0, 1.9, 2.1]), 0.0, 2.0, 0.0)
    assert h.tolist() == [0.0, 1.0, 1.0, 1.0, 0.0]


def test_standstill_gives_finite_forces():
    state = make_state([0.0, 5.0], [5.0, 5.0], [0.0, 0.0], [20.0, 20.0])
    with np.errstate(all="raise"):
        ax, ay = accel(state)
    assert np.isfinite(ax).all() and np.isfinite(ay).all()
    assert ax[1] > 0  # nobody ahead within reach: accelerates towards its desired speed


def test_edge_bound_at_a_discriminant_of_exactly_zero_is_the_root():
    # T = 0.25, ū = −1: disc = T²ū² − 4Tūv + 8ū(Tv − d) = 0 at v = 4.0625, d = 0.5 (exact in binary); the double
    # root (Tū − 2v)/(2T) = −16.75, where a negative discriminant gives ū
    assert edge_bound(np.array([4.0625, 4.0625]), np.array([0.5, 0.4]), T, -1.0).tolist() == [-16.75, -1.0]


def test_edge_bound_stops_exactly_at_the_edge():
    ubar = -1.8
    for v, d in [(0.0, 1.0), (0.5, 2.0), (1.0, 0.8), (-0.5, 0.3)]:
        u = float(edge_bound(np.array(v), np.array(d), T, ubar))
        # travel this step with u, then brake at |ubar| to a stop: exactly d
        travelled = v * T + 0.5 * u * T * T + (v + u * T) ** 2 / (2 * -ubar)
        assert travelled == pytest.approx(d, abs=1e-9)
    assert float(edge_bound(np.array(0.0), np.array(0.0), T, ubar)) == pytest.approx(0.0, abs=1e-12)
    # moving fast towards an edge already reached: no real root, full braking
    assert float(edge_bound(np.array(2.0), np.array(0.0), T, ubar)) == ubar


# -- forces on hand-built cases ----------------------------------------------------------------

def test_leader_in_ramp_region_by_hand():
    # i at 20 m/s behind j (also 20 m/s) 22 m ahead in the same lateral position.
    state = make_state([100.0, 122.0], [5.0, 5.0], [20.0, 20.0], [20.0, 20.0])
    ax, ay = accel(state)
    ux = 20 - 0.7 * 20                   # 6 m/s
    lx = 20 * 0.65                       # 13 m
    dxx = ux**2 / (2 * 3.0) + 3.5         # 9.5 m
    plateau = lx / 2 + dxx + 2.5          # 18.5 m
    mag = (lx / 2 + plateau - 22) / (lx / 2)  # falling ramp: 3 / 6.5
    fx = -mag
    expected = 3.0 * fx + (erfc(0.0) - 1.0)  # k_x = c_x = 3.0 with nudging off
    degree = abs(fx) ** 0.25
    gap = 22 - 3.5
    v_safe = min(gap / 0.25, 20 - 0.1)
    wall = ((1 - degree) * 0 + degree * (v_safe - 20)) / T
    assert wall > expected  # the wall does not bind here
    assert ax[0] == pytest.approx(expected)
    assert ay[0] == pytest.approx(0.0, abs=1e-12)
    # the leader sees the follower only as a nudge, which is off: free driving at vd → 0
    assert ax[1] == pytest.approx(0.0, abs=1e-12)


def test_close_leader_saturates_braking():
    state = make_state([100.0, 110.0], [5.0, 5.0], [20.0, 10.0], [20.0, 20.0])
    ax, _ = accel(state)
    assert ax[0] == -4.0  # the reference's effective (integer) bound, not −4.5


def test_gain_and_braking_decel_are_one_parameter():
    # nudging on: k_x = c_x = 5.0 for both the gain on Σf_x and D_x (the reference's nudging setting)
    state = make_state([100.0, 120.0], [5.0, 5.0], [20.0, 20.0], [20.0, 20.0])
    ax, _ = accel(state, nudging=True)
    ux, lx = 6.0, 13.0
    plateau = lx / 2 + ux**2 / (2 * 5.0) + 3.5 + 2.5  # 16.1 m
    fx = -(lx / 2 + plateau - 20.0) / (lx / 2)  # 0.4
    wall = abs(fx) ** 0.25 * (19.9 - 20.0) / T
    assert ax[0] == pytest.approx(min(5.0 * fx, wall))
    # the old mix (gain 5.0, c_x 3.0) gave a plateau of 18.5 m: f_x ≈ −0.77, ax ≈ −3.85
    assert ax[0] > -2.5


def test_background_lateral_bound_is_one_mps2():
    # a vehicle squeezed from the left and alongside: its lateral force saturates at −1.0, not −1.8
    state = make_state([100.0, 101.0, 101.0], [5.0, 6.9, 5.0 + 2.0], [20.0, 20.0, 20.0], [20.0, 20.0, 20.0])
    _, ay = accel(state)
    assert ay[0] == -1.0


def test_summed_repulsions_are_those_of_largest_magnitude():
    # A almost alongside (dx 1 m, dy 2.3 m): mag 1 but |f_x| = cos θ ≈ 0.40; B straight ahead at
    # 20 m: mag = |f_x| ≈ 0.85. With one summed repulsion, the largest *magnitude* is A's, so its
    # f_y ≈ −0.92 is summed (the old |f_x| rule summed B and gave ay = 0).
    state = make_state([100.0, 101.0, 120.0], [5.0, 7.3, 5.0], [20.0, 20.0, 20.0], [20.0, 20.0, 20.0])
    _, ay = accel(state, max_repulsions=1)
    theta = math.atan2(2.3, 1.0)
    assert ay[0] == pytest.approx(-math.sin(theta))


def test_wall_leader_is_chosen_among_the_summed_repulsions_only():
    # same scene: B has the most negative f_x of all repulsions, but only A is summed, so A leads the
    # x-wall. A's bumper gap is negative (alongside), so the wall brakes at the hard bound; with B as
    # leader (gap 16.5 m, v_s = 19.9 m/s) the wall would allow ≈ −0.4·Σ only.
    state = make_state([100.0, 101.0, 120.0], [5.0, 7.3, 5.0], [20.0, 20.0, 20.0], [20.0, 20.0, 20.0])
    ax_one, _ = accel(state, max_repulsions=1)
    ax_two, _ = accel(state, max_repulsions=2)
    assert ax_one[0] == -4.0
    fx_a = -math.cos(math.atan2(2.3, 1.0))
    fx_b = -((13.0 / 2 + 13.0 / 2 + 6.0**2 / 6.0 + 3.5 + 2.5 - 20.0) / (13.0 / 2))
    assert fx_b < fx_a  # B is the stronger |f_x|: with both summed, B leads
    degree = abs(fx_b) ** 0.25
    wall = degree * (19.9 - 20.0) / T
    assert ax_two[0] == pytest.approx(max(min(3.0 * (fx_a + fx_b), wall), -4.0))


def test_lateral_force_is_clipped_again_after_the_lateral_speed_rule():
    # slow vehicle with a large lateral speed: |vy'| ≤ 0.5·vx asks for −8 m/s², the bound is −1
    state = make_state([100.0], [5.1], [2.0], [20.0], vy=[3.0])
    _, ay = accel(state)
    assert ay[0] == -1.0


def test_nudge_from_behind_only_when_switched_on():
    state = make_state([100.0, 122.0], [5.0, 5.0], [20.0, 20.0], [20.0, 20.0])
    ax_off, _ = accel(state, nudging=False)
    ax_on, _ = accel(state, nudging=True)
    assert ax_off[1] == pytest.approx(0.0, abs=1e-12)
    # behind: ux = vx_j = 20 → D_x = 400/6 + 3.5, plateau covers 22 m → f_x = +1, ×0.9 ×5 → clipped at 2.0
    assert ax_on[1] == 2.0


def test_lateral_repulsion_by_hand():
    # j ahead and 1 m to the left: pushes i to the right by sin θ
    state = make_state([100.0, 110.0], [5.0, 6.0], [20.0, 20.0], [20.0, 20.0])
    _, ay = accel(state)
    theta = math.atan2(1.0, 10.0)
    assert ay[0] == pytest.approx(-math.sin(theta) * 1.0)


def test_only_the_strongest_repulsions_are_summed():
    # two leaders ahead of vehicle 0; with max_repulsions=1 only the nearer (stronger) counts
    state = make_state([100.0, 121.0, 122.5], [5.0, 5.0, 3.0], [20.0, 20.0, 20.0], [20.0, 20.0, 20.0])
    ax_all, ay_all = accel(state)
    ax_one, ay_one = accel(state, max_repulsions=1)
    assert ay_one[0] == pytest.approx(0.0, abs=1e-12)  # the aligned one is stronger, f_y = 0
    assert ay_all[0] > 0.0  # the second one (to the right) pushes left
    assert ax_all[0] < ax_one[0]


def test_road_edge_bound_limits_lateral_acceleration():
    # alone, close to the left edge, drifting left: must accelerate right at least U
    y = W - 0.9 - 0.2
    state = make_state([100.0], [y], [20.0], [20.0], vy=[0.5])
    _, ay = accel(state)
    lower = -float(edge_bound(np.array(-1.05 * 0.5), np.array(y - 0.9), T, -1.0))
    upper = float(edge_bound(np.array(1.05 * 0.5), np.array(0.2), T, -1.0))
    assert ay[0] <= upper + 1e-12
    assert ay[0] >= max(lower, -1.0) - 1e-12
    assert ay[0] < 0


def test_speed_bounds_no_reverse_and_no_overspeed():
    state = make_state([100.0, 105.0], [5.0, 5.0], [0.5, 0.0], [20.0, 20.0])
    ax, _ = accel(state)
    assert ax[0] >= -0.5 / T - 1e-12
    fast = make_state([100.0], [5.0], [30.0], [20.0])
    ax_fast, _ = accel(fast)
    assert ax_fast[0] <= (1.2 * 20 - 30) / T + 1e-12


# -- ring, dynamics, collisions ----------------------------------------------------------------

def test_wrap_maps_to_half_open_interval():
    assert wrap(np.array([499.0 - 1.0, 1.0 - 499.0, 250.0, -250.0]), L).tolist() == [-2.0, 2.0, -250.0, -250.0]


def test_forces_see_neighbours_across_the_seam():
    seam = make_state([495.0, 10.0], [5.0, 5.0], [20.0, 20.0], [20.0, 20.0])
    plain = make_state([100.0, 115.0], [5.0, 5.0], [20.0, 20.0], [20.0, 20.0])
    assert accel(seam)[0][0] == pytest.approx(accel(plain)[0][0])


def test_plan_step_is_ballistic_and_clips_at_the_edge():
    cmd = plan_step(
        np.array([0.0, 0.0]), np.array([5.0, W - 1.0]), np.array([20.0, 20.0]), np.array([0.2, 1.0]),
        np.array([1.8, 1.8]), np.array([1.0, 0.0]), np.array([0.4, 0.0]), T, W, 0.001,
    )
    assert cmd.vx_next[0] == 20.25
    assert cmd.dy[0] == pytest.approx(0.2 * T + 0.5 * 0.4 * T * T)
    assert cmd.vy_next[0] == pytest.approx(0.3)
    assert not cmd.boundary_contact[0]
    # second vehicle would cross the left edge: clipped to 1 mm inside, vy = 0, counted
    assert cmd.boundary_contact[1]
    assert (W - 1.0) + cmd.dy[1] == pytest.approx(W - 0.9 - 0.001)
    assert cmd.vy_next[1] == 0.0
    assert float(ballistic_distance(np.array(20.0), np.array(21.0), T)) == pytest.approx(20 * T + 0.5 * 4 * T * T)


def test_plan_step_clips_at_both_edges_with_a_tolerance_and_the_realised_accelerations():
    # T = 0.25 s, width 2 m, clearance 0.125 m, tolerance 0.0625 m on an 8 m road: lines at 1.125 and 6.875 m
    cmd = plan_step(
        np.zeros(5), np.array([1.25, 6.78125, 6.8125, 4.0, 4.0]), np.array([1.0, 10.0, 10.0, 10.0, 0.5]),
        np.array([-1.0, 0.5, 0.5, 0.5, 0.0]), np.full(5, 2.0), np.array([-6.0, 0.5, 0.0, -1.0, 0.0]),
        np.array([-2.0, 0.0, 0.0, 1.0, 0.0]), T, 8.0, 0.125, contact_tolerance=0.0625,
    )
    # 0: 1.25 − 0.25 − 0.0625 = 0.9375 m, past the right line: clipped there, a contact, vy' = 0, and the
    # realised ay the one giving dy = −0.125 m: 2·(−0.125 + 0.25)/T² = 4 m/s²; vx floored: ax = −1/T = −4
    assert (cmd.dy[0], cmd.vy_next[0], cmd.ay[0], bool(cmd.boundary_contact[0])) == (-0.125, 0.0, 4.0, True)
    assert (cmd.vx_next[0], cmd.ax[0]) == (0.0, -4.0)
    # 1: 0.03125 m past the left line, within the tolerance: clipped, no contact, vy and ay kept
    assert (cmd.dy[1], cmd.vy_next[1], cmd.ay[1], bool(cmd.boundary_contact[1])) == (0.09375, 0.5, 0.0, False)
    assert (cmd.vx_next[1], cmd.ax[1]) == (10.125, 0.5)
    # 2: exactly the tolerance past the line: still no contact
    assert (cmd.dy[2], bool(cmd.boundary_contact[2])) == (0.0625, False)
    # 3: inside the road: dy = vy·T + ½·ay·T², vy' = vy + ay·T
    assert (cmd.dy[3], cmd.vy_next[3], cmd.ay[3], cmd.ax[3]) == (0.15625, 0.75, 1.0, -1.0)
    assert (cmd.vx_next[4], cmd.dy[4], bool(cmd.boundary_contact.any())) == (0.5, 0.0, True)
    # per-vehicle bounds instead of the road: vehicle 0 within [2, 5], vehicle 1 within [0, 9] (1 m wide)
    cmd = plan_step(np.zeros(2), np.array([4.25, 8.0]), np.full(2, 10.0), np.array([1.0, 1.0]), np.ones(2),
                    np.zeros(2), np.zeros(2), T, 99.0, 0.125, bounds=(np.array([2.0, 0.0]), np.array([5.0, 9.0])))
    assert cmd.dy.tolist() == [0.125, 0.25] and cmd.boundary_contact.tolist() == [True, False]  # lines 4.375, 8.375
    cmd = plan_step(np.zeros(1), np.array([3.25]), np.full(1, 10.0), np.array([-1.0]), np.full(1, 2.0), np.zeros(1),
                    np.zeros(1), T, 99.0, 0.125, bounds=(2.0, 5.0))
    assert (cmd.dy[0], bool(cmd.boundary_contact[0])) == (-0.125, True)  # the low line, 2 m wide: 2 + 1 + 0.125
    assert float(ballistic_distance(np.array(8.0), np.array(10.0), T)) == 2.25  # (8 + ½·2)·T


def test_agent_accelerations_are_clipped_to_bounds_top_speed_and_the_lateral_ratio():
    bounds = AccelerationBounds(ax_min=-3.0, ax_max=2.0, ay_min=-6.5, ay_max=8.0)
    ax, ay = clip_accelerations([-5.0, 3.0, 3.0, 1.0], [9.0, -9.0, 1.0, 0.0], bounds,
                                [10.0, 10.0, 19.75, 20.0], 20.0, T)
    # ax within [−3, 2] and no faster than 20 m/s after the step: (20 − 19.75)/T = 1, (20 − 20)/T = 0
    assert ax.tolist() == [-3.0, 2.0, 1.0, 0.0] and ay.tolist() == [8.0, -6.5, 1.0, 0.0]
    # |vy'| ≤ 0.1·vx = 1 m/s: with vy = 0.5, ay ∈ [−(1 + 0.5)/T, (1 − 0.5)/T] = [−6, 2]; with vy = −0.5, [−2, 6]
    _, ay = clip_accelerations(np.zeros(4), [5.0, -7.0, 7.0, -5.0], bounds, 10.0, 30.0, T,
                               vy=np.array([0.5, 0.5, -0.5, -0.5]), lateral_ratio=0.1)
    assert ay.tolist() == [2.0, -6.0, 6.0, -2.0]
    # the ratio never widens the bounds: at 100 m/s it allows ±40 m/s², the bounds keep [−6.5, 8]
    _, ay = clip_accelerations(np.zeros(2), [9.0, -9.0], bounds, 100.0, 200.0, T, vy=0.0, lateral_ratio=0.1)
    assert ay.tolist() == [8.0, -6.5]
    assert clip_acceleration(-5.0, 9.0, bounds, 10.0, 20.0, T) == (-3.0, 8.0)
    # one agent: the same clips, vy = 0 unless given
    assert clip_acceleration(0.0, 5.0, bounds, 10.0, 30.0, T, lateral_ratio=0.1) == (0.0, 4.0)
    assert clip_acceleration(0.0, -7.0, bounds, 10.0, 30.0, T, vy=-0.5, lateral_ratio=0.1) == (0.0, -2.0)
    _, ay = clip_accelerations(0.0, 5.0, bounds, 10.0, 30.0, T, lateral_ratio=0.1)
    assert float(ay) == 4.0
    # a lateral speed beyond the ratio asks for more than the bound: the bound again (−6.5, not −8)
    _, ay = clip_accelerations([0.0, 0.0], [0.0, 0.0], bounds, 0.0, 30.0, T, vy=np.array([2.0, -3.0]),
                               lateral_ratio=0.1)
    assert ay.tolist() == [-6.5, 8.0]  # the ratio asks for −8 and +12 m/s²
    assert all(type(v) is float for v in clip_acceleration(0.0, 0.0, bounds, 10.0, 20.0, T))


def test_the_dynamics_and_the_strongest_forces_compute_as_torch_on_tensors():
    """The batched environment on a device passes tensors — to the agents' clip some of its arrays as tensors and
    others as numbers: the namespace is the tensor's, whichever argument it is, and the numbers numpy's."""
    torch = pytest.importorskip("torch")
    bounds = AccelerationBounds(ax_min=-3.0, ax_max=2.0, ay_min=-6.5, ay_max=8.0)
    for ax, ay, vx in ((torch.tensor([5.0]), 9.0, 19.75), (5.0, torch.tensor([9.0]), 19.75),
                       (5.0, 9.0, torch.tensor([19.75]))):
        got = clip_accelerations(ax, ay, bounds, vx, 20.0, T)
        assert all(isinstance(v, torch.Tensor) for v in got)
        assert [v.flatten().tolist() for v in got] == [[1.0], [8.0]]
    arrays = [np.array([0.0, 1.0]), np.array([5.0, 9.5]), np.array([2.0, 0.5]), np.array([1.0, 1.0]),
              np.full(2, 1.8), np.array([-10.0, 1.0]), np.array([0.5, 2.0])]
    want = plan_step(*arrays, T, W, 0.001)
    got = plan_step(*(torch.from_numpy(a) for a in arrays), T, W, 0.001)
    for f in dataclasses.fields(want):
        assert isinstance(getattr(got, f.name), torch.Tensor), f.name
        np.testing.assert_array_equal(getattr(got, f.name).numpy(), getattr(want, f.name), err_msg=f.name)
    assert want.boundary_contact.tolist() == [False, True] and want.vx_next.tolist() == [0.0, 0.75]
    # the strongest forces: fewer rows than k (every non-zero one), and rows with more non-zero ones than k
    rng = np.random.default_rng(2)
    for mag, k in ((np.array([[[0.0, 0.5, 0.2], [0.3, 0.0, 0.0], [0.1, 0.4, 0.0]]] * 2), 6),
                   (rng.permutation(np.linspace(0.0, 1.0, 2 * 8 * 8)).reshape(2, 8, 8), 3)):
        chosen = strongest_mask(torch.from_numpy(mag), k)
        assert isinstance(chosen, torch.Tensor)
        np.testing.assert_array_equal(chosen.numpy(), strongest_mask(mag, k))
    assert strongest_mask(mag, 3).sum(axis=-1).tolist() == [[3] * 8, [3] * 8]
    # the road-edge bound and the force ramps: the tensor's namespace whichever argument is one
    for v, d in ((torch.tensor([4.0]), 0.5), (4.0, torch.tensor([0.5]))):
        bound = edge_bound(v, d, T, -1.0)
        assert isinstance(bound, torch.Tensor) and bound.tolist() == edge_bound(np.array([4.0]), 0.5, T, -1.0).tolist()
    for t, w, l in ((torch.tensor([2.5]), 1.0, 2.0), (2.5, torch.tensor([1.0]), 2.0), (2.5, 1.0, torch.tensor([2.0]))):
        h = symmetric_trapezoid(t, w, l)
        assert isinstance(h, torch.Tensor) and h.tolist() == [0.5]
    # the driver model over a padded batch of runs, and over runs without padding (the diagonal cleared alone)
    from lanefree_sumo.sim.xp_torch import numpy_transcendentals

    cfg = merge_config(DriverConfig(), {"neighbour_range_m": 40.0})  # k = 6: no forces tie for the last place
    n = 9
    columns = [rng.uniform(0.0, 120.0, (2, n)), rng.uniform(1.2, 8.8, (2, n)), rng.uniform(0.0, 25.0, (2, n)),
               rng.uniform(-1.0, 1.0, (2, n)), np.full((2, n), 4.0), np.full((2, n), 1.8), np.full((2, n), 22.0)]
    present = np.ones((2, n), dtype=bool)
    present[1, 7:] = False
    ring = np.array([[120.0], [100.0]])
    for mask in (present, None):
        want = driver_accelerations(VehicleState([], *columns, present), cfg, ring, W, T, 0.05, present=mask)
        twin = VehicleState([], *(torch.from_numpy(c) for c in columns), torch.from_numpy(present))
        with numpy_transcendentals():
            got = driver_accelerations(twin, cfg, torch.from_numpy(ring), W, T, 0.05,
                                       present=None if mask is None else torch.from_numpy(mask))
        rows = present if mask is not None else slice(None)  # padded rows' values are no one's
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g.numpy()[rows], w[rows])


def test_a_padded_batch_of_runs_is_driven_as_each_run_alone_bit_for_bit():
    """Runs of 17, 19 and 23 vehicles padded to 40 rows, with nudging on: every sum over neighbours (repulsions,
    nudges, the diagnostics) rounds as the run's own, and the x-wall's leader is each row's. (The padding regroups
    numpy's pairwise sums: in this scene both nudge sums over the padded rows would differ in a last bit.)"""
    cfg = merge_config(DriverConfig(), {"nudging": True, "neighbour_range_m": 60.0})
    rng = np.random.default_rng(17)
    sizes, rows, rings = [17, 19, 23], 40, [80.0, 90.0, 100.0]
    runs = [VehicleState([f"v{i}" for i in range(n)], rng.uniform(0.0, ring, n), rng.uniform(1.2, W - 1.2, n),
                         rng.uniform(5.0, 25.0, n), rng.uniform(-1.0, 1.0, n), rng.uniform(3.0, 5.0, n),
                         rng.uniform(1.5, 2.2, n), rng.uniform(15.0, 28.0, n), np.ones(n, bool))
            for n, ring in zip(sizes, rings)]
    present = np.arange(rows)[None, :] < np.array(sizes)[:, None]
    columns = []
    for name in ("x", "y", "vx", "vy", "length", "width", "v_desired"):
        column = np.zeros((3, rows)) if name != "y" else np.full((3, rows), W / 2)
        for k, run in enumerate(runs):
            column[k, :run.n] = getattr(run, name)
        columns.append(column)
    details: dict[str, np.ndarray] = {}
    ax, ay = driver_accelerations(VehicleState([], *columns, present), cfg, np.array(rings)[:, None], W, T, 0.05,
                                  details=details, present=present)
    for k, (run, ring) in enumerate(zip(runs, rings)):
        alone: dict[str, np.ndarray] = {}
        ax_k, ay_k = driver_accelerations(run, cfg, ring, W, T, 0.05, details=alone)
        np.testing.assert_array_equal(ax[k, :run.n], ax_k)
        np.testing.assert_array_equal(ay[k, :run.n], ay_k)
        for name, value in alone.items():
            np.testing.assert_array_equal(details[name][k, :run.n], value, err_msg=name)
    assert details["wall_binds"].any() and np.isfinite(details["leader_gap_m"]).any()


def test_the_driver_keeps_to_each_vehicles_own_bounds():
    """A vehicle between bounds 2 and 5 m (an open road's part) drives as one at y − 2 on a road 3 m wide."""
    cfg = DriverConfig()
    inside = make_state([100.0], [3.0], [20.0], [20.0], vy=[-1.0], width=1.5)  # 0.25 m from its right bound
    shifted = make_state([100.0], [1.0], [20.0], [20.0], vy=[-1.0], width=1.5)
    ay = driver_accelerations(inside, cfg, L, W, T, bounds=(np.array([2.0]), np.array([5.0])))[1]
    assert ay.tolist() == driver_accelerations(shifted, cfg, L, 3.0, T)[1].tolist()
    assert ay[0] > driver_accelerations(inside, cfg, L, W, T)[1][0]  # the bound pushes it back to the left


def test_a_vehicle_without_a_leader_has_no_wall_and_no_leader_gap():
    # alone and faster than desired: the target-speed force brakes it, no x-wall (whatever the wall would be)
    details: dict[str, np.ndarray] = {}
    driver_accelerations(make_state([100.0, 300.0], [5.0, 5.0], [21.0, 21.0], [20.0, 20.0]), DriverConfig(), L, W,
                         T, details=details)
    assert details["wall_binds"].tolist() == [False, False] and np.isnan(details["leader_gap_m"]).all()


def test_the_strongest_forces_are_chosen_row_by_row_in_a_batch_of_runs():
    mag = np.zeros((2, 8, 8))
    mag[0, 0, 1:6] = [0.5, 0.4, 0.3, 0.2, 0.1]  # a row with more than k = 3 forces, no column with more than 1
    mag[1, 3, [0, 2, 7]] = [0.2, 0.9, 0.4]  # exactly k
    mag[1, 5, [1, 4]] = [0.3, 0.6]
    expected = np.zeros(mag.shape, dtype=bool)
    expected[0, 0, [1, 2, 3]] = expected[1, 3, [0, 2, 7]] = expected[1, 5, [1, 4]] = True
    np.testing.assert_array_equal(strongest_mask(mag, 3), expected)
    for k in range(2):
        np.testing.assert_array_equal(strongest_mask(mag[k], 3), expected[k])


def test_the_road_edge_bound_keeps_no_clearance_unless_one_is_given():
    state = make_state([100.0], [W - 0.9 - 0.3], [20.0], [20.0], vy=[0.4])  # 0.3 m from the left edge, drifting left
    cfg = DriverConfig()
    ay = driver_accelerations(state, cfg, L, W, T)[1]
    assert ay.tolist() == driver_accelerations(state, cfg, L, W, T, edge_clearance=0.0)[1].tolist()
    assert ay[0] > driver_accelerations(state, cfg, L, W, T, edge_clearance=0.2)[1][0]


def test_negative_speed_is_floored():
    cmd = plan_step(np.zeros(1), np.full(1, 5.0), np.full(1, 0.5), np.zeros(1), np.full(1, 1.8),
                    np.full(1, -4.5), np.zeros(1), T, W, 0.001)
    assert cmd.vx_next[0] == 0.0 and cmd.ax[0] == pytest.approx(-2.0)


def test_overlap_uses_rectangles_and_the_seam():
    state = make_state([499.0, 1.0, 250.0, 251.0], [5.0, 5.5, 2.0, 3.9], [0, 0, 0, 0], [20] * 4)
    ov = overlap_matrix(state, L)
    assert ov[0, 1] and ov[1, 0]  # 2 m apart across the seam, 0.5 m lateral
    assert not ov[2, 3]  # 1.9 m lateral ≥ 1.8 m: touching is not overlapping
    assert ov.sum() == 2


def test_collision_event_counted_once_per_contact():
    tracker = CollisionTracker(3)
    contact = np.zeros((3, 3), bool)
    contact[0, 1] = contact[1, 0] = True
    none = np.zeros((3, 3), bool)
    events = [len(tracker.update(m)) for m in (none, contact, contact, contact, none, contact)]
    assert events == [0, 1, 0, 0, 0, 1]
    assert tracker.update(contact).tolist() == []


# -- spawning and the numpy simulation ---------------------------------------------------------

@pytest.mark.parametrize("density", [70, 90, 120])
def test_spawn_never_overlaps_and_stays_on_road(density):
    cfg = merge_config(LaneFreeConfig(), {"scenario": {"density_veh_per_km": density}})
    for seed in range(5):
        state = spawn(cfg, np.random.default_rng(seed))
        assert state.n == round(density * L / 1000)
        assert not overlap_matrix(state, L).any()
        assert (state.y - state.width / 2 > 0).all() and (state.y + state.width / 2 < W).all()
        assert ((state.v_desired >= 18) & (state.v_desired <= 22)).all()


def test_spawn_rejects_density_that_does_not_fit_and_names_the_maximum():
    cfg = merge_config(LaneFreeConfig(), {"scenario": {"density_veh_per_km": 2000}})
    top = max_density(cfg)
    for check in (lambda c: spawn(c, np.random.default_rng(0)), check_fits):  # the check without a draw too
        with pytest.raises(ConfigError, match=f"maximum is {top:.0f} veh/km"):
            check(cfg)
    full = merge_config(cfg, {"scenario": {"density_veh_per_km": top}})
    check_fits(full)
    assert not overlap_matrix(spawn(full, np.random.default_rng(0)), L).any()


def test_numpy_simulation_is_deterministic_per_seed():
    cfg = merge_config(LaneFreeConfig(), {"backend": "numpy", "scenario": {"density_veh_per_km": 90}})
    runs = []
    for _ in range(2):
        sim = Simulation(cfg)
        sim.reset(seed=7)
        for _ in range(200):
            sim.step()
        runs.append(np.concatenate([sim.state.x, sim.state.y, sim.state.vx, sim.state.vy]))
    assert np.array_equal(runs[0], runs[1])
    other = Simulation(cfg)
    other.reset(seed=8)
    assert not np.array_equal(other.state.x, Simulation(cfg).reset(seed=7).x)


def test_config_rejects_unknown_keys_with_the_valid_ones():
    with pytest.raises(ConfigError, match="valid keys here: .*density_veh_per_km"):
        merge_config(LaneFreeConfig(), {"scenario": {"densty": 3}})


def test_fast_symmetric_trapezoid_equals_the_general_h():
    rng = np.random.default_rng(0)
    t = rng.uniform(-30, 30, 500)
    w = rng.uniform(0.0, 8.0, 500)
    w[:50] = 0.0  # zero-width ramps: steps
    l = rng.uniform(0.0, 15.0, 500)
    assert symmetric_trapezoid(np.abs(t), w, l) == pytest.approx(trapezoid_h(t, w, l, w), abs=1e-12)
    # a step (w = 0, a standing vehicle's longitudinal ramp) at exactly its edge |t| = l is 1, as H's
    steps = symmetric_trapezoid(np.array([2.0, 2.0, 2.5]), np.zeros(3), np.array([2.5, 2.0, 2.0]))
    assert steps.tolist() == [1.0, 1.0, 0.0] == trapezoid_h(np.array([2.0, 2.0, 2.5]), 0.0, np.array([2.5, 2.0, 2.0]),
                                                            0.0).tolist()


def test_force_details_report_the_wall_leader_and_its_gap():
    # the scene of the wall-leader test: with one summed repulsion, A (alongside, gap 1 − 3.5 m) leads
    state = make_state([100.0, 101.0, 120.0], [5.0, 7.3, 5.0], [20.0, 20.0, 20.0], [20.0, 20.0, 20.0])
    details: dict[str, np.ndarray] = {}
    cfg = merge_config(DriverConfig(), {"max_repulsions": 1})
    driver_accelerations(state, cfg, L, W, T, details=details)
    assert details["leader_gap_m"][0] == pytest.approx(1.0 - 3.5)
    assert details["wall_binds"][0]
    assert details["sum_fx"][0] == pytest.approx(-math.cos(math.atan2(2.3, 1.0)))
    assert np.isnan(details["leader_gap_m"][2])  # the front vehicle has nobody ahead within 100 m


# -- exact boundaries: touching boxes, edge ends ---------------------------------------------------

def test_boxes_that_touch_do_not_overlap_on_either_axis_or_across_the_seam():
    # lengths 4 and 2 m, widths 2 and 1 m: half sums 3 m and 1.5 m, exact in binary
    def pair(x, y):
        state = make_state(x, y, [0, 0], [20, 20])
        state.length[:] = [4.0, 2.0]
        state.width[:] = [2.0, 1.0]
        return overlap_matrix(state, L)

    assert not pair([100.0, 103.0], [5.0, 5.0]).any()  # nose to tail, 3 m apart
    assert not pair([103.0, 100.0], [5.0, 5.0]).any()  # the other order
    assert not pair([100.0, 100.0], [5.0, 6.5]).any()  # side by side, 1.5 m apart
    assert not pair([100.0, 100.0], [6.5, 5.0]).any()
    assert not pair([499.0, 2.0], [5.0, 5.0]).any()  # across the seam: wrap(2 − 499) = 3 m
    inside = pair([100.0, 102.96875], [5.0, 6.46875])  # 1/32 m inside on both axes
    assert inside.tolist() == [[False, True], [True, False]]
    assert pair([499.0, 1.96875], [5.0, 5.0])[0, 1]
    assert not pair([100.0, 102.96875], [5.0, 6.5]).any()  # inside on one axis only


def test_several_collision_events_start_in_one_step_and_each_pair_is_counted_once():
    tracker = CollisionTracker(4)
    m = np.zeros((4, 4), bool)
    m[0, 1] = m[1, 0] = m[2, 3] = m[3, 2] = m[0, 3] = m[3, 0] = True
    assert tracker.update(m).tolist() == [[0, 1], [0, 3], [2, 3]]  # three pairs start together, i < j
    m2 = m.copy()
    m2[1, 2] = m2[2, 1] = True  # one more pair while the others go on
    assert tracker.update(m2).tolist() == [[1, 2]]
    # vehicle 1 leaves the road: rows 0, 2, 3 keep their pairs; a new vehicle overlaps nobody yet
    tracker.keep(np.array([True, False, True, True]))
    tracker.add(1)
    now = np.zeros((4, 4), bool)
    now[1, 2] = now[2, 1] = True  # old vehicles 2 and 3: the same contact, no new event
    now[0, 3] = now[3, 0] = True  # old vehicle 0 and the newcomer: a new event
    assert tracker.update(now).tolist() == [[0, 3]]


def test_one_steps_collision_events_are_split_by_who_took_part():
    # rows 1 and 4 are agents; vehicle 1's view of six events starting in one step
    pairs = np.array([[0, 1], [1, 4], [1, 2], [0, 2], [3, 4], [2, 3]])
    agents = np.array([1, 4])
    # vehicle 1's: (0,1), (1,4), (1,2); with another agent: (1,4); background only: (0,2), (2,3)
    assert count_events(pairs, 1, agents) == (3, 1, 2)
    # agent 4's: (1,4), (3,4); with an agent: (1,4) — the pair (3,4) has one agent, so it is no background event
    assert count_events(pairs, 4, agents) == (2, 1, 2)
    assert count_events(pairs, 1, np.array([1])) == (3, 0, 3)  # alone: (0,2), (2,3), (3,4) are background
    assert count_events(np.zeros((0, 2), dtype=np.int64), 1, agents) == (0, 0, 0)
    assert count_events(np.array([[2, 3]]), 1, agents) == (0, 0, 1)


def test_a_vehicle_exactly_at_the_end_of_an_edge_is_at_the_start_of_the_next():
    # 500 m ring, 4 edges of 125 m
    assert EDGES == 4
    edge, pos = ring_to_edge(np.array([0.0, 124.5, 125.0, 250.0, 374.5, 375.0, 499.5]), 500.0)
    assert edge.tolist() == [0, 0, 1, 2, 2, 3, 3]
    assert pos.tolist() == [0.0, 124.5, 0.0, 0.0, 124.5, 0.0, 124.5]
    # x = L (outside [0, L), a rounding of x ≈ L) stays on the last edge, at its very end
    edge, pos = ring_to_edge(np.array([500.0]), 500.0)
    assert (edge.tolist(), pos.tolist()) == ([3], [125.0])
    # the inverse, at every edge start and end
    assert edge_to_ring(np.array([0, 1, 3, 3]), np.array([0.0, 0.0, 0.0, 125.0]), 500.0).tolist() == \
        [0.0, 125.0, 375.0, 500.0]
    assert float(edge_to_ring(2, 1.5, 300.0)) == 151.5  # 2 × 75 + 1.5


# -- the driver model against a plain per-vehicle reading of specification §3 -----------------------------

def _trapezoid(abs_t: float, rise: float, plateau: float) -> float:
    """H from |t| with equal rise and fall: 1 on [0, plateau], linear to 0 over ``rise``; a step when rise = 0."""
    if rise == 0.0:
        return 1.0 if abs_t <= plateau else 0.0
    return min(max((rise + plateau - abs_t) / rise, 0.0), 1.0)


class _TieError(Exception):
    """Two forces of equal magnitude compete for the last place among the summed ones."""


def _reference_accelerations(state: VehicleState, cfg: DriverConfig, ring: float, road: float, t: float,
                             clearance: float, lateral_target: float) -> tuple[list[float], list[float]]:
    """Specification §3 one vehicle and one neighbour at a time, in plain floats (the module's independent twin)."""
    n = len(state.x)
    k = cfg.effective_gain_x
    ax_all, ay_all = [], []
    for i in range(n):
        xi, yi, vxi, vyi = (float(a[i]) for a in (state.x, state.y, state.vx, state.vy))
        li, wi, vdi = float(state.length[i]), float(state.width[i]), float(state.v_desired[i])
        reps, nudges = [], []
        for j in range(n):
            if j == i:
                continue
            dx = float(wrap(np.array([state.x[j] - xi]), ring)[0])
            dy = float(state.y[j]) - yi
            ahead = dx >= 0.0
            uy = abs(vyi - float(state.vy[j]))
            mag_y = _trapezoid(abs(dy), uy * cfg.time_headway_y_s + cfg.lateral_ramp_offset_m,
                               0.5 * (wi + float(state.width[j])) + cfg.lateral_margin_m)
            vxj = float(state.vx[j])
            ux = max(0.0, vxi - (1.0 - cfg.speed_share_ahead) * vxj) if ahead else vxj
            lxh = 0.5 * cfg.time_headway_x_s * vxi
            plateau = lxh + ux * ux / (2.0 * k) + 0.5 * (li + float(state.length[j])) + cfg.longitudinal_margin_m
            mag = _trapezoid(abs(dx), lxh, plateau) * mag_y
            if abs(dx) > cfg.neighbour_range_m or mag <= 0.0:
                continue
            dist = math.hypot(dx, dy)
            entry = (mag, -dx / dist * mag, -dy / dist * mag, j)
            (reps if ahead else nudges).append(entry)
        for group, most in ((reps, cfg.max_repulsions), (nudges, cfg.max_nudges)):
            group.sort(reverse=True)
            if len(group) > most and group[most - 1][0] == group[most][0]:
                raise _TieError  # which of two equally strong forces is summed is not specified
        reps = reps[:cfg.max_repulsions]
        sum_fx, sum_fy = sum(e[1] for e in reps), sum(e[2] for e in reps)
        if cfg.nudging:
            nudges = nudges[:cfg.max_nudges]
            sum_fx += cfg.nudge_scale_x * sum(e[1] for e in nudges)
            sum_fy += cfg.nudge_scale_y * sum(e[2] for e in nudges)
        ax = k * sum_fx + math.erfc(vxi - vdi) - 1.0
        ay = cfg.coef_fy * sum_fy + math.erfc(vyi - lateral_target) - 1.0
        lead = min(reps, key=lambda e: e[1], default=None)
        if lead is not None and lead[1] < 0.0:  # 1. the x-wall
            j = lead[3]
            degree = abs(min(max(lead[1], -1.0), 1.0)) ** cfg.wall_exponent
            gap = float(wrap(np.array([(state.x[j] - 0.5 * state.length[j]) - (xi + 0.5 * li)]), ring)[0])
            v_safe = min(gap / cfg.wall_time_gap_s, float(state.vx[j]) - cfg.wall_speed_margin_mps)
            ax = min(ax, ((1.0 - degree) * (vdi - vxi) + degree * (v_safe - vxi)) / t)
        room_left = max(0.0, road - clearance - yi - 0.5 * wi)  # 2. the road edges
        room_right = max(0.0, yi - clearance - 0.5 * wi)
        u, f = cfg.edge_decel_mps2, cfg.edge_speed_factor
        ay = min(ay, float(edge_bound(np.array(f * vyi), np.array(room_left), t, u)))
        ay = max(ay, -float(edge_bound(np.array(-f * vyi), np.array(room_right), t, u)))
        b = cfg.bounds  # 3.–5.
        ax = min(max(ax, b.ax_min), b.ax_max)
        ay = min(max(ay, b.ay_min), b.ay_max)
        ax = min(max(ax, -vxi / t), (cfg.overspeed_factor * vdi - vxi) / t)
        r = cfg.lateral_speed_ratio
        ay = max(min(ay, (r * vxi - vyi) / t), -(r * vxi + vyi) / t)
        ay_all.append(min(max(ay, b.ay_min), b.ay_max))
        ax_all.append(ax)
    return ax_all, ay_all


@pytest.mark.parametrize("nudging", [False, True])
def test_driver_accelerations_equal_a_per_vehicle_reading_of_the_specification(nudging):
    # every parameter off its default, so that a dropped factor or a swapped one shows
    cfg = merge_config(DriverConfig(), {
        "neighbour_range_m": 30.0, "speed_share_ahead": 0.4, "time_headway_x_s": 0.8, "time_headway_y_s": 0.35,
        "gain_x": 2.5, "gain_x_nudging": 4.0, "longitudinal_margin_m": 1.5, "lateral_ramp_offset_m": 0.7,
        "lateral_margin_m": 0.3, "coef_fy": 1.3, "max_repulsions": 2, "nudging": nudging, "max_nudges": 2,
        "nudge_scale_x": 0.7, "nudge_scale_y": 1.2, "wall_exponent": 0.5, "wall_time_gap_s": 0.4,
        "wall_speed_margin_mps": 0.3, "edge_decel_mps2": -1.5, "edge_speed_factor": 1.1, "overspeed_factor": 1.3,
        "lateral_speed_ratio": 0.4, "bounds": {"ax_min": -6.0, "ax_max": 5.0, "ay_min": -2.5, "ay_max": 3.0},
    })
    ring, road, clearance, target = 150.0, 10.0, 0.05, 0.15
    rng = np.random.default_rng(7 + nudging)
    checked = 0
    while checked < 8:
        n = 9
        state = VehicleState(
            [f"v{i}" for i in range(n)], rng.uniform(0.0, ring, n), rng.uniform(1.2, road - 1.2, n),
            rng.uniform(0.0, 25.0, n), rng.uniform(-1.5, 1.5, n), rng.uniform(3.0, 5.0, n),
            rng.uniform(1.5, 2.2, n), rng.uniform(15.0, 28.0, n), np.ones(n, bool))
        ax, ay = driver_accelerations(state, cfg, ring, road, T, edge_clearance=clearance, lateral_target=target)
        try:
            ax_ref, ay_ref = _reference_accelerations(state, cfg, ring, road, T, clearance, target)
        except _TieError:
            continue
        checked += 1
        assert ax.tolist() == pytest.approx(ax_ref, rel=1e-12, abs=1e-12)
        assert ay.tolist() == pytest.approx(ay_ref, rel=1e-12, abs=1e-12)
