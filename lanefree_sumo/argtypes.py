"""argparse value types shared by every ``lanefree`` sub-command: each parses one option's text
and turns a bad value into one line naming the expected unit (argparse prints it and exits 2)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path
from typing import Any

from lanefree_sumo.config import LaneFreeConfig, check_value, validate_density
from lanefree_sumo.errors import ConfigError


def density(text: str) -> float:
    """A background density (veh/km) within the config's allowed range."""
    try:
        return validate_density(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


SEED_RANGE: tuple[int, int] = next(f for f in fields(LaneFreeConfig) if f.name == "seed").metadata["range"]
"""The config's range of seeds."""


def seed(text: str) -> int:
    """A seed: a whole number within the config's range of ``seed`` (0 … 2³¹ − 1)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    try:
        return int(check_value("seed", int, value, SEED_RANGE))
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


MAX_BATCH_SEEDS = 4096
"""The most seeds ``--seeds`` trains as one batch (each run holds its own replay buffer: a DDPG run's is ≈ 20 MiB,
so 4096 runs ≈ 80 GiB — more than a single machine's memory is refused before anything is written)."""


def seeds(text: str) -> list[int]:
    """Seeds of a batch: a range ``A-B`` (both included) or a list ``A,B,C`` of distinct seeds, each within the
    config's range of ``seed``, at most :data:`MAX_BATCH_SEEDS` of them."""
    try:
        if "-" in text:
            low, high = (int(part) for part in text.split("-", 1))
            if high < low:
                raise ValueError
            ends = [low, high]
        else:
            ends = [int(part) for part in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seeds as A-B (A <= B) or A,B,C, got {text!r}") from None
    for value in ends:  # the bounds before any list is built: 0-99999999999999999999 is refused at once
        seed(str(value))
    count = ends[1] - ends[0] + 1 if "-" in text else len(ends)
    if count > MAX_BATCH_SEEDS:
        raise argparse.ArgumentTypeError(f"{count} seeds in {text!r}; a batch trains at most {MAX_BATCH_SEEDS} "
                                         "(each run keeps its own replay buffer): split them over several batches")
    values = list(range(ends[0], ends[1] + 1)) if "-" in text else ends
    if len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"seeds repeat in {text!r}; give each seed once")
    return values


def _of(kind: type, unit: str) -> str:
    """'of episodes' for counts, 'in m/s' for measures."""
    return f"of {unit}" if kind is int else f"in {unit}"


def _number(kind: type, unit: str, text: str) -> Any:
    try:
        value = kind(text)
    except ValueError:
        what = f"a whole number of {unit}" if kind is int else f"a number in {unit}"
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not (isinstance(value, int) or math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a finite number in {unit}, got {text!r}")
    return value


def positive(kind: type, unit: str) -> Callable[[str], Any]:
    """A number of type ``kind`` (int or float) > 0, in ``unit``."""

    def parse(text: str) -> Any:
        value = _number(kind, unit, text)
        if value <= 0:
            raise argparse.ArgumentTypeError(f"expected a positive number {_of(kind, unit)}, got {text!r}")
        return value

    return parse


def nonnegative(kind: type, unit: str) -> Callable[[str], Any]:
    """A number of type ``kind`` (int or float) ≥ 0, in ``unit``."""

    def parse(text: str) -> Any:
        value = _number(kind, unit, text)
        if value < 0:
            raise argparse.ArgumentTypeError(f"expected a non-negative number {_of(kind, unit)}, got {text!r}")
        return value

    return parse


def size(text: str) -> tuple[int, int]:
    """A window size ``WIDTHxHEIGHT`` in pixels, each at least 16."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels, e.g. 1024x768, got {text!r}") from None
    if w < 16 or h < 16:
        raise argparse.ArgumentTypeError(f"size must be at least 16x16 pixels, got {text!r}")
    return w, h


def setting(text: str) -> tuple[str, Any]:
    """``section.key=value`` of ``--set``: (dotted key, value parsed as YAML, e.g. ``0.5``, ``true``,
    ``[64, 64]``, ``absolute``). The key is checked against the config when the config is built."""
    import yaml

    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key or any(not part.isidentifier() for part in key.split(".")):
        raise argparse.ArgumentTypeError(f"'{text}' is not KEY=VALUE with a dotted config key, e.g. "
                                         "reward.broad_stretch=absolute")
    try:
        return key, yaml.safe_load(value)
    except yaml.YAMLError:
        raise argparse.ArgumentTypeError(f"the value of '{text}' is not a YAML scalar or list") from None


def add_config_options(parser: argparse.ArgumentParser) -> None:
    """``--config FILE`` and ``--set KEY=VALUE``: any config value from the command line."""
    parser.add_argument("--config", type=Path, default=None, metavar="FILE",
                        help="YAML file of config overrides, nested as in a run's config.yaml (see 'lanefree config'); "
                        "options given on the command line override it")
    parser.add_argument("--set", type=setting, action="append", default=[], metavar="KEY=VALUE",
                        dest="settings", help="set one config value, e.g. --set reward.broad_stretch=absolute "
                        "(repeatable; applied last; 'lanefree config' lists every key with its unit)")
