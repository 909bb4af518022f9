"""Command-line options, each declared once: :class:`Option` names its flag and the config key it sets;
the schema (:mod:`lanefree_sumo.config.schema`) gives its meaning (the field's docstring, through
:func:`~lanefree_sumo.config.describe.field_docs`), its default, and its allowed values (a ``Literal``
type: the choices; a ``range``: a positive or non-negative number). :func:`add_options` turns a verb's
declarations into its argparse arguments, :func:`config_overrides` into the config overrides of the
options given on the command line.
"""

from __future__ import annotations

import argparse
import re
import shlex
import sys
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any, get_args, get_origin

from lanefree_sumo import argtypes
from lanefree_sumo.config import RETIRED, LaneFreeConfig, layered_config, nested_overrides
from lanefree_sumo.config.describe import field_docs

_FROM_SCHEMA: Any = object()
"""The default of an option that takes its default from the schema."""


@dataclass(frozen=True)
class Option:
    """One option of one verb (or of several verbs that mean the same by it).

    ``key``: the dotted key of the field the option stands for, in ``schema`` (a config dataclass; by default
    the run's :class:`~lanefree_sumo.config.LaneFreeConfig`, whose options become config overrides). Without a
    key, ``note`` is the whole help text and the verb reads the value from the parsed arguments."""

    flag: str
    """``--name`` (or a positional's name, without dashes)."""
    key: str | None = None
    schema: type = LaneFreeConfig
    unit: str = ""
    """The value's unit, named in ``--help`` and in a bad value's one-line error (a count's: what it counts)."""
    note: str = ""
    """What the verb adds to the field's meaning (or the whole help text of an option without a key)."""
    type: Callable[[str], Any] | None = None
    """The value's parser; by default one derived from the field (a number's sign from its range)."""
    default: Any = _FROM_SCHEMA
    negatable: bool = False
    """A switch that also has ``--no-NAME``."""
    group: str = ""
    """Options of one verb with the same group exclude each other."""
    extra: Mapping[str, Any] = field(default_factory=dict)
    """Further ``add_argument`` keywords (metavar, nargs, action, dest, choices)."""

    @property
    def sets_config(self) -> bool:
        """The option overrides a key of the run's config."""
        return self.key is not None and self.schema is LaneFreeConfig

    @property
    def names(self) -> tuple[str, ...]:
        """The spellings on the command line (``--x`` and, when negatable, ``--no-x``)."""
        return (self.flag, "--no-" + self.flag[2:]) if self.negatable else (self.flag,)


def schema_field(schema: type, key: str) -> tuple[type, Any, Any]:
    """(owning dataclass, annotation, default) of the dotted ``key`` of ``schema``."""
    owner: Any = schema()
    *sections, leaf = key.split(".")
    for section in sections:
        owner = getattr(owner, section)
    if not is_dataclass(owner) or leaf not in {f.name for f in fields(owner)}:
        raise KeyError(f"{key} is not a key of {schema.__name__}")
    return type(owner), typing.get_type_hints(type(owner))[leaf], getattr(owner, leaf)


def _plain(text: str) -> str:
    """A schema docstring as help text: reST roles and literals as plain words."""
    text = re.sub(r":\w+:`~?(?:[^`<]*<)?([^`>]*)>?`", lambda m: m.group(1).split(".")[-1], text)
    return text.replace("``", "")


def _shown(value: Any, unit: str) -> str:
    """A default as ``--help`` shows it, with its unit."""
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        value = f"{value:g}"
    elif isinstance(value, tuple):
        value = "x".join(map(str, value))
    return f"{value}{unit}" if unit in ("", "%") else f"{value} {unit}"


def _number_type(kind: type, unit: str, owner: type, leaf: str) -> Callable[[str], Any]:
    """A number's parser: non-negative when the field's range starts at or below 0, else positive."""
    bounds = next(f for f in fields(owner) if f.name == leaf).metadata.get("range")
    return (argtypes.nonnegative if bounds is not None and bounds[0] <= 0 else argtypes.positive)(kind, unit)


