"""Each command-line option declared once: its flag and config key in one :class:`Option`, its meaning, default
and choices taken from the schema, its config override generated from it."""

from __future__ import annotations

import argparse
import ast
import typing
from pathlib import Path

import pytest

from lanefree_sumo.cli import VERBS, build_parser
from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.config.describe import field_docs
from lanefree_sumo.options import (
    RETIRED_FLAGS,
    Option,
    _plain,
    add_options,
    argument,
    config_overrides,
    schema_field,
    verb_config,
)

ROOT = Path(__file__).resolve().parent.parent
DECLARED = {name: getattr(module, "OPTIONS", ()) for name, module in VERBS.items()}


def _parse(options: tuple[Option, ...], argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_options(parser, options)
    args = parser.parse_args(argv)
    args.given = {token.split("=", 1)[0] for token in argv if token.startswith("--")}
    args.config, args.settings = None, []
    return args


@pytest.mark.parametrize("verb", sorted(name for name, options in DECLARED.items() if options))
def test_every_keyed_option_takes_its_meaning_default_and_choices_from_the_schema(verb):
    for option in DECLARED[verb]:
        if option.key is None:
            assert option.note, f"{verb} {option.flag}: an option without a key needs its help text"
            continue
        owner, annotation, default = schema_field(option.schema, option.key)
        meaning = field_docs().get((owner.__name__, option.key.rsplit(".", 1)[-1]))
        assert meaning, f"{verb} {option.flag}: the schema field {option.key} has no docstring"
        _, kwargs = argument(option)
        assert kwargs["help"].startswith(_plain(meaning).replace("%", "%%")), (verb, option.flag)
        if typing.get_origin(annotation) is typing.Literal:
            assert kwargs["choices"] == typing.get_args(annotation)
        if option.default is not None and "default" in kwargs and option.flag.startswith("--"):
            assert kwargs["default"] in (default, option.default)


def test_numbers_name_their_unit_in_help_and_in_a_bad_value():
    train = DECLARED["train"]
    episodes = next(o for o in train if o.flag == "--episodes")
    _, kwargs = argument(episodes)
    assert "default 625 episodes" in kwargs["help"]
    with pytest.raises(argparse.ArgumentTypeError, match="positive number of episodes"):
        kwargs["type"]("0")
    with pytest.raises(SystemExit):
        _parse(train, ["--envs", "0"])


def test_only_the_options_given_override_the_config():
    train = DECLARED["train"]
    assert config_overrides(_parse(train, []), train) == {}
    args = _parse(train, ["--density", "90", "--shield", "--episodes", "3"])
    assert config_overrides(args, train) == {"scenario": {"density_veh_per_km": 90.0}, "train": {
        "episodes": 3}, "shield": {"enabled": True}}
    cfg = verb_config(args, train)
    assert (cfg.scenario.density_veh_per_km, cfg.train.episodes, cfg.shield.enabled) == (90.0, 3, True)
    assert verb_config(_parse(train, []), train) == LaneFreeConfig()


def test_options_that_exclude_each_other_are_one_group():
    rollout = DECLARED["rollout"]
    with pytest.raises(SystemExit):
        _parse(rollout, ["--policy", "idle", "--run", "somewhere"])


def _flags(node: ast.expr) -> bool:
    """Whether ``node`` spells option names: ``"--x"`` or a tuple of them."""
    if isinstance(node, ast.Tuple):
        return bool(node.elts) and all(_flags(e) for e in node.elts)
    return isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value.startswith("--")


def _key_beside_flag(source: str) -> list[str]:
    """The tuples of ``source`` that pair a dotted config key with option names (``("a.b", "--x")``,
    ``("a.b", ("--x",), value)``)."""
    return [ast.unparse(node) for node in ast.walk(ast.parse(source)) if isinstance(node, ast.Tuple)
            and len(node.elts) >= 2 and isinstance(first := node.elts[0], ast.Constant)
            and isinstance(first.value, str) and "." in first.value and _flags(node.elts[1])]


def test_the_verbs_declare_no_flag_to_key_mapping_of_their_own():
    """No verb module spells a dotted config key beside a flag: the keys live in the declarations only."""
    assert _key_beside_flag('x = [("road.length_m", "--length", 1), ("train.overlap", ("--overlap", "--no-overlap"))]')\
        == ["('road.length_m', '--length', 1)", "('train.overlap', ('--overlap', '--no-overlap'))"]
    for module in VERBS.values():
        path = Path(module.__file__ or "")
        assert not _key_beside_flag(path.read_text()), path.name


def test_every_verb_is_in_the_parser_and_its_help_has_units():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert set(sub.choices) == set(VERBS)
    assert "veh/km" in sub.choices["simulate"].format_help() and "in s" in sub.choices["simulate"].format_help()
    assert "default 70 veh/km" in sub.choices["train"].format_help().replace("\n", " ").replace("  ", " ")


def test_every_verb_declares_each_of_its_options_once_as_an_option():
    """No verb adds an argument of its own: each is an :class:`Option` of its ``OPTIONS`` (``--config`` and
    ``--set`` come from :func:`~lanefree_sumo.argtypes.add_config_options`, the retired flags from
    :func:`~lanefree_sumo.options.add_retired_flags`)."""
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for name, verb in sub.choices.items():
        declared = [spelling for option in DECLARED[name] for spelling in option.names]
        assert len(declared) == len(set(declared)), name
        parsed = {spelling for action in verb._actions if not isinstance(action, argparse._HelpAction)
                  for spelling in (action.option_strings or [action.dest])}
        assert parsed - {"--config", "--set", *RETIRED_FLAGS} <= set(declared) <= parsed, name


def test_the_architecture_pages_option_table_is_the_declarations():
    from lanefree_sumo.options import option_table

    text = (ROOT / "docs" / "architecture.md").read_text()
    documented = text.split("<!-- option table -->\n", 1)[1].split("<!-- /option table -->", 1)[0]
    assert documented == option_table(DECLARED), "regenerate the table with lanefree_sumo.options.option_table"
