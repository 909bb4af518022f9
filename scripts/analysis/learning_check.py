"""Learning check of a training path against reference runs: DDPG fzoc 70 veh/km, the first
150 episodes of each run. Prints the mean over episodes 101–150 per run and per group, the difference of
group means with a 95 % bootstrap CI over runs, and draws the smoothed curves of both groups in one PNG.

    python scripts/analysis/learning_check.py --new RUN [RUN ...] --reference RUN [RUN ...] --out FILE.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from lanefree_sumo.experiments.analysis.claims import difference_ci  # noqa: E402

METRICS = ("collisions", "speed_dev_mps", "overtakes", "return")


def first(run: Path, episodes: int) -> pd.DataFrame:
    return pd.read_csv(run / "episodes.csv").set_index("episode").loc[1:episodes]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--new", type=Path, nargs="+", required=True)
    parser.add_argument("--reference", type=Path, nargs="+", required=True)
    parser.add_argument("--episodes", type=int, default=150)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    groups = {"new": [first(r, args.episodes) for r in args.new],
              "reference": [first(r, args.episodes) for r in args.reference]}
    window = slice(args.episodes - 49, args.episodes)
    print(f"| metric (episodes {window.start}–{window.stop}) | new runs | reference runs | new − reference [95 % CI] |")
    print("|---|---|---|---|")
    for metric in METRICS:
        per = {g: [float(d[metric].loc[window].mean()) for d in runs] for g, runs in groups.items()}
        diff, low, high = difference_ci(per["new"], per["reference"])
        print(f"| {metric} | {' / '.join(f'{v:.2f}' for v in per['new'])} | "
              f"{' / '.join(f'{v:.2f}' for v in per['reference'])} | {diff:+.2f} [{low:+.2f}, {high:+.2f}] |")
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, metric in zip(axes, METRICS[:3]):
        for g, colour in (("reference", "tab:blue"), ("new", "tab:orange")):
            for k, d in enumerate(groups[g]):
                ax.plot(d.index, d[metric].rolling(10, min_periods=1).mean(), color=colour, alpha=0.8,
                        label=f"{g}" if k == 0 else None)
        ax.set_title(metric)
        ax.set_xlabel("episode")
    axes[0].legend()
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)


if __name__ == "__main__":
    main()
