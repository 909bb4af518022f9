"""The vector entry point: K LaneFree-v0 environments as one batched world, bit for bit the single env."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.wrappers.vector import ClipAction, NormalizeObservation, RecordEpisodeStatistics

import lanefree_sumo  # noqa: F401 - registers LaneFree-v0 and its vector entry point
from lanefree_sumo.config import ConfigError
from lanefree_sumo.rl.vector_env import LaneFreeVectorEnv

SHORT = {"sim": {"episode_steps": 25}, "scenario": {"density_veh_per_km": 90}}
STEP_KEYS = ("c_x", "c_y", "c_f", "y_d", "v_d_eff", "blocked", "collided", "overtook", "reward", "overtakes",
             "collision_events", "boundary_contact", "ax", "ay", "shield_intervened", "shield_correction")


def make_vec(num_envs: int, config: dict | None = None, **kwargs) -> LaneFreeVectorEnv:
    env = gym.make_vec("LaneFree-v0", num_envs=num_envs, vectorization_mode="vector_entry_point",
                       config=SHORT if config is None else config, **kwargs)
    assert isinstance(env, LaneFreeVectorEnv)
    return env


def actions_for(space: gym.Space, rng: np.random.Generator, k: int, kind: str) -> np.ndarray:
    if kind == "discrete":
        return rng.integers(0, space.n, size=k)
    return rng.uniform(-1.2, 1.2, size=(k, 2)).astype(np.float32)  # beyond the bounds: clipped alike


def assert_obs_equal(vector_obs, k: int, single_obs) -> None:
    if isinstance(single_obs, dict):
        for key in single_obs:
            np.testing.assert_array_equal(vector_obs[key][k], single_obs[key])
    else:
        np.testing.assert_array_equal(vector_obs[k], single_obs)


@pytest.mark.parametrize("obs_kind,action_kind", [("vector", "continuous"), ("vector", "discrete"),
                                                  ("set", "continuous")])
def test_each_sub_env_is_lanefree_v0_with_its_seed_across_episode_ends(obs_kind, action_kind):
    config = {**SHORT, "observation": {"kind": obs_kind}, "action": {"kind": action_kind}}
    k = 3
    vec = make_vec(k, config)
    singles = [gym.make("LaneFree-v0", config=config) for _ in range(k)]
    assert vec.single_observation_space == singles[0].observation_space
    assert vec.single_action_space == singles[0].action_space
    obs, info = vec.reset(seed=11)
    for i, env in enumerate(singles):
        single_obs, single_info = env.reset(seed=11 + i)
        assert_obs_equal(obs, i, single_obs)
        assert info["episode_seed"][i] == single_info["episode_seed"] == 11 + i
    rng = np.random.default_rng(4)
    pending = [False] * k
    ends = resets = 0
    for t in range(2 * SHORT["sim"]["episode_steps"] + 5):
        act = actions_for(singles[0].action_space, rng, k, action_kind)
        obs, reward, terminated, truncated, info = vec.step(act)
        for i, env in enumerate(singles):
            if pending[i]:  # NEXT_STEP: this step is the next episode's reset, the action unused
                single_obs, single_info = env.reset()
                pending[i] = False
                resets += 1
                assert_obs_equal(obs, i, single_obs)
                assert (reward[i], terminated[i], truncated[i]) == (0.0, False, False)
                assert info["_episode_seed"][i] and info["episode_seed"][i] == single_info["episode_seed"]
                assert not info["_c_x"][i]
                continue
            single_obs, single_reward, single_term, single_trunc, single_info = env.step(act[i])
            assert_obs_equal(obs, i, single_obs)
            assert reward[i] == single_reward, (t, i)
            assert (terminated[i], truncated[i]) == (single_term, single_trunc)
            for key in STEP_KEYS:
                assert info[f"_{key}"][i] and info[key][i] == single_info[key], (t, i, key)
                assert info[key].dtype == np.asarray(single_info[key]).dtype, key
            if single_term or single_trunc:
                ends += 1
                pending[i] = True
                assert info["episode_metrics"]["_episode"][i]
                for key, value in single_info["episode_metrics"].items():
                    if key != "wall_s":
                        assert info["episode_metrics"][key][i] == value, (key, i)
            else:
                assert "episode_metrics" not in info or not info["episode_metrics"]["_episode"][i]
    assert ends == 2 * k and resets == 2 * k
    vec.close()


def test_seed_lists_partial_resets_and_reproducibility():
    vec = make_vec(2)
    obs_a, info = vec.reset(seed=[7, 3])
    assert list(info["episode_seed"]) == [7, 3]
    again = make_vec(2)
    obs_b, _ = again.reset(seed=[7, 3])
    np.testing.assert_array_equal(obs_a, obs_b)
    for _ in range(5):
        step_a = vec.step(np.zeros((2, 2)))[0]
        step_b = again.step(np.zeros((2, 2)))[0]
    np.testing.assert_array_equal(step_a, step_b)
    obs, info = vec.reset(seed=[9, 9], options={"reset_mask": np.array([False, True])})
    assert list(info["_episode_seed"]) == [False, True] and info["episode_seed"][1] == 9
    np.testing.assert_array_equal(obs[0], step_a[0])  # the unmasked world goes on where it was
    fresh = make_vec(1)
    np.testing.assert_array_equal(obs[1], fresh.reset(seed=9)[0][0])


def test_gymnasium_vector_wrappers_run_on_it():
    vec = ClipAction(NormalizeObservation(RecordEpisodeStatistics(make_vec(4))))
    assert vec.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    obs, _ = vec.reset(seed=0)
    assert obs.shape == (4, 24)
    finished = 0
    for _ in range(SHORT["sim"]["episode_steps"] + 2):
        obs, reward, terminated, truncated, info = vec.step(vec.action_space.sample() * 3)
        if "episode" in info:
            finished += int(info["_episode"].sum())
            assert np.all(info["episode"]["l"][info["_episode"]] == SHORT["sim"]["episode_steps"])
    assert finished == 4
    assert np.isfinite(obs).all()


@pytest.mark.parametrize("bad,message", [
    (np.zeros((2, 2)), r"shape \(3, 2\)"),
    (np.zeros(6), r"shape \(3, 2\)"),
    (np.array([[0.0, 0.0], [np.nan, 0.0], [0.0, 0.0]]), "environment\\(s\\) 1 are not finite"),
])
def test_bad_actions_are_one_clear_error_and_step_nothing(bad, message):
    vec = make_vec(3)
    vec.reset(seed=0)
    before = vec.batch.steps
    with pytest.raises(ValueError, match=message):
        vec.step(bad)
    np.testing.assert_array_equal(vec.batch.steps, before)


def test_bad_discrete_actions_and_arguments():
    vec = make_vec(2, {**SHORT, "action": {"kind": "discrete"}})
    vec.reset(seed=0)
    with pytest.raises(ValueError, match="whole number 0 … 8"):
        vec.step(np.array([3, 9]))
    with pytest.raises(ValueError, match="one seed per environment"):
        vec.reset(seed=[1, 2, 3])
    with pytest.raises(ValueError, match="reset_mask"):
        vec.reset(options={"reset_mask": [1, 0]})
    with pytest.raises(ValueError, match="num_envs"):
        LaneFreeVectorEnv(0)
    with pytest.raises(RuntimeError, match="reset"):
        make_vec(1).step(np.zeros((1, 2)))


@pytest.mark.parametrize("config,named", [
    ({"backend": "libsumo"}, "backend 'libsumo'"),
    ({"road": {"kind": "onramp"}}, "road.kind = 'onramp'"),
    ({"scenario": {"agents": 2}}, "scenario.agents = 2"),
    ({"shield": {"enabled": True}}, "shield.enabled"),
])
def test_what_is_not_batched_is_refused_in_one_line_naming_sync(config, named):
    with pytest.raises(ConfigError, match=named) as err:
        make_vec(2, config)
    assert "vectorization_mode='sync'" in str(err.value) and "\n" not in str(err.value)


def test_frames_of_every_world():
    vec = make_vec(2, render_mode="rgb_array")
    vec.reset(seed=1)
    vec.step(np.zeros((2, 2)))
    frames = vec.render()
    assert len(frames) == 2 and frames[0].dtype == np.uint8 and frames[0].ndim == 3
    assert not np.array_equal(frames[0], frames[1])  # two seeds, two scenes


def test_the_errors_and_refusals_word_for_word():
    """Each message whole, as a user reads it (the tests above match a part)."""
    with pytest.raises(ConfigError) as err:
        make_vec(2, {"gui": True})
    assert str(err.value) == ("backend 'sumo-gui': the vector entry point runs its worlds as numpy arrays (the same "
                              "episodes as libsumo); use gymnasium.make_vec('LaneFree-v0', num_envs, "
                              "vectorization_mode='sync', config=...) for it")
    with pytest.raises(ConfigError) as err:
        make_vec(2, {"shield": {"enabled": True}})
    assert str(err.value).startswith("shield.enabled: the vector entry point has no safety shield yet; use ")
    with pytest.raises(ValueError) as err:
        make_vec(2, render_mode="human")
    assert str(err.value) == ("render_mode 'human': the vector entry point renders 'rgb_array' frames (sumo-gui, "
                              "'human', runs under vectorization_mode='sync')")
    for bad in (True, 2.0, 0, -1):
        with pytest.raises(ValueError) as err:
            LaneFreeVectorEnv(bad, SHORT)
        assert str(err.value) == f"num_envs must be a whole number ≥ 1, got {bad!r}"
    fresh = make_vec(2)
    with pytest.raises(RuntimeError) as err:
        fresh.step(np.zeros((2, 2)))
    assert str(err.value) == "call reset() before step()"
    with pytest.raises(RuntimeError) as err:
        make_vec(2, render_mode="rgb_array").render()
    assert str(err.value) == "call reset() before render()"
    with pytest.raises(ValueError) as err:
        fresh.reset(options={"reset_mask": np.array([True, False])})
    assert str(err.value) == "reset: the first reset starts every environment (reset_mask all True)"
    fresh.reset(seed=0)
    with pytest.raises(ValueError) as err:
        fresh.step(np.array([[0.0, np.inf], [0.0, 0.0]]))
    assert str(err.value) == ("step: the actions of environment(s) 0 are not finite; a diverged policy must not "
                              "drive the car")
    wide = make_vec(3)
    wide.reset(seed=0)
    with pytest.raises(ValueError, match=r"environment\(s\) 0, 2 are not finite"):
        wide.step(np.array([[np.nan, 0.0], [0.0, 0.0], [0.0, -np.inf]]))
    discrete = make_vec(2, {**SHORT, "action": {"kind": "discrete"}})
    discrete.reset(seed=0)
    with pytest.raises(ValueError) as err:
        discrete.step(np.zeros((2, 2)))
    assert str(err.value) == "step: 2 discrete actions expected (shape (2,)), got shape (2, 2)"


@pytest.mark.parametrize("actions,ok", [([0, 8], True), ([8, 8], True), ([9, 0], False), ([-1, 0], False),
                                        ([1.5, 2], False), ([2, 2.5], False), ([np.nan, 0], False)])
def test_a_discrete_action_is_a_whole_number_in_range(actions, ok):
    vec = make_vec(2, {**SHORT, "action": {"kind": "discrete"}})
    vec.reset(seed=0)
    if ok:
        vec.step(np.array(actions))
        np.testing.assert_array_equal(vec.batch.steps, [1, 1])
    else:
        with pytest.raises(ValueError, match="one whole number 0 … 8 per environment"):
            vec.step(np.array(actions))
        np.testing.assert_array_equal(vec.batch.steps, [0, 0])


def test_defaults_spaces_and_info_dtypes():
    one = LaneFreeVectorEnv(config=SHORT)
    assert one.num_envs == 1
    vec = make_vec(3)
    assert vec.observation_space == gym.vector.utils.batch_space(vec.single_observation_space, 3)
    assert vec.observation_space.shape == (3, 24) and vec.action_space.shape == (3, 2)
    assert vec.action_space == gym.vector.utils.batch_space(vec.single_action_space, 3)
    obs, info = vec.reset(options={"reset_mask": np.array([True, True, True])})  # a full mask starts them all
    assert info["episode_seed"].dtype == np.int64 and info["_episode_seed"].dtype == np.bool_
    seeds = info["episode_seed"]
    assert np.all((seeds >= 0) & (seeds < 2**31 - 1)) and len(set(seeds.tolist())) == 3  # fresh entropy, one each
    for _ in range(SHORT["sim"]["episode_steps"]):
        vec.step(np.zeros((3, 2)))
    _, reward, _, _, info = vec.step(np.zeros((3, 2)))  # NEXT_STEP: every world starts its next episode
    assert info["episode_seed"].dtype == np.int64 and info["_episode_seed"].all()
    assert len(set(info["episode_seed"].tolist())) == 3 and reward.dtype == np.float64 and not reward.any()
    _, info = vec.reset(seed=1)  # no mask: every world, the mask's dtype as gymnasium's
    assert info["_episode_seed"].dtype == np.bool_ and info["_episode_seed"].all()


def test_one_worlds_autoreset_leaves_the_others_going():
    """Two worlds out of step (world 1 restarted at step 5): world 0's episode end and restart leave world 1 where
    LaneFree-v0 with its seed would be."""
    vec = make_vec(2)
    vec.reset(seed=[4, 8])
    for _ in range(5):
        vec.step(np.zeros((2, 2)))
    vec.reset(seed=[0, 6], options={"reset_mask": np.array([False, True])})
    single = gym.make("LaneFree-v0", config=SHORT)
    single_obs, _ = single.reset(seed=6)
    for _ in range(SHORT["sim"]["episode_steps"] - 5 + 1):
        obs, _, terminated, truncated, info = vec.step(np.zeros((2, 2)))
        single_obs, _, single_term, single_trunc, _ = single.step(np.zeros(2))
        np.testing.assert_array_equal(obs[1], single_obs)
        assert not (terminated[1] or truncated[1]) and not (single_term or single_trunc)
    assert info["_episode_seed"].tolist() == [True, False]  # world 0 restarted on this step, world 1 went on


def test_a_worlds_frame_is_lanefree_v0s_frame():
    vec = make_vec(2, render_mode="rgb_array")
    singles = [gym.make("LaneFree-v0", config=SHORT, render_mode="rgb_array") for _ in range(2)]
    vec.reset(seed=[5, 6])
    for env, seed in zip(singles, (5, 6)):
        env.reset(seed=seed)
    rng = np.random.default_rng(2)
    for _ in range(12):
        act = rng.uniform(-1, 1, (2, 2))
        vec.step(act)
        for k, env in enumerate(singles):
            env.step(act[k])
    for frame, env in zip(vec.render(), singles):
        np.testing.assert_array_equal(frame, env.render())
