"""The on-ramp (an open road): its boundaries, vehicles entering and leaving, merging, and the ring untouched."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lanefree_sumo.config import ConfigError, LaneFreeConfig, merge_config
from lanefree_sumo.sim.collisions import CollisionTracker
from lanefree_sumo.sim.road import OPEN_ROAD_WRAP_M, road_of
from lanefree_sumo.sim.simulation import Simulation, run_simulation
from lanefree_sumo.sim.state import wrap

from conftest import lanefree


def onramp(**onramp_settings) -> LaneFreeConfig:
    return merge_config(LaneFreeConfig(), {"backend": "numpy", "scenario": {"density_veh_per_km": 20},
                                           "road": {"kind": "onramp", "onramp": onramp_settings}})


def test_the_ramps_boundaries_close_in_the_merge_zone():
    road = road_of(onramp())
    assert (road.length_m, road.ramp_start_m, road.merge_start_m, road.ramp_end_m) == (1980.0, 1000.0, 1280.0, 1480.0)
    x = np.array([500.0, 1100.0, 1280.0, 1380.0, 1480.0, 1600.0])
    lo, hi = road.bounds(x, np.ones(6, dtype=bool))
    assert np.allclose(lo, [-3.0, -3.0, -3.0, -1.5, 0.0, 0.0])
    assert np.allclose(hi, [0.0, 0.0, 10.2, 10.2, 10.2, 10.2])  # confined to the ramp before the merge zone
    lo, hi = road.bounds(x, np.zeros(6, dtype=bool))
    assert np.all(lo == 0.0) and np.all(hi == 10.2)
    ring = road_of(LaneFreeConfig())
    assert ring.bounds(x, None) == (0.0, 10.2) and ring.wrap_length == 500.0
    d = np.array([-1979.0, -0.1, 0.0, 3.3, 1979.0])  # an open road never wraps, bit for bit
    assert np.array_equal(wrap(d, OPEN_ROAD_WRAP_M), d)
    with pytest.raises(ConfigError, match="road.onramp.merge_m"):
        road_of(onramp(merge_m=500.0))
    with pytest.raises(ConfigError, match="agent_main_start_m"):
        road_of(onramp(agent_start="main", agent_main_start_m=2500.0))


def test_the_collision_tracker_follows_rows_leaving_and_entering():
    tracker = CollisionTracker(3)
    both = np.array([[False, True, False], [True, False, False], [False, False, False]])
    assert tracker.update(both).tolist() == [[0, 1]]
    tracker.keep(np.array([False, True, True]))  # vehicle 0 left: the pair is forgotten
    tracker.add(1)
    overlap = np.zeros((3, 3), dtype=bool)
    overlap[0, 2] = overlap[2, 0] = True
    assert tracker.update(overlap).tolist() == [[0, 2]]
    assert tracker.update(overlap).tolist() == []  # the same contact is one event


def test_traffic_enters_merges_and_leaves_without_collisions():
    """At a named demand (2400 veh/h on the main road, 300 veh/h on the ramp, 600 s): no collision, every
    ramp vehicle merged before the ramp's end, vehicles in = vehicles out + on the road."""
    cfg = onramp()
    steps = int(600 / cfg.sim.step_s)
    sim = Simulation(cfg)
    seen_rows: set[int] = set()
    summary = run_simulation(cfg, steps, on_step=lambda k, state, result: seen_rows.add(state.n), sim=sim)
    o = summary["onramp"]
    assert summary["background_collisions"] == 0
    assert o["entered_ramp"] >= 30 and o["merged"] >= 30
    assert o["ramp_end_reached_unmerged"] == 0
    assert o["started_on_road"] + o["entered_main"] + o["entered_ramp"] == o["left"] + o["on_road"]
    assert o["merged"] + o["ramp_on_road_unmerged"] == o["entered_ramp"]  # a ramp vehicle leaves only merged
    assert o["left"] > 0 and len(seen_rows) > 10  # rows changed as vehicles came and went
    assert summary["min_lateral_margin_m"] > -1e-6  # every body inside its boundaries at every step
    assert 2000 < o["outflow_veh_per_h"] < 3200


