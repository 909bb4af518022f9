"""LaneFree-v0 on the real SUMO: the checkers, full episodes, actions, observations, info."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import lanefree_sumo  # noqa: F401 - registers LaneFree-v0
from lanefree_sumo.config import ConfigError
from lanefree_sumo.rl.env import LaneFreeEnv
from lanefree_sumo.rl.rewards import PRESETS, reciprocal_reward

pytestmark = pytest.mark.sumo

METRIC_COLUMNS = {
    "episode", "steps", "return", "collisions", "collision_steps", "background_collisions", "speed_dev_mps",
    "mean_speed_mps", "overtakes", "boundary_contacts", "mean_c_x", "mean_c_y", "mean_c_f", "mean_reward",
    "density", "seed", "reward_preset", "wall_s",
}


@pytest.fixture
def make():
    envs = []

    def factory(config=None, registered=False):
        config = {"backend": "libsumo", **(config or {})}  # these tests drive the real SUMO
        env = gym.make("LaneFree-v0", config=config) if registered else LaneFreeEnv(config)
        envs.append(env)
        return env

    yield factory
    for env in envs:
        env.close()


@pytest.mark.parametrize(
    "obs_kind,action_kind",
    [("vector", "continuous"), ("vector", "discrete"), ("set", "continuous"), ("set", "discrete")],
)
def test_gymnasium_and_sb3_checkers_pass(make, obs_kind, action_kind):
    config = {"observation": {"kind": obs_kind}, "action": {"kind": action_kind}}
    env = make(config, registered=True)
    gym_check_env(env.unwrapped, skip_render_check=True)
    env.close()
    sb3_check_env(make(config), warn=True)


def test_random_policy_runs_full_episodes_at_every_density(make):
    for density in (70, 90, 120):
        env = make({"backend": "libsumo", "scenario": {"density_veh_per_km": density}})
        obs, _ = env.reset(seed=density)
        assert env.sim.state.n == round(density / 2) + 1
        steps, collided_steps, info = 0, 0, {}
        done = False
        while not done:
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            assert env.observation_space.contains(obs)
            collided_steps += info["collided"]
            # the reward is exactly the paper's Eq. 16 of the reported terms
            w = PRESETS[env.cfg.reward.preset]
            assert reward == pytest.approx(
                reciprocal_reward(info["c_x"], info["c_y"], info["c_f"], info["collided"], info["overtook"],
                                  w.w_x, w.w_y, w.w_f)
            )
            steps += 1
            done = terminated or truncated
        assert steps == 800 and truncated and not terminated
        metrics = info["episode_metrics"]
        assert METRIC_COLUMNS <= set(metrics)
        assert metrics["steps"] == 800 and metrics["density"] == density
        assert metrics["collision_steps"] == collided_steps
        assert metrics["collisions"] <= collided_steps
        env.close()  # libsumo runs one simulation per process


def test_reset_with_seed_is_reproducible(make):
    env = make()
    runs = []
    for _ in range(2):
        obs, _ = env.reset(seed=5)
        trace = [obs]
        for k in range(60):
            obs, reward, *_ = env.step(np.array([np.sin(k / 7), np.cos(k / 5)]))
            trace.append(np.append(obs, reward))
        runs.append(np.concatenate(trace))
    assert np.array_equal(runs[0], runs[1])
    other, _ = env.reset(seed=6)
    assert not np.array_equal(other, runs[0][: len(other)])


def test_continuous_action_mapping_and_clipping(make):
    env = make()
    f = env.action_to_acceleration
    assert f([0.0, 0.0]) == (0.0, 0.0)
    assert f([1.0, 1.0]) == (2.0, pytest.approx(1.8))
    assert f([-1.0, -1.0]) == (-4.5, pytest.approx(-1.8))
    assert f([0.5, 0.0])[0] == 1.0 and f([-0.5, 0.0])[0] == -2.25
    assert f([7.0, -3.0]) == f([1.0, -1.0])  # outside the box: clipped


def test_discrete_actions_follow_the_spec_table(make):
    env = make({"action": {"kind": "discrete"}})
    table = [env.action_to_acceleration(k) for k in range(9)]
    assert table == [(0, 0), (2, 0), (-2, 0), (0, 1), (0, -1), (2, 1), (-2, 1), (2, -1), (-2, -1)]


@pytest.mark.parametrize("bad", [[np.nan, 0.0], [0.0, np.inf]])
def test_non_finite_action_is_a_clear_error(make, bad):
    env = make()
    env.reset(seed=0)
    env.step(np.zeros(2))
    with pytest.raises(ValueError, match="at step 2 of episode 1 is not finite"):
        env.step(np.array(bad))


def test_raw_observation_matches_the_simulation_and_uses_placeholders(make):
    env = make({"observation": {"scale": False, "range_m": 0.5}})
    obs, _ = env.reset(seed=2)
    state, a = env.sim.state, env.unwrapped._agent
    assert obs[:4] == pytest.approx([state.y[a], state.vx[a], state.vy[a], 20.0], abs=1e-5)
    # no vehicle within 0.5 m: every neighbour slot is the placeholder far ahead at the agent's speed
    rows = obs[4:].reshape(5, 4)
    assert np.allclose(rows, [[0.5, 0.0, state.vx[a], state.vy[a]]] * 5, atol=1e-5)


def test_vector_observation_is_scaled_and_nearest_first(make):
    env = make()
    obs, _ = env.reset(seed=3)
    assert np.abs(obs).max() <= 1.5  # O(1)
    rows = obs[4:].reshape(5, 4)
    dist = np.hypot(rows[:, 0] * 80.0, rows[:, 1] * 10.2)
    assert np.all(np.diff(dist) >= -1e-4)


def test_set_observation_lists_everyone_in_range(make):
    env = make({"observation": {"kind": "set", "max_rows": 40}})
    obs, _ = env.reset(seed=4)
    dx = env.sim.offsets[0][env._agent]
    in_range = int((np.abs(dx) <= 80.0).sum()) - 1
    others = obs["others"]
    assert others[:, 4].sum() == in_range
    assert np.all(others[in_range:] == 0.0)


def test_config_errors_name_the_valid_choices():
    with pytest.raises(ConfigError, match="valid keys here"):
        LaneFreeEnv({"reward": {"presett": "x"}})
    with pytest.raises(ConfigError, match="valid: collision, overtake_collision"):
        LaneFreeEnv({"reward": {"preset": "speed"}})
    with pytest.raises(ConfigError, match="valid: vector, set"):
        LaneFreeEnv({"observation": {"kind": "image"}})


def test_collision_can_terminate_when_asked(make):
    env = make({"episode": {"terminate_on_collision": True}, "scenario": {"density_veh_per_km": 120}})
    env.reset(seed=1)
    rng = np.random.default_rng(0)
    for _ in range(800):
        # full throttle with random lateral jerks: runs into the traffic ahead
        _, reward, terminated, truncated, info = env.step(np.array([1.0, rng.uniform(-1, 1)]))
        if terminated or truncated:
            break
    assert terminated and info["collided"] and not truncated
    assert info["collision_events"] == 1 and reward < 0
    assert info["episode_metrics"]["collisions"] == 1


def test_set_encoder_trains_on_the_real_env(make):
    from stable_baselines3 import DQN

    from lanefree_sumo.rl.encoder import SetFeaturesExtractor

    env = make({"observation": {"kind": "set"}, "action": {"kind": "discrete"}})
    model = DQN("MultiInputPolicy", env, learning_starts=50, buffer_size=500, batch_size=16, seed=0,
                policy_kwargs={"features_extractor_class": SetFeaturesExtractor, "net_arch": [32]})
    model.learn(total_timesteps=150)
    obs, _ = env.reset(seed=9)
    action, _ = model.predict(obs, deterministic=True)
    assert env.action_space.contains(int(action))


def test_agent_speed_is_capped(make):
    env = make({"scenario": {"agent_max_speed_mps": 25.0}})
    env.reset(seed=0)
    top = 0.0
    for _ in range(80):  # 20 s of full throttle: would reach 18 + 40 m/s without the cap
        env.step(np.array([1.0, 0.0]))
        top = max(top, float(env.sim.state.vx[env._agent]))
    assert top == pytest.approx(25.0)


@pytest.mark.parametrize("config,named", [
    ({"reward": 3}, "'reward' is a section"),
    ({"observation": {"range_m": -5}}, "observation.range_m"),
    ({"observation": {"n_neighbours": -1}}, "observation.n_neighbours"),
    ({"observation": {"max_rows": 0}}, "observation.max_rows"),
    ({"observation": {"speed_scale_mps": 0}}, "observation.speed_scale_mps"),
    ({"scenario": {"agent_bounds": {"ax_max": -1}}}, "scenario.agent_bounds.ax_max"),
])
def test_the_python_api_validates_the_config_by_key(config, named):
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        gym.make("LaneFree-v0", config={**config, "backend": "numpy"})


def test_a_discrete_action_must_be_a_whole_number_in_range():
    env = gym.make("LaneFree-v0", config={"backend": "numpy", "action": {"kind": "discrete"}})
    env.reset(seed=0)
    for bad in (9, -1, 2.5):
        with pytest.raises(ValueError, match="one whole number 0 … 8"):
            env.step(bad)
    env.step(np.int64(3))  # numpy integers are fine
    env.close()
