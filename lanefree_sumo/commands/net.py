"""``lanefree net``: a ring network built with netconvert."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.options import Option, add_options, config_overrides

OPTIONS: tuple[Option, ...] = (
    Option("--length", "road.length_m", unit="m"),
    Option("--width", "road.width_m", unit="m"),
    Option("--out-dir", type=Path, note="folder for the files (default sumo_nets/)"),
)


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """The ``net`` sub-command's parser."""
    p = subparsers.add_parser(
        "net",
        help="build a ring network with netconvert",
        description="Write plain node/edge files of a one-lane ring and build the SUMO network with netconvert.",
    )
    add_options(p, OPTIONS)
    return p


def run(args: argparse.Namespace) -> int:
    """``lanefree net``: build the network and print its path."""
    from lanefree_sumo.sim.backends.sumo import build_ring_net
    from lanefree_sumo.sim.network import NETS_DIR

    net = build_ring_net(merge_config(LaneFreeConfig(), config_overrides(args, OPTIONS)), args.out_dir or NETS_DIR)
    print(net)
    return 0
