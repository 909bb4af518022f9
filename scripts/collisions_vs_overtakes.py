"""Collisions against overtakes, one point per run (what drives the gap to the paper).

Reads a sweep's ``runs.csv`` (``lanefree report SWEEP`` writes it) and draws two panels: the last 50
training episodes (with exploration noise) and the deterministic evaluation (``eval/``, where a run has
one), collisions per episode against overtakes per episode, log-log, one marker per algorithm and one
colour per reward preset and density. Each panel's title carries the Spearman rank correlation over its
runs. Writes ``collisions_vs_overtakes.png`` into the sweep folder.

    python scripts/collisions_vs_overtakes.py [SWEEP]   (default results/paper)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
MARKERS = {"ddpg": "o", "dqn": "s", "ddqn": "D", "dueling": "^", "per": "v"}
FLOOR = 0.1
"""Means below it (per episode; 0 collisions with the shield, say) are drawn at it: a log axis cannot show 0."""


def settings(runs: pd.DataFrame) -> pd.Series:
    """Each run's reward preset and density, as the legend names it."""
    return runs["reward_preset"] + " " + runs["density"].map("{:g} veh/km".format)


def panels(runs: pd.DataFrame) -> list[tuple[str, pd.DataFrame]]:
    """(title, frame with columns setting, algorithm, overtakes, collisions) of each panel with runs."""
    out = []
    for title, prefix in (("training, last 50 episodes", ""), ("deterministic evaluation", "eval_")):
        if prefix and not {f"{prefix}episodes", f"{prefix}overtakes", f"{prefix}collisions"} <= set(runs):
            continue  # a runs.csv without evaluation columns
        chosen = runs[runs[f"{prefix}episodes"] > 0] if prefix else runs
        frame = pd.DataFrame({
            "setting": settings(chosen),
            "algorithm": chosen["algorithm"],
            "overtakes": chosen[f"{prefix}overtakes"].astype(float),
            "collisions": chosen[f"{prefix}collisions"].astype(float),
        })
        if len(frame):
            out.append((title, frame))
    return out


def draw(runs: pd.DataFrame, path: Path) -> None:
    """The figure of :func:`panels` into ``path`` (PNG)."""
    shown = panels(runs)
    figure, axes = plt.subplots(1, len(shown), figsize=(6.5 * len(shown), 5.5), squeeze=False)
    colours = {s: plt.get_cmap("tab20")(k % 20) for k, s in enumerate(sorted(set(settings(runs))))}
    for ax, (title, frame) in zip(axes[0], shown):
        for (setting, algorithm), group in frame.groupby(["setting", "algorithm"]):
            ax.scatter(group["overtakes"].clip(lower=FLOOR), group["collisions"].clip(lower=FLOOR),
                       marker=MARKERS.get(algorithm, "x"), color=colours[setting], s=42, alpha=0.85,
                       edgecolors="black", linewidths=0.4, label=f"{algorithm}, {setting}")
        rho = frame["overtakes"].corr(frame["collisions"], method="spearman")
        ax.set(xscale="log", yscale="log", xlabel=f"overtakes per episode (below {FLOOR:g}: at {FLOOR:g})",
               ylabel=f"collisions per episode (below {FLOOR:g}: at {FLOOR:g})",
               title=f"{title}: {len(frame)} runs, Spearman ρ = {rho:.2f}")
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", ncol=3, fontsize=8, frameon=False)
    figure.tight_layout(rect=(0, 0.06 + 0.025 * ((len(labels) + 2) // 3), 1, 1))
    figure.savefig(path, dpi=110)
    plt.close(figure)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep", nargs="?", type=Path, default=ROOT / "results" / "paper",
                        help="a sweep folder holding runs.csv")
    args = parser.parse_args(argv)
    source = args.sweep / "runs.csv"
    if not source.is_file():
        print(f"collisions_vs_overtakes: {source} does not exist; run `lanefree report {args.sweep}` first",
              file=sys.stderr)
        return 2
    runs = pd.read_csv(source)
    missing = {"algorithm", "reward_preset", "density", "overtakes", "collisions"} - set(runs)
    if missing:
        print(f"collisions_vs_overtakes: {source} lacks column(s) {', '.join(sorted(missing))}; is it a sweep's "
              "runs.csv?", file=sys.stderr)
        return 2
    out = args.sweep / "collisions_vs_overtakes.png"
    if runs.empty:  # no complete run yet: nothing to draw, and no figure of runs that are gone
        out.unlink(missing_ok=True)
        print(f"{source}: no complete run yet, no figure")
        return 0
    draw(runs, out)
    print(f"{out}: {len(runs)} runs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
