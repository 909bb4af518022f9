"""What each variant of a sweep does to each cell, measured against the sweep's ``default`` variant.

A *cell* is an (algorithm, reward preset, density) of the grid; a *variant* one open modelling choice
switched (a grid's ``variants``). Per cell and variant, over the runs' last ``last`` episodes:

* **racing fraction**: the share of runs whose mean speed is above :data:`RACING_SPEED_MPS` (the agent's
  desired speed is 20 m/s; a calm run holds 18–21, a racing one 25–30);
* per metric (collisions, the speed deviation per step and per episode, overtakes, the return and its three
  parts): the variant's mean over runs minus the default's, the 95 % percentile-bootstrap CI of that
  difference (each group resampled on its own) and the exact two-sided permutation p of the rank test
  (:func:`~lanefree_sumo.experiments.analysis.claims.rank_test`).

Verdict per cell and variant (:func:`verdict`):

* *decides racing*: the racing fractions differ by at least one half and the mean speeds differ (rank test
  p ≤ :data:`ALPHA`);
* *moves the numbers*: otherwise, a metric whose CI excludes 0 with p ≤ :data:`ALPHA`;
* *no effect detected*: neither (with few runs a lack of power, not evidence of no effect);
* *too few runs*: fewer than :data:`~lanefree_sumo.experiments.analysis.claims.MIN_RUNS` complete runs on a side.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import pandas as pd

from lanefree_sumo.experiments.analysis import markdown
from lanefree_sumo.experiments.analysis.claims import ALPHA, MIN_RUNS, difference_ci, rank_test
from lanefree_sumo.experiments.storage.rundata import RunData, RunKey

RACING_SPEED_MPS = 24.0
"""A run races when its mean speed over its last episodes is above this (m/s)."""
BASELINE = "default"
"""The variant every other is measured against."""
EFFECT_METRICS: tuple[tuple[str, str], ...] = (
    ("mean_speed_mps", "mean speed (m/s)"),
    ("collisions", "collisions / episode"),
    ("speed_dev_mps", "speed deviation per step (m/s)"),
    ("speed_dev_episode_mps", "speed deviation per episode (m/s)"),
    ("overtakes", "overtakes / episode"),
    ("return", "return"),
    ("return_reciprocal", "return: reciprocal term"),
    ("return_bonus", "return: overtake bonus"),
    ("return_collision", "return: collision penalty"),
)
"""(episodes.csv column, label): the metrics compared, in the tables' order."""
COLUMNS = ("algorithm", "reward_preset", "density", "variant", "metric", "n_default", "n_variant", "default_mean",
           "variant_mean", "difference", "ci95_low", "ci95_high", "rank_p")
"""Columns of ``effects.csv``: one row per cell, variant and metric (``racing_fraction`` first)."""


def _per_run(runs: Sequence[RunData], metric: str, last: int) -> list[float]:
    """Each run's mean of ``metric`` over its last ``last`` episodes (runs without the column left out)."""
    return [float(r.episodes[metric].iloc[-last:].mean()) for r in runs if metric in r.episodes]


def _racing(runs: Sequence[RunData], last: int) -> list[float]:
    """1.0 for each run that races (:data:`RACING_SPEED_MPS`), else 0.0."""
    return [float(v > RACING_SPEED_MPS) for v in _per_run(runs, "mean_speed_mps", last)]


def effect_table(groups: Mapping[RunKey, Sequence[RunData]], last: int = 50) -> pd.DataFrame:
    """The rows of ``effects.csv`` (:data:`COLUMNS`) for every cell that has the :data:`BASELINE` variant."""
    records = []
    for (algo, preset, density, variant), runs in groups.items():
        base = groups.get((algo, preset, density, BASELINE))
        if variant == BASELINE or base is None:
            continue
        metrics = [("racing_fraction", _racing(base, last), _racing(runs, last))]
        metrics += [(m, _per_run(base, m, last), _per_run(runs, m, last)) for m, _ in EFFECT_METRICS]
        for metric, a, b in metrics:
            diff, low, high = difference_ci(b, a)
            records.append({
                "algorithm": algo, "reward_preset": preset, "density": density, "variant": variant,
                "metric": metric, "n_default": len(a), "n_variant": len(b),
                "default_mean": float(np.mean(a)) if a else math.nan,
                "variant_mean": float(np.mean(b)) if b else math.nan, "difference": diff,
                "ci95_low": low, "ci95_high": high, "rank_p": rank_test(b, a, 0)[1]})
    return pd.DataFrame.from_records(records, columns=list(COLUMNS))


def verdict(rows: pd.DataFrame) -> str:
    """The verdict (module docstring) of one cell and variant from its rows of :func:`effect_table`."""
    by_metric = rows.set_index("metric")
    if min(by_metric["n_default"].min(), by_metric["n_variant"].min()) < MIN_RUNS:
        return "too few runs"
    racing, speed = by_metric.loc["racing_fraction"], by_metric.loc["mean_speed_mps"]
    if abs(racing["difference"]) >= 0.5 and speed["rank_p"] <= ALPHA:
        return "decides racing"
    moved = by_metric[(by_metric["rank_p"] <= ALPHA) & ((by_metric["ci95_low"] > 0) | (by_metric["ci95_high"] < 0))]
    return "moves the numbers" if len(moved.index.difference(["racing_fraction"])) else "no effect detected"


def _figure(row: pd.Series, digits: int) -> str:
    """``variant − default [CI] (p)`` of one row."""
    if math.isnan(row["difference"]):
        return "–"
    ci = "" if math.isnan(row["ci95_low"]) else f" [{row['ci95_low']:+.{digits}f}, {row['ci95_high']:+.{digits}f}]"
    p = "" if math.isnan(row["rank_p"]) else f" (p {row['rank_p']:.3f})"
    return f"{row['difference']:+.{digits}f}{ci}{p}"


