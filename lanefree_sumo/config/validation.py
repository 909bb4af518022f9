"""Merging dict overrides into the config and THE validation of every value.

:func:`merge_config` merges a plain mapping recursively (unknown keys are errors naming the valid
ones); :func:`check_value` checks one value against its field's type and ``range`` metadata;
:func:`validate_config` checks a whole config; :func:`missing_keys` finds what a saved config lacks;
:func:`nested_overrides` and :func:`read_config_file` turn ``--set KEY=VALUE`` and ``--config FILE`` into
overrides.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

from lanefree_sumo.config.schema import ResolvedConfig
from lanefree_sumo.errors import ConfigError


def merge_config(base: Any, overrides: Mapping[str, Any], path: str = "") -> Any:
    """Return a copy of dataclass ``base`` with ``overrides`` merged in recursively.

    Unknown keys raise :class:`ConfigError` naming the valid ones. A
    :class:`~.schema.ResolvedConfig` merged with overrides is a plain :class:`~.schema.LaneFreeConfig`: what the
    run derived from its values may no longer hold, so it is resolved again.
    """
    if not isinstance(overrides, Mapping):
        raise ConfigError(f"config{path or ''} must be a mapping, got {type(overrides).__name__}")
    profile = _profile_of(overrides) if not path else None
    if profile is not None:  # the profile's keys first, so the keys given beside it win
        base = merge_config(base, _profile_overrides(profile))
    valid = {f.name: f for f in fields(base)}
    changes: dict[str, Any] = {}
    for key, value in overrides.items():
        where = f"{path}.{key}" if path else key
        if where in RETIRED:
            raise ConfigError(f"config '{where}' was removed: {RETIRED[where]}; leave it out")
        if key not in valid:
            raise ConfigError(
                f"unknown config key '{where}'; valid keys here: {', '.join(sorted(valid))}"
            )
        current = getattr(base, key)
        if is_dataclass(current) and not isinstance(value, Mapping) and not is_dataclass(value):
            raise ConfigError(f"config '{where}' is a section: give a mapping of its keys "
                              f"({', '.join(f.name for f in fields(current))}), not {value!r}")
        if is_dataclass(current) and isinstance(value, Mapping):
            changes[key] = merge_config(current, value, where)
        elif is_dataclass(current) and is_dataclass(value):
            if type(value) is not type(current):
                raise ConfigError(f"config '{where}' is a {type(current).__name__} section, not a "
                                  f"{type(value).__name__}")
            changes[key] = validate_config(value, where)
        else:
            if isinstance(current, tuple) and isinstance(value, list):
                value = tuple(value)
            changes[key] = check_value(where, _field_types(type(base))[key], value, valid[key].metadata.get("range"))
    merged = dataclasses.replace(base, **changes)
    return merged.unresolved() if isinstance(merged, ResolvedConfig) else merged


def _profile_of(overrides: Mapping[str, Any]) -> Any:
    """The ``train.profile`` a top-level override mapping sets, or None."""
    train = overrides.get("train")
    return train.get("profile") if isinstance(train, Mapping) else None


def _profile_overrides(name: Any) -> dict[str, Any]:
    """The overrides of learner profile ``name`` (:data:`~.schema.LEARNER_PROFILES`)."""
    from lanefree_sumo.config.schema import LEARNER_PROFILES

    if not isinstance(name, str) or name not in LEARNER_PROFILES:
        raise ConfigError(f"config 'train.profile' = {name!r} is not allowed; valid: {', '.join(LEARNER_PROFILES)}")
    return LEARNER_PROFILES[name]


RETIRED: dict[str, str] = {
    "train.fast_learner": "every run computes its algorithm's one update (the batched learner, or SB3's own on "
                          "SB3's loop), the numbers the fast learner gave",
    "train.lean_loop": "every run collects with one loop (the batched trainer's, or SB3's), the numbers the lean "
                       "loop gave",
    "train.overlap": "a run steps its environment and its update in turn (the numbers of --no-overlap); for speed "
                     "train several seeds at once with --seeds",
}
"""Config keys that once chose between implementations giving the same numbers (or, ``train.overlap``, a
speed trade), and what replaced each: given as an override they are refused in one line; a saved config
(:func:`drop_retired`) still loads without them."""


def drop_retired(data: Mapping[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """A saved config's mapping without its :data:`RETIRED` keys, and the dotted keys dropped."""
    kept, dropped = dict(data), []
    for key in RETIRED:
        section, _, leaf = key.rpartition(".")
        inner = kept.get(section)
        if isinstance(inner, Mapping) and leaf in inner:
            kept[section] = {k: v for k, v in inner.items() if k != leaf}
            dropped.append(key)
    return kept, dropped


