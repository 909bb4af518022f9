"""Rewrite the README's results table from a sweep's ``summary.csv`` (one source for the numbers).

The table sits between ``<!-- results-table -->`` and ``<!-- /results-table -->`` in README.md; one row per
setting of the summary, in its order: runs complete, and per metric the mean over runs [95 % bootstrap CI
over runs] (the paper's value). Everything outside the markers is left as it is; the file is replaced whole
(``write_atomic``: written next to it, then renamed), so a reader never sees half a table.

    python scripts/readme_results.py [--summary results/paper/summary.csv] [--readme README.md]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import pandas as pd

from lanefree_sumo.experiments.storage.rundir import write_atomic
from lanefree_sumo.experiments.sweep.summary import interval_text

ROOT = Path(__file__).resolve().parent.parent
BEGIN, END = "<!-- results-table -->", "<!-- /results-table -->"
ALGORITHM_LABELS = {"ddpg": "", "dqn": "**DQN**", "ddqn": "**DDQN**", "dueling": "**dueling DDQN**",
                    "per": "**PER** (DDQN, prioritised replay)"}
HEADER = ("| DDPG unless noted, reward preset (70 veh/km unless noted) | runs | collisions / episode (paper) "
          "| speed deviation per step, mean \\|v_x − v_d\\| in m/s (paper) | per episode, \\|mean (v_x − v_d)\\| "
          "| signed, mean (v_x − v_d) | \\|ln(ours / paper)\\|: collisions, per step, per episode, \\|signed\\| |"
          "\n|---|---|---|---|---|---|---|")
"""The paper's speed figure read three ways (docs/interpretation.md): the headline one per step, as the paper words
it and results/interpretations/protocol.md argues; the per-episode magnitude and the signed mean beside it."""


def cell(row: pd.Series, metric: str) -> str:
    """``mean [low, high] (paper)`` of ``metric`` to 2 decimals (the summary's own format, shorter)."""
    text = interval_text(row[f"{metric}_mean"], row[f"{metric}_ci95_low"], row[f"{metric}_ci95_high"], digits=2)
    paper = row[f"paper_{metric}"]
    return text if pd.isna(paper) else f"{text} ({paper:g})"


def distances(row: pd.Series) -> str:
    """|ln(ours / paper)| of collisions and of each speed reading (the signed one by its magnitude); – without a
    paper value."""
    pairs = [("collisions", "paper_collisions")] + [(m, "paper_speed_dev_mps") for m in
                                                   ("speed_dev_mps", "speed_dev_episode_mps", "speed_error_mps")]
    out = []
    for metric, paper in pairs:
        ours, ref = abs(float(row[f"{metric}_mean"])), row[paper]
        out.append("–" if pd.isna(ref) or ours <= 0 else f"{abs(math.log(ours / float(ref))):.2f}")
    return ", ".join(out)


def plain(row: pd.Series, metric: str) -> str:
    """``mean [low, high]`` of ``metric`` to 2 decimals, no paper value (the paper gives one reading)."""
    return interval_text(row[f"{metric}_mean"], row[f"{metric}_ci95_low"], row[f"{metric}_ci95_high"], digits=2)


def label(row: pd.Series) -> str:
    """The setting as the README names it: algorithm when not DDPG, preset, density when not 70 veh/km."""
    parts = [ALGORITHM_LABELS.get(row["algorithm"], f"**{row['algorithm']}**"), row["reward_preset"]]
    if row["density"] != 70.0:
        parts.append(f"**{row['density']:g} veh/km**")
    return ", ".join(part for part in parts if part)


def table(summary: Path) -> str:
    """The markdown table of every setting in ``summary`` (a sweep's summary.csv)."""
    try:
        rows = pd.read_csv(summary)
    except (pd.errors.EmptyDataError, pd.errors.ParserError) as error:
        raise ValueError(f"{summary} is not a sweep's summary.csv ({error})") from None
    lines = [HEADER]
    for _, row in rows.iterrows():
        complete, planned = int(row["n_runs"]), int(row["runs_planned"])
        runs = str(complete) if complete == planned else f"{complete} of {planned}"
        lines.append(f"| {label(row)} | {runs} | {cell(row, 'collisions')} | {cell(row, 'speed_dev_mps')} "
                     f"| {plain(row, 'speed_dev_episode_mps')} | {plain(row, 'speed_error_mps')} | {distances(row)} |")
    return "\n".join(lines)


def rewrite(readme: Path, new_table: str) -> bool:
    """Put ``new_table`` between the markers of ``readme``; True when the file changed."""
    text = readme.read_text()
    if text.count(BEGIN) != 1 or text.count(END) != 1 or text.index(BEGIN) > text.index(END):
        raise ValueError(f"{readme} needs one '{BEGIN}' line before one '{END}' line around the results table")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    updated = f"{head}{BEGIN}\n{new_table}\n{END}{tail}"
    if updated == text:
        return False
    write_atomic(readme, updated)
    return True


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--summary", type=Path, default=ROOT / "results" / "paper" / "summary.csv",
                        help="a sweep's summary.csv (lanefree report writes it)")
    parser.add_argument("--readme", type=Path, default=ROOT / "README.md", help="the file holding the markers")
    args = parser.parse_args(argv)
    if not args.summary.is_file():
        print(f"readme_results: {args.summary} does not exist; run `lanefree report` on the sweep first",
              file=sys.stderr)
        return 2
    if not args.readme.is_file():
        print(f"readme_results: {args.readme} does not exist; name the file holding the markers with --readme",
              file=sys.stderr)
        return 2
    try:
        changed = rewrite(args.readme, table(args.summary))
    except ValueError as error:
        print(f"readme_results: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        print(f"readme_results: cannot update {args.readme} from {args.summary}: {error.strerror or error}; "
              "the README is unchanged", file=sys.stderr)
        return 2
    except KeyError as error:
        print(f"readme_results: {args.summary} has no column {error}; is it a sweep's summary.csv?", file=sys.stderr)
        return 2
    print(f"{args.readme}: results table {'rewritten' if changed else 'already up to date'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
