"""A learning vehicle on the on-ramp: the checkers, SUMO and numpy alike, merging and leaving, training."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from pettingzoo.test import parallel_api_test
from stable_baselines3.common.env_checker import check_env as sb3_check_env

from lanefree_sumo.config import ConfigError
from lanefree_sumo.rl.env import LaneFreeEnv
from lanefree_sumo.rl.multi_agent import parallel_env

from conftest import lanefree

ONRAMP = {"backend": "numpy", "road": {"kind": "onramp"}, "scenario": {"density_veh_per_km": 20}}


@pytest.mark.parametrize("backend,kind", [
    ("numpy", "vector"), ("numpy", "set"),
    pytest.param("libsumo", "vector", marks=pytest.mark.sumo), pytest.param("traci", "set", marks=pytest.mark.sumo),
])
def test_gymnasium_and_sb3_checkers_pass(backend, kind):
    """On every backend: the checkers reset, step and reset again with one seed (vehicles have entered and
    left between the resets)."""
    env = LaneFreeEnv({**ONRAMP, "backend": backend, "observation": {"kind": kind}})
    try:
        gym_check_env(env, skip_render_check=True)
        sb3_check_env(env, warn=False)
    finally:
        env.close()


@pytest.mark.parametrize("backend", ["numpy", pytest.param("libsumo", marks=pytest.mark.sumo),
                                     pytest.param("traci", marks=pytest.mark.sumo)])
def test_resets_in_a_row_with_and_without_steps_between_start_the_same_episode(backend):
    env = LaneFreeEnv({"backend": backend, "road": {"kind": "onramp"}})
    try:
        first, _ = env.reset(seed=3)
        again, _ = env.reset(seed=3)  # no step between
        np.testing.assert_array_equal(first, again)
        ids = set(env.sim.state.ids)
        for _ in range(40):  # long enough for vehicles to enter the road (ids the reset state does not have)
            env.step(np.zeros(2, dtype=np.float32))
        assert set(env.sim.state.ids) - ids, "no vehicle entered: the test would not cover the case"
        after, _ = env.reset(seed=3)
        np.testing.assert_array_equal(first, after)
        env.reset()
        env.step(np.zeros(2, dtype=np.float32))
    finally:
        env.close()


def _episode(backend: str, start: str, actions: np.ndarray) -> list:
    env = LaneFreeEnv({**ONRAMP, "backend": backend, "road": {"kind": "onramp", "onramp": {"agent_start": start}}})
    obs, _ = env.reset(seed=8)
    steps = [obs]
    try:
        for action in actions:
            out = env.step(action)
            steps.append(out)
            if out[2] or out[3]:
                break
    finally:
        env.close()
    return steps


@pytest.mark.sumo
def test_numpy_gives_sumos_on_ramp_episode_with_the_agent():
    actions = np.random.default_rng(1).uniform(-0.3, 1.0, (300, 2)).astype(np.float32)
    numpy_steps, sumo_steps = _episode("numpy", "ramp", actions), _episode("libsumo", "ramp", actions)
    assert len(numpy_steps) == len(sumo_steps) > 100
    assert np.array_equal(numpy_steps[0], sumo_steps[0])
    for mine, theirs in zip(numpy_steps[1:], sumo_steps[1:]):
        assert np.array_equal(mine[0], theirs[0]) and mine[1:4] == theirs[1:4]
        mine_info, their_info = dict(mine[4]), dict(theirs[4])
        mine_metrics, their_metrics = mine_info.pop("episode_metrics", None), their_info.pop("episode_metrics", None)
        assert mine_info == their_info
        if mine_metrics is not None:
            mine_metrics.pop("wall_s"), their_metrics.pop("wall_s")
            assert mine_metrics == their_metrics


def test_a_merging_agent_merges_and_leaves_the_road_and_an_idle_one_stops_at_the_ramps_end():
    steer_left = np.tile(np.array([0.2, 0.3], dtype=np.float32), (800, 1))
    steps = _episode("numpy", "ramp", steer_left)
    obs, _, terminated, truncated, info = steps[-1]
    metrics = info["episode_metrics"]
    assert terminated and not truncated and metrics["left_road"]
    assert metrics["merged"] and 0 < metrics["time_to_merge_s"] < 60
    assert obs.shape == (4 + 4 + 4 * 5,) and obs[6] == 0.0 and obs[7] == 1.0  # merged: not on the ramp

    idle = _episode("numpy", "ramp", np.zeros((400, 2), dtype=np.float32))
    first, last = idle[0], idle[-1][0]
    assert first[6] == 1.0 and first[4] * 10.2 == pytest.approx(-3.0)  # on the ramp, its lower boundary
    assert not idle[-1][2]  # it did not leave: it stopped at the ramp's end
    assert last[1] * 25.0 < 1.0  # vx (scaled by 25 m/s) near 0

    main = _episode("numpy", "main", np.zeros((800, 2), dtype=np.float32))
    metrics = main[-1][4]["episode_metrics"]
    assert metrics["left_road"] and not metrics["merged"] and np.isnan(metrics["time_to_merge_s"])


NEAR_THE_END = {**ONRAMP, "sim": {"episode_steps": 200},
                "road": {"kind": "onramp", "onramp": {"agent_start": "main", "agent_main_start_m": 1800.0}}}


def _several(k: int) -> dict:
    return {**NEAR_THE_END, "scenario": {"density_veh_per_km": 20, "agents": k}}


def test_agents_leave_the_on_ramp_one_by_one_as_pettingzoo_says():
    """Several agents near the road's end: each is done when it leaves (terminated), drops out of ``agents``
    and off the road, while the others go on; PettingZoo's API test agrees."""
    parallel_api_test(parallel_env(_several(3)), num_cycles=300)
    env = parallel_env(_several(3))
    env.reset(seed=2)
    finished: dict[str, int] = {}
    speeds = {"agent": 1.0, "agent1": 0.0, "agent2": -0.5}  # they leave at different steps
    while env.agents:
        _, _, terminations, truncations, infos = env.step({n: np.array([speeds[n], 0.0]) for n in env.agents})
        for name in terminations:
            if terminations[name] or truncations[name]:
                finished[name] = env.sim.steps
                metrics = infos[name]["episode_metrics"]
                assert metrics["left_road"] == terminations[name]
                assert name not in env.agents and name not in env.sim.current()[0].ids
    assert set(finished) == {"agent", "agent1", "agent2"} and len(set(finished.values())) > 1
    assert finished["agent"] <= finished["agent1"] <= finished["agent2"]
    env.close()
    with pytest.raises(ConfigError, match="do not fit"):
        parallel_env({**ONRAMP, "scenario": {"density_veh_per_km": 20, "agents": 60}}).reset(seed=0)


