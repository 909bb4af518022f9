"""Learning curves of grouped runs (``lanefree report`` and the sweep summary): one PNG per
metric, each group a line (mean over its runs of a trailing moving average) with a ± std band and
the paper's value dashed."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lanefree_sumo.errors import ReportError
from lanefree_sumo.experiments.analysis.paper import GroupKey, paper_reference
from lanefree_sumo.experiments.storage.rundata import RunData, RunKey

CURVE_METRICS: tuple[tuple[str, str, str], ...] = (
    # (column, file name, y-axis label with unit)
    ("return", "curves_return.png", "episode return (sum of step rewards, dimensionless)"),
    ("collisions", "curves_collisions.png", "agent collisions per episode (count)"),
    ("speed_dev_mps", "curves_speed_dev.png", "speed deviation mean |vx − v_d| (m/s)"),
)
"""Learning-curve figures: one per metric, all groups as lines."""


def group_label(key: GroupKey | RunKey) -> str:
    """Legend label ``algo / preset / d70`` (``… / variant`` for a non-default one)."""
    algo, preset, density = key[:3]
    variant = key[3] if len(key) > 3 else ""
    return f"{algo} / {preset} / d{density:g}" + (f" / {variant}" if variant else "")


def smoothed_curve(runs: Sequence[RunData], column: str, smooth: int) -> pd.DataFrame:
    """Columns ``mean``, ``std``, ``n`` per episode: each run's trailing ``smooth``-episode moving
    average, then mean and sample std (ddof=1) over the runs that reached that episode."""
    series = [r.episodes[column].rolling(window=smooth, min_periods=1).mean() for r in runs]
    aligned = pd.concat(series, axis=1)
    return pd.DataFrame({"mean": aligned.mean(axis=1), "std": aligned.std(axis=1, ddof=1),
                         "n": aligned.count(axis=1)})


def plot_curves(groups: dict[Any, list[RunData]], column: str, ylabel: str, path: Path,
                smooth: int) -> None:
    """One PNG: every group as a line (mean over runs) with a ± std band; paper value dashed."""
    try:
        from matplotlib import colormaps
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.lines import Line2D
    except ImportError as exc:  # matplotlib is an optional dependency
        raise ReportError(f"matplotlib is needed for the curves ({exc}); pip install matplotlib") from None
    fig = Figure(figsize=(9.0, 5.5), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if len(groups) <= 10:
        colours: list[Any] = [f"C{i}" for i in range(len(groups))]
    else:  # more groups than the default cycle: spread over tab20 (repeats beyond 20)
        colours = [colormaps["tab20"](i % 20) for i in range(len(groups))]
    any_paper = False
    for colour, (key, runs) in zip(colours, groups.items()):
        curve = smoothed_curve(runs, column, smooth)
        x = curve.index.to_numpy(dtype=float)
        mean = curve["mean"].to_numpy(dtype=float)
        std = curve["std"].to_numpy(dtype=float)
        ax.plot(x, mean, color=colour, lw=1.6, label=f"{group_label(key)} (n={len(runs)})")
        band = np.isfinite(std)
        if band.any():
            ax.fill_between(x, mean - np.where(band, std, 0), mean + np.where(band, std, 0),
                            where=band, color=colour, alpha=0.2, lw=0)
        ref = paper_reference(key[0], key[1], key[2], runs[0].road)
        if ref is not None and column in ("collisions", "speed_dev_mps"):
            ax.axhline(getattr(ref, column), color=colour, ls="--", lw=1.0)
            any_paper = True
    handles, labels = ax.get_legend_handles_labels()
    if any_paper:
        handles.append(Line2D([], [], color="grey", ls="--"))
        labels.append("paper value (docs/specification.md §10)")
    ax.set_xlabel("training episode")
    ax.set_ylabel(ylabel)
    ax.set_title(f"trailing {smooth}-episode moving average; line = mean, band = ± std over seeds", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, -0.12), fontsize=8, frameon=False)
    fig.savefig(path, format="png", bbox_inches="tight")


EVALUATION_FIGURES: tuple[tuple[str, str, str], ...] = (
    # (column, file name suffix, y-axis label with unit)
    ("collisions", "collisions", "agent collisions per evaluation episode (count)"),
    ("speed_dev_mps", "speed_dev", "speed deviation mean |vx − v_d| (m/s)"),
)
"""Figures of several evaluations side by side (``lanefree report RUN… --eval A B …``)."""


def evaluation_series(table: pd.DataFrame) -> list[tuple[Any, ...]]:
    """The bar series of each row of an evaluations table: (algorithm, preset, variant), and the density too
    when one evaluation holds such a series at several densities."""
    columns = ["algorithm", "reward_preset", "variant"]
    if table.groupby(["evaluation", *columns]).size().max() > 1:
        columns.append("density_veh_per_km")
    return [tuple(row) for row in table[columns].itertuples(index=False)]


def plot_evaluations(table: pd.DataFrame, column: str, ylabel: str, path: Path) -> None:
    """One PNG of grouped bars: along x the evaluations (``table['evaluation']``, in the table's order, each
    labelled with its evaluated densities), one bar per (algorithm, preset, variant) series = mean over runs of
    ``<column>_mean``, error bar ± ``<column>_std`` (sample std over runs), the value and n written above.
    When one evaluation holds a series at several densities (runs trained at 70, 90 and 120 veh/km, each
    evaluated at its own), the density is part of the series."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:  # matplotlib is an optional dependency
        raise ReportError(f"matplotlib is needed for the figures ({exc}); pip install matplotlib") from None
    evaluations = list(dict.fromkeys(table["evaluation"]))
    series = evaluation_series(table)
    series_keys = list(dict.fromkeys(series))
    fig = Figure(figsize=(max(6.0, 1.6 * len(evaluations) * max(1, len(series_keys)) ** 0.5 + 2.0), 5.0), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    width = 0.8 / len(series_keys)
    for k, key in enumerate(series_keys):
        algo, preset, variant = key[:3]
        density = f" / d{key[3]:g}" if len(key) > 3 else ""
        label: str | None = f"{algo} / {preset}{density}" + (f" / {variant}" if variant else "")
        for _, row in table[[s == key for s in series]].iterrows():
            x = evaluations.index(row["evaluation"]) - 0.4 + (k + 0.5) * width
            mean, std = float(row[f"{column}_mean"]), float(row[f"{column}_std"])
            ax.bar(x, mean, width * 0.9, color=f"C{k % 10}", label=label,
                   yerr=std if np.isfinite(std) else None, capsize=3, ecolor="black")
            label = None  # one legend entry per series
            ax.annotate(f"{mean:.2f}\nn={int(row['n_seeds'])}", (x, mean + (std if np.isfinite(std) else 0.0)),
                        ha="center", va="bottom", fontsize=7, xytext=(0, 2), textcoords="offset points")
    densities = {e: sorted(set(table.loc[table["evaluation"] == e, "density_veh_per_km"])) for e in evaluations}
    ax.set_xticks(range(len(evaluations)),
                  [f"{e}\n{', '.join(f'{d:g}' for d in densities[e])} veh/km" for e in evaluations])
    ax.set_ylabel(ylabel)
    ax.set_title("mean over runs; error bar = ± sample std over runs", fontsize=10)
    ax.grid(True, axis="y", alpha=0.3)
    ax.margins(y=0.15)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.15), fontsize=8, frameon=False)
    fig.savefig(path, format="png", bbox_inches="tight")
