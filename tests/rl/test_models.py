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


def test_the_retired_keys_are_refused_as_overrides_and_dropped_from_saved_configs(tmp_path, capsys):
    """``train.fast_learner``, ``train.lean_loop``, ``train.overlap``: one line each saying what replaced it when
    given; a saved config that names them loads (one note per key and process) and equals the one without."""
    import pytest
    import yaml

    from lanefree_sumo.config import RETIRED, ConfigError, LaneFreeConfig, config_to_dict, merge_config
    from lanefree_sumo.experiments.storage import rundir
    from lanefree_sumo.experiments.storage.rundir import read_config

    assert set(RETIRED) == {"train.fast_learner", "train.lean_loop", "train.overlap"}
    for key in RETIRED:
        section, leaf = key.split(".")
        with pytest.raises(ConfigError, match=rf"config '{key}' was removed: .*; leave it out"):
            merge_config(LaneFreeConfig(), {section: {leaf: True}})
    saved = config_to_dict(LaneFreeConfig())
    saved["train"].update(fast_learner=True, lean_loop=False, overlap=True)
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "config.yaml").write_text(yaml.safe_dump(saved))
    assert read_config(tmp_path / "a") == LaneFreeConfig() and not capsys.readouterr().err  # reading: silent
    rundir._NOTED_RETIRED.clear()  # as in a fresh process
    assert read_config(tmp_path / "a", note_retired=True) == read_config(tmp_path / "b", True) == LaneFreeConfig()
    notes = capsys.readouterr().err.splitlines()
    assert [n.split("'")[1] for n in notes] == list(RETIRED)  # each key once, though both folders name them
    assert all(n.startswith("lanefree: note: ") and "is ignored now (" in n for n in notes)