def test_a_seed_gives_the_same_open_road_episode():
    cfg = onramp(main_flow_veh_per_h=3000.0, ramp_flow_veh_per_h=600.0)
    runs = []
    for _ in range(2):
        sim = Simulation(cfg)
        sim.reset(7)
        for _ in range(400):
            sim.step()
        state = sim.current()[0]
        runs.append((list(state.ids), state.x.copy(), state.y.copy()))
        sim.close()
    assert runs[0][0] == runs[1][0]
    assert np.array_equal(runs[0][1], runs[1][1]) and np.array_equal(runs[0][2], runs[1][2])


@pytest.mark.sumo
def test_numpy_gives_sumos_on_ramp_bit_for_bit():
    """The SUMO-free backend keeps edge, lane, lane position and lateral offset as SUMO does: the same
    trajectories, step by step, while vehicles enter, cross from the ramp into the main road and leave."""
    runs = {}
    for backend in ("numpy", "libsumo"):
        cfg = merge_config(onramp(main_flow_veh_per_h=3000.0, ramp_flow_veh_per_h=600.0), {"backend": backend})
        sim = Simulation(cfg)
        sim.reset(4)
        steps = []
        for _ in range(600):
            sim.step()
            state = sim.current()[0]
            steps.append((list(state.ids), state.x.copy(), state.y.copy(), state.vx.copy()))
        runs[backend] = steps, sim.traffic.counts
        sim.close()
    (numpy_steps, numpy_counts), (sumo_steps, sumo_counts) = runs["numpy"], runs["libsumo"]
    assert numpy_counts == sumo_counts and sumo_counts.merged >= 15 and sumo_counts.left >= 50
    for mine, theirs in zip(numpy_steps, sumo_steps):
        assert mine[0] == theirs[0]
        for a, b in zip(mine[1:], theirs[1:]):
            assert np.array_equal(a, b)


@pytest.mark.sumo
def test_simulate_scenario_onramp_on_the_command_line(tmp_path):
    out = tmp_path / "onramp"
    res = lanefree("simulate", "--scenario", "onramp", "--seconds", "60", "--main-flow", "2000", "--ramp-flow", "400",
                   "--out", str(out), "--json")
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    assert summary["backend"] == "libsumo" and summary["onramp"]["entered_main"] > 0
    assert (out / "trajectory.csv").is_file()
    for args, needle in ((("--set", "road.onramp.merge_m=600"), "road.onramp.merge_m"),
                         (("--main-flow", "-5"), "--main-flow")):
        bad = lanefree("simulate", "--scenario", "onramp", "--out", str(tmp_path / "bad"), *args)
        assert bad.returncode == 2 and needle in bad.stderr and bad.stderr.count("\n") == 1, bad.stderr
        assert not (tmp_path / "bad").exists()


def test_an_arrival_behind_a_queue_at_the_entry_enters_slowly_and_stops_in_time():
    """A queue of stopped vehicles across the whole road 35 m past the entry (congestion spilled back): an
    arrival enters only at the speed from which braking at the driver's ax_min stops gap_x behind them,
    √(2·4·(35 − 6)) ≈ 15.2 m/s rather than its desired speed, and the queue is not hit."""
    from lanefree_sumo.sim.open_road import LATERAL_SLOTS
    from lanefree_sumo.sim.state import VehicleState

    cfg = onramp(main_flow_veh_per_h=14400.0, ramp_flow_veh_per_h=0.0)
    bg = cfg.scenario.background
    sim = Simulation(cfg)
    sim.reset(0)
    n = LATERAL_SLOTS + 1
    y = np.linspace(0.5 * bg.width_m + 0.1, cfg.road.width_m - 0.5 * bg.width_m - 0.1, n)
    front_of_queue = 0.5 * bg.length_m + 35.0 + bg.length_m
    queue = VehicleState([f"q{i}" for i in range(n)], np.full(n, front_of_queue), y, np.zeros(n), np.zeros(n),
                         np.full(n, bg.length_m), np.full(n, bg.width_m), np.zeros(n), np.ones(n, dtype=bool))
    sim.place(queue)
    result = sim.step()
    entered = result.entered
    assert entered is not None and entered.n == 1
    brake = -cfg.scenario.driver.bounds.ax_min
    assert entered.vx[0] == pytest.approx(np.sqrt(2 * brake * (35.0 - cfg.scenario.spawn.gap_x_m)))
    assert entered.vx[0] < entered.v_desired[0]
    collisions = 0
    for _ in range(80):  # 20 s; the queue wants to stand still (desired speed 0), arrivals keep coming
        collisions += len(sim.step().new_collisions)
    assert collisions == 0


