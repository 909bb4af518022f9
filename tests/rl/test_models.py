"""Training environments' episode seeds: a function of (run seed, env, episode) only (pure logic)."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from lanefree_sumo.rl.models import EpisodeSeeds, episode_seed


class Seeds(gym.Env):
    """Records the seed of every reset."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self) -> None:
        self.seen: list[int | None] = []

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        self.seen.append(seed)
        return np.zeros(1, np.float32), {}


def test_episode_seeds_depend_on_run_env_and_episode_only():
    seeds = [episode_seed(s, r, k) for s in (0, 1) for r in (0, 1) for k in range(1, 200)]
    assert all(0 <= x < 2**31 for x in seeds)
    assert len(set(seeds)) == len(seeds)  # distinct across runs, envs and episodes
    assert episode_seed(5, 0, 21) == episode_seed(5, 0, 21)


def test_a_resumed_schedule_continues_the_uninterrupted_one():
    whole, first, resumed = Seeds(), Seeds(), Seeds()
    env = EpisodeSeeds(whole, run_seed=3, rank=0, first_episode=1)
    for _ in range(6):
        env.reset(seed=123)  # SB3 passes the model's seed: the schedule decides
    env = EpisodeSeeds(first, 3, 0, 1)
    for _ in range(3):
        env.reset()
    env = EpisodeSeeds(resumed, 3, 0, 4)  # after a checkpoint at episode 3
    for _ in range(3):
        env.reset()
    assert whole.seen == first.seen + resumed.seen == [episode_seed(3, 0, k) for k in range(1, 7)]


def test_overlap_is_refused_where_it_would_silently_run_sb3s_order():
    import pytest

    from lanefree_sumo.config import ConfigError, LaneFreeConfig, merge_config
    from lanefree_sumo.rl.models import training_config

    for extra in ({"train": {"algo": "td3"}}, {"train": {"lean_loop": False}}, {"train": {"envs": 2}},
                  {"observation": {"kind": "set"}}):
        cfg = merge_config(merge_config(LaneFreeConfig(), {"train": {"overlap": True}}), extra)
        with pytest.raises(ConfigError, match="--overlap needs"):
            training_config(cfg)
    assert training_config(merge_config(LaneFreeConfig(), {"train": {"overlap": True}})).train.overlap
