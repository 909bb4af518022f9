"""The batched core: run k of a world of K rings is, bit for bit, the single ring simulation with the same seed."""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np
import pytest

from lanefree_sumo.config import ConfigError, LaneFreeConfig, merge_config
from lanefree_sumo.sim.dynamics import plan_step
from lanefree_sumo.sim.forces import driver_accelerations
from lanefree_sumo.sim.simulation import Simulation
from lanefree_sumo.sim.spawn import spawn
from lanefree_sumo.sim.state import VehicleState, pairwise_offsets, row_sum
from lanefree_sumo.sim.world import World, WorldParams, replace_runs, reset_world, step_world, world_of

RUNS = [(11, 70.0), (12, 120.0), (13, 90.0)]  # (seed, density): three vehicle counts, so rows are padded


def ring(seed: int, density: float, **extra) -> LaneFreeConfig:
    return merge_config(LaneFreeConfig(), {"seed": seed, "backend": "numpy", **extra,
                                           "scenario": {"density_veh_per_km": density, "with_agent": True}})


def test_row_sum_is_numpys_sum_of_each_rows_own_length():
    rng = np.random.default_rng(0)
    for n in [1, 5, 7, 8, 9, 16, 23, 46, 61, 127, 128, 129, 200, 300]:
        values = rng.normal(size=n) * 10.0 ** rng.integers(-6, 6, size=n)
        values[rng.random(n) < 0.7] = 0.0  # sparse, as the summed repulsions are
        padded = np.zeros((2, n + 37))
        padded[0, :n] = values
        padded[1] = rng.normal(size=n + 37)
        got = row_sum(padded, np.array([n, n + 37]))
        assert got[0] == values.sum() and got[1] == padded[1].sum(), n
        assert (row_sum(padded[:1, :n], np.array([n])) == values.sum()).all()


def test_row_sum_of_short_padded_rows_is_numpys_sum_of_their_entries_bit_for_bit():
    rng = np.random.default_rng(1)
    for width in range(1, 8):
        for count in range(width + 1):
            for entries in (rng.normal(size=count) * 10.0 ** rng.integers(-6, 6, size=count), np.full(count, -0.0)):
                padded = np.zeros((1, width))
                padded[0, :count] = entries
                got = row_sum(padded, np.array([count]))
                assert got.tobytes() == np.array([entries.sum()]).tobytes(), (width, count, entries)


def test_each_run_of_a_batch_is_the_single_simulation_bit_for_bit():
    cfgs = [ring(seed, density) for seed, density in RUNS]
    world = reset_world(cfgs, [seed for seed, _ in RUNS])
    params = WorldParams.of(cfgs)
    sims = [Simulation(cfg) for cfg in cfgs]
    states = [sim.reset(cfg.seed) for sim, cfg in zip(sims, cfgs)]
    counts = [s.n for s in states]
    assert len(set(counts)) == 3 and world.x.shape == (3, max(counts))
    rng = np.random.default_rng(5)
    collisions = 0
    for _ in range(300):
        accel = np.column_stack([rng.uniform(-4.5, 2.0, 3), rng.uniform(-1.8, 1.8, 3)])
        world, out = step_world(world, params, accel)
        for k, (sim, n) in enumerate(zip(sims, counts)):
            result = sim.step(accel[k])
            state, (dx, dy) = sim.current()
            for name in ("x", "y", "vx", "vy"):
                np.testing.assert_array_equal(getattr(world, name)[k, :n], getattr(state, name), err_msg=name)
            np.testing.assert_array_equal(out.ax[k, :n], result.ax)
            np.testing.assert_array_equal(out.ay[k, :n], result.ay)
            np.testing.assert_array_equal(out.boundary_contact[k, :n], result.boundary_contact)
            np.testing.assert_array_equal(out.overlap[k, :n, :n], result.overlap)
            np.testing.assert_array_equal(np.argwhere(out.new_collisions[k]), result.new_collisions)
            np.testing.assert_array_equal(world.dx[k, :n, :n], dx)
            np.testing.assert_array_equal(world.dy[k, :n, :n], dy)
            collisions += len(result.new_collisions)
            # padding stays where it is, overlaps nobody and touches no edge
            assert (world.vx[k, n:] == 0.0).all() and not out.overlap[k, n:].any() and not out.overlap[k, :, n:].any()
            assert not out.boundary_contact[k, n:].any()
    assert collisions > 0  # the random agents collide: new collisions were compared too
    assert (world.steps == 300).all()