def _backend_at(x, y, vx, **sim):
    """An :class:`OpenRoadNumpyBackend` of the default on-ramp (edges up [0, 1000), merge [1000, 1480) with the
    ramp at y −3…0 beside the main road, down from 1480; step 0.25 s) reset to vehicles at ``x``, ``y``, ``vx``."""
    from lanefree_sumo.sim.backends.numpy import OpenRoadNumpyBackend

    cfg = merge_config(onramp(), {"sim": sim})
    backend = OpenRoadNumpyBackend(cfg)
    backend.reset(_rows(x, y, vx))
    return backend


def _rows(x, y, vx):
    from lanefree_sumo.sim.state import VehicleState

    n = len(x)
    return VehicleState([f"v{i}" for i in range(n)], np.array(x, float), np.array(y, float), np.array(vx, float),
                        np.zeros(n), np.full(n, 4.0), np.full(n, 1.8), np.full(n, 30.0), np.ones(n, dtype=bool))


def _step(backend, vx_next, dy):
    from lanefree_sumo.sim.dynamics import StepCommand

    n = len(vx_next)
    zeros = np.zeros(n)
    return backend.step(StepCommand(np.array(vx_next, float), np.array(dy, float), zeros, zeros, zeros,
                                    np.zeros(n, dtype=bool)))


def test_the_numpy_backend_places_vehicles_on_edges_and_lanes_as_sumo_does():
    """Edge by x (an edge begins at its offset), the ramp's lane 0 only beside it (y < 0), the position on the
    edge and the offset from the lane's centre (the ramp's at −1.5 m, the main road's at 5.1 m)."""
    backend = _backend_at([999.0, 1000.0, 1000.0, 1480.0, 1300.0, 1479.0],
                          [5.1, -1.0, 0.0, 6.1, -2.0, 5.1], np.zeros(6))
    assert backend._edge.tolist() == [0, 1, 1, 2, 1, 1]
    assert backend._lane.tolist() == [0, 0, 1, 0, 0, 1]
    assert backend._pos.tolist() == [999.0, 0.0, 0.0, 0.0, 300.0, 479.0]
    assert backend._lat == pytest.approx([0.0, 0.5, -5.1, 1.0, -0.5, 0.0], abs=1e-12)
    x, y, vx = _step(backend, np.zeros(6), np.zeros(6))  # standing still: every vehicle where it was
    assert x.tolist() == [999.0, 1000.0, 1000.0, 1480.0, 1300.0, 1479.0]
    assert y == pytest.approx([5.1, -1.0, 0.0, 6.1, -2.0, 5.1], abs=1e-12) and vx.tolist() == [0.0] * 6


def test_the_numpy_backend_hands_vehicles_over_to_the_next_edge_as_sumo_does():
    """The ballistic distance (v + ½(v' − v))·T along the edge; past the edge's end (not at it) the vehicle is on
    the next edge, on the main road's lane; the last edge never ends. A ramp vehicle carried past the merge edge
    keeps its offset from the lane centre — now the main road's — unless its lateral move is tiny: then its y."""
    backend = _backend_at(
        [999.0, 999.0, 1479.5, 1479.5, 2179.5, 1479.5, 1479.5, 1479.5, 1479.5],
        [5.1, 5.1, -1.0, 6.1, 5.1, -1.0, -1.0, -1.0, -1.0],
        np.full(9, 4.0), sumo_min_lateral_speed_mps=0.4)  # lateral moves shorter than 0.1 m are set
    x, y, vx = _step(backend, [4.0, 6.0, 4.0, 4.0, 4.0, 4.0, 4.0, 4.0, 4.0],
                     [0.0, 0.0, 0.0, 0.0, 0.0, 0.05, -0.05, 0.1, -0.5])
    assert x.tolist() == [1000.0, 1000.25, 1480.5, 1480.5, 2180.5, 1480.5, 1480.5, 1480.5, 1480.5]
    assert backend._edge.tolist() == [0, 1, 2, 2, 2, 2, 2, 2, 2]
    assert backend._lane.tolist() == [0, 1, 0, 0, 0, 0, 0, 0, 0]
    assert backend._pos.tolist() == [1000.0, 0.25, 0.5, 0.5, 700.5, 0.5, 0.5, 0.5, 0.5]
    assert y == pytest.approx([5.1, 5.1, 5.6, 6.1, 5.1, -0.95, -1.05, 5.7, 5.1], abs=1e-9)
    assert vx.tolist() == [4.0, 6.0, 4.0, 4.0, 4.0, 4.0, 4.0, 4.0, 4.0]


