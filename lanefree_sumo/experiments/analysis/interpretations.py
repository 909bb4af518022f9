"""The interpretation study's score and pick, as ``results/interpretations/protocol.md`` fixes them.

For a variant v and the seven DDPG cells of Tables 5–6 at 70 veh/km: each run's means of ``collisions`` and
``speed_dev_mps`` over its last 50 training episodes; per cell the means over its runs (seeds 0–4), C(v, c) and
S(v, c); the distance to the paper

    D(v) = (1 / 14) · Σ_c [ |ln(C(v, c) / P_C(c))| + |ln(S(v, c) / P_S(c))| ]

(a cell mean of 0 enters as :data:`FLOOR`); the pick is the variant of smallest D, ties to the earlier of
:data:`VARIANTS`. Where a variant does not change a cell (no overtake bonus is paid there) its runs are another
variant's (:data:`STANDS_FOR`). Beside the pick, not deciding: D(v) − D(default) with a 95 % percentile bootstrap
CI, the runs resampled within each cell and paired by seed across variants.

The inputs are the per-run tables ``runs.csv`` of sweep folders (``lanefree sweep --summary`` writes them: one
row per complete run with its last-50 means), so every figure comes from committed ``episodes.csv`` files.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lanefree_sumo.experiments.analysis.paper import DEFAULT_DENSITY, paper_reference

VARIANTS: tuple[str, ...] = ("default", "once_per_vehicle", "cap25", "both")
"""The variants of the protocol, in the order that breaks ties."""
CELLS: tuple[str, ...] = ("collision", "fields", "fields_collision", "overtake_collision", "fields_overtake_collision",
                          "fields_zones_overtake_collision", "zones_overtake_collision")
"""The reward presets of the seven DDPG cells of Tables 5–6 (70 veh/km)."""
BONUS_CELLS: tuple[str, ...] = ("overtake_collision", "fields_overtake_collision", "fields_zones_overtake_collision",
                                "zones_overtake_collision")
"""The cells whose preset pays an overtake bonus: the bonus variants differ from the others only there."""
STANDS_FOR: Mapping[str, str] = {"once_per_vehicle": "default", "both": "cap25"}
"""Where no bonus is paid, a bonus variant's runs are these variants' runs."""
SEEDS: tuple[int, ...] = (0, 1, 2, 3, 4)
"""The seeds of every cell."""
FLOOR = 0.01
"""A cell mean of 0 collisions per episode enters the log ratio as this (below any value the paper reports)."""
METRICS: tuple[str, ...] = ("collisions", "speed_dev_mps")
"""The two metrics of the score (the per-step |v_x − v_d| reading of the speed deviation)."""


@dataclass(frozen=True)
class Score:
    """A variant's distance to the paper: D, the per-cell log ratios ``{preset: (collisions, speed)}`` and, for
    variants other than the default, D − D(default) with its bootstrap CI (NaN for the default)."""

    variant: str
    distance: float
    log_ratios: dict[str, tuple[float, float]]
    difference: float
    low: float
    high: float


def source_variant(variant: str, preset: str) -> str:
    """The variant whose runs stand for ``variant`` in the cell of ``preset`` (:data:`STANDS_FOR`)."""
    return STANDS_FOR.get(variant, variant) if preset not in BONUS_CELLS else variant


def cell_values(runs: pd.DataFrame, variant: str) -> dict[str, np.ndarray]:
    """``{preset: [seeds, 2]}``: each cell's runs (seeds :data:`SEEDS` in order) × (collisions, speed deviation)
    of ``variant`` from ``runs`` (columns ``variant``, ``reward_preset``, ``density``, ``seed`` and :data:`METRICS`;
    the default's rows have variant ``default`` or ""). ValueError naming a missing run."""
    out = {}
    for preset in CELLS:
        source = source_variant(variant, preset)
        names = {source} | ({""} if source == "default" else set())
        cell = runs[runs["variant"].astype(object).fillna("").isin(names) & (runs["reward_preset"] == preset)
                    & np.isclose(runs["density"].astype(float), DEFAULT_DENSITY) & runs["seed"].isin(SEEDS)]
        cell = cell.sort_values("seed")
        if list(cell["seed"]) != list(SEEDS):
            raise ValueError(f"variant {variant}: the {preset} cell ({source}'s runs) has seeds {list(cell['seed'])}, "
                             f"not {list(SEEDS)}")
        out[preset] = cell[list(METRICS)].to_numpy(dtype=float)
    return out


def distance(values: Mapping[str, np.ndarray]) -> tuple[float, dict[str, tuple[float, float]]]:
    """D and the per-cell log ratios ln(ours / paper) of cell values ``{preset: [runs, 2]}`` (module docstring)."""
    ratios = {}
    for preset in CELLS:
        ref = paper_reference("ddpg", preset, DEFAULT_DENSITY)
        assert ref is not None
        means = values[preset].mean(axis=0)
        ratios[preset] = (math.log(max(means[0], FLOOR) / ref.collisions), math.log(max(means[1], FLOOR)
                                                                                      / ref.speed_dev_mps))
    return float(np.mean([abs(r) for pair in ratios.values() for r in pair])), ratios


def scores(runs: pd.DataFrame, variants: Sequence[str] = VARIANTS, resamples: int = 10_000,
           seed: int = 0) -> list[Score]:
    """Every variant's :class:`Score` (module docstring); the bootstrap draws the same seeds for every variant
    in a cell (paired by seed), from ``numpy.random.default_rng(seed)``."""
    values = {v: cell_values(runs, v) for v in variants}
    rng = np.random.default_rng(seed)
    draws = {preset: rng.integers(0, len(SEEDS), size=(resamples, len(SEEDS))) for preset in CELLS}
    boot = {}
    for v in variants:
        samples = np.empty(resamples)
        for i in range(resamples):
            samples[i] = distance({p: values[v][p][draws[p][i]] for p in CELLS})[0]
        boot[v] = samples
    out = []
    base = distance(values["default"])[0] if "default" in values else math.nan
    for v in variants:
        d, ratios = distance(values[v])
        if v == "default" or "default" not in values:
            out.append(Score(v, d, ratios, math.nan, math.nan, math.nan))
            continue
        diff = boot[v] - boot["default"]
        low, high = np.percentile(diff, [2.5, 97.5])
        out.append(Score(v, d, ratios, d - base, float(low), float(high)))
    return out


def pick(results: Sequence[Score]) -> Score:
    """The variant of smallest D, ties to the earlier in :data:`VARIANTS` order."""
    order = {v: i for i, v in enumerate(VARIANTS)}
    return min(results, key=lambda s: (s.distance, order.get(s.variant, len(order))))


def phase1_markdown(results: Sequence[Score]) -> str:
    """The phase-1 table: D per variant, D − D(default) [CI], the pick, the per-cell log ratios."""
    chosen = pick(results)
    lines = ["| variant | D (mean abs log ratio) | D − D(default) [95 % CI] |", "|---|---|---|"]
    for s in results:
        diff = "–" if math.isnan(s.difference) else f"{s.difference:+.3f} [{s.low:+.3f}, {s.high:+.3f}]"
        lines.append(f"| {'**' + s.variant + '**' if s is chosen else s.variant} | {s.distance:.3f} | {diff} |")
    undecided = not math.isnan(chosen.difference) and chosen.low <= 0.0 <= chosen.high
    lines += ["", f"Picked: **{chosen.variant}**" + (" (not distinguishable from the defaults: the CI of D − "
                                                      "D(default) contains 0)" if undecided else ""), "",
              "ln(ours / paper) per cell, collisions / speed deviation:", "",
              "| cell | " + " | ".join(s.variant for s in results) + " |", "|---|" + "---|" * len(results)]
    for preset in CELLS:
        lines.append(f"| {preset} | " + " | ".join(f"{s.log_ratios[preset][0]:+.2f} / {s.log_ratios[preset][1]:+.2f}"
                                                   for s in results) + " |")
    return "\n".join(lines) + "\n"


PHASE1_SOURCES: tuple[str, ...] = ("paper", "interpretations/phase1_bonus", "interpretations/phase1_cap25")
"""The sweep folders under ``results/`` whose ``runs.csv`` phase 1 reads: the defaults' and the two grids'."""


def phase1_runs(results: Path) -> pd.DataFrame:
    """The runs of phase 1 from the ``runs.csv`` of :data:`PHASE1_SOURCES` under ``results`` (the defaults' from
    ``results/paper``, their variant empty: :func:`cell_values` reads it as ``default``); FileNotFoundError naming a
    missing table."""
    frames = []
    for name in PHASE1_SOURCES:
        table = pd.read_csv(results / name / "runs.csv")
        frames.append(table[table["algorithm"] == "ddpg"])
    return pd.concat(frames)  # the rows' index is not read: cells are picked by their columns


RUN_FOLDERS: Mapping[str, str] = {"default": "paper", "once_per_vehicle": "interpretations/phase1_bonus",
                                  "both": "interpretations/phase1_bonus", "cap25": "interpretations/phase1_cap25"}
"""The sweep folder under ``results/`` holding each variant's run folders."""


def run_folder(results: Path, variant: str, preset: str, seed: int) -> Path:
    """The run folder of ``variant``'s ``preset`` cell, seed ``seed`` (the variant it stands for where it does not
    differ: :func:`source_variant`)."""
    source = source_variant(variant, preset)
    suffix = "" if source == "default" else f"_{source}"
    return results / RUN_FOLDERS[source] / "runs" / f"ddpg_{preset}_d{DEFAULT_DENSITY:g}{suffix}_s{seed}"


def claims_by_variant(results: Path, variants: Sequence[str] = VARIANTS) -> pd.DataFrame:
    """The paper's claims of Tables 5–6 decided under each variant (the claims' own rule and columns, one block of
    rows per variant, column ``variant``), from the run folders' ``episodes.csv``."""
    from lanefree_sumo.experiments.analysis.claims import check_claims, decidable
    from lanefree_sumo.experiments.storage.rundata import read_run

    comparisons = decidable({("ddpg", preset, DEFAULT_DENSITY) for preset in CELLS})
    tables = []
    for variant in variants:
        groups = {("ddpg", preset, DEFAULT_DENSITY): [read_run(run_folder(results, variant, preset, seed))
                                                      for seed in SEEDS] for preset in CELLS}
        tables.append(check_claims(groups, comparisons=comparisons).assign(variant=variant))
    return pd.concat(tables, ignore_index=True)


def claims_markdown(table: pd.DataFrame) -> str:
    """One row per claim, one verdict column per variant (alone; and as a family, after the slash)."""
    variants = list(dict.fromkeys(table["variant"]))
    lines = ["| claim | " + " | ".join(variants) + " |", "|---|" + "---|" * len(variants)]
    for claim in dict.fromkeys(table["claim"]):
        cells = []
        for v in variants:
            row = table[(table["claim"] == claim) & (table["variant"] == v)].iloc[0]
            cells.append(f"{row['verdict']} / {row['verdict_holm']}")
        lines.append(f"| {claim} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


READINGS: tuple[tuple[str, str], ...] = (
    ("collisions", "collisions / episode"),
    ("speed_dev_mps", "per-step \\|v_x − v_d\\| (m/s)"),
    ("speed_dev_episode_mps", "per-episode \\|mean v_x − v_d\\| (m/s)"),
    ("speed_error_mps", "signed mean v_x − v_d (m/s)"),
)
"""(``episodes.csv`` column, label): the collisions and the three readings of the speed deviation
(``protocol.md``), reported per cell; the score reads the first two."""
LAST = 50
"""The training episodes at the end of each run that every figure of phase 1 averages."""


def readings_by_variant(results: Path, variants: Sequence[str] = VARIANTS) -> pd.DataFrame:
    """Per variant and cell (rows in that order): the means over the cell's runs of each run's last
    :data:`LAST`-episode means of :data:`READINGS`, the runs that race (a last-50 mean speed above
    :data:`~.effects.RACING_SPEED_MPS`), and the paper's values; from the run folders' ``episodes.csv``."""
    from lanefree_sumo.experiments.analysis.effects import RACING_SPEED_MPS
    from lanefree_sumo.experiments.storage.rundata import read_run

    rows = []
    for variant in variants:
        for preset in CELLS:
            runs = [read_run(run_folder(results, variant, preset, seed)).episodes.iloc[-LAST:] for seed in SEEDS]
            ref = paper_reference("ddpg", preset, DEFAULT_DENSITY)
            assert ref is not None
            rows.append({"variant": variant, "cell": preset,
                         **{m: float(np.mean([r[m].mean() for r in runs])) for m, _ in READINGS},
                         "racing": sum(int(r["mean_speed_mps"].mean() > RACING_SPEED_MPS) for r in runs),
                         "paper_collisions": ref.collisions, "paper_speed_dev_mps": ref.speed_dev_mps})
    return pd.DataFrame(rows)


def readings_markdown(table: pd.DataFrame) -> str:
    """One row per cell and variant: collisions and the three speed readings beside the paper's, the racing runs."""
    lines = ["| cell | variant | " + " | ".join(label for _, label in READINGS) + " | paper: collisions / speed "
             "deviation | racing runs |", "|---|---|" + "---|" * (len(READINGS) + 2)]
    for preset in CELLS:
        for row in table[table["cell"] == preset].itertuples():
            values = " | ".join(f"{getattr(row, m):.2f}" for m, _ in READINGS)
            lines.append(f"| {preset} | {row.variant} | {values} | {row.paper_collisions:g} / "
                         f"{row.paper_speed_dev_mps:g} | {row.racing} of {len(SEEDS)} |")
    return "\n".join(lines) + "\n"


FIGURE_METRICS: tuple[str, ...] = ("collisions / episode", "speed deviation per step (m/s)")
"""The two panels of :func:`ours_vs_paper`, in :data:`METRICS` order."""


def figure_points(results: Sequence[Score]) -> list[dict[str, tuple[list[float], list[float]]]]:
    """Per metric (:data:`METRICS` order), per variant: (the paper's values, ours) over :data:`CELLS` — ours the
    paper's times exp(the cell's log ratio), i.e. the cell's mean (or :data:`FLOOR` for a cell mean of 0)."""
    out: list[dict[str, tuple[list[float], list[float]]]] = []
    for m in range(len(METRICS)):
        panel = {}
        for s in results:
            paper = []
            for preset in CELLS:
                ref = paper_reference("ddpg", preset, DEFAULT_DENSITY)
                assert ref is not None
                paper.append(ref.collisions if m == 0 else ref.speed_dev_mps)
            panel[s.variant] = (paper, [v * math.exp(s.log_ratios[c][m]) for v, c in zip(paper, CELLS)])
        out.append(panel)
    return out


def ours_vs_paper(results: Sequence[Score], path: Path) -> Any:
    """The log-log figure at ``path`` (PNG, 1100 × 495 pixels): each cell's value against the paper's, per metric
    (:data:`FIGURE_METRICS`) and variant, with the diagonal (equal) over the points' span widened 1.5× either
    way; returns the (closed) matplotlib figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    for ax, label, panel in zip(axes, FIGURE_METRICS, figure_points(results)):
        for variant, (paper, ours) in panel.items():
            ax.scatter(paper, ours, label=variant)
        values = [v for paper, ours in panel.values() for v in paper + ours]
        span = [min(values) / 1.5, max(values) * 1.5]
        ax.plot(span, span, color="grey", lw=1)
        ax.set(xscale="log", yscale="log", xlabel=f"paper: {label}", ylabel=f"ours: {label}")
    axes[0].legend(title="variant")
    fig.suptitle("Tables 5–6, DDPG, 70 veh/km: each cell's last-50 mean over 5 runs against the paper's")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return fig


def write_phase1(results: Path) -> Path:
    """``results/interpretations/phase1.md`` and ``ours_vs_paper.png`` from the committed run tables."""
    out = results / "interpretations"
    found = scores(phase1_runs(results))
    (out / "phase1.md").write_text(phase1_page(results, found))
    ours_vs_paper(found, out / "ours_vs_paper.png")
    return out / "phase1.md"


def phase1_page(results: Path, found: Sequence[Score] | None = None) -> str:
    """The text of ``phase1.md`` from the run tables and run folders under ``results`` (``found``: the scores,
    computed here when not given)."""
    if found is None:
        found = scores(phase1_runs(results))
    return ("# Interpretation study, phase 1: the distance to the paper\n\n"
            "Computed by `python -m lanefree_sumo.experiments.analysis.interpretations` from the `runs.csv` of "
            + ", ".join(f"`results/{name}`" for name in PHASE1_SOURCES)
            + " as `protocol.md` defines it: 7 DDPG cells of Tables 5–6 at 70 veh/km, seeds 0–4, each run's last 50 "
            "training episodes.\n\n" + phase1_markdown(found) + "\n![ours against the paper](ours_vs_paper.png)\n\n"
            "## Every cell under the three readings of the speed deviation\n\nMeans over the cell's 5 runs of each "
            f"run's last {LAST} training episodes (the score reads the collisions and the per-step reading); a run "
            "races when its last-50 mean speed is above 24 m/s (the desired speed is 20). Where a variant does not "
            "change a cell, its runs are those of the variant it stands for (`protocol.md`).\n\n"
            + readings_markdown(readings_by_variant(results)) + "\n"
            "## The paper's claims of Tables 5–6 under each variant\n\nEach cell: the verdict of the claim alone / as "
            "one family of this variant's claims (Holm; `lanefree_sumo/experiments/analysis/claims.py`), 5 runs a "
            "side.\n\n"
            + claims_markdown(claims_by_variant(results)))


if __name__ == "__main__":
    import sys

    try:
        print(write_phase1(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("results")))
    except (FileNotFoundError, ValueError) as exc:
        raise SystemExit(f"error: {exc}") from None
