"""rl/env_batch.SlotBatch: K runs of several agents or environments, one row per slot, as SB3's loop steps them —
each row equal, step by step, to the VecEnv SB3's loop trains on (SharedPolicyVecEnv for the agents of one
simulation, a DummyVecEnv of LaneFree-v0 environments with their episode seeds), across episode ends that come at
different steps (agents leaving the on-ramp, episodes ended by a collision); and its arguments checked."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.errors import ConfigError
from lanefree_sumo.rl.env_batch import SlotBatch
from lanefree_sumo.rl.models import _env_factory, episode_seed, make_vec_env, training_config

ONRAMP_AGENTS = {"road": {"kind": "onramp", "onramp": {"agent_start": "main", "agent_main_start_m": 1800.0}},
                 "scenario": {"density_veh_per_km": 20, "agents": 3}, "sim": {"episode_steps": 200},
                 "train": {"algo": "ddpg"}}
"""Three agents that leave the on-ramp's main road one after another within an episode."""
COLLIDING_ENVS = {"scenario": {"density_veh_per_km": 120}, "episode": {"terminate_on_collision": True},
                  "sim": {"episode_steps": 120}, "train": {"algo": "ddpg", "envs": 3}}
"""Three environments whose episodes end at the first collision: at different steps."""


def _config(overrides: dict[str, Any], seed: int = 5) -> LaneFreeConfig:
    return training_config(merge_config(LaneFreeConfig(), {**overrides, "seed": seed}))


def _same_steps(cfg: LaneFreeConfig, steps: int) -> tuple[int, int]:
    """Step SB3's VecEnv of ``cfg`` and a SlotBatch of it with the same random actions; assert every step's rows
    equal; returns (episode ends seen, steps where only some slots ended)."""
    vec = make_vec_env(cfg) if cfg.scenario.agents > 1 else _dummy(cfg)
    slots = SlotBatch([cfg])
    rng = np.random.default_rng(0)
    try:
        assert np.array_equal(vec.reset(), slots.reset())
        ends = partial = 0
        for _ in range(steps):
            actions = rng.uniform(-1.0, 1.0, size=(slots.rows, 2)).astype(np.float32) * 3.0
            vec_obs, vec_reward, vec_done, infos = vec.step(actions)
            obs, reward, terminated, truncated, info = slots.step(actions)
            done = terminated | truncated
            assert np.array_equal(done, vec_done)
            assert np.array_equal(reward.astype(np.float32), vec_reward)
            for row in np.flatnonzero(done):  # the terminal observation, its time-limit flag and its metrics
                assert np.array_equal(obs[row], infos[row]["terminal_observation"])
                assert truncated[row] == infos[row]["TimeLimit.truncated"]
                mine, theirs = info["episode_metrics"][row], infos[row]["episode_metrics"]
                assert mine.keys() == theirs.keys()
                assert all(_same(mine[key], theirs[key]) for key in mine if key != "wall_s"), (mine, theirs)
            assert all(info["episode_metrics"][row] is None for row in np.flatnonzero(~done))
            ends += int(done.sum())
            partial += int(done.any() and not done.all())
            after = slots.reset([0]) if done.any() else obs
            assert np.array_equal(after, vec_obs)
        return ends, partial
    finally:
        vec.close()
        slots.close()


def _same(a: Any, b: Any) -> bool:
    """Equal values, NaN equal to NaN (a metric the episode did not reach)."""
    both_nan = isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b)
    return bool(both_nan or a == b)


def _dummy(cfg: LaneFreeConfig) -> Any:
    """SB3's DummyVecEnv of ``cfg.train.envs`` LaneFree-v0 environments with their episode seeds (what
    ``make_vec_env`` runs in processes)."""
    from stable_baselines3.common.vec_env import DummyVecEnv

    return DummyVecEnv([_env_factory(cfg, rank, cfg.seed, 1, False) for rank in range(cfg.train.envs)])


def test_the_agents_of_one_simulation_are_sb3s_shared_policy_vec_env_as_they_leave_the_on_ramp():
    ends, _ = _same_steps(_config(ONRAMP_AGENTS), 400)
    assert ends >= 6  # two episodes or more, each ended for all three agents


def test_several_environments_are_sb3s_vec_env_when_their_episodes_end_at_different_steps():
    ends, partial = _same_steps(_config(COLLIDING_ENVS), 300)
    assert ends >= 3 and partial >= 1


def test_each_environment_of_each_run_starts_from_its_own_episode_seed():
    from lanefree_sumo.rl.env import LaneFreeEnv

    cfgs = [_config(COLLIDING_ENVS, seed) for seed in (5, 6)]
    batch = SlotBatch(cfgs)
    first = batch.reset()
    assert first.shape[0] == 6 and batch.episode.tolist() == [1] * 6
    for k, seed in enumerate((5, 6)):
        for r in range(3):
            obs, _ = LaneFreeEnv(cfgs[k]).reset(seed=episode_seed(seed, r, 1))
            assert np.array_equal(obs, first[3 * k + r]), (k, r)
    assert len({row.tobytes() for row in first}) == 6  # six traffic seeds, six first observations
    batch.close()


def test_a_slot_batchs_bad_arguments_are_one_clear_error():
    cfg = _config(COLLIDING_ENVS)
    batch = SlotBatch([cfg, cfg])
    batch.reset()
    with pytest.raises(ValueError, match=r"one action per slot of the batch's 2 run\(s\) × 3 expected, got shape"):
        batch.step(np.zeros((2, 2), dtype=np.float32))
    for runs in ([2], [-1], [0, 0], [True]):
        with pytest.raises(ValueError, match=r"reset: runs are distinct indices 0 … 1 of this batch"):
            batch.reset(runs)
    actions = np.zeros((6, 2), dtype=np.float32)
    actions[4, 1] = np.nan
    _, reward, _, _, info = batch.step(actions)
    assert list(info["stopped"]) == [1] and "is not finite" in info["stopped"][1] and batch.stopped.tolist() == [
        False, True]
    assert reward[3:].tolist() == [0.0] * 3  # a stopped run is never stepped again
    batch.close()
    with pytest.raises(ConfigError, match="share scenario.agents and train.envs"):
        SlotBatch([cfg, _config({**COLLIDING_ENVS, "train": {"algo": "ddpg", "envs": 2}})])
    with pytest.raises(ConfigError, match="several environments do not train; the numpy backend gives"):
        SlotBatch([_config({**COLLIDING_ENVS, "train": {"algo": "ddpg", "envs": 3, "backend": "libsumo"}})])
    inside = _config({**ONRAMP_AGENTS, "train": {"algo": "ddpg", "backend": "libsumo"}})
    with pytest.raises(ConfigError, match="one run of several agents trains alone, not in a batch"):
        SlotBatch([inside, inside])
    with pytest.raises(ConfigError, match="train.device = cpu"):
        SlotBatch([cfg], device="cuda")
