"""A variant against a baseline over every source: training windows and each evaluation, run by run.

For each comparison (a label, the variant's runs and the baseline's runs) and each source (training over
episodes 1–12, about the 10 000 steps over which Liu et al. compare training rewards; over all episodes;
over the last 50; the last 50 episodes of each evaluation folder the runs have): the difference variant −
baseline of the per-run means of the return, collisions per episode and speed deviation (m/s), with the
95 % percentile-bootstrap CI over runs and the two-sided rank test of
:mod:`lanefree_sumo.experiments.analysis.claims`, decided by the claims' one rule: *<variant> worse* /
*<variant> better* when the CI excludes 0 and the rank test has p ≤ ``ALPHA`` (worse: a lower return, more
collisions, a larger speed deviation), *undecided* when only the CI does, *no difference detected* when it
contains 0 (few runs a side: low power, not equivalence), *too few runs* below :data:`MIN_RUNS` runs on a side.

A sweep whose grid names variants in ``compare`` writes this page as ``verdict.md``
(:func:`lanefree_sumo.experiments.sweep.summary.summarize`); the second paper's comparison is the
built-in grid ``varobs``. ``lanefree report RUN … --compare`` writes it for run folders of any origin: each way
the runs differ from the defaults against the default runs of the same setting (:func:`against_defaults`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from lanefree_sumo.experiments.analysis import markdown
from lanefree_sumo.experiments.analysis.claims import ALPHA, MIN_RUNS, difference_ci, per_run, rank_test
from lanefree_sumo.experiments.storage.rundata import RunData, RunKey, UnusableRunError, read_run

LIU_EPISODES = (1, 12)
"""Liu et al. compare rewards over 10 000 training steps: episodes 1–12 (800 steps each; 9600 steps)."""
TRAINING_SOURCES: tuple[tuple[str, str, tuple[int, int] | None], ...] = (
    ("", "training, episodes 1–12 (Liu et al.'s 10 000 steps)", LIU_EPISODES),
    ("", "training, all {episodes} episodes", (1, 0)),
    ("", "training, last 50 episodes", None))
"""(``""``: the training episodes; label; episodes averaged per run: a window, ``(1, 0)`` for all of them,
None for the last 50)."""
EVALUATIONS: tuple[tuple[str, str], ...] = (
    ("eval", "deterministic, 70 veh/km"),
    ("eval_d90", "zero-shot, 90 veh/km"),
    ("eval_d120", "zero-shot, 120 veh/km"),
    ("eval_onramp", "zero-shot, on-ramp"))
"""(evaluation folder, label) of the evaluations the comparison reads, in this order, where a run has them
(``lanefree evaluate RUN --out eval``; ``--density 90 --out eval_d90``; ``--scenario onramp --out eval_onramp``)."""
METRICS = (("return", "return", 1), ("collisions", "collisions / episode", -1),
           ("speed_dev_mps", "speed deviation (m/s)", -1))
"""(column, label, +1 when higher is better)."""
LAST = 50
TOO_FEW = f"too few runs (< {MIN_RUNS} a side)"


@dataclass(frozen=True)
class Sides:
    """One comparison: its label (a table's first column) and the run folders of each side."""

    label: str
    variant: Sequence[Path]
    baseline: Sequence[Path]


def setting_label(algorithm: str, preset: str, density: float) -> str:
    """A comparison's label: its setting."""
    return f"{algorithm} / {preset} / d{density:g}"


def against_defaults(groups: Mapping[RunKey, Sequence[RunData]]) -> dict[str, list[Sides]]:
    """Per variant of ``groups`` other than the defaults (``""``), one comparison per (algorithm, preset, density)
    where both the variant and the defaults have runs; variants without such a setting are left out."""
    out: dict[str, list[Sides]] = {}
    for (algorithm, preset, density, variant), runs in groups.items():
        baseline = groups.get((algorithm, preset, density, ""))
        if variant and baseline:
            out.setdefault(variant, []).append(Sides(setting_label(algorithm, preset, density),
                                                     [run.path for run in runs], [run.path for run in baseline]))
    return out


UNDECIDED = "undecided"
"""A CI off zero whose rank test does not reach :data:`~lanefree_sumo.experiments.analysis.claims.ALPHA` (3 runs a side
never does, two-sided: its smallest p is 0.10)."""


def reading(better: int, low: float, high: float, p: float, variant: str = "set") -> str:
    """The verdict of a variant − baseline difference whose CI is [low, high] and whose two-sided rank test gives
    ``p`` (``better`` +1 when higher is better): the claims' one rule, both at
    :data:`~lanefree_sumo.experiments.analysis.claims.ALPHA`."""
    if math.isnan(low):
        return TOO_FEW
    if low <= 0 <= high:
        return "no difference detected"
    if not p <= ALPHA:
        return UNDECIDED
    return f"{variant} better" if (low > 0) == (better > 0) else f"{variant} worse"


def _mean_text(values: list[float]) -> str:
    return f"{sum(values) / len(values):.2f}" if values else "–"


def readable(runs: Sequence[Path], source: str, first: int | None = None) -> list[RunData]:
    """The runs that have ``source`` (``""``: training; an evaluation a machine without the model could not run
    is absent); ``first``: training episodes 1 … ``first`` only, as :func:`~.rundata.read_run`."""
    out = []
    for run in runs:
        try:
            out.append(read_run(run, source, first))
        except UnusableRunError:
            continue
    return out


def sources(comparisons: Sequence[Sides], episodes: int,
            evaluations: bool = True) -> list[tuple[str, str, tuple[int, int] | None]]:
    """The training windows (``episodes``: the planned episodes per run) and, with ``evaluations``, every
    evaluation of :data:`EVALUATIONS` that some run of ``comparisons`` has."""
    out = [(folder, label.format(episodes=episodes), (1, episodes) if window == (1, 0) else window)
           for folder, label, window in TRAINING_SOURCES]
    if not evaluations:
        return out
    runs = [run for sides in comparisons for run in (*sides.variant, *sides.baseline)]
    for folder, label in EVALUATIONS:
        if any((run / folder / "episodes.csv").is_file() for run in runs):
            out.append((folder, label, None))
    return out


def rows(comparisons: Sequence[Sides], episodes: int, variant: str = "set",
         first: int | None = None) -> list[list[str]]:
    """One table row per comparison, source and metric: label, source, metric, runs a side, each side's mean,
    the difference with its CI, the rank test and the verdict (``variant`` names the variant in it).
    ``first``: every run read over its training episodes 1 … ``first`` only (``episodes`` is then ``first``), and
    no evaluation (they are of the final models)."""
    out = []
    every = sources(comparisons, episodes, evaluations=first is None)
    for sides in comparisons:
        read: dict[str, dict[str, list[RunData]]] = {}  # source -> side -> runs: each source read once
        for source, label, window in every:
            if source not in read:
                read[source] = {"variant": readable(sides.variant, source, first),
                                "baseline": readable(sides.baseline, source, first)}
            data = read[source]
            for column, name, better in METRICS:
                a = per_run(data["variant"], column, LAST, window)
                b = per_run(data["baseline"], column, LAST, window)
                diff, low, high = difference_ci(a, b)
                above, p = rank_test(a, b, 0)
                ci = "" if math.isnan(low) else f" [{low:+.2f}, {high:+.2f}]"
                rank = "–" if math.isnan(p) else f"{above:g}/{len(a) * len(b)}, p = {p:.2f}"
                out.append([sides.label, label, name, f"{len(a)}, {len(b)}", _mean_text(a), _mean_text(b),
                            ("–" if math.isnan(diff) else f"{diff:+.2f}") + ci, rank,
                            reading(better, low, high, p, variant)])
    return out


def verdict_markdown(comparisons: Sequence[Sides], episodes: int, title: str, setting: str,
                     written_by: str, variant: str = "set", baseline: str = "vector", label: str = "algorithm",
                     first: int | None = None) -> str:
    """The page: how to read it, then the table (``setting``: what every run trained on, a sentence's start;
    ``label``: the heading of the comparisons' column; ``first``: as :func:`rows`)."""
    cut = (f"; every run read over its first {first} training episodes only (longer runs cut there; no "
           "evaluation, those are of the final models)") if first is not None else ""
    lines = [f"# {title}", "",
             f"{setting}{cut}; per-run means over the last 50 episodes of "
             "each source (training also over its first 12 episodes, about the 10 000 steps over which Liu et al. "
             f"compare training rewards, and over all {episodes}), then {variant} − {baseline} with a 95 % "
             "percentile-bootstrap CI over runs and the two-sided rank test (pairs of runs with "
             f"{variant} above {baseline}, ties ½; exact permutation p). "
             f"Verdict, the rule of the paper's claims: *{variant} worse* or "
             f"*{variant} better* when the CI excludes 0 and the rank test has p ≤ {ALPHA} (worse: lower return, more "
             f"collisions, larger speed deviation), *{UNDECIDED}* when the CI excludes 0 but the rank test does "
             "not reach it, *no difference detected* when the CI contains 0 (few runs a side: low power, not "
             f"equivalence), *too few runs* below {MIN_RUNS} runs on a side. With 3 runs against 3 the two-sided "
             f"rank test cannot go below p = 0.10 (every {variant} run on one side of every {baseline} run), so "
             "no difference is decided there: more runs a side decide. Written by "
             f"{written_by} from the run folders.", ""]
    lines += markdown.table([label, "source", "metric", f"n ({variant}, {baseline})", variant, baseline,
                             f"{variant} − {baseline} [95 % CI]", f"rank: {variant} > {baseline}, p", "verdict"],
                            rows(comparisons, episodes, variant, first))
    return "\n".join(lines) + "\n"
