"""``lanefree config``: a config as YAML with each key's meaning, unit and allowed values as comments.

The meanings are the attribute docstrings of :mod:`.schema` (read from its source, so they cannot
drift from the code), the allowed values its ``Literal`` types and ``range`` metadata.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import typing
from functools import cache
from typing import Any, get_args, get_origin

import yaml

from lanefree_sumo.config import schema
from lanefree_sumo.config.validation import config_to_dict


@cache
def field_docs() -> dict[tuple[str, str], str]:
    """(class name, field name) → the first sentence of the field's docstring in :mod:`.schema`."""
    docs: dict[tuple[str, str], str] = {}
    for node in ast.parse(inspect.getsource(schema)).body:
        if not isinstance(node, ast.ClassDef):
            continue
        body = node.body
        for here, after in zip(body, body[1:]):
            if (isinstance(here, ast.AnnAssign) and isinstance(here.target, ast.Name)
                    and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                    and isinstance(after.value.value, str)):
                text = " ".join(after.value.value.split())
                docs[(node.name, here.target.id)] = re.split(r"(?<! al)\.\s+(?=[A-Z`(])", text)[0].rstrip(".")
    return docs


def _allowed(cls: type, f: dataclasses.Field) -> str:
    kind = typing.get_type_hints(cls)[f.name]
    if get_origin(kind) is typing.Literal:
        return "one of " + ", ".join(str(v) for v in get_args(kind))
    bounds = f.metadata.get("range")
    optional = type(None) in get_args(kind)
    return (f"{bounds[0]:g} … {bounds[1]:g}" if bounds else "") + (" or null" if optional and bounds else "")


def describe_config(cfg: Any) -> str:
    """``cfg`` as YAML, one ``key: value  # meaning [allowed]`` line per leaf, sections nested."""
    docs = field_docs()
    lines = ["# lanefree_sumo configuration (lanefree config); pass an edited copy back with --config FILE"]

    def walk(obj: Any, indent: str) -> None:
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if dataclasses.is_dataclass(value):
                doc = (type(value).__doc__ or "").strip().splitlines()[0] if type(value).__doc__ else ""
                lines.append(f"{indent}{f.name}:" + (f"  # {doc}" if doc else ""))
                walk(value, indent + "  ")
                continue
            text = yaml.safe_dump({f.name: config_to_dict_value(value)}, default_flow_style=True,
                                  sort_keys=False).strip()[1:-1]
            paper = f.metadata.get("paper", "")
            notes = [n for n in (docs.get((type(obj).__name__, f.name), ""), _allowed(type(obj), f),
                                 f"the paper: {paper}" if paper else "") if n]
            lines.append(f"{indent}{text}" + (f"  # {'; '.join(notes)}" if notes else ""))

    walk(cfg, "")
    return "\n".join(lines) + "\n"


def config_to_dict_value(value: Any) -> Any:
    """A leaf value as it appears in ``config.yaml`` (tuples as lists)."""
    return config_to_dict(value) if dataclasses.is_dataclass(value) else (list(value) if isinstance(value, tuple)
                                                                          else value)
