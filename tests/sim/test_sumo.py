"""The real SUMO: backends agree with the SUMO-free physics, runs are deterministic, resets
are exact, background traffic is sane, and bad networks give clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.sim.backends.sumo import SumoBackend, SumoError
from lanefree_sumo.sim.network import default_net_path
from lanefree_sumo.sim.simulation import Simulation
from lanefree_sumo.sim.spawn import spawn
from lanefree_sumo.sim.state import wrap

pytestmark = pytest.mark.sumo

L = 500.0


def config(backend: str, density: float = 90, **extra) -> LaneFreeConfig:
    return merge_config(LaneFreeConfig(), {"backend": backend, "scenario": {"density_veh_per_km": density}, **extra})


def run(sim: Simulation, seed: int, steps: int) -> list[np.ndarray]:
    sim.reset(seed)
    out = []
    for _ in range(steps):
        sim.step()
        out.append(np.stack([sim.state.x, sim.state.y, sim.state.vx]))
    return out


@pytest.mark.parametrize("backend,steps", [("libsumo", 800), ("traci", 800)])
def test_sumo_follows_the_reference_physics(backend, steps):
    reference = Simulation(config("numpy"))
    sumo_sim = Simulation(config(backend))
    try:
        ref = run(reference, 3, steps)
        got = run(sumo_sim, 3, steps)
    finally:
        sumo_sim.close()
    worst_x = max(np.abs(wrap(g[0] - r[0], L)).max() for g, r in zip(got, ref))
    worst_y = max(np.abs(g[1] - r[1]).max() for g, r in zip(got, ref))
    worst_v = max(np.abs(g[2] - r[2]).max() for g, r in zip(got, ref))
    assert worst_x <= 1e-6 and worst_y <= 1e-6 and worst_v <= 1e-6, (worst_x, worst_y, worst_v)
    # the traffic really moved: laps and lateral motion happened
    assert np.abs(got[-1][0] - got[0][0]).max() > 0
    assert np.ptp(np.stack([g[1] for g in got]), axis=0).max() > 0.1


def test_libsumo_is_deterministic_and_reset_is_exact():
    sim = Simulation(config("libsumo"))
    try:
        first = run(sim, 11, 120)
        second = run(sim, 11, 120)  # same process, fast reset, same seed
        state = sim.reset(12)
        placed = sim.backend.read()
    finally:
        sim.close()
    assert all(np.array_equal(a, b) for a, b in zip(first, second))
    assert np.array_equal(placed[0], state.x) and np.array_equal(placed[2], state.vx)
    assert np.abs(placed[1] - state.y).max() < 1e-12


@pytest.mark.parametrize("density", [70, 90, 120])
def test_background_traffic_is_sane(density):
    """0 collisions, always on the road, and at 70 veh/km mean speed within 10 % of desired."""
    sim = Simulation(config("libsumo", density))
    try:
        for seed in range(3):
            state = sim.reset(seed)
            collisions = 0
            speeds = []
            min_margin = np.inf
            for _ in range(800):
                result = sim.step()
                collisions += len(result.new_collisions)
                speeds.append(state.vx.mean())
                margin = np.minimum(state.y - state.width / 2, 10.2 - state.y - state.width / 2)
                min_margin = min(min_margin, margin.min())
            assert collisions == 0, (density, seed)
            assert min_margin > 0, (density, seed, min_margin)
            if density == 70:
                ratio = np.mean(speeds) / state.v_desired.mean()
                assert ratio >= 0.9, (seed, ratio)
    finally:
        sim.close()


def test_second_libsumo_simulation_in_one_process_is_refused():
    first = SumoBackend(config("libsumo"))
    try:
        with pytest.raises(SumoError, match="one environment per process"):
            SumoBackend(config("libsumo"))
    finally:
        first.close()


def test_corrupt_network_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "broken.net.xml"
    bad.write_text("<net><edge id='e0'")
    with pytest.raises(SumoError, match="not a readable SUMO network"):
        SumoBackend(config("libsumo", net_file=str(bad)))
    with pytest.raises(SumoError, match="does not exist"):
        SumoBackend(config("libsumo", net_file=str(tmp_path / "missing.net.xml")))


def test_network_of_another_size_is_rejected():
    default_net = default_net_path(config("libsumo"))
    longer = merge_config(config("libsumo"), {"road": {"length_m": 600.0}, "net_file": str(default_net)})
    with pytest.raises(SumoError, match="pass matching --length/--width"):
        SumoBackend(longer)


def test_other_ring_sizes_are_built_on_demand(tmp_path):
    from lanefree_sumo.sim.backends.sumo import build_ring_net

    cfg = merge_config(config("libsumo", 70), {"road": {"length_m": 300.0, "width_m": 7.0}})
    net = build_ring_net(cfg, tmp_path)
    sim = Simulation(merge_config(cfg, {"net_file": str(net)}))
    try:
        state = sim.reset(0)
        assert state.n == 21
        for _ in range(40):
            sim.step()
        assert (state.x < 300.0).all() and (state.y < 7.0).all()
    finally:
        sim.close()
    assert spawn(cfg, np.random.default_rng(0)).n == 21


def test_networks_of_other_sizes_are_built_in_the_cache_never_in_the_package(tmp_path, monkeypatch):
    """An on-ramp (or ring) of sizes without a committed network gets one built on first use in the user's cache
    folder; the package's sumo_nets/ is only read."""
    from lanefree_sumo.sim.backends.sumo import check_onramp_net, resolve_net
    from lanefree_sumo.sim.network import NETS_DIR

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    committed = sorted(p.name for p in NETS_DIR.iterdir())
    assert resolve_net(config("libsumo")).parent == NETS_DIR
    cfg = merge_config(config("libsumo"), {"road": {"kind": "onramp", "width_m": 12.0}})
    net = resolve_net(cfg)
    cache = tmp_path / "lanefree_sumo" / "nets"
    assert net == cache / "onramp_U1000_R480_D500_W12_w3.net.xml"
    check_onramp_net(net, cfg)
    assert sorted(p.name for p in cache.iterdir()) == sorted(
        f"onramp_U1000_R480_D500_W12_w3.{ext}.xml" for ext in ("add", "con", "edg", "net", "nod"))
    assert resolve_net(cfg) == net  # built once
    assert sorted(p.name for p in NETS_DIR.iterdir()) == committed