def test_a_run_reset_alone_starts_as_a_fresh_simulation_and_the_others_go_on():
    cfgs = [ring(seed, density) for seed, density in RUNS]
    params = WorldParams.of(cfgs)
    world = reset_world(cfgs, [seed for seed, _ in RUNS])
    accel = np.zeros((3, 2))
    for _ in range(5):
        world, _ = step_world(world, params, accel)
    before = world
    world = replace_runs(world, [1], [spawn(cfgs[1], np.random.default_rng(99))])
    fresh = reset_world([cfgs[1]], [99])
    n = int(fresh.counts[0])
    assert world.steps.tolist() == [5, 0, 5]
    np.testing.assert_array_equal(world.x[1, :n], fresh.x[0])
    np.testing.assert_array_equal(world.x[[0, 2]], before.x[[0, 2]])
    np.testing.assert_array_equal(world.overlap[1, :n, :n], fresh.overlap[0])


def test_runs_that_must_share_a_parameter_are_refused():
    with pytest.raises(ConfigError, match="these differ: step_s, min_lateral_move_m$"):
        WorldParams.of([ring(0, 70.0), ring(1, 70.0, sim={"step_s": 0.2})])
    with pytest.raises(ConfigError, match="acceleration bounds; these differ: agent_bounds$"):
        WorldParams.of([ring(0, 70.0), ring(1, 70.0),
                        merge_config(ring(2, 70.0), {"scenario": {"agent_bounds": {"ax_max": 3.0}}})])
    with pytest.raises(ConfigError, match="^a batch needs at least one run$"):
        WorldParams.of([])
    with pytest.raises(ConfigError, match="ring"):
        WorldParams.of([ring(0, 70.0, road={"kind": "onramp"})])


def _state(x, y, vx, vy, v_desired, controlled) -> VehicleState:
    n = len(x)
    return VehicleState([f"v{i}" for i in range(n)], np.array(x, float), np.array(y, float), np.array(vx, float),
                        np.array(vy, float), np.full(n, 4.0), np.full(n, 1.8), np.array(v_desired, float),
                        np.array(controlled, dtype=bool))


ROADS = ([500.0, 400.0], [10.2, 8.0])
"""The hand-built batch's rings: 500 m × 10.2 m and 400 m × 8 m (edges of 125 and 100 m)."""


def _hand_built_batch():
    """Two rings (:data:`ROADS`), three agents each (rows 0, 2, 4 and 0, 2, 3), run 1 padded by one row; every
    parameter the step passes on off its default."""
    settings = {"backend": "numpy",
                "sim": {"step_s": 0.5, "edge_clearance_m": 0.05, "edge_contact_tolerance_m": 0.01,
                        "sumo_min_lateral_speed_mps": 0.25},  # lateral moves under 0.125 m are set
                "scenario": {"with_agent": True, "agents": 3, "agent_max_speed_mps": 20.0,
                             "agent_lateral_speed_ratio": 0.1}}
    cfgs = [merge_config(LaneFreeConfig(), settings),
            merge_config(LaneFreeConfig(), {**settings, "road": {"length_m": 400.0, "width_m": 8.0}})]
    states = [
        # agent at the top speed's reach crossing edge 0 → 1; background; agent ending exactly at the ring's end,
        # drifting onto the clip line by less than the tolerance; background near the left edge moving left;
        # agent moving sideways by exactly 0.125 m
        _state([124.0, 250.0, 495.0, 60.0, 300.0], [5.1, 5.1, 0.95, 8.6, 0.98], [19.5, 25.0, 10.0, 20.0, 10.0],
               [1.5, 0.0, -0.01, 0.8, 0.25], [20.0, 25.0, 10.0, 22.0, 10.0], [False, True, False, True, False]),
        # agent crossing the seam, at a quarter of the road, into the standing agent's rear; background standing
        # on the padded row's place (x = 0, y = W/2) across the seam; agent asking for more than ax_max
        _state([398.0, 399.9, 4.0, 200.0], [1.3, 4.0, 1.5, 6.0], [6.0, 0.0, 0.0, 5.0], [0.1, 0.0, 0.0, 0.0],
               [6.0, 0.0, 5.0, 5.0], [False, True, False, False]),
    ]
    accel = np.array([[[5.0, 1.5], [0.0, 0.0], [0.0, 0.0]], [[-10.0, 0.0], [-1.0, 1.0], [3.0, 0.0]]])
    return cfgs, states, accel


