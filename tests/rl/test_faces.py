"""The faces as the RL libraries meet them: frames and videos, the one-liners on the defaults, numpy-typed info,
the module-qualified id from a fresh process."""

from __future__ import annotations

import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.wrappers import RecordVideo
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize, VecVideoRecorder

import lanefree_sumo  # noqa: F401 - registers LaneFree-v0
from lanefree_sumo.rl.env import LaneFreeEnv
from lanefree_sumo.rl.multi_agent import SharedPolicyVecEnv, parallel_env
from lanefree_sumo.rl.render import AGENT

SHORT = {"sim": {"episode_steps": 12}}


def agent_pixels(frame: np.ndarray) -> int:
    return int(np.all(frame == np.array(AGENT, dtype=np.uint8), axis=-1).sum())


def test_rgb_array_frames_show_the_road_and_the_agent():
    env = gym.make("LaneFree-v0", render_mode="rgb_array", config=SHORT)
    assert env.metadata["render_fps"] == 4 and "rgb_array" in env.metadata["render_modes"]
    env.reset(seed=2)
    first = env.render()
    assert first.dtype == np.uint8 and first.ndim == 3 and first.shape[2] == 3
    assert first.shape[0] % 2 == 0 and first.shape[1] % 2 == 0
    assert agent_pixels(first) > 100  # the agent's box in the window, its dot in the overview
    for _ in range(6):
        env.step(np.array([1.0, 0.5], dtype=np.float32))
    assert not np.array_equal(env.render(), first)
    env.close()


def test_frames_of_the_on_ramp_and_of_several_agents():
    ramp = gym.make("LaneFree-v0", render_mode="rgb_array", config={"road": {"kind": "onramp"}})
    ramp.reset(seed=0)
    ring = gym.make("LaneFree-v0", render_mode="rgb_array")
    ring.reset(seed=0)
    assert ramp.render().shape[0] > ring.render().shape[0]  # the acceleration lane below the main road
    par = parallel_env({"scenario": {"agents": 3}}, render_mode="rgb_array")
    par.reset(seed=0)
    many = par.render()
    single = ring.render()
    assert agent_pixels(many) > agent_pixels(single)


def test_without_a_render_mode_nothing_is_drawn_and_a_wrong_mode_is_a_value_error():
    env = LaneFreeEnv(SHORT)
    env.reset(seed=0)
    assert env.render() is None
    with pytest.raises(ValueError, match="render_mode 'ansi' is not one of rgb_array, human"):
        LaneFreeEnv(SHORT, render_mode="ansi")
    assert LaneFreeEnv(SHORT, render_mode="human").cfg.gui  # sumo-gui shows it (not started here)


def test_record_video_writes_an_mp4(tmp_path):
    env = RecordVideo(gym.make("LaneFree-v0", render_mode="rgb_array", config=SHORT), str(tmp_path / "videos"),
                      episode_trigger=lambda episode: True, disable_logger=True)
    env.reset(seed=0)
    done = False
    while not done:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        done = terminated or truncated
    env.close()
    videos = list((tmp_path / "videos").glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 1000


def test_the_one_liners_work_with_no_config():
    sync = gym.make_vec("LaneFree-v0", num_envs=3)  # gymnasium's default, sync: three numpy worlds, one process
    obs, _ = sync.reset(seed=0)
    assert obs.shape == (3, 24)
    sync.step(sync.action_space.sample())
    sync.close()
    dummy = VecNormalize(make_vec_env("LaneFree-v0", n_envs=2, vec_env_cls=DummyVecEnv))
    assert dummy.reset().shape == (2, 24)
    dummy.step(np.zeros((2, 2)))
    dummy.close()


def test_sb3_subprocesses_and_its_video_recorder(tmp_path):
    # worker processes start fresh (forkserver): the module-qualified id imports the package there
    vec = make_vec_env("lanefree_sumo:LaneFree-v0", n_envs=2, vec_env_cls=SubprocVecEnv, env_kwargs={"config": SHORT})
    assert vec.render_mode == "rgb_array"
    vec = VecVideoRecorder(vec, str(tmp_path), record_video_trigger=lambda step: step == 0, video_length=8)
    vec.reset()
    for _ in range(10):
        vec.step(np.zeros((2, 2)))
    vec.close()
    assert list(tmp_path.glob("*.mp4"))


def test_info_is_numpy_typed_with_the_same_keys_every_step():
    env = gym.make("LaneFree-v0", config=SHORT)
    _, info = env.reset(seed=0)
    assert isinstance(info["episode_seed"], np.integer)
    keys = None
    for _ in range(SHORT["sim"]["episode_steps"]):
        _, _, _, truncated, info = env.step(env.action_space.sample())
        step_keys = set(info) - {"episode_metrics"}
        keys = keys or step_keys
        assert step_keys == keys
        for key in keys:
            assert isinstance(info[key], np.generic) and hasattr(info[key], "dtype"), key
    assert truncated and "episode_metrics" in info


def test_a_process_that_never_imported_the_package_finds_it_by_module_id():
    code = ("import gymnasium as gym; env = gym.make('lanefree_sumo:LaneFree-v0'); obs, _ = env.reset(seed=0); "
            "print(obs.shape, env.unwrapped.cfg.backend)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    assert out.stdout.strip() == "(24,) numpy"


def test_shared_policy_vec_env_takes_an_int_or_a_function_of_the_episode():
    par = parallel_env({**SHORT, "scenario": {"agents": 2}})
    by_int = SharedPolicyVecEnv(par, 5)
    by_int.reset()
    assert par.episode_seed == 5
    by_int.reset()
    assert par.episode_seed == 6
    SharedPolicyVecEnv(par, lambda episode: 40 + episode).reset()
    assert par.episode_seed == 41
    with pytest.raises(TypeError, match="seeds is an int .* not str"):
        SharedPolicyVecEnv(par, "0")


@pytest.mark.sumo
def test_a_second_libsumo_env_names_the_numpy_backend():
    from lanefree_sumo.sim.backends.sumo import SumoError

    first = LaneFreeEnv({**SHORT, "backend": "libsumo"})
    first.reset(seed=0)
    try:
        with pytest.raises(SumoError, match="config=\\{'backend': 'numpy'\\}"):
            LaneFreeEnv({**SHORT, "backend": "libsumo"}).reset(seed=0)
    finally:
        first.close()
