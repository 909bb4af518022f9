"""``lanefree simulate``: background traffic only, written as trajectories and a summary."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

from lanefree_sumo import argtypes
from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.errors import EXIT_INTERRUPTED, UsageError
from lanefree_sumo.options import DENSITY, SEED, Option, add_options, command_line, verb_config
from lanefree_sumo.sim.road import road_kind

DEFAULTS = LaneFreeConfig()
EPISODE_S = DEFAULTS.sim.episode_steps * DEFAULTS.sim.step_s
GUI = {"gui": True, "backend": "traci"}
"""The config the ``--gui`` switch sets (sumo-gui runs over TraCI)."""

OPTIONS: tuple[Option, ...] = (
    Option("--scenario", "road.kind", note="its sizes and demands: road.onramp in 'lanefree config'"),
    Option("--main-flow", "road.onramp.main_flow_veh_per_h", unit="veh/h", note="on-ramp only"),
    Option("--ramp-flow", "road.onramp.ramp_flow_veh_per_h", unit="veh/h", note="on-ramp only"),
    replace(DENSITY, note="on the on-ramp: of the main road at the start"),
    Option("--seconds", unit="s", type=argtypes.positive(float, "s"), default=EPISODE_S,
           note=f"simulated time in s (default {EPISODE_S:g} = {DEFAULTS.sim.episode_steps} steps of "
           f"{DEFAULTS.sim.step_s:g} s)"),
    SEED,
    Option("--out", type=Path, note="output folder (default runs/sim-d<density>-s<seed>, on the on-ramp "
           "runs/sim-onramp-d<density>-s<seed>); refused if it exists"),
    Option("--overwrite", note="replace an existing output folder", extra={"action": "store_true"}),
    Option("--backend", "backend"),
    Option("--gui", note="show the run in sumo-gui (uses the TraCI backend)", extra={"action": "store_true"}),
    Option("--nudging", "scenario.driver.nudging"),
    Option("--net", "net_file", note="e.g. one built by 'lanefree net'"),
    Option("--length", "road.length_m", unit="m", note="ring only"),
    Option("--width", "road.width_m", unit="m"),
    Option("--json", note="print the summary as one JSON object on stdout's last line",
           extra={"action": "store_true"}),
    Option("--no-trajectory", note="skip the per-step trajectory CSV", extra={"action": "store_true"}),
)

ROAD_OPTIONS: dict[str, tuple[str, ...]] = {"ring": ("--length",), "onramp": ("--main-flow", "--ramp-flow")}
"""The options that size or feed one road only."""


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """The ``simulate`` sub-command's parser."""
    p = subparsers.add_parser(
        "simulate",
        help="run background traffic only and write trajectories and a summary",
        description="Run the force-based background traffic on the ring road (or the on-ramp) and write a "
        "per-step trajectory CSV (t, id, x, y, vx, vy, ax, ay) plus summary.json, config.yaml and command.txt "
        "into --out.",
    )
    add_options(p, OPTIONS)
    argtypes.add_config_options(p)
    return p


def _check_road_options(args: argparse.Namespace, cfg: LaneFreeConfig) -> None:
    """Refuse an option of another road than ``cfg``'s: it would be ignored."""
    for road, names in ROAD_OPTIONS.items():
        given = sorted(args.given & set(names))
        if road != cfg.road.kind and given:
            lengths = ("; the on-ramp's lengths are road.onramp.upstream_m, ramp_m, merge_m and downstream_m "
                       "(--set)") if road == "ring" else ""
            raise UsageError(f"{given[0]} applies to --scenario {road} only, not to the {cfg.road.kind}{lengths}")


def run(args: argparse.Namespace) -> int:
    """``lanefree simulate``: print the summary; EXIT_INTERRUPTED when stopped early."""
    cfg = verb_config(args, OPTIONS, GUI if args.gui else None)
    _check_road_options(args, cfg)
    from lanefree_sumo.experiments.runners.simulate import simulate

    tag = road_kind(cfg).tag
    road = f"{tag}-" if tag else ""  # a ring and an on-ramp run do not collide
    out = args.out or Path("runs") / f"sim-{road}d{cfg.scenario.density_veh_per_km:g}-s{cfg.seed}"
    summary = simulate(cfg, args.seconds, out, command_line(), overwrite=args.overwrite,
                       write_trajectory=not args.no_trajectory, progress=not args.json)
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"{summary['steps']} steps, {summary['vehicles']} vehicles, "
            f"{summary['background_collisions']} collisions, mean speed {summary['mean_speed_mps']:.2f} m/s "
            f"(desired {summary['mean_desired_speed_mps']:.2f}), min margin {summary['min_lateral_margin_m']:.3f} m, "
            f"{summary['wall_s']:.1f} s -> {out}"
        )
        if "onramp" in summary:
            o = summary["onramp"]
            print(f"on-ramp: {o['entered_main']} entered the main road, {o['entered_ramp']} the ramp, "
                  f"{o['left']} left, "
                  f"{o['on_road']} on the road at the end; {o['merged']} merged, {o['ramp_end_reached_unmerged']} "
                  f"reached the ramp's end unmerged; outflow {o['outflow_veh_per_h']:.0f} veh/h")
    return 0 if not summary["interrupted"] else EXIT_INTERRUPTED
