"""``lanefree report``: learning curves and paper-style tables from run folders, or a sweep's summary."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from lanefree_sumo import argtypes
from lanefree_sumo.config import ReportConfig
from lanefree_sumo.errors import UsageError
from lanefree_sumo.options import Option, add_options

OPTIONS: tuple[Option, ...] = (
    Option("runs", type=Path, extra={"nargs": "*", "metavar": "RUN"},
           note="run folders made by 'lanefree train', or sweep folders made by 'lanefree sweep' (at least one)"),
    Option("--out", type=Path, default=Path("report"),
           note="output folder (default report/: outside runs/, which holds run folders only)"),
    Option("--last", "last_episodes", schema=ReportConfig, unit="episodes"),
    Option("--smooth", "smooth_episodes", schema=ReportConfig, unit="episodes"),
    Option("--eval", extra={"nargs": "*", "metavar": "NAME"},
           note="tabulate each run's evaluation RUN/NAME/episodes.csv (default NAME eval; e.g. eval_d120, "
           "eval_shield) instead of its training episodes, at the evaluated density; several NAMEs: the "
           "evaluations side by side in one table and two bar charts (evaluations_collisions.png, "
           "evaluations_speed_dev.png), no learning curves. Put the RUN folders before --eval"),
    Option("--compare", extra={"action": "store_true"},
           note="also write verdict.md: each way the runs differ from the defaults (their variant) against the "
           "default runs of the same setting, over training episodes 1-12, all, the last 50 and every evaluation "
           "the runs have: difference with a bootstrap CI, rank test and verdict (run folders only, without --eval)"),
    Option("--against", type=Path, extra={"nargs": "+", "metavar": "RUN"},
           note="run folders of one group (e.g. DDPG's, to set TD3 or another algorithm against them): verdict.md "
           "then compares every other group of the RUN folders with that group (these runs and any RUN folders of "
           "it), as --compare does (which this implies), instead of each variant with the defaults of its setting; "
           "runs of different lengths need --first (run folders only, without --eval). Put the RUN folders before "
           "--against"),
    Option("--first", type=argtypes.positive(int, "episodes"), default=None, extra={"metavar": "N"},
           note="read every run over its first N training episodes only, e.g. 150-episode runs against the first "
           "150 of 625-episode ones: longer runs are cut there, shorter ones skipped, and the planned number of "
           "episodes no longer separates variants (run folders only, without --eval; --compare then reads no "
           "evaluation)"),
)


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """The ``report`` sub-command's parser."""
    p = subparsers.add_parser(
        "report",
        help="learning curves and paper-style tables from run folders",
        description="Group run folders by (algorithm, reward preset, density, variant: every other setting in "
        "which a run's config differs from the defaults, e.g. shield.enabled=True), average the seeds, and write "
        "learning curves (return, collisions, speed deviation per episode; mean ± std over seeds, smoothed) as PNG "
        "and a table of last-50-episode means ± std with the paper's numbers (docs/specification.md §10) as "
        "summary.csv and summary.md, and where the runs decide one of the paper's claims (default runs of two "
        "settings a claim compares), the claims table with bootstrap CIs and exact rank tests as claims.csv and "
        "claims.md. Unusable runs are named and skipped. Given a sweep folder (one with "
        "sweep.yaml), writes the sweep's summary into it instead: last-50 means with 95 % bootstrap CIs over "
        "seeds, as 'lanefree sweep'. Given several sweep folders, writes each one's summary into it and puts their "
        "variants' effects on one page, --out/effects.md: each open choice's verdict in every cell, then each "
        "cell's figures.",
    )
    add_options(p, OPTIONS)
    return p


