"""The vector entry point as an SB3 VecEnv (lanefree_sumo/rl/sb3_vec_env.py): sub-environment k is environment k of
SB3's own DummyVecEnv over LaneFree-v0, bit for bit across SB3's same-step resets, and SB3's algorithms and
wrappers train on it."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3 import DQN, SAC
from stable_baselines3.common.vec_env import DummyVecEnv, VecMonitor, VecNormalize

import lanefree_sumo  # noqa: F401 - registers LaneFree-v0
from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.sb3_vec_env import BatchedVecEnv, env_infos

SHORT = {"sim": {"episode_steps": 25}, "scenario": {"density_veh_per_km": 90}}

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def assert_obs_equal(a: Any, b: Any) -> None:
    """Observations (arrays, or dicts of arrays) equal in value and dtype."""
    if isinstance(b, dict):
        assert set(a) == set(b)
        for key in b:
            assert_obs_equal(a[key], b[key])
        return
    assert a.dtype == b.dtype
    np.testing.assert_array_equal(a, b)


def assert_info_equal(a: dict[str, Any], b: dict[str, Any]) -> None:
    """One sub-environment's step info equal key by key (the episode's wall time aside)."""
    assert set(a) == set(b), set(a) ^ set(b)
    for key, value in b.items():
        if key == "terminal_observation":
            assert_obs_equal(a[key], value)
        elif key == "episode_metrics":
            assert set(a[key]) == set(value)
            assert {n: a[key][n] for n in value if n != "wall_s"} == {n: v for n, v in value.items() if n != "wall_s"}
        else:
            assert a[key] == value and type(a[key]) is type(value), (key, a[key], value)


@pytest.mark.parametrize("obs_kind,action_kind", [("vector", "continuous"), ("vector", "discrete"),
                                                  ("set", "continuous")])
def test_each_sub_env_is_dummyvecenvs_lanefree_v0_across_same_step_resets(obs_kind: str, action_kind: str) -> None:
    config = {**SHORT, "observation": {"kind": obs_kind}, "action": {"kind": action_kind}}
    k = 3
    batched = BatchedVecEnv(k, config)
    dummy = DummyVecEnv([lambda: gym.make("LaneFree-v0", config=config)] * k)
    assert (batched.observation_space, batched.action_space) == (dummy.observation_space, dummy.action_space)
    assert batched.seed(11) == dummy.seed(11) == [11, 12, 13]
    assert_obs_equal(batched.reset(), dummy.reset())
    assert batched.reset_infos == dummy.reset_infos == [{"episode_seed": 11 + i} for i in range(k)]
    rng = np.random.default_rng(4)
    ends = 0
    for _ in range(2 * SHORT["sim"]["episode_steps"] + 5):
        actions = (rng.integers(0, 9, size=k) if action_kind == "discrete"
                   else rng.uniform(-1, 1, size=(k, 2)).astype(np.float32))
        obs, reward, done, infos = batched.step(actions)
        obs_d, reward_d, done_d, infos_d = dummy.step(actions)
        assert_obs_equal(obs, obs_d)
        assert reward.dtype == reward_d.dtype == np.float32 and np.array_equal(reward, reward_d)
        assert np.array_equal(done, done_d)
        for mine, theirs in zip(infos, infos_d):
            assert_info_equal(mine, theirs)
        if done.any():
            ends += int(done.sum())
            assert batched.reset_infos == dummy.reset_infos  # the next episodes' traffic seeds
            assert all(infos[i]["TimeLimit.truncated"] for i in np.flatnonzero(done))  # 25 steps, no collision end
    assert ends == 2 * k
    batched.close()


def test_sb3_trains_and_wraps_it() -> None:
    """SAC (continuous) and DQN (discrete) learn on it under SB3's VecMonitor and VecNormalize; VecMonitor reports
    every ended episode; a model predicts one action per sub-environment."""
    vec = VecNormalize(VecMonitor(BatchedVecEnv(2, SHORT)))
    sac = SAC("MlpPolicy", vec, learning_starts=20, batch_size=16, buffer_size=500, seed=0, device="cpu")
    sac.learn(total_timesteps=60)
    assert len(sac.ep_info_buffer) == 2 and all(info["l"] == 25 for info in sac.ep_info_buffer)  # type: ignore[union-attr]
    actions, _ = sac.predict(vec.reset(), deterministic=True)
    assert actions.shape == (2, 2)
    discrete = VecMonitor(BatchedVecEnv(2, {**SHORT, "action": {"kind": "discrete"}}))
    dqn = DQN("MlpPolicy", discrete, learning_starts=20, batch_size=16, buffer_size=500, seed=0, device="cpu")
    dqn.learn(total_timesteps=60)
    assert dqn.num_timesteps >= 60 and len(dqn.ep_info_buffer) == 2  # type: ignore[arg-type]


def test_frames_what_it_shares_and_what_it_refuses() -> None:
    vec = BatchedVecEnv(2, SHORT, render_mode="rgb_array")
    vec.reset()
    frames = vec.get_images()
    assert len(frames) == 2 and all(f is not None and f.ndim == 3 and f.shape[2] == 3 for f in frames)
    assert vec.render().ndim == 3  # type: ignore[union-attr]  (SB3 tiles the frames)
    assert vec.get_attr("render_mode") == ["rgb_array", "rgb_array"]
    assert vec.env_is_wrapped(VecMonitor) == [False, False]
    with pytest.raises(AttributeError, match="share render_mode"):
        vec.get_attr("np_random")
    with pytest.raises(AttributeError, match="rows of one world"):
        vec.set_attr("render_mode", None)
    with pytest.raises(AttributeError, match="make_vec_env"):
        vec.env_method("reset")
    with pytest.raises(RuntimeError, match="step_async"):
        vec.step_wait()
    with pytest.raises(ConfigError, match="sync"):
        BatchedVecEnv(2, {"backend": "libsumo"})


def test_vector_info_becomes_one_dict_per_env() -> None:
    info = {"a": np.array([1.0, 2.0]), "_a": np.array([True, False]),
            "m": {"x": np.array([0, 7]), "_x": np.array([False, True])}, "_m": np.array([False, True])}
    assert env_infos(info, 2) == [{"a": 1.0}, {"m": {"x": 7}}]