def test_shared_policy_training_and_evaluation_on_the_on_ramp(tmp_path):
    run = tmp_path / "run"
    res = lanefree("train", "--scenario", "onramp", "--agents", "3", "--density", "20", "--episodes", "2",
                   "--episode-steps", "200", "--out", str(run), "--set", "train.actor_critic.learning_starts_steps=60",
                   "--set", "road.onramp.agent_start=main", "--set", "road.onramp.agent_main_start_m=1800")
    assert res.returncode == 0, res.stderr
    with open(run / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["episode"], r["agent"]) for r in rows] == [(e, a) for e in "12" for a in ("agent", "agent1", "agent2")]
    res = lanefree("evaluate", str(run), "--episodes", "2")
    assert res.returncode == 0, res.stderr
    with open(run / "eval" / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 6 and {r["left_road"] for r in rows} <= {"True", "False"}


def test_the_shield_keeps_a_random_policy_from_colliding_on_the_on_ramp():
    """The shield with each vehicle's own boundaries and the open road's offsets: a random policy's
    collisions on the same traffic (main road 3000 veh/h) with and without it."""
    from lanefree_sumo.config import LaneFreeConfig, merge_config
    from lanefree_sumo.experiments.runners.rollout import rollout

    road = {"kind": "onramp", "onramp": {"main_flow_veh_per_h": 3000}}
    base = merge_config(LaneFreeConfig(), {**ONRAMP, "road": road, "sim": {"episode_steps": 400}})
    plain = rollout(base, "random", 4, seed=9)
    shielded = rollout(merge_config(base, {"shield": {"enabled": True}}), "random", 4, seed=9)
    assert plain["collisions"] > 0 and shielded["shield_interventions"] > 0
    assert shielded["collisions"] == 0


def test_train_scenario_onramp_writes_the_merge_metrics(tmp_path):
    run = tmp_path / "run"
    res = lanefree("train", "--scenario", "onramp", "--density", "20", "--episodes", "2", "--episode-steps", "120",
                   "--out", str(run), "--set", "train.actor_critic.learning_starts_steps=60")
    assert res.returncode == 0, res.stderr
    with open(run / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 and {"merged", "time_to_merge_s", "left_road"} <= set(rows[0])
    res = lanefree("evaluate", str(run), "--episodes", "1", "--record")
    assert res.returncode == 0, res.stderr
    assert (run / "eval" / "trajectories" / "episode_0001.vehicles.csv").is_file()
    res = lanefree("evaluate", str(run), "--episodes", "1", "--scenario", "ring")
    assert res.returncode == 2 and "only ring-trained policies" in res.stderr and res.stderr.count("\n") == 1
    assert not (run / "eval_ring").exists()
    res = lanefree("mixed-autonomy", str(run), "--agents", "0,1", "--episodes", "1")
    assert res.returncode == 2 and "runs on the ring" in res.stderr
    res = lanefree("train", "--scenario", "onramp", "--agents", "2", "--envs", "2", "--out", str(tmp_path / "two"))
    assert res.returncode == 2 and "--envs 1" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.parametrize("kind", ["vector", "set"])
def test_a_ring_policy_is_evaluated_on_the_on_ramp_zero_shot(tmp_path, kind):
    """The variable-dimension experiment's transfer: a ring-trained policy drives on the on-ramp's main road
    with the ring's observation (no road features); the set policy sees whatever number of vehicles is there."""
    run = tmp_path / "ring"
    res = lanefree("train", "--density", "70", "--episodes", "1", "--episode-steps", "80", "--obs", kind,
                   "--out", str(run), "--set", "train.actor_critic.learning_starts_steps=40")
    assert res.returncode == 0, res.stderr
    res = lanefree("evaluate", str(run), "--episodes", "2", "--scenario", "onramp", "--density", "20")
    assert res.returncode == 0, res.stderr
    out = run / "eval_onramp_d20"
    with open(out / "episodes.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 and all(row["density"] == "20.0" for row in rows) and "left_road" in rows[0]
    saved = (out / "config.yaml").read_text()
    assert "kind: onramp" in saved and "road_features: false" in saved and "agent_start: main" in saved