def test_a_step_of_the_world_is_each_runs_physics_and_sumos_arithmetic():
    """Against values by hand and the physics called on each run alone: the agents' commands clipped to their
    bounds, top speed and lateral ratio; the background driven by the driver model with the road's clearance;
    the edge clip within the contact tolerance; SUMO's position on the edge, handed over only past its end; a
    tiny lateral move set; the padded row exerting no force and overlapping nobody; collision events started."""
    cfgs, states, accel = _hand_built_batch()
    params = WorldParams.of(cfgs)
    world = world_of(states, *ROADS)
    assert world.agent_rows.tolist() == [[0, 2, 4], [0, 2, 3]] and world.present[1].tolist() == [True] * 4 + [False]
    assert world.edge.tolist() == [[0, 2, 3, 0, 2], [3, 3, 0, 2, 0]] and world.pos[1, [0, 2]].tolist() == [98.0, 4.0]
    details: dict[str, np.ndarray] = {}
    new, out = step_world(world, params, accel, details)
    agents = np.array([[0, 2, 4], [0, 2, 3]])

    # ax to the top speed (20 − 19.5)/0.5, ay to the lateral ratio (0.1·19.5 − 1.5)/0.5; ax_min; a standing
    # agent's braking floored at vx = 0 and its lateral move held at 0.1·0 = 0; ax_max
    assert np.take_along_axis(out.ax, agents, 1).tolist() == [[1.0, 0.0, 0.0], [-4.5, 0.0, 2.0]]
    assert out.ay[0, 0] == pytest.approx(0.9, abs=1e-12) and out.ay[1, 2] == 0.0
    assert np.take_along_axis(new.vx, agents, 1).tolist() == [[20.0, 10.0, 10.0], [3.75, 0.0, 6.0]]
    assert new.vy[0, 0] == pytest.approx(1.95, abs=1e-12) and new.vy[0, 2] == -0.01  # no contact: vy kept
    assert not out.boundary_contact.any()
    # SUMO's positions: (19.5 + ½·0.5)·0.5 = 9.875 m from 124 → edge 1 at 8.875; 5 m to exactly edge 3's end
    # (x = 500, not wrapped); (6 − ½·2.25)·0.5 = 2.4375 m from 398 → edge 0 at 0.4375
    assert np.take_along_axis(new.edge, agents, 1).tolist() == [[1, 3, 2], [0, 0, 2]]
    assert np.take_along_axis(new.pos, agents, 1).tolist() == [[8.875, 125.0, 55.0], [0.4375, 4.0, 2.75]]
    assert np.take_along_axis(new.x, agents, 1).tolist() == [[133.875, 500.0, 305.0], [0.4375, 4.0, 202.75]]
    assert new.y[0, 0] == pytest.approx(5.1 + 0.75 + 0.1125, abs=1e-12)
    assert new.y[0, 2] == pytest.approx(0.95, abs=1e-12)  # at the clip line 0.9 + 0.05
    # lateral moves: run 1's agent 0.05 m (< 0.125 m): its y is set to y + dy (1.35; driven from its offset from
    # the centre it would be 1.3499999999999996); run 0's third agent exactly 0.125 m: driven, offset + dy
    assert new.y[1, 0] == 1.35 and new.lat[1, 0] == 1.35 - 4.0
    assert new.lat[0, 4] == (0.98 - 5.1) + 0.125 and new.y[0, 4] == 1.1050000000000004
    # the padded row stays where it was and takes part in nothing (the background stands on its place)
    assert (new.x[1, 4], new.y[1, 4], new.vx[1, 4], out.ax[1, 4], out.ay[1, 4]) == (0.0, 4.0, 0.0, 0.0, 0.0)
    assert new.x[1, 1] == world.x[1, 1] and new.y[1, 1] == 4.0
    assert not out.overlap[1, 4].any() and not out.overlap[1, :, 4].any() and not world.overlap[1, 4].any()
    # the agent's front now overlaps the standing agent's rear (0.4375 + 2 > 4 − 2): one event, i < j
    assert np.argwhere(out.new_collisions).tolist() == [[1, 0, 2]] and out.overlap[1, 0, 2] and out.overlap[1, 2, 0]
    assert new.steps.tolist() == [1, 1] and world.steps.tolist() == [0, 0]

    # the background rows: the driver model and the dynamics of each run alone
    for k, (cfg, state) in enumerate(zip(cfgs, states)):
        n, rows = state.n, [1] if k else [1, 3]
        run_details: dict[str, np.ndarray] = {}
        ax, ay = driver_accelerations(state, cfg.scenario.driver, cfg.road.length_m, cfg.road.width_m, 0.5, 0.05,
                                      details=run_details)
        cmd = plan_step(state.x, state.y, state.vx, state.vy, state.width, ax, ay, 0.5, cfg.road.width_m, 0.05, 0.01)
        np.testing.assert_allclose(out.ax[k, rows], cmd.ax[rows], rtol=0, atol=1e-12)
        np.testing.assert_allclose(out.ay[k, rows], cmd.ay[rows], rtol=0, atol=1e-12)
        np.testing.assert_allclose(new.vx[k, rows], cmd.vx_next[rows], rtol=0, atol=1e-12)
        np.testing.assert_allclose(new.y[k, rows], state.y[rows] + cmd.dy[rows], rtol=0, atol=1e-12)
        for name, value in run_details.items():
            np.testing.assert_array_equal(details[name][k, :n], value, err_msg=name)
    assert out.ay[0, 3] < 0.0 < states[0].vy[3]  # the left edge's bound (with the clearance) brakes the drift
    assert details["wall_binds"].shape == (2, 5)