ADDED_LATER: tuple[str, ...] = ("observation.encoder", "shield", "reward.broad_stretch",
                               "train.backend", "scenario.agents", "road.kind",
                               "road.onramp", "observation.road_features",
                               "reward.overtake_bonus", "scenario.agent_lateral_speed_ratio", "train.profile",
                               "train.dqn.loss", "train.dqn.max_grad_norm", "train.actor_critic.warmup_actions",
                               "train.device", "train.actor_critic.pre_tanh_penalty", "shield.fallback_steers_clear")
"""Config keys added after run folders were first written; a saved config without them gets their
default. Every other key must be present in a saved config (a missing one means a cut file)."""


SAME_RESULTS: tuple[str, ...] = ("train.checkpoint_every_episodes", "train.torch_threads", "gui", "backend",
                                  "train.backend")
"""Config keys that do not change what a training run computes: the backends give the same episodes (proven by
a test). Runs differing only here are runs of one setting (report groups, sweep adoption)."""


def missing_keys(base: Any, data: Mapping[str, Any], path: str = "") -> list[str]:
    """Dotted keys of config dataclass ``base`` that the saved mapping ``data`` lacks (leaves and
    whole sections), except those in :data:`ADDED_LATER`."""
    missing: list[str] = []
    for f in fields(base):
        where = f"{path}.{f.name}" if path else f.name
        if where in ADDED_LATER:
            continue
        if f.name not in data:
            missing.append(where)
        elif is_dataclass(getattr(base, f.name)) and isinstance(data[f.name], Mapping):
            missing += missing_keys(getattr(base, f.name), data[f.name], where)
    return missing


def validate_config(cfg: Any, path: str = "") -> Any:
    """Check every field of a (nested) config dataclass with :func:`check_value`; return it."""
    types = _field_types(type(cfg))
    for f in fields(cfg):
        where = f"{path}.{f.name}" if path else f.name
        value = getattr(cfg, f.name)
        if is_dataclass(value):
            validate_config(value, where)
        else:
            check_value(where, types[f.name], value, f.metadata.get("range"))
    return cfg


_FIELD_TYPES: dict[Any, dict[str, Any]] = {}


def _field_types(cls: Any) -> dict[str, Any]:
    """Resolved annotations of a config dataclass (cached)."""
    if cls not in _FIELD_TYPES:
        _FIELD_TYPES[cls] = typing.get_type_hints(cls)
    return _FIELD_TYPES[cls]


def check_value(where: str, annotation: Any, value: Any, bounds: tuple[float, float] | None = None) -> Any:
    """THE validation of one config value against its field's type (``Literal`` values, numbers
    within the field's ``range`` metadata — each entry's, for a list —, flags, names, tuples); returns the
    value, ints widened to float where a float is expected. Raises ConfigError naming the key and what is
    allowed."""
    value = _check_type(where, annotation, value)
    if bounds is None or value is None:
        return value
    for key, item in ([(f"{where}[{i}]", v) for i, v in enumerate(value)] if isinstance(value, tuple)
                      else [(where, value)]):
        if not bounds[0] <= item <= bounds[1]:
            low, high = (f"{v:d}" if isinstance(v, int) else f"{v:g}" for v in bounds)
            raise ConfigError(f"config '{key}' = {item!r} is out of range; allowed {low} … {high}")
    return value


def _check_type(where: str, annotation: Any, value: Any) -> Any:
    origin = get_origin(annotation)
    if origin in (typing.Union, types.UnionType):  # ``X | None``: null, or a value of X
        return _check_optional(where, annotation, value)
    if origin is Literal:
        allowed = get_args(annotation)
        if value not in allowed:
            raise ConfigError(f"config '{where}' = {value!r} is not allowed; valid: {', '.join(map(str, allowed))}")
        return value
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"config '{where}' must be true or false, got {value!r}")
        return value
    if annotation is int:  # numpy's integers too (numbers.Integral), kept as Python ints
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise ConfigError(f"config '{where}' must be a whole number, got {value!r}")
        return int(value)
    if annotation is float:  # numpy's floats too (numbers.Real), kept as Python floats
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
            raise ConfigError(f"config '{where}' must be a finite number, got {value!r}")
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"config '{where}' must be text, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, tuple):
            raise ConfigError(f"config '{where}' must be a list, got {value!r}")
        args = get_args(annotation)
        item_types = [args[0]] * len(value) if len(args) == 2 and args[1] is Ellipsis else list(args)
        if len(item_types) != len(value):
            raise ConfigError(f"config '{where}' must have {len(item_types)} entries, got {len(value)}")
        return tuple(check_value(f"{where}[{i}]", t, v) for i, (t, v) in enumerate(zip(item_types, value)))
    return value