def test_the_numpy_backend_moves_vehicles_sideways_and_onto_the_main_road_as_sumo_does():
    """A lateral move shifts the offset from the lane centre (a tiny one sets y); a ramp vehicle whose centre
    passes the ramp's edge (1.5 m from its centre, not at it) changes to the main road's lane and keeps its y;
    on every other lane an offset beyond 1.5 m changes nothing."""
    backend = _backend_at([500.0, 1200.0, 1200.0, 1200.0, 1600.0, 1200.0],
                          [5.1, -1.0, -1.0, 5.1, 5.1, -1.0], np.zeros(6), sumo_min_lateral_speed_mps=0.4)
    x, y, vx = _step(backend, np.zeros(6), [2.0, 1.0, 1.25, 2.0, 2.0, 0.05])
    assert x.tolist() == [500.0, 1200.0, 1200.0, 1200.0, 1600.0, 1200.0]
    assert y == pytest.approx([7.1, 0.0, 0.25, 7.1, 7.1, -0.95], abs=1e-9)
    assert backend._lane.tolist() == [0, 0, 1, 1, 0, 0]
    assert backend._lat == pytest.approx([2.0, 1.5, 0.25 - 5.1, 2.0, 2.0, 0.55], abs=1e-9)
    returned = y.copy()
    y[:] = 0.0  # the arrays returned are the caller's: the backend keeps its own
    x, y, vx = _step(backend, [2.0, 0.0, 0.0, 0.0, 0.0, 0.0], np.zeros(6))
    assert x.tolist() == [500.25, 1200.0, 1200.0, 1200.0, 1600.0, 1200.0] and vx.tolist() == [2.0] + [0.0] * 5
    assert y == pytest.approx(returned, abs=1e-9)  # the new lane's centre and offset give the same y


def test_the_numpy_backend_adds_and_removes_vehicles_in_order():
    from lanefree_sumo.sim.backends.numpy import OpenRoadNumpyBackend

    empty = OpenRoadNumpyBackend(onramp())  # a new backend's road is empty
    assert [(a.tolist(), a.dtype.kind) for a in _step(empty, [], [])] == [([], "f")] * 3
    backend = OpenRoadNumpyBackend(onramp())
    backend.add(_rows([100.0, 1200.0], [5.1, -1.0], [8.0, 4.0]))
    assert backend._pos.tolist() == [100.0, 200.0] and backend._vx.dtype.kind == "f"
    assert backend._edge.tolist() == [0, 1] and backend._lane.tolist() == [0, 0]
    backend.add(_rows([1010.0, 0.0], [6.1, 3.1], [2.0, 0.0]))
    x, y, vx = _step(backend, [8.0, 4.0, 2.0, 0.0], np.zeros(4))
    assert x.tolist() == [102.0, 1201.0, 1010.5, 0.0] and vx.tolist() == [8.0, 4.0, 2.0, 0.0]
    assert y == pytest.approx([5.1, -1.0, 6.1, 3.1], abs=1e-12)
    assert backend._lane.tolist() == [0, 0, 1, 0]
    backend.remove(np.array([False, True, False, True]))
    x, y, vx = _step(backend, [4.0, 4.0], [0.0, 0.5])
    assert x.tolist() == [1202.0, 0.5] and vx.tolist() == [4.0, 4.0]  # (0 + ½·4)·0.25 from rest
    assert y == pytest.approx([-1.0, 3.6], abs=1e-12)
    assert backend._edge.tolist() == [1, 0] and backend._lane.tolist() == [0, 0]


def test_every_road_kind_is_declared_once_and_every_table_by_kind_covers_them():
    """A road kind is named in the config (``RoadKind``) and declared in ``sim/road.py``; the tables keyed by kind
    (SUMO's networks and backends) hold every one, so a new kind cannot silently take the ring's code."""
    from lanefree_sumo.config import ROAD_KINDS
    from lanefree_sumo.sim.backends.sumo import BACKENDS, NETWORKS
    from lanefree_sumo.sim.road import ROAD_KIND_SPECS

    for table in (ROAD_KIND_SPECS, NETWORKS, BACKENDS):
        assert set(table) == set(ROAD_KINDS)
    assert all(spec.name == name for name, spec in ROAD_KIND_SPECS.items())
