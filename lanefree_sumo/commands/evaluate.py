"""``lanefree evaluate``: a trained policy, deterministic, on fresh seeds."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from lanefree_sumo import argtypes
from lanefree_sumo.config import EvaluationConfig
from lanefree_sumo.errors import EXIT_INTERRUPTED
from lanefree_sumo.options import DENSITY, Option, add_options

EVAL = EvaluationConfig()

OPTIONS: tuple[Option, ...] = (
    Option("run", type=Path, extra={"metavar": "RUN"}, note="run folder made by 'lanefree train'"),
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


def run(args: argparse.Namespace) -> int:
    """``lanefree evaluate``: print the summary line; EXIT_INTERRUPTED when stopped early."""
    from lanefree_sumo.experiments.evaluate import evaluate, summary_line

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