VERDICTS = ("decides racing", "moves the numbers", "no effect detected", "too few runs")
"""The verdicts from the strongest to the weakest: a choice's verdict over several cells is its strongest."""


def _explanation(last: int) -> str:
    return (f"Per run: the mean over its last {last} episodes. Racing: a run whose mean speed is above "
            f"{RACING_SPEED_MPS:g} m/s. Each figure: the variant's mean over runs minus the default's, "
            "[95 % percentile-bootstrap CI] (exact two-sided rank-test p). Verdicts: *decides racing* (the racing "
            f"fractions differ by half or more and the mean speeds with p ≤ {ALPHA}), *moves the numbers* (a CI "
            f"excludes 0 with p ≤ {ALPHA}), *no effect detected* (with few runs: low power), *too few runs* "
            f"(below {MIN_RUNS} a side).")


def _cell_name(algo: str, preset: str, density: float) -> str:
    return f"{algo} / {preset} / {density:g} veh/km"


def _racing_share(by_metric: pd.DataFrame) -> str:
    """``default → variant`` racing fractions of one cell and variant, – where a side has no run."""
    racing = by_metric.loc["racing_fraction"]
    if math.isnan(racing["default_mean"]) or math.isnan(racing["variant_mean"]):
        return "–"
    return f"{racing['default_mean']:.0%} → {racing['variant_mean']:.0%}"


def _run_counts(by_metric: pd.DataFrame) -> str:
    """``default, variant``: the complete runs a side of one cell and variant."""
    racing = by_metric.loc["racing_fraction"]
    return f"{int(racing['n_default'])}, {int(racing['n_variant'])}"


def overview(table: pd.DataFrame) -> tuple[list[str], list[list[str]]]:
    """(headers, rows) of the choice-by-cell table: per variant its verdict in each cell (with the racing
    fractions and the runs a side; – where it has no complete runs) and its strongest verdict over the cells where
    it was measured with enough runs (*too few runs* only where no cell has enough)."""
    cells = list(dict.fromkeys(zip(table["algorithm"], table["reward_preset"], table["density"])))
    rows = []
    for variant, of_variant in table.groupby("variant", sort=False):
        found: list[str] = []
        entries = []
        for algo, preset, density in cells:
            rows_of = of_variant[(of_variant["algorithm"] == algo) & (of_variant["reward_preset"] == preset)
                                 & (of_variant["density"] == density)]
            if rows_of.empty:  # not in that sweep's grid, or none of its runs complete
                entries.append("–")
                continue
            by_metric = rows_of.set_index("metric")
            found.append(verdict(rows_of))
            entries.append(f"{found[-1]} (racing {_racing_share(by_metric)}; runs {_run_counts(by_metric)})")
        rows.append([str(variant), min(found, key=VERDICTS.index), *entries])
    return ["choice", "verdict (strongest over the cells)", *(_cell_name(*cell) for cell in cells)], rows


def study_markdown(table: pd.DataFrame, last: int, sources: Sequence[str]) -> str:
    """The study page of several sweeps' effects (``lanefree report SWEEP SWEEP … --out DIR``: ``effects.md``):
    the choice-by-cell table (:func:`overview`), then each cell's figures as in a sweep's ``effects.md``."""
    lines = ["# Each open choice against the defaults, every cell", "",
             f"From the sweeps {', '.join(f'`{s}`' for s in sources)}. {_explanation(last)}", ""]
    if table.empty:
        return "\n".join(lines + ["No cell has both a `default` and another variant with complete runs yet.", ""])
    headers, rows = overview(table)
    lines += markdown.table(headers, rows, fence="effects-overview")
    lines += ["", "Runs: the default's and the choice's complete runs in the cell. –: no complete runs of the choice "
              "in that cell (not in its grid, or not finished).", ""]
    return "\n".join(lines + _cell_sections(table))


def effects_markdown(table: pd.DataFrame, last: int) -> str:
    """``effects.md``: per cell, one row per variant with its verdict, racing fraction and each metric's
    difference from the default."""
    lines = ["# Each open choice against the defaults", "", _explanation(last), ""]
    if table.empty:
        return "\n".join(lines + ["No cell has both a `default` and another variant with complete runs yet.", ""])
    return "\n".join(lines + _cell_sections(table))


def _cell_sections(table: pd.DataFrame) -> list[str]:
    """Per cell: a heading and one row per variant with its verdict, racing fraction and each metric's
    difference from the default."""
    lines: list[str] = []
    shown = ("collisions", "speed_dev_mps", "speed_dev_episode_mps", "overtakes", "return", "return_bonus")
    labels = dict(EFFECT_METRICS)
    for (algo, preset, density), cell in table.groupby(["algorithm", "reward_preset", "density"], sort=False):
        lines += [f"## {_cell_name(algo, preset, density)}", ""]
        headers = ["variant", "runs (default, variant)", "verdict", "racing runs (default → variant)",
                   *(labels[m] for m in shown)]
        rows = []
        for variant, rows_of in cell.groupby("variant", sort=False):
            by_metric = rows_of.set_index("metric")
            rows.append([str(variant), _run_counts(by_metric), verdict(rows_of), _racing_share(by_metric),
                         *(_figure(by_metric.loc[m], 2) for m in shown)])
        lines += markdown.table(headers, rows, fence=f"effects-{algo}-{preset}-{density:g}") + [""]
    return lines
