"""The multi-agent ring: PettingZoo's own API and seed tests, k = 1 against LaneFree-v0, collisions between
agents, the shared-policy VecEnv under SB3's checker and training."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from lanefree_sumo.config import ConfigError
from lanefree_sumo.rl.env import LaneFreeEnv
from lanefree_sumo.rl.multi_agent import LaneFreeParallelEnv, SharedPolicyVecEnv, parallel_env

SHORT = {"sim": {"episode_steps": 40}, "backend": "numpy"}


def _config(agents: int, **extra) -> dict:
    return {**SHORT, "scenario": {"agents": agents, "density_veh_per_km": 70}, **extra}


@pytest.mark.parametrize("kind", ["vector", "set"])
def test_pettingzoo_parallel_api_test_passes(kind):
    env = parallel_env(_config(4, observation={"kind": kind}))
    parallel_api_test(env, num_cycles=100)  # 100 cycles > 40 steps: truncation and removal happen
    assert env.agents == []
    env.close()


def test_pettingzoo_parallel_seed_test_passes():
    parallel_seed_test(lambda: parallel_env(_config(3)), num_cycles=60)


def test_discrete_actions_and_the_agents_rows():
    env = parallel_env(_config(3, action={"kind": "discrete"}))
    obs, infos = env.reset(seed=5)
    assert env.agents == ["agent", "agent1", "agent2"]
    state = env.sim.current()[0]
    assert state.ids[-3:] == ["agent", "agent1", "agent2"] and not state.controlled[-3:].any()
    assert state.controlled[:-3].all() and state.n == 35 + 3  # the agents come on top of 70 veh/km on 500 m
    _, rewards, _, _, infos = env.step({name: 1 for name in env.agents})  # +ax for everyone
    assert all(infos[name]["ax"] > 0 for name in env.agents)
    assert set(rewards) == set(env.agents)
    env.close()


def _episodes(env, multi: bool, seeds, actions) -> list:
    """Every step's (observation, reward, terminated, truncated, info) of ``env`` for the given seeds and
    actions; the multi-agent env's agent 'agent' unwrapped to LaneFree-v0's shapes."""
    steps = []
    try:
        for seed, episode_actions in zip(seeds, actions):
            obs, info = env.reset(seed=seed)
            steps.append((obs["agent"], info["agent"]) if multi else (obs, info))
            for action in episode_actions:
                out = env.step({"agent": action} if multi else action)
                steps.append(tuple(part["agent"] for part in out) if multi else out)
            if multi:
                assert env.agents == []
    finally:
        env.close()
    return steps


@pytest.mark.parametrize("backend", ["numpy", pytest.param("libsumo", marks=pytest.mark.sumo)])
def test_one_agent_gives_lanefree_v0s_episodes(backend):
    """Same seed, same actions: the same observations, rewards, flags and infos, step by step (shield on,
    so its per-agent path is compared too)."""
    config = {"sim": {"episode_steps": 60}, "backend": backend, "scenario": {"density_veh_per_km": 90},
              "shield": {"enabled": True}}
    actions = np.random.default_rng(0).uniform(-1, 1, (2, 60, 2)).astype(np.float32)
    single = _episodes(LaneFreeEnv(config), False, (11, 12), actions)
    multi = _episodes(parallel_env(config), True, (11, 12), actions)
    assert len(single) == len(multi) == 2 * 61
    ends = 0
    for got, want in zip(multi, single):
        assert len(got) == len(want)
        assert np.array_equal(got[0], want[0])
        assert got[1:-1] == want[1:-1]
        info, expected = dict(got[-1]), dict(want[-1])
        metrics, expected_metrics = info.pop("episode_metrics", None), expected.pop("episode_metrics", None)
        assert info == expected
        if expected_metrics is not None:
            ends += 1
            metrics, expected_metrics = dict(metrics), dict(expected_metrics)
            metrics.pop("wall_s"), expected_metrics.pop("wall_s")
            assert metrics.pop("agent") == "agent" and metrics.pop("agent_collisions") == 0
            assert metrics == expected_metrics
    assert ends == 2


def test_collisions_between_agents_are_counted_apart():
    """Two agents steered into each other: each counts the collision, also as one with an agent; the
    background-only count does not include it."""
    env = parallel_env(_config(2, scenario={"agents": 2, "density_veh_per_km": 2}))
    env.reset(seed=0)
    state = env.sim.current()[0]
    a, b = env.agent_rows
    # put the two agents side by side, 0.5 m apart laterally, same speed, and steer them together
    state.x[b] = state.x[a]
    state.y[a], state.y[b] = 4.0, 6.5
    env.sim.place(state)
    for _ in range(40):
        _, _, _, _, infos = env.step({"agent": np.array([0.0, 1.0]), "agent1": np.array([0.0, -1.0])})
    for name in ("agent", "agent1"):
        metrics = infos[name]["episode_metrics"]
        assert metrics["collisions"] >= 1
        assert metrics["agent_collisions"] == metrics["collisions"]
        assert metrics["background_collisions"] == 0
    env.close()


def test_bad_calls_get_clear_errors():
    env = parallel_env(_config(2))
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})
    env.reset(seed=1)
    with pytest.raises(ValueError, match="missing"):
        env.step({"agent": np.zeros(2)})
    with pytest.raises(ValueError, match="not live"):
        env.step({"agent": np.zeros(2), "agent1": np.zeros(2), "agent7": np.zeros(2)})
    with pytest.raises(ValueError, match="not finite"):
        env.step({"agent": np.array([np.nan, 0.0]), "agent1": np.zeros(2)})
    env.close()
    with pytest.raises(ConfigError, match="agents"):
        LaneFreeEnv({"scenario": {"agents": 2}})
    with pytest.raises(ConfigError, match="scenario.agents"):
        parallel_env({"scenario": {"agents": 0}})
    with pytest.raises(ConfigError, match="does not fit"):
        parallel_env({"scenario": {"agents": 60, "density_veh_per_km": 400}, "backend": "numpy"}).reset(seed=0)


def test_shared_policy_vec_env_passes_sb3s_checks_and_resets_with_the_schedule():
    from stable_baselines3.common.vec_env import VecEnv

    env = LaneFreeParallelEnv(_config(3))
    seeds = []
    vec = SharedPolicyVecEnv(env, seeds=lambda episode: seeds.append(episode) or 1000 + episode, first_episode=4)
    assert isinstance(vec, VecEnv) and vec.num_envs == 3
    obs = vec.reset()
    assert obs.shape == (3, *vec.observation_space.shape) and env.episode_seed == 1004
    for _ in range(40):
        obs, rewards, dones, infos = vec.step(np.zeros((3, 2), dtype=np.float32))
        assert rewards.shape == (3,) and dones.shape == (3,)
    assert dones.all() and seeds == [4, 5] and env.episode_seed == 1005
    for info in infos:
        assert info["TimeLimit.truncated"] and info["episode"]["l"] == 40
        assert info["terminal_observation"].shape == vec.observation_space.shape
        assert info["episode_metrics"]["agent"] in ("agent", "agent1", "agent2")
    vec.close()
