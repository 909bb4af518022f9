"""Every number a user can set has a range, checked before anything is written (issue: data safety)."""

from __future__ import annotations

import types
import typing
from dataclasses import fields, is_dataclass
from pathlib import Path

import pytest
import yaml

from lanefree_sumo.config import LaneFreeConfig, merge_config, validate_config
from lanefree_sumo.errors import ConfigError

from conftest import lanefree


def numeric_fields(cfg: object, path: str = "") -> list[tuple[str, object]]:
    """(dotted key, dataclass field) of every number or list of numbers in ``cfg``, sections nested."""
    found: list[tuple[str, object]] = []
    hints = typing.get_type_hints(type(cfg))
    for f in fields(cfg):  # type: ignore[arg-type]
        where = f"{path}.{f.name}" if path else f.name
        value = getattr(cfg, f.name)
        if is_dataclass(value):
            found += numeric_fields(value, where)
            continue
        kind = hints[f.name]
        args = typing.get_args(kind) if typing.get_origin(kind) in (tuple, typing.Union, types.UnionType) else (kind,)
        if any(a in (int, float) for a in args):
            found.append((where, f))
    return found


def test_every_number_of_the_config_has_a_range():
    found = numeric_fields(LaneFreeConfig())
    assert len(found) > 100
    unranged = [key for key, f in found if "range" not in f.metadata]  # type: ignore[attr-defined]
    assert not unranged, unranged
    validate_config(LaneFreeConfig())  # the defaults lie inside their ranges


@pytest.mark.parametrize("key,value", [
    ("train.torch_threads", 0), ("train.actor_critic.learning_rate", -1), ("train.actor_critic.actor_layers", [-1]),
    ("train.actor_critic.ppo_n_steps", 0), ("train.actor_critic.gamma", 5), ("train.actor_critic.tau", 2),
    ("train.actor_critic.batch_size", 0), ("train.actor_critic.buffer_size", 0),
    ("train.actor_critic.critic_layers", [64, 0]), ("train.dqn.epsilon_decay_episodes", 0),
    ("train.dqn.target_update_steps", 0), ("sim.lateral_resolution_m", 0), ("train.episodes", 0),
    ("scenario.background.color_rgb", [0, 0, 256]), ("reward.critical_exponents", [4, 4, 1e300]),
])
def test_out_of_range_values_name_the_key(key, value):
    *sections, leaf = key.split(".")
    overrides: dict = {leaf: value}
    for section in reversed(sections):
        overrides = {section: overrides}
    with pytest.raises(ConfigError, match=rf"config '{key}(\[\d\])?' = .* is out of range; allowed"):
        merge_config(LaneFreeConfig(), overrides)


def test_bad_numbers_from_the_command_line_and_a_sweep_grid_write_nothing(tmp_path: Path):
    """On the command line, in a --config file and in a sweep grid: one line naming the key, before any folder
    (or Ray) starts."""
    out = tmp_path / "out"
    res = lanefree("train", "--set", "train.torch_threads=0", "--episodes", "1", "--out", str(out))
    assert res.returncode == 2 and "'train.torch_threads' = 0 is out of range" in res.stderr, res.stderr
    assert res.stderr.count("\n") == 1
    config = tmp_path / "c.yaml"
    config.write_text(yaml.safe_dump({"train": {"dqn": {"target_update_steps": 0}}}))
    res = lanefree("train", "--algo", "dqn", "--config", str(config), "--episodes", "1", "--out", str(out))
    assert res.returncode == 2 and "'train.dqn.target_update_steps' = 0" in res.stderr and res.stderr.count("\n") == 1
    grid = tmp_path / "grid.yaml"
    grid.write_text(yaml.safe_dump({"reward_presets": ["collision"], "n_seeds": 1, "episodes": 1,
                                    "overrides": {"train": {"actor_critic": {"gamma": 5}}}}))
    res = lanefree("sweep", str(grid), "--out", str(out))
    assert res.returncode == 2 and "'train.actor_critic.gamma' = 5" in res.stderr and res.stderr.count("\n") == 1
    res = lanefree("simulate", "--scenario", "onramp", "--seconds", "1e300", "--out", str(out))
    assert res.returncode == 2 and "longer than a simulation may run" in res.stderr and res.stderr.count("\n") == 1
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["c.yaml", "grid.yaml"]


@pytest.mark.parametrize("verb", [("rollout", "--backend", "numpy"), ("evaluate", "no-such-run")])
def test_a_seed_option_outside_the_configs_range_is_one_line(verb):
    """rollout's and evaluate's --seed are seeds like the config's: one line, not gymnasium's error."""
    res = lanefree(*verb, "--episodes", "1", "--seed", "-5")
    assert res.returncode == 2 and "'seed' = -5 is out of range; allowed 0 … 2147483647" in res.stderr, res.stderr
    assert res.stderr.count("\n") == 1
