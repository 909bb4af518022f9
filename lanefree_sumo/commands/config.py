"""``lanefree config``: the config a verb would start from, as YAML with each key's unit and meaning."""

from __future__ import annotations

import argparse
from typing import Any

from lanefree_sumo import argtypes
from lanefree_sumo.options import verb_config


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """The ``config`` sub-command's parser."""
    p = subparsers.add_parser(
        "config",
        help="print the resolved config as YAML, each key with its unit and meaning",
        description="Print the configuration that 'lanefree train' / 'simulate' would start from (the defaults, "
        "then --config FILE, then every --set) as YAML, with each key's unit, allowed values and meaning as a "
        "comment. Save it, edit it, and pass it back with --config FILE.",
    )
    argtypes.add_config_options(p)
    return p


def run(args: argparse.Namespace) -> int:
    """``lanefree config``: print the described config."""
    from lanefree_sumo.config.describe import describe_config

    print(describe_config(verb_config(args, ())), end="")
    return 0