def test_a_world_pads_its_runs_to_the_rows_asked_and_refuses_what_does_not_fit():
    _, states, _ = _hand_built_batch()
    world = world_of(states, *ROADS, rows=6)
    assert (world.runs, world.counts.tolist(), world.x.shape, world.dx.shape) == (2, [5, 4], (2, 6), (2, 6, 6))
    assert world.present.tolist() == [[True] * 5 + [False], [True] * 4 + [False] * 2]
    # padding: at rest at x = 0 on the centre line, of zero size, not driven, on edge 0
    for name, fill in (("x", 0.0), ("vx", 0.0), ("vy", 0.0), ("length", 0.0), ("width", 0.0), ("v_desired", 0.0),
                       ("lat", 0.0), ("pos", 0.0), ("edge", 0), ("controlled", False)):
        assert getattr(world, name)[1, 4:].tolist() == [fill, fill], name
    assert world.y[:, 5].tolist() == [5.1, 4.0] and world.y[1, 4] == 4.0
    assert world.lat[0, :5] == pytest.approx(np.array([5.1, 5.1, 0.95, 8.6, 0.98]) - 5.1, abs=1e-12)
    assert world.edge.dtype.kind == "i" and world.steps.tolist() == [0, 0] and world.steps.dtype.kind == "i"
    assert world.controlled[0].tolist() == [False, True, False, True, False, False]
    assert world.agent_rows.tolist() == [[0, 2, 4], [0, 2, 3]]
    assert world.road_length.tolist() == ROADS[0] and world.road_width.tolist() == ROADS[1]
    np.testing.assert_array_equal(world.dx[0, :5, :5], pairwise_offsets(states[0], 500.0)[0])
    assert world.dx[1, 0, 2] == 6.0 and world.dy[1, 0, 2] == pytest.approx(0.2, abs=1e-12)  # across the seam
    assert not world.overlap.any()  # the background on the padded rows' place overlaps none of them
    assert world_of(states, *ROADS, rows=5).x.shape == (2, 5)  # exactly the most vehicles
    with pytest.raises(ValueError, match="more vehicles than the world's 4 rows"):
        world_of(states, *ROADS, rows=4)
    two_agents = replace(states[1], controlled=np.array([False, True, False, True]))
    with pytest.raises(ConfigError, match="^the runs of one batch must have the same number of agents$"):
        world_of([states[0], two_agents], *ROADS)
    with pytest.raises(ConfigError, match="^the runs of one batch must have the same number of agents$"):
        replace_runs(world, [1], [two_agents])
    assert replace_runs(world, [], []) is world