def _check_optional(where: str, annotation: Any, value: Any) -> Any:
    """A value of ``X | None``: null, or a value of X."""
    if value is None:
        return None
    kinds = [a for a in get_args(annotation) if a is not type(None)]
    try:
        return _check_type(where, kinds[0], value)
    except ConfigError as exc:
        raise ConfigError(f"{exc} (or null)") from None


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """Plain nested dict (tuples as lists) for YAML/JSON."""

    def conv(v: Any) -> Any:
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        if isinstance(v, list):
            return [conv(x) for x in v]
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        return v

    return conv(dataclasses.asdict(cfg))


def config_differences(cfg: Any, base: Any, ignore: tuple[str, ...] = ()) -> dict[str, Any]:
    """Dotted keys (``reward.k_r_s_per_m``) where ``cfg`` differs from ``base``, with ``cfg``'s
    value, except keys in or under ``ignore``; in the order of the schema."""

    def flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in d.items():
            key = f"{prefix}{k}"
            out.update(flat(v, key + ".") if isinstance(v, dict) else {key: v})
        return out

    mine, theirs = flat(config_to_dict(cfg)), flat(config_to_dict(base))
    under = tuple(f"{k}." for k in ignore)
    return {k: v for k, v in mine.items() if theirs.get(k) != v and k not in ignore and not k.startswith(under)}


def validate_density(density: object) -> float:
    """Check a density is a finite positive number (veh/km)."""
    try:
        value = float(density)  # type: ignore[arg-type]  # anything float() takes; the rest is an error
    except (TypeError, ValueError):
        raise ConfigError(f"density must be a number in veh/km, got {density!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ConfigError(f"density must be a positive finite number in veh/km, got {density!r}")
    return value


def nested_overrides(settings: Sequence[tuple[str, Any]]) -> dict[str, Any]:
    """``[("reward.k_r", 0.5), …]`` → ``{"reward": {"k_r": 0.5}}`` (later settings win)."""
    out: dict[str, Any] = {}
    for key, value in settings:
        *sections, leaf = key.split(".")
        node = out
        for section in sections:
            child = node.setdefault(section, {})
            if not isinstance(child, dict):
                raise ConfigError(f"config key '{key}' goes below '{section}', which is set to a value")
            node = child
        node[leaf] = value
    return out


def load_yaml(text: str, source: str) -> Any:
    """``text`` (of file ``source``) parsed as YAML, safe types only; a key repeated in one mapping is a
    ConfigError naming it and both lines: YAML would keep the last silently, so a section given twice would
    drop the first block."""
    import yaml

    class UniqueKeys(yaml.SafeLoader):
        def construct_mapping(self, node: Any, deep: bool = False) -> Any:
            lines: dict[Any, int] = {}
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=deep)
                line = key_node.start_mark.line + 1
                if isinstance(key, typing.Hashable) and key in lines:
                    raise ConfigError(f"{source}: key '{key}' is given twice (lines {lines[key]} and {line}); "
                                      "give each key once")
                lines[key] = line
            return super().construct_mapping(node, deep)

    return yaml.load(text, Loader=UniqueKeys)  # noqa: S506 (a SafeLoader)


def read_yaml_file(path: Path, what: str) -> Any:
    """The YAML file ``path`` parsed (:func:`load_yaml`); a file that cannot be read, is not UTF-8 text or is not
    YAML is a one-line ConfigError calling it ``what`` (``config file``, ``grid file``)."""
    import yaml

    try:
        return load_yaml(path.read_text(encoding="utf-8"), str(path))
    except OSError as exc:
        reason = " ".join(str(exc.strerror or exc).split())[:200]
        raise ConfigError(f"cannot read the {what} {path}: {reason}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path} is not a text (UTF-8) YAML file") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path} is not valid YAML ({' '.join(str(exc).split())[:200]})") from None


def read_config_file(path: Path) -> dict[str, Any]:
    """The overrides in a YAML file (any part of the config, nested as in ``config.yaml``); a key given twice
    is refused."""
    data = read_yaml_file(path, "config file")
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path} must hold a mapping of config sections, not a {type(data).__name__}")
    return dict(data)


def layered_config(base: Any, config_file: Path | None, options: Sequence[Mapping[str, Any]],
                   settings: Sequence[tuple[str, Any]]) -> Any:
    """The one order in which a verb builds its config: ``base`` (the defaults, or a run's config), then the
    ``--config FILE`` overrides, then each mapping of ``options`` (the verb's options), then every ``--set``
    KEY=VALUE; validated whole."""
    cfg = base
    if config_file is not None:
        cfg = merge_config(cfg, read_config_file(config_file))
    for overrides in options:
        if overrides:
            cfg = merge_config(cfg, overrides)
    return validate_config(merge_config(cfg, nested_overrides(settings)))
