"""``lanefree evaluate``: a trained policy, deterministic, on fresh seeds."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from lanefree_sumo import argtypes
from lanefree_sumo.config import EvaluationConfig
from lanefree_sumo.errors import EXIT_INTERRUPTED, UsageError
from lanefree_sumo.options import DENSITY, Option, add_options

EVAL = EvaluationConfig()

OPTIONS: tuple[Option, ...] = (
    Option("run", type=Path, extra={"metavar": "RUN"}, note="run folder made by 'lanefree train'; a sweep folder "
           "or a 'train --seeds' folder: every finished run of it whose evaluation is not complete yet"),
    Option("--episodes", "episodes", schema=EvaluationConfig, unit="episodes"),
    replace(DENSITY, default=None, note="default: the training density"),
    Option("--seed", type=argtypes.seed, default=None,
           note=f"base seed; episode k uses seed+{EVAL.seed_offset}+k (default: the training seed)"),
    Option("--record", note="write trajectories/episode_NNNN.csv of every vehicle", extra={"action": "store_true"}),
    Option("--out", type=Path, note="output folder (default RUN/eval, RUN/eval_d<density>, "
           "RUN/eval_onramp[_d<density>], with _shield or _noshield appended when --shield changes the run's "
           "setting)"),
    Option("--overwrite", note="replace an existing output folder", extra={"action": "store_true"}),
    Option("--shield", "shield.enabled", negatable=True, default=None,
           note="for this evaluation, e.g. an unshielded policy shielded (default: as trained; output eval_shield/ "
           "or eval_noshield/)"),
    Option("--scenario", "road.kind", default=None,
           note="the road to evaluate on (default: the run's own); onramp drives a ring-trained policy on the "
           "on-ramp's main road with the ring's observation, output eval_onramp/"),
)


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """The ``evaluate`` sub-command's parser."""
    p = subparsers.add_parser(
        "evaluate",
        help="run a trained policy deterministically on fresh seeds",
        description="Evaluate RUN's final model (or newest checkpoint) deterministically; writes RUN/eval/episodes.csv "
        "(RUN/eval_d<density>/ at another density, RUN/eval_onramp/ on the on-ramp) and, with --record, one "
        "trajectory CSV of all vehicles per episode.",
    )
    add_options(p, OPTIONS)
    return p


def runs_of(folder: Path) -> list[Path] | None:
    """The run folders of a sweep folder (its ``runs/``) or a batch folder (its ``batch.json``), in order; None
    when ``folder`` is neither (a run folder, or a mistake the one-run path names)."""
    from lanefree_sumo.experiments.runners.batch import batch_runs, is_batch
    from lanefree_sumo.experiments.sweep.manifest import MANIFEST

    if (folder / MANIFEST).is_file():
        return sorted(p for p in (folder / "runs").iterdir() if p.is_dir()) if (folder / "runs").is_dir() else []
    if is_batch(folder):
        return batch_runs([folder])
    return None


def _run_many(args: argparse.Namespace, runs: list[Path]) -> int:
    """``lanefree evaluate SWEEP|BATCH``: every finished run whose evaluation is missing or short, one summary
    line each, then the tally."""
    from lanefree_sumo.experiments.runners.evaluate import evaluate_many, summary_line

    if args.out is not None:
        raise UsageError(f"--out names one output folder; each run of {args.run} is evaluated into its own "
                         "(drop --out)")
    done = evaluate_many(runs, episodes=args.episodes, density=args.density, seed=args.seed, record=args.record,
                         overwrite=args.overwrite, shield=args.shield, scenario=args.scenario,
                         report=lambda result: print(summary_line(result), flush=True))
    print(f"{args.run}: {len(done.evaluated)} run(s) evaluated, {len(done.complete)} already complete, "
          f"{len(done.unfinished)} without a final model (not finished)")
    if done.interrupted:
        print(f"lanefree: interrupted; rerun the same command to evaluate the rest of {args.run}", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0


def run(args: argparse.Namespace) -> int:
    """``lanefree evaluate``: print the summary line; EXIT_INTERRUPTED when stopped early."""
    from lanefree_sumo.experiments.runners.evaluate import evaluate, summary_line

    many = runs_of(args.run)
    if many is not None:
        return _run_many(args, many)

    result = evaluate(args.run, episodes=args.episodes, density=args.density, seed=args.seed, record=args.record,
                      out=args.out, overwrite=args.overwrite, shield=args.shield,
                      scenario=args.scenario)
    if result.kept_earlier:
        print(f"lanefree: interrupted; the earlier evaluation in {result.out} is kept (the new one was not complete)",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    if result.interrupted:
        print(f"lanefree: interrupted; kept {result.episodes} complete episode(s) in {result.out}", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(summary_line(result))
    return 0
