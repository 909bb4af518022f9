"""Liu et al.'s claim, decided run by run: the set encoder loses nothing against the fixed vector.

For each comparison (DDPG, the experiment's design; DQN, Liu et al.'s own Q-network; fields_zones_overtake_collision at
70 veh/km) and each source (training over episodes 1–12, about the 10 000 steps over which Liu et al. compare
training rewards, over all 625 and over the last 50; the last 50 episodes of the deterministic evaluation at
70 veh/km, zero-shot at 90 and 120 veh/km and on the on-ramp): the difference set − vector of the per-run means
of the return, collisions per episode and speed deviation (m/s), with the 95 % percentile-bootstrap CI over
runs and the two-sided rank test of ``lanefree_sumo.experiments.claims`` (the first paper's claims use the
same). A run counts once it has finished (its deterministic evaluation ``eval/`` exists). Verdicts: *set
worse* / *set better* when the CI excludes 0 (worse: a lower return, more collisions, a larger speed
deviation), *no difference detected* when it contains 0 (3 runs a side: low power, not equivalence), *too few
runs* below 3 runs on a side. Writes ``results/varobs/verdict.md``.

    python scripts/varobs_verdict.py [ROOT]   (default: this checkout)
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from lanefree_sumo.experiments import markdown
from lanefree_sumo.experiments.claims import difference_ci, per_run, rank_test
from lanefree_sumo.experiments.rundata import RunData, UnusableRunError, read_run, read_run_config
from lanefree_sumo.experiments.rundir import write_atomic

ROOT = Path(__file__).resolve().parent.parent

CELL = "fields_zones_overtake_collision_d70"
COMPARISONS = (("ddpg", "set"), ("dqn", "set_dqn"))
"""(algorithm, the set-encoder sweep's folder under results/varobs): its vector runs are the paper sweep's."""
LIU_EPISODES = (1, 12)
"""Liu et al. compare rewards over 10 000 training steps: our episodes 1-12 (800 steps each; 9600 steps)."""
SOURCES: tuple[tuple[str, str, tuple[int, int] | None], ...] = (
    ("", "training, episodes 1–12 (Liu et al.'s 10 000 steps)", LIU_EPISODES),
    ("", "training, all 625 episodes", (1, 625)),
    ("", "training, last 50 episodes", None),
    ("eval", "deterministic, 70 veh/km", None),
    ("eval_d90", "zero-shot, 90 veh/km", None),
    ("eval_d120", "zero-shot, 120 veh/km", None),
    ("eval_onramp", "zero-shot, on-ramp", None))
"""(evaluation folder, "" for training; label; episodes averaged per run, None for the last 50)."""
METRICS = (("return", "return", 1), ("collisions", "collisions / episode", -1),
           ("speed_dev_mps", "speed deviation (m/s)", -1))
"""(column, label, +1 when higher is better)."""
LAST = 50
SET_OBSERVATION = "observation.kind=set"
"""In the variant (``lanefree report``: how a run's config differs from the defaults) of a set run."""
TOO_FEW = "too few runs (< 3 a side)"


def finished_runs(root: Path, algorithm: str, sweep: str) -> dict[str, list[Path]]:
    """The finished vector and set runs of one comparison (a finished run has its ``eval/``)."""
    vector = [root / "results" / "paper" / "runs" / f"{algorithm}_{CELL}_s{seed}" for seed in range(3)]
    sets = sorted((root / "results" / "varobs" / sweep / "runs").glob("*"))
    return {side: [run for run in runs if (run / "eval" / "episodes.csv").is_file()]
            for side, runs in (("set", sets), ("vector", vector))}


def readable(runs: list[Path], source: str, algorithm: str, observation_set: bool) -> list[RunData]:
    """The runs that have ``source`` (an evaluation a machine without the model could not run is absent) and
    are of the comparison's cell: ``algorithm``, fields_zones_overtake_collision, trained at 70 veh/km, with the
    set observation or not (``observation_set``)."""
    out = []
    for run in runs:
        try:
            data = read_run(run, source)
            trained = read_run_config(run)
        except UnusableRunError:
            continue
        if trained[:3] == (algorithm, "fields_zones_overtake_collision", 70.0) and \
                (SET_OBSERVATION in trained[4]) == observation_set:
            out.append(data)
    return out


def reading(better: int, low: float, high: float) -> str:
    """The verdict of a set − vector difference whose CI is [low, high]."""
    if math.isnan(low):
        return TOO_FEW
    if low <= 0 <= high:
        return "no difference detected"
    return "set better" if (low > 0) == (better > 0) else "set worse"


def mean_text(values: list[float]) -> str:
    return f"{sum(values) / len(values):.2f}" if values else "–"


def rows(root: Path) -> list[list[str]]:
    """One table row per comparison, source and metric."""
    out = []
    for algorithm, sweep in COMPARISONS:
        runs = finished_runs(root, algorithm, sweep)
        for source, label, window in SOURCES:
            data = {side: readable(paths, source, algorithm, side == "set") for side, paths in runs.items()}
            for column, name, better in METRICS:
                a = per_run(data["set"], column, LAST, window)
                b = per_run(data["vector"], column, LAST, window)
                diff, low, high = difference_ci(a, b)
                above, p = rank_test(a, b, 0)
                ci = "" if math.isnan(low) else f" [{low:+.2f}, {high:+.2f}]"
                rank = "–" if math.isnan(p) else f"{above:g}/{len(a) * len(b)}, p = {p:.2f}"
                out.append([algorithm.upper(), label, name, f"{len(a)}, {len(b)}", mean_text(a), mean_text(b),
                             ("–" if math.isnan(diff) else f"{diff:+.2f}") + ci, rank, reading(better, low, high)])
    return out


def verdict_markdown(root: Path) -> str:
    """The page: how to read it, then the table."""
    lines = ["# Liu et al.'s claim: the set encoder against the fixed vector", "",
             "fields_zones_overtake_collision, trained at 70 veh/km; per-run means over the last 50 episodes of "
             "each source (training also over its first 12 episodes, about the 10 000 steps over which Liu et al. "
             "compare training rewards, and over all 625), then set − vector with a 95 % percentile-bootstrap CI over "
             "runs and the two-sided rank test (pairs of runs with set above vector, ties ½; exact permutation p). "
             "Verdict: *set worse* or "
             "*set better* when the CI excludes 0 (worse: lower return, more collisions, larger speed deviation), "
             "*no difference detected* when it contains 0 (3 runs a side: low power, not equivalence), *too few runs* "
             "below 3 runs on a side. With 3 runs against 3 the percentile bootstrap resamples few distinct means "
             "and its CI is narrow, and the two-sided rank test cannot go below p = 0.10 (every set run on one side "
             "of every vector run): read both. Written by `scripts/varobs_verdict.py` from the run folders.", ""]
    lines += markdown.table(["algorithm", "source", "metric", "n (set, vector)", "set", "vector",
                             "set − vector [95 % CI]", "rank: set > vector, p", "verdict"], rows(root))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", nargs="?", type=Path, default=ROOT,
                        help="checkout holding results/ (default: this one)")
    args = parser.parse_args(argv)
    out = args.root / "results" / "varobs"
    if not out.is_dir():
        print(f"varobs_verdict: no folder {out} (run the variable-dimension experiment first)", file=sys.stderr)
        return 2
    write_atomic(out / "verdict.md", verdict_markdown(args.root))
    print(f"wrote {out / 'verdict.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