def run(args: argparse.Namespace) -> int:
    """``lanefree report``: write the report and print its summary table."""
    from lanefree_sumo.experiments.analysis.report import report
    from lanefree_sumo.experiments.runners.batch import batch_runs
    from lanefree_sumo.experiments.sweep.manifest import MANIFEST

    sources = _evaluation_names(args.eval)
    if not args.runs:
        raise UsageError("lanefree report needs at least one RUN folder (or one sweep folder), before --eval or "
                         "--against")
    args.runs = batch_runs(args.runs)  # a 'lanefree train --seeds' folder stands for its runs
    sweeps = [path for path in args.runs if (path / MANIFEST).is_file()]
    if sweeps and len(sweeps) < len(args.runs):
        other = next(path for path in args.runs if path not in sweeps)
        raise UsageError(f"{sweeps[0]} is a sweep folder and {other} is not: report sweep folders alone or together, "
                         "run folders apart")
    if args.compare and (sweeps or args.eval is not None):
        raise UsageError("--compare reads run folders' training episodes and every evaluation they have: "
                         + ("a sweep writes its own verdict.md (a grid's `compare`)" if sweeps else "drop --eval"))
    if args.against is not None and (sweeps or args.eval is not None):
        raise UsageError("--against compares run folders' training episodes: "
                         + ("a sweep writes its own verdict.md (a grid's `compare`)" if sweeps else "drop --eval"))
    if args.first is not None and (sweeps or args.eval is not None):
        raise UsageError("--first cuts run folders' training episodes: "
                         + ("a sweep's summary reads its runs whole" if sweeps else
                            "evaluations are of the final models, drop --eval"))
    if len(sweeps) > 1:
        return _report_study(args, sweeps)
    if sweeps:
        return _report_sweep(args, sweeps)
    result = report(args.runs, args.out, last=args.last, smooth=args.smooth, source=sources, compare=args.compare,
                    first=args.first, against=args.against)
    for path, reason in result.skipped:
        print(f"skipped {path}: {reason}", file=sys.stderr)
    for note in result.notes:
        print(f"note: {note}", file=sys.stderr)
    rows = "group(s)" if isinstance(sources, str) or len(sources) == 1 else "row(s), one per evaluation and group"
    extra = [path.name for path in result.files if path.name in ("claims.md", "verdict.md")]
    print(f"{len(result.table)} {rows} -> {args.out}" + (f" (and {', '.join(extra)})" if extra else ""))
    print((args.out / "summary.md").read_text())
    return 0


def _evaluation_names(names: list[str] | None) -> list[str] | str:
    """``report --eval``'s names: "" without the option (training episodes), ["eval"] for a bare ``--eval``;
    a path among them is refused (the run folders were put after ``--eval``)."""
    if names is None:
        return ""
    names = [name.rstrip("/") for name in names]
    for name in names:
        if not name or "/" in name or name in (".", ".."):
            raise UsageError(f"--eval takes evaluation folder names inside each run (eval, eval_d120, …), got "
                             f"{name!r}: put the RUN folders before --eval")
    return names or ["eval"]


def _report_sweep(args: argparse.Namespace, sweeps: list[Path]) -> int:
    """``lanefree report SWEEP_DIR``: the sweep's summary with bootstrap CIs, written into it."""
    from lanefree_sumo.experiments.sweep.summary import summarize

    if "--out" in args.given or args.eval is not None:
        bad = "--out" if "--out" in args.given else "--eval"
        raise UsageError(f"a sweep's summary is written into the sweep folder {sweeps[0]} from its training runs; "
                         f"drop {bad}")
    result = summarize(sweeps[0], last=args.last, smooth=args.smooth)
    for name, reason in result.incomplete:
        print(f"not in the summary: {name} ({reason})", file=sys.stderr)
    for note in result.notes:
        print(f"note: {note}", file=sys.stderr)
    print(f"{len(result.table)} setting(s) -> {sweeps[0]}")
    print((sweeps[0] / "summary.md").read_text())
    return 0


def _report_study(args: argparse.Namespace, sweeps: list[Path]) -> int:
    """``lanefree report SWEEP SWEEP … [--out DIR]``: each sweep's summary, and their effects on one page."""
    from lanefree_sumo.experiments.sweep.summary import summarize_study

    if args.eval is not None:
        raise UsageError("the sweeps' summaries and effects come from their training runs; drop --eval")
    summaries, page = summarize_study(sweeps, args.out, last=args.last, smooth=args.smooth)
    for folder, result in zip(sweeps, summaries):
        for name, reason in result.incomplete:
            print(f"not in the summary of {folder}: {name} ({reason})", file=sys.stderr)
        for note in result.notes:
            print(f"note ({folder}): {note}", file=sys.stderr)
    print(f"{len(sweeps)} sweeps' summaries written into them; their effects -> {page}")
    print(page.read_text())
    return 0
