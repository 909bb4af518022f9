"""The config's one validation (config/validation.py) in this process, message by message: a section given as a
dataclass, the learner profiles, the retired keys of saved configs, the keys a saved config may lack, nullable
fields, differences between configs, densities, ``--set`` keys, YAML with a key given twice, and the order in
which a verb layers its config."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.config.validation import (
    config_differences,
    config_to_dict,
    drop_retired,
    layered_config,
    load_yaml,
    missing_keys,
    nested_overrides,
    validate_config,
    validate_density,
)
from lanefree_sumo.errors import ConfigError

BASE = LaneFreeConfig()


def _refused(overrides: dict) -> str:
    with pytest.raises(ConfigError) as caught:
        merge_config(BASE, overrides)
    return str(caught.value)


def test_a_section_given_as_a_dataclass_is_validated_field_by_field_with_its_dotted_names() -> None:
    train = BASE.train
    assert _refused({"train": dataclasses.replace(train, device="gpu")}) == \
        "config 'train.device' = 'gpu' is not allowed; valid: cpu, torch-cpu, cuda"
    assert _refused({"train": dataclasses.replace(train, checkpoint_every_episodes=0)}) == \
        "config 'train.checkpoint_every_episodes' = 0 is out of range; allowed 1 … 10000000"
    deep = dataclasses.replace(train, dqn=dataclasses.replace(train.dqn, loss="l1"))
    assert _refused({"train": deep}) == "config 'train.dqn.loss' = 'l1' is not allowed; valid: huber, squared"
    nullable = dataclasses.replace(train, dqn=dataclasses.replace(train.dqn, max_grad_norm="big"))
    assert _refused({"train": nullable}) == \
        "config 'train.dqn.max_grad_norm' must be a finite number, got 'big' (or null)"
    assert _refused({"train": {"dqn": {"max_grad_norm": 0.0}}}) == \
        "config 'train.dqn.max_grad_norm' = 0.0 is out of range; allowed 1e-09 … 1e+09"
    assert merge_config(BASE, {"train": {"dqn": {"max_grad_norm": None}}}).train.dqn.max_grad_norm is None
    kept = dataclasses.replace(train, episodes=7)
    assert merge_config(BASE, {"train": kept}).train == kept
    assert validate_config(BASE) is BASE
    with pytest.raises(ConfigError, match=r"^config 'seed' must be a whole number, got 1.5$"):
        validate_config(dataclasses.replace(BASE, seed=1.5))


def test_a_learner_profile_is_one_of_its_names() -> None:
    assert _refused({"train": {"profile": "keras"}}) == \
        "config 'train.profile' = 'keras' is not allowed; valid: sb3, kerasrl"
    assert _refused({"train": {"profile": 3}}) == "config 'train.profile' = 3 is not allowed; valid: sb3, kerasrl"
    assert merge_config(BASE, {"train": {"profile": "kerasrl"}}).train.dqn.loss == "squared"


def test_a_saved_config_loses_its_retired_keys_and_only_those() -> None:
    saved = {"seed": 1, "train": {"fast_learner": True, "episodes": 3, "lean_loop": False}, "reward": {"x": 1}}
    kept, dropped = drop_retired(saved)
    assert kept == {"seed": 1, "train": {"episodes": 3}, "reward": {"x": 1}}
    assert dropped == ["train.fast_learner", "train.lean_loop"]
    assert saved["train"] == {"fast_learner": True, "episodes": 3, "lean_loop": False}  # the input is left alone
    assert drop_retired({"train": 5}) == ({"train": 5}, []) and drop_retired({}) == ({}, [])
    assert drop_retired({"train": {"episodes": 3}}) == ({"train": {"episodes": 3}}, [])


def test_the_keys_a_saved_config_lacks_are_named_and_a_value_is_not_a_section() -> None:
    whole = config_to_dict(BASE)
    assert missing_keys(BASE, whole) == []
    cut = {**whole, "train": {k: v for k, v in whole["train"].items() if k not in ("episodes", "dqn")}}
    del cut["seed"]
    assert missing_keys(BASE, cut) == ["train.episodes", "train.dqn", "seed"]  # in the schema's order
    odd = {**whole, "seed": {"a": 1}}  # a value where a leaf is: present, not read as a section
    assert missing_keys(BASE, odd) == []
    added_later = {**whole, "train": {k: v for k, v in whole["train"].items() if k != "device"}}
    assert missing_keys(BASE, added_later) == []


def test_config_to_dict_turns_tuples_and_lists_into_lists_all_the_way_down() -> None:
    @dataclass
    class Nested:
        pairs: list = field(default_factory=lambda: [(1, 2), [3, (4, 5)]])
        table: dict = field(default_factory=lambda: {"a": (6,)})

    assert config_to_dict(Nested()) == {"pairs": [[1, 2], [3, [4, 5]]], "table": {"a": [6]}}


def test_the_differences_between_two_configs_are_dotted_keys_minus_what_is_ignored() -> None:
    other = merge_config(BASE, {"seed": 4, "reward": {"overtake_reward": 0.5}, "train": {"episodes": 9,
                                                                                   "dqn": {"loss": "squared"}}})
    assert config_differences(other, BASE) == {"seed": 4, "reward.overtake_reward": 0.5, "train.episodes": 9,
                                               "train.dqn.loss": "squared"}
    assert config_differences(other, BASE, ignore=("train.dqn", "seed")) == {"reward.overtake_reward": 0.5,
                                                                             "train.episodes": 9}
    assert config_differences(other, BASE, ignore=("train",)) == {"seed": 4, "reward.overtake_reward": 0.5}
    assert config_differences(other, BASE, ignore=("train.e",)) == {  # a prefix of a name is not its section
        "seed": 4, "reward.overtake_reward": 0.5, "train.episodes": 9, "train.dqn.loss": "squared"}
    assert config_differences(BASE, BASE) == {}


@pytest.mark.parametrize("value", [0, -1, 0.0, math.inf, math.nan, "-3"])
def test_a_density_that_is_not_positive_and_finite_is_refused(value: object) -> None:
    with pytest.raises(ConfigError) as caught:
        validate_density(value)
    assert str(caught.value) == f"density must be a positive finite number in veh/km, got {value!r}"


def test_a_density_is_a_number() -> None:
    assert validate_density("0.5") == 0.5 and validate_density(90) == 90.0
    with pytest.raises(ConfigError) as caught:
        validate_density("many")
    assert str(caught.value) == "density must be a number in veh/km, got 'many'"
    with pytest.raises(ConfigError, match=r"^density must be a number in veh/km, got None$"):
        validate_density(None)


def test_set_keys_nest_and_a_key_below_a_value_is_refused() -> None:
    assert nested_overrides([("reward.k", 1), ("train.dqn.loss", "x"), ("reward.k", 2)]) == {
        "reward": {"k": 2}, "train": {"dqn": {"loss": "x"}}}
    with pytest.raises(ConfigError) as caught:
        nested_overrides([("reward", 1), ("reward.k", 2)])
    assert str(caught.value) == "config key 'reward.k' goes below 'reward', which is set to a value"


def test_yaml_with_a_key_given_twice_names_both_lines() -> None:
    assert load_yaml("a: 1\nb: [1, 2]\nc: {d: 3}\n", "f.yaml") == {"a": 1, "b": [1, 2], "c": {"d": 3}}
    with pytest.raises(ConfigError) as caught:
        load_yaml("a: 1\nb: 2\na: 3\n", "f.yaml")
    assert str(caught.value) == "f.yaml: key 'a' is given twice (lines 1 and 3); give each key once"
    with pytest.raises(ConfigError) as caught:
        load_yaml("train:\n  episodes: 1\n\n  episodes: 2\n", "g.yaml")
    assert str(caught.value) == "g.yaml: key 'episodes' is given twice (lines 2 and 4); give each key once"


def test_a_verbs_config_is_the_file_then_its_options_then_each_set(tmp_path: Path) -> None:
    file = tmp_path / "c.yaml"
    file.write_text("seed: 5\ntrain:\n  episodes: 2\n  checkpoint_every_episodes: 2\n")
    cfg = layered_config(BASE, file, [{"train": {"episodes": 3}}, {}], [("train.checkpoint_every_episodes", 3)])
    assert (cfg.seed, cfg.train.episodes, cfg.train.checkpoint_every_episodes) == (5, 3, 3)
    assert layered_config(BASE, None, [], []) == BASE
    with pytest.raises(ConfigError, match="'train.episodes' = 0 is out of range"):
        layered_config(BASE, file, [], [("train.episodes", 0)])


def test_merge_config_names_what_is_wrong() -> None:
    with pytest.raises(ConfigError) as caught:
        merge_config(BASE, [1, 2])  # type: ignore[arg-type]
    assert str(caught.value) == "config must be a mapping, got list"
    removed = _refused({"train": {"fast_learner": True}})
    assert removed.startswith("config 'train.fast_learner' was removed: every run computes its algorithm's one "
                              "update") and removed.endswith("; leave it out")
    names = ", ".join(sorted(f.name for f in dataclasses.fields(BASE.train)))
    assert _refused({"train": {"epsiodes": 3}}) == f"unknown config key 'train.epsiodes'; valid keys here: {names}"
    assert _refused({"gui": "yes"}) == "config 'gui' must be true or false, got 'yes'"


@dataclass(frozen=True)
class _Shapes:
    """A config section of its own (no schema class has each of these shapes)."""

    name: str = "a"
    pair: tuple[int, float] = (1, 2.5)
    many: tuple[int, ...] = ()
    items: list = field(default_factory=list)


def test_text_tuples_and_other_shapes_of_a_section_of_its_own() -> None:
    """A class validated for the first time (its annotations resolved then): text, a fixed-length tuple of two
    types, a tuple of any length, and a plain list left as it is."""
    fine = _Shapes(many=(1, 2, 3), items=[1, "x"])
    assert validate_config(fine) is fine
    for shapes, message in (
            (_Shapes(name=3), "config 'name' must be text, got 3"),
            (_Shapes(pair=5), "config 'pair' must be a list, got 5"),
            (_Shapes(pair=(1,)), "config 'pair' must have 2 entries, got 1"),
            (_Shapes(pair=(1, "a")), "config 'pair[1]' must be a finite number, got 'a'"),
            (_Shapes(pair=(1.5, 2.0)), "config 'pair[0]' must be a whole number, got 1.5"),
            (_Shapes(many=(1, 2, "x")), "config 'many[2]' must be a whole number, got 'x'")):
        with pytest.raises(ConfigError) as caught:
            validate_config(shapes)
        assert str(caught.value) == message


def test_a_config_file_that_cannot_be_used_is_one_line_naming_it(tmp_path: Path) -> None:
    from lanefree_sumo.config.validation import read_config_file

    missing = tmp_path / "none.yaml"
    with pytest.raises(ConfigError) as caught:
        read_config_file(missing)
    assert str(caught.value) == f"cannot read the config file {missing}: No such file or directory"
    binary = tmp_path / "b.yaml"
    binary.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ConfigError) as caught:
        read_config_file(binary)
    assert str(caught.value) == f"{binary} is not a text (UTF-8) YAML file"
    broken = tmp_path / "broken.yaml"
    broken.write_text("train: {episodes: [1, 2\n" + "x" * 150 + ": 1\n")  # YAML's message: 215 characters
    with pytest.raises(ConfigError) as caught:
        read_config_file(broken)
    said = str(caught.value)
    assert said.startswith(f"{broken} is not valid YAML (") and said.endswith(")")
    inside = said[len(f"{broken} is not valid YAML ("):-1]
    assert len(inside) == 200 and "  " not in inside and "\n" not in inside and "flow sequence" in inside
    listed = tmp_path / "list.yaml"
    listed.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError) as caught:
        read_config_file(listed)
    assert str(caught.value) == f"{listed} must hold a mapping of config sections, not a list"
    twice = tmp_path / "twice.yaml"
    twice.write_text("seed: 1\nseed: 2\n")
    with pytest.raises(ConfigError) as caught:
        read_config_file(twice)
    assert str(caught.value) == f"{twice}: key 'seed' is given twice (lines 1 and 2); give each key once"
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert read_config_file(empty) == {}


def test_a_section_takes_a_mapping_or_its_own_class_and_a_value_takes_neither() -> None:
    names = ", ".join(f.name for f in dataclasses.fields(BASE.train))
    assert _refused({"train": 5}) == f"config 'train' is a section: give a mapping of its keys ({names}), not 5"
    assert _refused({"train": BASE.reward}) == "config 'train' is a TrainConfig section, not a RewardConfig"
    assert _refused({"seed": BASE.train}).startswith("config 'seed' must be a whole number, got TrainConfig(")
    assert _refused({"seed": [1, 2]}) == "config 'seed' must be a whole number, got [1, 2]"  # a list stays a list
