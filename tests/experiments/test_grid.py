"""The grid of a sweep (experiments/sweep/grid.py), function by function, at values worked out by hand: names,
orders, merges, budgets, the manifest's form and every one-line error with its whole text. No run trains here."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from lanefree_sumo.errors import ConfigError, UsageError
from lanefree_sumo.experiments.sweep.grid import (
    BUILTIN_GRIDS,
    MAX_SEEDS,
    Cell,
    Grid,
    _merged,
    _owned,
    _subset,
    builtin_descriptions,
    builtin_grid,
    load_grid,
    make_setting,
    parse_grid,
    validate_grid,
)

CAP = {"default": {}, "cap": {"scenario.agent_max_speed_mps": 25}}
"""A variant beside the default one."""


def grid_of(**data) -> Grid:
    """The grid of a YAML mapping with one preset unless ``data`` says otherwise."""
    return parse_grid({"reward_presets": ["collision"], **data}, "g", "g.yaml")


def error_of(data) -> str:
    with pytest.raises(ConfigError) as err:
        parse_grid(data, "g", "g.yaml")
    return str(err.value)


# -- settings and cells ---------------------------------------------------------------------------

def test_a_settings_label_name_and_tables():
    plain, variant = make_setting("ddpg", "collision", 70), make_setting("dqn", "fields", "90.5", "cap")
    assert plain.density == 70.0 and isinstance(plain.density, float) and plain.variant == ""
    assert variant.density == 90.5
    assert plain.label == "ddpg / collision / d70" and variant.label == "dqn / fields / d90.5 / cap"
    assert Cell(plain, 3).name == "ddpg_collision_d70_s3" and Cell(variant, 0).name == "dqn_fields_d90.5_cap_s0"
    assert make_setting("ddpg", "collision", 70.0000004).density == 70.0  # rounded to 6 decimals
    assert make_setting("ddpg", "collision", 70.000001).density == 70.000001
    # the paper's tables that report a setting: Tables 6, 7 and 8 share DDPG with the full reward at 70 veh/km
    assert make_setting("ddpg", "fields_zones_overtake_collision", 70).tables == (6, 7, 8)
    assert make_setting("ddpg", "fields_zones_overtake_collision", 90, "cap").tables == (7,)
    assert make_setting("ddpg", "collision", 70).tables == (5,)
    assert make_setting("ddpg", "collision", 90).tables == ()
    assert make_setting("td3", "collision", 70).tables == ()


def test_cells_are_seed_major_and_each_run_config_is_overrides_then_variant_then_the_grids_keys():
    grid = grid_of(reward_presets=["collision", "fields"], seeds=[4, 2], episodes=3, variants=CAP,
                   overrides={"scenario": {"agent_max_speed_mps": 30, "agent_lateral_speed_ratio": 0.3}})
    assert [c.name for c in grid.cells()] == [
        "ddpg_collision_d70_default_s4", "ddpg_fields_d70_default_s4", "ddpg_collision_d70_cap_s4",
        "ddpg_fields_d70_cap_s4", "ddpg_collision_d70_default_s2", "ddpg_fields_d70_default_s2",
        "ddpg_collision_d70_cap_s2", "ddpg_fields_d70_cap_s2"]
    default, cap = grid.config(grid.cells()[0]), grid.config(grid.cells()[3])
    assert (default.seed, default.reward.preset, default.scenario.density_veh_per_km, default.train.algo,
            default.train.episodes) == (4, "collision", 70.0, "ddpg", 3)
    assert default.scenario.agent_max_speed_mps == 30 and cap.scenario.agent_max_speed_mps == 25  # variant wins
    assert default.scenario.agent_lateral_speed_ratio == cap.scenario.agent_lateral_speed_ratio == 0.3
    assert cap.reward.preset == "fields"
    assert grid.variant_overrides(grid.settings[2]) == {"scenario": {"agent_max_speed_mps": 25.0}}
    assert grid.variant_overrides(grid.settings[0]) == {}
    assert grid.variant_overrides(make_setting("ddpg", "collision", 70)) == {}
    # a variant name that is not the grid's has no overrides (a manifest's old setting)
    assert grid.variant_overrides(make_setting("ddpg", "collision", 70, "gone")) == {}


def test_a_variants_road_and_device_are_its_own():
    grid = grid_of(variants={"ring": {}, "ramp": {"road.kind": "onramp"}})
    assert [grid.road(s) for s in grid.settings] == ["ring", "onramp"]
    assert grid_of(overrides={"road": {"kind": "onramp"}}).road(make_setting("ddpg", "collision", 70)) == "onramp"
    assert not grid.on_cuda()
    assert grid_of(variants={"cpu": {}, "gpu": {"train.device": "cuda"}}).on_cuda()
    assert grid_of(variants={"gpu": {"train.device": "cuda"}, "cpu": {}}).on_cuda()
    assert grid_of(overrides={"train": {"device": "cuda"}}).on_cuda()


# -- budget ---------------------------------------------------------------------------------------

def test_the_budget_against_the_papers():
    paper = builtin_grid("table5")
    assert paper.episode_steps == 800
    assert paper.budget() == {"episodes": 625, "paper_episodes": 625, "seeds": 10, "paper_seeds": 10,
                              "episode_steps": 800, "paper_episode_steps": 800, "reduced": False, "notes": []}
    small = paper.with_budget(seeds=3, episodes=100, episode_steps=200)
    assert small.seeds == (0, 1, 2) and small.episodes == 100 and small.episode_steps == 200
    assert small.budget() == {"episodes": 100, "paper_episodes": 625, "seeds": 3, "paper_seeds": 10,
                              "episode_steps": 200, "paper_episode_steps": 800, "reduced": True, "notes": [
                                  "100 episodes per run instead of the paper's 625",
                                  "3 seed(s) per setting instead of the paper's 10",
                                  "episodes of 200 steps instead of the paper's 800"]}
    assert paper.overrides == {} and paper.seeds == tuple(range(10))  # with_budget copies
    # more than the paper's is noted but not reduced; one short of it on any axis is reduced
    more = paper.with_budget(seeds=11, episodes=626, episode_steps=801).budget()
    assert not more["reduced"] and len(more["notes"]) == 3
    for short in ({"seeds": 9}, {"episodes": 624}, {"episode_steps": 799}):
        assert paper.with_budget(**short).budget()["reduced"], short
    assert paper.with_budget(episodes=625, seeds=10, episode_steps=800).budget()["notes"] == []


def test_with_budget_merges_the_set_overrides_without_touching_the_grids_own():
    grid = grid_of(overrides={"sim": {"episode_steps": 40}, "train": {"checkpoint_every_episodes": 1}})
    before = grid.to_dict()
    wider = grid.with_budget(settings={"sim": {"step_s": 0.5}, "scenario": {"agent_max_speed_mps": 28}},
                             episode_steps=60)
    assert wider.overrides == {"sim": {"episode_steps": 60, "step_s": 0.5}, "train": {"checkpoint_every_episodes": 1},
                               "scenario": {"agent_max_speed_mps": 28.0}}
    assert grid.to_dict() == before and grid.overrides["sim"] == {"episode_steps": 40}
    assert wider.seeds == grid.seeds and wider.episodes == grid.episodes and wider.name == "g"
    same = grid.with_budget()
    assert same.to_dict() == before
    for seeds in (0, MAX_SEEDS + 1, 10**20):  # refused before a seed list is built
        with pytest.raises(ConfigError) as err:
            grid.with_budget(seeds=seeds)
        assert str(err.value) == f"--seeds {seeds}: a sweep trains 1 to {MAX_SEEDS} seeds per setting"
    assert grid.with_budget(seeds=MAX_SEEDS).seeds[-1] == MAX_SEEDS - 1 and grid.with_budget(seeds=1).seeds == (0,)
    with pytest.raises(ConfigError) as err:
        grid.with_budget(episodes=0)
    assert str(err.value) == "grid command line: episodes must be ≥ 1, got 0"


def test_merged_is_a_deep_copy_with_the_extra_keys_winning():
    base = {"a": {"b": 1, "c": {"d": 2}}, "e": 3}
    extra = {"a": {"c": {"f": 4}, "b": 5}, "e": {"g": 6}, "h": {"i": 7}}
    out = _merged(base, extra)
    assert out == {"a": {"b": 5, "c": {"d": 2, "f": 4}}, "e": {"g": 6}, "h": {"i": 7}}
    out["a"]["c"]["d"] = 99
    out["h"]["i"] = 99
    assert base == {"a": {"b": 1, "c": {"d": 2}}, "e": 3} and extra["h"] == {"i": 7}
    alone = _merged(base, {})  # what only the base has is copied too
    alone["a"]["c"]["d"] = 99
    assert base["a"]["c"] == {"d": 2}
    assert _merged({}, {}) == {} and _merged({"x": 1}, {}) == {"x": 1}


def test_more_seeds_adds_the_smallest_unused_ones():
    grid = grid_of(seeds=[0, 2, 5], variants=CAP, compare=["cap"], episodes=4, overrides={"sim": {"step_s": 0.5}})
    assert grid.with_more_seeds(5, "sweep S").seeds == (0, 2, 5, 1, 3)
    assert grid.with_more_seeds(3, "sweep S").seeds == (0, 2, 5)
    assert grid.with_more_seeds(4, "sweep S").to_dict() == {**grid.to_dict(), "seeds": [0, 2, 5, 1]}
    assert grid_of(seeds=[2, 5]).with_more_seeds(4, "sweep S").seeds == (2, 5, 0, 1)
    with pytest.raises(UsageError) as err:
        grid.with_more_seeds(2, "sweep S")
    assert str(err.value) == ("sweep S has 3 seeds per setting; --seeds with --resume only adds seeds "
                              "(give N ≥ 3)")
    with pytest.raises(UsageError) as err:
        grid.with_more_seeds(MAX_SEEDS + 1, "sweep S")
    assert str(err.value) == f"--seeds {MAX_SEEDS + 1}: a sweep trains 1 to {MAX_SEEDS} seeds per setting"
    assert len(grid.with_more_seeds(MAX_SEEDS, "sweep S").seeds) == MAX_SEEDS


# -- the manifest's form --------------------------------------------------------------------------

def test_to_dict_and_from_dict():
    grid = grid_of(n_seeds=2, episodes=3, variants=CAP, compare=["cap"],
                   overrides={"sim": {"episode_steps": 40}, "scenario": {"agent_bounds": {"ax_min": -3}}})
    saved = grid.to_dict()
    assert saved == {
        "name": "g",
        "settings": [{"algorithm": "ddpg", "reward_preset": "collision", "density": 70.0, "variant": "default",
                      "tables": [5]},
                     {"algorithm": "ddpg", "reward_preset": "collision", "density": 70.0, "variant": "cap",
                      "tables": [5]}],
        "seeds": [0, 1], "episodes": 3,
        "overrides": {"sim": {"episode_steps": 40}, "scenario": {"agent_bounds": {"ax_min": -3.0}}},  # normalised
        "variants": {"default": {}, "cap": {"scenario": {"agent_max_speed_mps": 25.0}}}, "compare": ["cap"]}
    loaded = Grid.from_dict(yaml.safe_load(yaml.safe_dump(saved)), "m.yaml")
    assert loaded == grid and loaded.to_dict() == saved
    plain = grid_of(densities=[90], seeds=[1])
    assert plain.to_dict() == {"name": "g", "settings": [{"algorithm": "ddpg", "reward_preset": "collision",
                                                          "density": 90.0, "tables": []}],
                               "seeds": [1], "episodes": 625, "overrides": {}}
    assert Grid.from_dict(plain.to_dict(), "m.yaml") == plain
    old = {key: value for key, value in plain.to_dict().items() if key != "overrides"}  # keys absent or null
    assert Grid.from_dict({**old, "variants": None, "compare": None}, "m.yaml") == plain


@pytest.mark.parametrize(("data", "message"), [
    ({"name": "x"}, "KeyError: 'settings'"),
    ({"name": "x", "settings": [{"algorithm": "ddpg"}], "seeds": [0], "episodes": 1}, "KeyError: 'reward_preset'"),
    ({"name": "x", "settings": [{"algorithm": "ddpg", "reward_preset": "collision", "density": "x"}], "seeds": [0],
      "episodes": 1}, "ValueError: could not convert string to float: 'x'"),
    ({"name": "x", "settings": 3, "seeds": [0], "episodes": 1}, "TypeError: 'int' object is not iterable"),
])
def test_an_unreadable_saved_grid_is_one_line(data, message):
    with pytest.raises(ConfigError) as err:
        Grid.from_dict(data, "m.yaml")
    assert str(err.value) == f"m.yaml: the grid is unreadable ({message})"


def test_a_saved_grid_is_validated_again():
    saved = grid_of().to_dict()
    with pytest.raises(ConfigError) as err:
        Grid.from_dict({**saved, "episodes": 0}, "m.yaml")
    assert str(err.value) == "grid m.yaml: episodes must be ≥ 1, got 0"


# -- built-in grids and files ---------------------------------------------------------------------

def test_built_in_grids_by_name_and_their_descriptions(tmp_path, monkeypatch):
    assert BUILTIN_GRIDS == ("paper", "table5", "table6", "table7", "table8", "varobs")
    table6 = builtin_grid("table6")
    assert table6.name == "table6" and [s.preset for s in table6.settings] == [
        "fields_zones_overtake_collision", "fields_overtake_collision", "zones_overtake_collision"]
    assert load_grid("table6") == table6
    descriptions = builtin_descriptions()
    assert list(descriptions) == list(BUILTIN_GRIDS)
    assert descriptions["table5"] == ("Table 5 of the paper (Karalakou et al. 2023): its settings, 10 seeds, "
                                      "625 episodes")
    with pytest.raises(ConfigError) as err:
        builtin_grid("table9")
    assert str(err.value) == ("unknown grid 'table9'; use one of paper, table5, table6, table7, table8, varobs or a "
                              "YAML file")
    # a file named like a built-in grid is the built-in grid only by its bare name
    monkeypatch.chdir(tmp_path)
    (tmp_path / "table6").write_text("reward_presets: [fields]\nn_seeds: 1\n")
    assert load_grid("table6") == table6
    fields = (make_setting("ddpg", "fields", 70),)
    assert load_grid("./table6").settings == load_grid(tmp_path / "table6").settings == fields


def test_a_grid_file_is_named_after_it_and_a_bad_one_is_one_line(tmp_path):
    good = tmp_path / "study.yaml"
    good.write_text("reward_presets: [fields]\nseeds: [3]\n", encoding="utf-8")
    grid = load_grid(good)
    assert grid.name == "study" and grid.seeds == (3,) and grid.settings == (make_setting("ddpg", "fields", 70),)
    assert load_grid(str(good)) == grid
    names = "paper, table5, table6, table7, table8, varobs"
    for missing in (tmp_path / "nosuch.yaml", tmp_path):
        with pytest.raises(ConfigError) as err:
            load_grid(missing)
        assert str(err.value) == f"unknown grid '{missing}': neither a built-in grid ({names}) nor a YAML file"
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ConfigError) as err:
        load_grid(binary)
    assert str(err.value) == f"{binary} is not a text (UTF-8) YAML file"  # the config files' own reader
    bad = tmp_path / "bad.yaml"
    bad.write_text("reward_presets: [fields\n" + "x" * 300 + "\n", encoding="utf-8")
    with pytest.raises(ConfigError) as err:
        load_grid(bad)
    text = str(err.value)
    assert text.startswith(f"{bad} is not valid YAML (") and text.endswith(")") and "\n" not in text
    bad.write_text("reward_presets: [nonsense]\n", encoding="utf-8")
    with pytest.raises(ConfigError) as err:
        load_grid(bad)
    assert str(err.value).startswith(f"grid {bad}: reward_presets: 'nonsense' is not a reward preset; choose from ")


def test_an_unreadable_grid_files_reason_is_on_one_line_and_at_most_200_characters(tmp_path, monkeypatch):
    path = tmp_path / "g.yaml"
    path.write_text("reward_presets: [fields]\n")

    def refuse(*args, **kwargs):
        raise OSError("first line\n   second " + "y" * 400)

    monkeypatch.setattr(Path, "read_text", refuse)
    with pytest.raises(ConfigError) as err:
        load_grid(path)
    reason = ("first line second " + "y" * 400)[:200]
    assert str(err.value) == f"cannot read the grid file {path}: {reason}"


# -- parsing --------------------------------------------------------------------------------------

def test_the_defaults_of_a_grid_file():
    grid = parse_grid({"reward_presets": "fields"}, "n", "s.yaml")  # a single value stands for a list of one
    assert grid.name == "n" and grid.settings == (make_setting("ddpg", "fields", 70),)
    assert grid.seeds == tuple(range(10)) and grid.episodes == 625 and grid.overrides == {}
    assert grid.variants == {} and grid.compare == ()
    assert grid_of(seeds=3).seeds == (3,) and grid_of(n_seeds=MAX_SEEDS).seeds[-1] == MAX_SEEDS - 1
    assert grid_of(overrides=None).overrides == {} and grid_of(episodes=1).episodes == 1
    grid = grid_of(algorithms=["ddpg", "dqn"], reward_presets=["collision", "fields"], densities=[70, 90.5])
    assert [s.label for s in grid.settings] == [
        "ddpg / collision / d70", "ddpg / collision / d90.5", "ddpg / fields / d70", "ddpg / fields / d90.5",
        "dqn / collision / d70", "dqn / collision / d90.5", "dqn / fields / d70", "dqn / fields / d90.5"]
    assert grid_of(densities="90").settings == (make_setting("ddpg", "collision", 90),)


def test_a_grid_of_tables_is_their_settings_once_each_in_the_papers_order():
    grid = parse_grid({"tables": [6, 5]}, "t", "t.yaml")
    assert [s.preset for s in grid.settings] == [
        "collision", "fields", "fields_collision", "overtake_collision", "fields_overtake_collision",
        "fields_zones_overtake_collision", "zones_overtake_collision"]
    assert parse_grid({"tables": 5}, "t", "t.yaml").settings == builtin_grid("table5").settings
    seven = parse_grid({"tables": [7]}, "t", "t.yaml")
    assert [s.density for s in seven.settings] == [70.0, 90.0, 120.0, 70.0, 90.0, 120.0]


def test_variants_are_every_setting_once_each_in_their_order():
    grid = grid_of(reward_presets=["collision", "fields"], variants={"b": None, "a": {"reward.overtake_bonus":
                                                                                      "once_per_vehicle"}})
    assert [(s.preset, s.variant) for s in grid.settings] == [("collision", "b"), ("fields", "b"),
                                                              ("collision", "a"), ("fields", "a")]
    assert grid.variants == {"b": {}, "a": {"reward": {"overtake_bonus": "once_per_vehicle"}}}
    assert grid.config(grid.cells()[2]).reward.overtake_bonus == "once_per_vehicle"
    assert grid.config(grid.cells()[0]).reward.overtake_bonus != "once_per_vehicle"
    assert grid_of(variants=CAP, compare="cap").compare == ("cap",)
    assert grid_of(variants={"default": {}, "x": {}, "y": {}}, compare=["y", "x"]).compare == ("y", "x")
    assert grid_of(variants={"x" * 40: {}}).settings[0].variant == "x" * 40
    assert grid_of(variants={"0_a": {}}).settings[0].variant == "0_a"


where = "grid g.yaml"
ALGORITHMS = "ddpg, td3, sac, ppo, dqn, ddqn, dueling, per"


@pytest.mark.parametrize(("data", "message"), [
    ([1, 2], f"{where}: expected a mapping with keys algorithms, reward_presets, densities, tables, seeds, n_seeds, "
             "episodes, overrides, variants, compare"),
    ({"reward_presets": ["collision"], "seed": 1}, f"{where}: unknown key 'seed'; allowed keys: algorithms, "
     "reward_presets, densities, tables, seeds, n_seeds, episodes, overrides, variants, compare"),
    ({"algorithms": ["ddpg"]}, f"{where}: key 'reward_presets' is missing; list the reward presets to train (or the "
     "paper's 'tables')"),
    ({"reward_presets": []}, f"{where}: reward_presets is empty; give at least one reward preset"),
    ({"reward_presets": ["collision"], "algorithms": []}, f"{where}: algorithms is empty; give at least one algorithm"),
    ({"reward_presets": ["collision"], "algorithms": ["dqnn"]},
     f"{where}: algorithms: 'dqnn' is not an algorithm; choose from {ALGORITHMS}"),
    ({"reward_presets": ["collision"], "algorithms": [3]},
     f"{where}: algorithms: 3 is not an algorithm; choose from {ALGORITHMS}"),
    ({"reward_presets": ["collision"], "algorithms": ["ddpg", "dqn", "ddpg"]},
     f"{where}: algorithms lists an algorithm twice"),
    ({"reward_presets": ["collision", "collision"]}, f"{where}: reward_presets lists a reward preset twice"),
    ({"reward_presets": ["collision"], "densities": [True]},
     f"{where}: densities: density must be a number in veh/km, got True"),
    ({"reward_presets": ["collision"], "densities": [70, "x"]},
     f"{where}: densities: density must be a number in veh/km, got 'x'"),
    ({"reward_presets": ["collision"], "densities": []},
     f"{where}: densities must list at least one density, each once"),
    ({"reward_presets": ["collision"], "densities": [70, 70.0]},
     f"{where}: densities must list at least one density, each once"),
    ({"reward_presets": ["collision"], "densities": [70, 70.0000001]},
     f"{where}: ddpg / collision / d70 and ddpg / collision / d70 would be the same run folder ddpg_collision_d70_s0; "
     "give densities that differ within 6 significant digits"),
    ({"reward_presets": ["collision"], "tables": [5]}, f"{where}: give either 'tables' or algorithms, reward_presets, "
     "densities, not both ('reward_presets' is given too)"),
    ({"tables": [5], "densities": [70], "algorithms": ["ddpg"]}, f"{where}: give either 'tables' or algorithms, "
     "reward_presets, densities, not both ('algorithms' is given too)"),
    *(({"tables": tables}, f"{where}: tables must list distinct tables of the paper (5, 6, 7, 8), got {tables!r}")
      for tables in ([4], [6, 6], [], [True], ["5"], 9)),
    ({"reward_presets": ["collision"], "seeds": [0], "n_seeds": 1},
     f"{where}: give either 'seeds' or 'n_seeds', not both"),
    *(({"reward_presets": ["collision"], "seeds": seeds},
       f"{where}: seeds must be distinct whole numbers ≥ 0, got {seeds!r}")
      for seeds in ([], [-1], [0, 0], [1, 1.0], [True], ["1"], -2)),
    *(({"reward_presets": ["collision"], "n_seeds": n},
       f"{where}: n_seeds must be a whole number from 1 to {MAX_SEEDS}, got {n!r}")
      for n in (0, MAX_SEEDS + 1, True, 2.0, "3")),
    *(({"reward_presets": ["collision"], "episodes": e}, f"{where}: episodes must be a whole number ≥ 1, got {e!r}")
      for e in (0, -1, True, 2.5, "3")),
    ({"reward_presets": ["collision"], "overrides": [1, 2]}, f"{where}: overrides must be a mapping of config keys "
     "(e.g. overrides: {sim: {episode_steps: 400}}), got [1, 2]"),
    ({"reward_presets": ["collision"], "variants": {}},
     f"{where}: variants must be a mapping of variant names to mappings of dotted config keys"),
    ({"reward_presets": ["collision"], "variants": ["a"]},
     f"{where}: variants must be a mapping of variant names to mappings of dotted config keys"),
    *(({"reward_presets": ["collision"], "variants": {name: {}}},
       f"{where}: variant name {name!r} must be 1-40 lower-case letters, digits or _")
      for name in ("Cap", "_a", "a-b", "x" * 41, "", 3)),
    ({"reward_presets": ["collision"], "variants": {"a": {1: 2}}},
     f"{where}: variants.a must be a mapping of dotted config keys to values"),
    ({"reward_presets": ["collision"], "variants": {"a": [1]}},
     f"{where}: variants.a must be a mapping of dotted config keys to values"),
    ({"reward_presets": ["collision"], "compare": ["cap"]},
     f"{where}: compare sets variants against the variant 'default'; name one in variants"),
    ({"reward_presets": ["collision"], "variants": {"cap": {}}, "compare": ["cap"]},
     f"{where}: compare sets variants against the variant 'default'; name one in variants"),
    ({"reward_presets": ["collision"], "variants": CAP, "compare": []},
     f"{where}: compare is empty; give at least one variant other than 'default'"),
    ({"reward_presets": ["collision"], "variants": CAP, "compare": ["default"]},
     f"{where}: compare: 'default' is not a variant other than 'default'; choose from cap"),
    ({"reward_presets": ["collision"], "variants": CAP, "compare": ["cap", "cap"]},
     f"{where}: compare lists a variant other than 'default' twice"),
])
def test_a_bad_grid_is_one_line_naming_what_is_wrong(data, message):
    assert error_of(data) == message


# -- validation -----------------------------------------------------------------------------------

@pytest.mark.parametrize("key", ["seed", "train.episodes", "train.algo", "reward.preset",
                                 "scenario.density_veh_per_km"])
def test_overrides_and_variants_cannot_set_what_the_grid_sets(key):
    from lanefree_sumo.config import nested_overrides

    advice = "is set by the grid itself (use algorithms, reward_presets, densities, seeds or episodes)"
    overrides = nested_overrides([(key, 1)])
    assert error_of({"reward_presets": ["collision"], "overrides": overrides}) == f"{where}: overrides.{key} {advice}"
    assert error_of({"reward_presets": ["collision"], "variants": {"default": {}, "v": {key: 1}}}) == (
        f"{where}: variants.v.{key} {advice}")


def test_owned_finds_the_grids_keys_at_any_depth_and_subset_takes_the_given_ones():
    assert _owned({"seed": 1, "train": {"algo": "x", "dqn": {"seed": 2}}, "sim": 3}) == ["seed", "train.algo"]
    assert _owned({"reward": {"preset": {"deeper": 1}}}) == ["reward.preset"]
    assert _owned({}) == [] and _owned({"scenario": {"agents": 2}}) == []
    full = {"a": {"b": 1, "c": 2, "d": {"e": 3, "f": 4}}, "g": 5, "h": {"i": 6}}
    assert _subset(full, {"a": {"b": 0, "d": {"f": 0}}, "g": 0, "h": {}}) == {"a": {"b": 1, "d": {"f": 4}}, "g": 5}
    assert _subset(full, {}) == {}


def test_validation_of_a_grid_built_in_python():
    setting = make_setting("ddpg", "collision", 70)
    cases = [
        (Grid("n", (setting,), (0,), 0), "episodes must be ≥ 1, got 0"),
        (Grid("n", (), (0,), 1), "the grid has no runs"),
        (Grid("n", (setting,), (), 1), "the grid has no runs"),
        (Grid("n", (setting,), (0,), 1, [1]), "overrides must be a mapping of config keys, got [1]"),  # type: ignore
        (Grid("n", (setting,), (0,), 1, {"scenario": {"agents": 2}}), "overrides.scenario.agents = 2: sweeps train "
         "one learning vehicle per run in this version (use lanefree train --agents K)"),
        (Grid("n", (setting,), (0,), 1, {}, {"v": {"train": {"nope": 1}}}), "variants.v: unknown config key "
         "'train.nope'; valid keys here: actor_critic, algo, backend, checkpoint_every_episodes, device, dqn, envs, "
         "episodes, profile, torch_threads"),
        (Grid("n", (setting,), (0,), 1, {"sim": {"nope": 1}}), "overrides: unknown config key 'sim.nope'; valid keys "
         "here: edge_clearance_m, edge_contact_tolerance_m, episode_steps, lateral_resolution_m, route_loops, step_s, "
         "sumo_min_lateral_speed_mps"),
        (Grid("n", (make_setting("ddpg", "collision", 1000),), (0,), 1), "ddpg / collision / d1000: density 1000 "
         "veh/km (500 vehicles) does not fit on a 500 m × 10.2 m ring; the maximum is 414 veh/km"),
        (Grid("n", (make_setting("td3", "collision", 70),), (0,), 1, {"train": {"profile": "kerasrl"}}),
         "td3 / collision / d70: train.actor_critic.warmup_actions = policy (what train.profile = kerasrl sets) is "
         "built for ddpg only; td3 takes SB3's uniform warm-up; add --set train.actor_critic.warmup_actions=uniform "
         "beside the profile"),
    ]
    for grid, message in cases:
        with pytest.raises(ConfigError) as err:
            validate_grid(grid, "here")
        assert str(err.value) == f"grid here: {message}"
    # a scenario that is not a mapping is the config's error, and one agent is the grid's own
    with pytest.raises(ConfigError, match=r"^grid here: overrides: config 'scenario' is a section"):
        validate_grid(Grid("n", (setting,), (0,), 1, {"scenario": 3}), "here")
    assert validate_grid(Grid("n", (setting,), (0,), 1, {"scenario": {"agents": 1}}), "here").overrides == {
        "scenario": {"agents": 1}}


def test_each_density_is_checked_for_fit_once_per_road(monkeypatch):
    """The fit check runs once per (density, road length), however many settings share them."""
    import lanefree_sumo.sim.spawn as spawn

    checked = []
    real = spawn.check_fits
    monkeypatch.setattr(spawn, "check_fits", lambda cfg: checked.append(
        (cfg.scenario.density_veh_per_km, cfg.road.length_m)) or real(cfg))
    grid = grid_of(algorithms=["ddpg", "dqn"], reward_presets=["collision", "fields"], densities=[70, 90],
                   variants={"ring": {}, "short": {"road.length_m": 400}})
    assert len(grid.settings) == 16
    assert sorted(checked) == [(70.0, 400.0), (70.0, 500.0), (90.0, 400.0), (90.0, 500.0)]


def test_a_grid_holds_at_most_its_bound_of_seeds():
    with pytest.raises(ConfigError) as err:
        validate_grid(Grid("n", (make_setting("ddpg", "collision", 70),), tuple(range(MAX_SEEDS + 1)), 1), "here")
    assert str(err.value) == f"grid here: {MAX_SEEDS + 1} seeds per setting; a sweep trains at most {MAX_SEEDS}"


def test_one_density_that_fits_does_not_hide_another_that_does_not():
    ok = make_setting("ddpg", "collision", 70)
    crowded = make_setting("ddpg", "fields", 400)
    assert validate_grid(Grid("n", (ok, crowded), (0,), 1), "here").settings == (ok, crowded)
    with pytest.raises(ConfigError) as err:
        validate_grid(Grid("n", (ok, make_setting("ddpg", "fields", 415)), (0,), 1), "here")
    assert str(err.value).startswith("grid here: ddpg / fields / d415: density 415 veh/km")


def test_validation_gives_the_overrides_as_the_config_normalises_them():
    grid = validate_grid(Grid("n", (make_setting("ddpg", "collision", 70),), (0,), 1,
                              {"scenario": {"agent_max_speed_mps": 25}}, {"v": {"sim": {"step_s": 1}}}), "here")
    assert grid.overrides == {"scenario": {"agent_max_speed_mps": 25.0}}
    assert isinstance(grid.overrides["scenario"]["agent_max_speed_mps"], float)
    assert grid.variants == {"v": {"sim": {"step_s": 1.0}}}
    assert isinstance(grid.variants["v"]["sim"]["step_s"], float)
    assert (grid.name, grid.seeds, grid.episodes) == ("n", (0,), 1)
