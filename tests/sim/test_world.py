"""The batched core: run k of a world of K rings is, bit for bit, the single ring simulation with the same seed."""

from __future__ import annotations

import numpy as np
import pytest

from lanefree_sumo.config import ConfigError, LaneFreeConfig, merge_config
from lanefree_sumo.sim.simulation import Simulation
from lanefree_sumo.sim.spawn import spawn
from lanefree_sumo.sim.state import row_sum
from lanefree_sumo.sim.world import WorldParams, replace_runs, reset_world, step_world

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
    with pytest.raises(ConfigError, match="step_s"):
        WorldParams.of([ring(0, 70.0), ring(1, 70.0, sim={"step_s": 0.2})])
    with pytest.raises(ConfigError, match="ring"):
        WorldParams.of([ring(0, 70.0, road={"kind": "onramp"})])
