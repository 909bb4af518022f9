"""The physics without SUMO: forces on hand-built cases, ramps, edge bounds, ring wrap,
dynamics, collisions counted once per contact, spawning."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import erfc

from lanefree_sumo.collisions import CollisionTracker, overlap_matrix
from lanefree_sumo.config import ConfigError, DriverConfig, LaneFreeConfig, merge_config
from lanefree_sumo.dynamics import ballistic_distance, plan_step
from lanefree_sumo.forces import driver_accelerations, edge_bound, ramp_g, trapezoid_h
from lanefree_sumo.simulation import Simulation
from lanefree_sumo.spawn import max_density, spawn
from lanefree_sumo.state import VehicleState, wrap

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
    expected = 5.0 * fx + (erfc(0.0) - 1.0)
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
    state = make_state([100.0, 110.0], [5.0, 5.0], [20.0, 20.0], [20.0, 20.0])
    ax, _ = accel(state)
    assert ax[0] == -4.5


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
    lower = -float(edge_bound(np.array(-1.05 * 0.5), np.array(y - 0.9), T, -1.8))
    upper = float(edge_bound(np.array(1.05 * 0.5), np.array(0.2), T, -1.8))
    assert ay[0] <= upper + 1e-12
    assert ay[0] >= max(lower, -1.8) - 1e-12
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
    with pytest.raises(ConfigError, match=f"maximum is {top:.0f} veh/km"):
        spawn(cfg, np.random.default_rng(0))
    full = merge_config(cfg, {"scenario": {"density_veh_per_km": top}})
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
    from lanefree_sumo.forces import symmetric_trapezoid

    rng = np.random.default_rng(0)
    t = rng.uniform(-30, 30, 500)
    w = rng.uniform(0.0, 8.0, 500)
    w[:50] = 0.0  # zero-width ramps: steps
    l = rng.uniform(0.0, 15.0, 500)
    assert symmetric_trapezoid(np.abs(t), w, l) == pytest.approx(trapezoid_h(t, w, l, w), abs=1e-12)
