"""results/varobs/verdict.md: the second paper's comparison on the committed runs, whose fixed-vector side lives
in the paper sweep (results/paper/runs) and whose set-encoder side in results/varobs/set and set_dqn.

The comparison itself (sources, statistics, verdicts) is :mod:`lanefree_sumo.experiments.comparison`, which a
sweep of the built-in grid ``varobs`` writes as its own ``verdict.md``; this script only names the committed
folders. A run counts once it has finished (its deterministic evaluation ``eval/`` exists) and is of the
comparison's cell: the algorithm, fields_zones_overtake_collision, trained at 70 veh/km, with the set observation
or not.

    python scripts/varobs_verdict.py [ROOT]   (default: this checkout)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lanefree_sumo.experiments.comparison import Sides, verdict_markdown
from lanefree_sumo.experiments.rundata import UnusableRunError, read_run_config
from lanefree_sumo.experiments.rundir import write_atomic

ROOT = Path(__file__).resolve().parent.parent

CELL = "fields_zones_overtake_collision_d70"
COMPARISONS = (("ddpg", "set"), ("dqn", "set_dqn"))
"""(algorithm, the set-encoder sweep's folder under results/varobs): its vector runs are the paper sweep's."""
EPISODES = 625
SET_OBSERVATION = "observation.kind=set"
"""In the variant (``lanefree report``: how a run's config differs from the defaults) of a set run."""


def _of_cell(run: Path, algorithm: str, observation_set: bool) -> bool:
    try:
        trained = read_run_config(run)
    except UnusableRunError:
        return False
    return trained[:3] == (algorithm, "fields_zones_overtake_collision", 70.0) and \
        (SET_OBSERVATION in trained[4]) == observation_set


def comparisons(root: Path) -> list[Sides]:
    """The finished runs of each comparison's cell, set and vector (a finished run has its ``eval/``)."""
    out = []
    for algorithm, sweep in COMPARISONS:
        vector = [root / "results" / "paper" / "runs" / f"{algorithm}_{CELL}_s{seed}" for seed in range(3)]
        sets = sorted((root / "results" / "varobs" / sweep / "runs").glob("*"))
        finished = {side: [run for run in runs if (run / "eval" / "episodes.csv").is_file()
                           and _of_cell(run, algorithm, side == "set")]
                    for side, runs in (("set", sets), ("vector", vector))}
        out.append(Sides(algorithm.upper(), finished["set"], finished["vector"]))
    return out


def verdict_page(root: Path) -> str:
    return verdict_markdown(comparisons(root), EPISODES, "Liu et al.'s claim: the set encoder against the fixed "
                            "vector", "fields_zones_overtake_collision, trained at 70 veh/km",
                            "`scripts/varobs_verdict.py`")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", nargs="?", type=Path, default=ROOT,
                        help="checkout holding results/ (default: this one)")
    args = parser.parse_args(argv)
    out = args.root / "results" / "varobs"
    if not out.is_dir():
        print(f"varobs_verdict: no folder {out} (run the variable-dimension experiment first)", file=sys.stderr)
        return 2
    write_atomic(out / "verdict.md", verdict_page(args.root))
    print(f"wrote {out / 'verdict.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
