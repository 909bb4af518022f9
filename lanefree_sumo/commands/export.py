"""``lanefree export``: a recorded episode as trajectory CSV and SUMO FCD XML."""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path
from typing import Any

from lanefree_sumo import argtypes
from lanefree_sumo.options import Option, add_options

OPTIONS: tuple[Option, ...] = (
    Option("run", type=Path, extra={"metavar": "RUN"}, note="run folder (or its eval folder) with a recording"),
    Option("--episode", type=argtypes.positive(int, "episodes"), default=1, note="recorded episode (default 1)"),
    Option("--out", type=Path, note="output folder (default RUN/eval/export)"),
    Option("--overwrite", note="replace existing export files", extra={"action": "store_true"}),
)


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """The ``export`` sub-command's parser."""
    p = subparsers.add_parser(
        "export",
        help="export a recorded episode as CSV and SUMO FCD XML",
        description="Write episode K of RUN's recording as trajectory CSV and as SUMO's own FCD XML (x, y, angle, "
        "type, speed, pos, lane, posLat) into --out, by replaying it headless in SUMO.",
    )
    add_options(p, OPTIONS)
    return p


def run(args: argparse.Namespace) -> int:
    """``lanefree export``: write both files, never over a run's own."""
    from lanefree_sumo.experiments.runners.replay import load_recording, replay
    from lanefree_sumo.experiments.storage.rundir import (
        OUTPUT_MARKER,
        check_new_file,
        find_eval_dir,
        new_file,
        trajectory_path,
    )

    load_recording(args.run, args.episode)  # a missing or damaged recording is said before any folder is made
    source = trajectory_path(find_eval_dir(args.run), args.episode)
    out = args.out or find_eval_dir(args.run) / "export"
    csv_out = out / f"episode_{args.episode:04d}.csv"
    fcd_out = out / f"episode_{args.episode:04d}.fcd.xml"
    for target in (csv_out, fcd_out):  # before any work: never a run's file, never a folder not export's own
        check_new_file(target, args.overwrite, "export", marker_folder=True)
    if not (out / OUTPUT_MARKER).exists() and not any(out.iterdir()):
        (out / OUTPUT_MARKER).write_text("export\n")
    result = replay(args.run, episode=args.episode, gui=False, fcd=fcd_out, overwrite=args.overwrite,
                    verb="export")
    with new_file(csv_out, "export") as tmp:
        shutil.copyfile(source, tmp)
    print(f"exported {result.steps} steps -> {csv_out} and {fcd_out}")
    return 0