def argument(option: Option) -> tuple[tuple[str, ...], dict[str, Any]]:
    """The ``add_argument`` names and keywords of ``option``."""
    kwargs: dict[str, Any] = {}
    help_parts = []
    default = None if option.default is _FROM_SCHEMA else option.default
    if option.key is not None:
        owner, annotation, schema_default = schema_field(option.schema, option.key)
        leaf = option.key.rsplit(".", 1)[-1]
        meaning = field_docs().get((owner.__name__, leaf), "")
        if meaning:
            help_parts.append(_plain(meaning))
        if option.default is _FROM_SCHEMA:
            default = schema_default
        if get_origin(annotation) is typing.Literal:
            kwargs["choices"] = get_args(annotation)
        elif annotation is bool:
            kwargs["action"] = argparse.BooleanOptionalAction if option.negatable else "store_true"
        elif annotation in (int, float) and option.type is None:
            kwargs["type"] = _number_type(annotation, option.unit, owner, leaf)
    if option.note:
        help_parts.append(option.note)
    if option.type is not None:
        kwargs["type"] = option.type
    if option.key is not None and option.default is _FROM_SCHEMA and default not in ("", None):
        help_parts.append(f"default {_shown(default, option.unit)}")
    kwargs.update(option.extra)
    kwargs["default"] = False if kwargs.get("action") == "store_true" and default is None else default
    kwargs["help"] = "; ".join(help_parts).replace("%", "%%")
    return (option.flag,), kwargs


def add_options(parser: argparse.ArgumentParser, options: Sequence[Option]) -> None:
    """Add ``options`` to ``parser`` in their order (those of one ``group`` mutually exclusive)."""
    groups: dict[str, Any] = {}
    for option in options:
        target: Any = parser
        if option.group:
            if option.group not in groups:
                groups[option.group] = parser.add_mutually_exclusive_group()
            target = groups[option.group]
        names, kwargs = argument(option)
        target.add_argument(*names, **kwargs)


RETIRED_FLAGS: dict[str, str] = {"--overlap": "train.overlap", "--no-overlap": "train.overlap"}
"""Flags that once set a :data:`~lanefree_sumo.config.RETIRED` key: given, they are refused in one line saying
what replaced them."""


class _Retired(argparse.Action):
    """A retired flag: the parser's one-line error with what replaced it."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        key = RETIRED_FLAGS[str(option_string)]
        parser.error(f"{option_string} was removed: {RETIRED[key]}; leave it out")


def add_retired_flags(parser: argparse.ArgumentParser, key: str) -> None:
    """Add the :data:`RETIRED_FLAGS` of config key ``key`` to ``parser`` (hidden from ``--help``)."""
    flags = [flag for flag, retired in RETIRED_FLAGS.items() if retired == key]
    parser.add_argument(*flags, nargs=0, action=_Retired, help=argparse.SUPPRESS)


def dest(option: Option) -> str:
    """The attribute of the parsed arguments that holds ``option``'s value."""
    return str(option.extra.get("dest", option.flag.lstrip("-").replace("-", "_")))


def config_overrides(args: argparse.Namespace, options: Sequence[Option]) -> dict[str, Any]:
    """The nested config overrides of the ``options`` given on the command line (``args.given``) that set a
    config key: an option left out keeps the value below it (the defaults, a run's config or ``--config
    FILE``)."""
    given: set[str] = getattr(args, "given", set())
    return nested_overrides([(str(o.key), getattr(args, dest(o))) for o in options
                             if o.sets_config and given & set(o.names)])


def option_table(verbs: Mapping[str, Sequence[Option]]) -> str:
    """The Markdown table of every option that stands for a schema field: its flag, the field (a run's config key,
    or ``SchemaClass.key`` for a verb's own defaults) and the verbs that take it (docs/architecture.md)."""
    rows: dict[tuple[str, str], list[str]] = {}
    for verb, options in verbs.items():
        for o in options:
            if o.key is not None:
                key = o.key if o.sets_config else f"{o.schema.__name__}.{o.key}"
                rows.setdefault((o.flag, key), []).append(verb)
    lines = ["| option | schema field | verbs |", "|---|---|---|"]
    lines += [f"| `{flag}` | `{key}` | {', '.join(names)} |" for (flag, key), names in sorted(rows.items())]
    return "\n".join(lines) + "\n"


def verb_config(args: argparse.Namespace, options: Sequence[Option], extra: Mapping[str, Any] | None = None,
                base: Any = None) -> LaneFreeConfig:
    """The config of a verb: ``base`` (the defaults), then ``--config FILE``, then the ``options`` given on the
    command line, then ``extra`` (overrides the verb derives), then every ``--set``; validated whole."""
    return layered_config(LaneFreeConfig() if base is None else base, args.config,
                          [config_overrides(args, options), extra or {}], args.settings)


def command_line() -> str:
    """The command line as typed, for a run's command.txt."""
    return shlex.join(["lanefree", *sys.argv[1:]])


DENSITY = Option("--density", "scenario.density_veh_per_km", unit="veh/km", type=argtypes.density)
"""``--density``: the background density, in every verb that takes one."""
SEED = Option("--seed", "seed", type=argtypes.seed)
"""``--seed``: the run's random seed."""