def test_a_run_replaced_keeps_its_road_and_the_others_are_untouched():
    cfgs, states, accel = _hand_built_batch()
    world, _ = step_world(world_of(states, *ROADS), WorldParams.of(cfgs), accel)
    fresh = _state([50.0, 399.0, 10.0, 20.0], [2.0, 6.0, 4.0, 4.0], [1.0, 2.0, 3.0, 4.0], [0.0] * 4,
                   [1.0, 2.0, 3.0, 4.0], [False, True, False, False])
    out = replace_runs(world, [1], [fresh])
    assert out.steps.tolist() == [1, 0] and world.steps.tolist() == [1, 1]
    assert out.road_length.tolist() == ROADS[0] and out.road_width.tolist() == ROADS[1]
    assert out.x[1].tolist() == [50.0, 399.0, 10.0, 20.0, 0.0] and out.edge[1].tolist() == [0, 3, 0, 0, 0]
    assert out.lat[1].tolist() == [-2.0, 2.0, 0.0, 0.0, 0.0] and out.dx[1, 1, 0] == 51.0  # across the 400 m seam
    for name in ("x", "y", "vx", "edge", "pos", "lat", "dx", "overlap"):
        np.testing.assert_array_equal(getattr(out, name)[0], getattr(world, name)[0], err_msg=name)
    assert world.x[1, 0] == 0.4375  # the world replaced from is unchanged


def test_a_world_moved_to_torch_and_back_holds_the_same_numbers():
    torch = pytest.importorskip("torch")
    from lanefree_sumo.sim.world import world_to

    _, states, _ = _hand_built_batch()
    world = world_of(states, *ROADS)
    twin = world_to(world, "torch-cpu")
    assert isinstance(twin.x, torch.Tensor) and twin.x.dtype == torch.float64 and twin.edge.dtype == torch.int64
    fresh = [replace(states[1], x=states[1].x + 1.0)]
    for numpy_world, torch_world in ((world, twin), (replace_runs(world, [1], fresh), replace_runs(twin, [1], fresh))):
        assert isinstance(torch_world.x, torch.Tensor)
        back = world_to(torch_world, "cpu")
        for f in fields(World):
            assert isinstance(getattr(back, f.name), np.ndarray), f.name
            np.testing.assert_array_equal(getattr(back, f.name), getattr(numpy_world, f.name), err_msg=f.name)


def test_a_step_on_torch_is_the_numpy_step_and_a_lateral_move_of_one_metre_is_driven():
    torch = pytest.importorskip("torch")
    from lanefree_sumo.sim.world import world_to
    from lanefree_sumo.sim.xp_torch import numpy_transcendentals

    cfgs, states, accel = _hand_built_batch()
    params = WorldParams.of(cfgs)
    world = world_of(states, *ROADS)
    new, out = step_world(world, params, accel)
    with numpy_transcendentals():
        twin, twin_out = step_world(world_to(world, "torch-cpu"), params, torch.from_numpy(accel))
    assert isinstance(twin.x, torch.Tensor) and isinstance(twin_out.ax, torch.Tensor)
    for name in ("x", "y", "vx", "vy", "edge", "pos", "lat", "overlap", "steps"):
        np.testing.assert_array_equal(getattr(twin, name).numpy(), getattr(new, name), err_msg=name)
    for name in ("ax", "ay", "boundary_contact", "new_collisions"):
        np.testing.assert_array_equal(getattr(twin_out, name).numpy(), getattr(out, name), err_msg=name)
    # one agent moving exactly 1 m sideways (2 m/s for 0.5 s): driven, as any move but none at all
    cfg = merge_config(LaneFreeConfig(), {"backend": "numpy", "sim": {"step_s": 0.5}, "scenario": {"with_agent": True}})
    alone = world_of([_state([100.0], [2.0], [10.0], [2.0], [10.0], [False])], [500.0], [10.2])
    moved, _ = step_world(alone, WorldParams.of([cfg]), np.zeros((1, 2)))
    assert (moved.y[0, 0], moved.lat[0, 0]) == (3.0, 3.0 - 5.1)
