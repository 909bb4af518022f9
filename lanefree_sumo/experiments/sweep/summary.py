"""A sweep's results: ``summary.csv``, ``summary.md`` and learning curves grouped per paper table.

Definitions (specification §8, §10):

* **Per run**: the mean of a metric over its last ``last`` episodes (50, the paper's; all of them
  when a run has fewer), as :mod:`lanefree_sumo.experiments.analysis.report` computes it. Only *complete*
  runs count (every episode of the budget and ``model.zip``; a copy of the results without the
  models, e.g. committed to git, counts when its ``episodes.csv`` holds exactly every episode of the
  budget); the others are listed.
* **Per setting**: the mean of the per-run values, with a 95 % percentile-bootstrap confidence
  interval over runs (:func:`bootstrap_ci`: 10 000 resamples of the runs with replacement, fixed
  random seed so a summary is reproducible; undefined — NaN, ``n/a`` — with fewer than 2 runs; with
  very few runs the percentile bootstrap is too narrow, so read n_runs beside it).
* **Paper values**: specification §10 where the paper has the setting.
* **Every run**: ``runs.csv`` and the second table of ``summary.md``, one row per complete run: its
  last-``last`` means, and the means over all episodes of its deterministic (``eval/``) and shielded
  (``eval_shield/``) evaluations where it has them (``lanefree evaluate``; empty where it has none).
* **Claims**: ``claims.csv``/``claims.md``, the paper's claims that compare two of the grid's
  settings, checked on the complete runs (:mod:`lanefree_sumo.experiments.analysis.claims`); neither file
  when no claim does (a grid of one setting).
* **Verdict**: ``verdict.md`` when the grid names variants in ``compare``: each of them against the variant
  ``default`` per setting, over training windows and every evaluation the runs have
  (:mod:`lanefree_sumo.experiments.analysis.comparison`).
* **Curves**: one PNG per table of the paper and metric (``curves/table7_collisions.png``; settings
  in no table in ``curves/other_*.png``) drawn by :func:`curves.plot_curves` (mean ± std over runs).

Columns of ``summary.csv``: algorithm, reward_preset, density (veh/km), episodes (budget per run),
n_runs (complete), collisions_mean, collisions_ci95_low, collisions_ci95_high (agent collisions per
episode), speed_dev_mps_mean, speed_dev_mps_ci95_low, speed_dev_mps_ci95_high (m/s),
paper_collisions, paper_speed_dev_mps, collisions_ratio, speed_dev_mps_ratio (ours / the paper's), then
runs_planned, seeds, episode_steps, last_episodes,
reduced_budget, paper_source.

Columns of ``runs.csv``: run (folder name), algorithm, reward_preset, density (veh/km), seed, episodes,
collisions, speed_dev_mps (m/s), overtakes, return (means over the last ``last`` episodes), then per
evaluation (``eval``, ``eval_shield``) ``<evaluation>_episodes`` (how many), ``<evaluation>_collisions``,
``<evaluation>_speed_dev_mps`` and ``<evaluation>_overtakes`` (means over them).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lanefree_sumo.config import ReportConfig
from lanefree_sumo.errors import ReportError, UsageError
from lanefree_sumo.experiments.analysis import markdown
from lanefree_sumo.experiments.analysis.claims import (
    Comparison,
    check_claims,
    claims_markdown,
    decidable,
    reading_comparisons,
)
from lanefree_sumo.experiments.analysis.comparison import Sides, setting_label, verdict_markdown
from lanefree_sumo.experiments.analysis.curves import CURVE_METRICS, plot_curves
from lanefree_sumo.experiments.analysis.effects import effect_table, effects_markdown, study_markdown
from lanefree_sumo.experiments.analysis.paper import paper_reference
from lanefree_sumo.experiments.analysis.statistics import BOOTSTRAP_RESAMPLES, CI_LEVEL, bootstrap_ci
from lanefree_sumo.experiments.storage.rundata import RunData, UnusableRunError, read_episodes, read_run
from lanefree_sumo.experiments.storage.rundir import EPISODES, RunDir, write_atomic
from lanefree_sumo.experiments.sweep.grid import DEFAULT_VARIANT, Cell, Grid, Setting
from lanefree_sumo.experiments.sweep.manifest import EFFECTS_CSV, EFFECTS_MD, SweepDir, read_manifest
from lanefree_sumo.experiments.sweep.state import COMPLETE, RunInfo, episode_numbers, inspect_run

METRICS = ("collisions", "speed_dev_mps", "speed_dev_episode_mps", "speed_error_mps")
"""Per setting, with CIs: collisions per episode; the speed deviation read per step (the mean of |vx − v_d|,
the paper's tables are compared with it), per episode (|mean vx − v_d|) and signed (mean vx − v_d), m/s."""
COLUMNS = (
    "algorithm", "reward_preset", "density", "variant", "episodes", "n_runs",
    *(f"{metric}_{part}" for metric in METRICS for part in ("mean", "ci95_low", "ci95_high")),
    "paper_collisions", "paper_speed_dev_mps", "collisions_ratio", "speed_dev_mps_ratio",
    "runs_planned", "seeds", "episode_steps", "last_episodes", "reduced_budget", "paper_source",
)

RUN_METRICS = ("collisions", "speed_dev_mps", "speed_dev_episode_mps", "speed_error_mps", "overtakes", "return",
               "return_reciprocal", "return_bonus", "return_collision")
"""Per run (last-``last`` means); the return's three parts are NaN for runs recorded before they were."""
EVALUATION_METRICS = ("collisions", "speed_dev_mps", "overtakes")
EVALUATIONS = (("eval", None), ("eval_shield", True))
"""(column prefix, ``shield`` of :meth:`RunDir.eval_dir`): the deterministic and the shielded evaluation."""
RUN_COLUMNS = (
    "run", "algorithm", "reward_preset", "density", "variant", "seed", "episodes", *RUN_METRICS,
    *(f"{name}_{column}" for name, _ in EVALUATIONS for column in ("episodes", *EVALUATION_METRICS)),
)


@dataclass
class SweepSummary:
    table: pd.DataFrame
    files: list[Path]
    incomplete: list[tuple[str, str]] = field(default_factory=list)
    """(run name, state and episodes) of the runs left out."""
    notes: list[str] = field(default_factory=list)
    effects: pd.DataFrame | None = None
    """Each variant against ``default`` (:func:`~lanefree_sumo.experiments.analysis.effects.effect_table`), in a grid
    with variants; else None."""


def _key(setting: Setting) -> tuple[str, str, float, str]:
    """(algorithm, preset, density, variant): a group of runs; ``[:3]`` the paper's cell."""
    return (setting.algorithm, setting.preset, round(float(setting.density), 6), setting.variant)


def last_mean(run: RunData, metric: str, last: int) -> float:
    """A run's mean of ``metric`` over its last ``last`` episodes (all of them when it has fewer); NaN where
    its file has no such column."""
    if metric not in run.episodes:
        return math.nan
    return float(run.episodes[metric].tail(last).mean())


def interval_text(mean: float, low: float, high: float, digits: int = 3) -> str:
    """``mean [low, high]`` to ``digits`` decimals; ``mean [n/a]`` without an interval (below 2 runs), ``–``
    without a mean (no run)."""
    if pd.isna(mean):
        return "–"
    if pd.isna(low):
        return f"{mean:.{digits}f} [n/a]"
    return f"{mean:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def _rows(grid: Grid, groups: dict[Any, list[RunData]], last: int) -> pd.DataFrame:
    budget = grid.budget()
    records = []
    for setting in grid.settings:
        runs = groups.get(_key(setting), [])
        rec: dict[str, Any] = {"algorithm": setting.algorithm, "reward_preset": setting.preset,
                               "density": setting.density, "variant": setting.variant, "episodes": grid.episodes,
                               "n_runs": len(runs)}
        for metric in METRICS:
            per_run = [value for value in (last_mean(r, metric, last) for r in runs) if not math.isnan(value)]
            low, high = bootstrap_ci(per_run)
            rec[f"{metric}_mean"] = float(np.mean(per_run)) if per_run else math.nan
            rec[f"{metric}_ci95_low"], rec[f"{metric}_ci95_high"] = low, high
        ref = paper_reference(*_key(setting)[:3], grid.road(setting))
        rec["paper_collisions"] = ref.collisions if ref else math.nan
        rec["paper_speed_dev_mps"] = ref.speed_dev_mps if ref else math.nan
        rec["collisions_ratio"] = rec["collisions_mean"] / ref.collisions if ref else math.nan
        rec["speed_dev_mps_ratio"] = rec["speed_dev_mps_mean"] / ref.speed_dev_mps if ref else math.nan
        rec.update(runs_planned=len(grid.seeds), seeds=";".join(str(r.seed) for r in runs),
                   episode_steps=grid.episode_steps, last_episodes=last, reduced_budget=bool(budget["reduced"]),
                   paper_source=ref.source if ref else "")
        records.append(rec)
    return pd.DataFrame.from_records(records, columns=list(COLUMNS))


def _run_rows(runs: Sequence[RunData], last: int, variants: dict[str, str]) -> tuple[pd.DataFrame, list[str]]:
    """``runs.csv``: one row per run (see the module's docstring; ``variants``: run folder name → its grid
    variant), and a note for each evaluation that exists but cannot be read (shown like a missing one)."""
    records, notes = [], []
    for run in runs:
        rec: dict[str, Any] = {"run": run.path.name, "algorithm": run.algorithm, "reward_preset": run.preset,
                               "density": run.density, "variant": variants.get(run.path.name, ""),
                               "seed": run.seed, "episodes": len(run.episodes)}
        rec.update({metric: last_mean(run, metric, last) for metric in RUN_METRICS})
        for name, shield in EVALUATIONS:
            path = RunDir(run.path).eval_dir(shield=shield) / EPISODES
            episodes = pd.DataFrame(columns=list(EVALUATION_METRICS))  # not evaluated (yet)
            if path.exists():
                try:
                    episodes = read_episodes(path)
                except UnusableRunError as exc:
                    notes.append(f"`runs/{run.path.name}/{name}/` left out of the every-run table: {exc}")
            rec[f"{name}_episodes"] = len(episodes)
            for metric in EVALUATION_METRICS:
                rec[f"{name}_{metric}"] = float(episodes[metric].mean()) if len(episodes) else math.nan
        records.append(rec)
    return pd.DataFrame.from_records(records, columns=list(RUN_COLUMNS)), notes


def _runs_markdown(runs: pd.DataFrame, last: int) -> list[str]:
    """The "every run" section of ``summary.md``, fenced by ``<!-- runs -->``."""
    def value(row: pd.Series, column: str, fmt: str) -> str:
        return "–" if pd.isna(row[column]) else f"{row[column]:{fmt}}"

    def evaluation(row: pd.Series, name: str) -> str:
        if not row[f"{name}_episodes"]:
            return "–"
        return (f"{row[f'{name}_collisions']:.2f} / {row[f'{name}_speed_dev_mps']:.2f} "
                f"({row[f'{name}_episodes']:d})")

    headers = ["algorithm", "reward preset", "density (veh/km)", "seed", f"collisions, last {last}",
               f"speed deviation (m/s), last {last}", f"overtakes, last {last}",
               "deterministic: collisions / speed deviation (episodes)", "shielded: the same"]
    rows = [[str(row["algorithm"]), str(row["reward_preset"]), f"{row['density']:g}", str(row["seed"]),
             value(row, "collisions", ".2f"), value(row, "speed_dev_mps", ".2f"), value(row, "overtakes", ".0f"),
             evaluation(row, "eval"), evaluation(row, "eval_shield")] for _, row in runs.iterrows()]
    return ["", "## Every run", "",
            f"Training: the mean over a run's last {last} episodes (with exploration noise). Deterministic "
            "(`eval/`) and shielded (`eval_shield/`): the mean over the evaluation's episodes, their number "
            "in brackets (`lanefree evaluate`; – where the run has none). Also in `runs.csv`.", "",
            *markdown.table(headers, rows, fence="runs")]


def _cell(row: pd.Series, metric: str, paper_col: str) -> str:
    text = interval_text(row[f"{metric}_mean"], row[f"{metric}_ci95_low"], row[f"{metric}_ci95_high"])
    paper = row[paper_col]
    if not pd.isna(paper):
        ratio = row[f"{metric}_ratio"]
        text += f" (paper {paper:g}" + ("" if pd.isna(ratio) else f", {ratio:.1f}×") + ")"
    return text


def summary_markdown(grid: Grid, table: pd.DataFrame, curves: dict[str, list[Path]], out: Path,
                     incomplete: Sequence[tuple[str, str]], notes: Sequence[str], last: int,
                     runs: pd.DataFrame | None = None) -> str:
    budget = grid.budget()
    lines = [f"# Sweep `{grid.name}`: summary", ""]
    if budget["reduced"]:
        lines += [f"**Reduced budget**: {'; '.join(budget['notes'])}. Not comparable with the paper's numbers.", ""]
    elif budget["notes"]:
        lines += [f"Budget differs from the paper's: {'; '.join(budget['notes'])}.", ""]
    if grid.overrides:
        lines += [f"Config overrides for every run: `{grid.overrides}`.", ""]
    lines += [
        f"Per run: the mean over its last {last} episodes (all of them when it has fewer); only complete runs "
        f"count. Cell: mean over runs [{CI_LEVEL:.0%} percentile-bootstrap CI over runs, {BOOTSTRAP_RESAMPLES} "
        "resamples; n/a below 2 runs, too narrow with very few] (paper value, docs/specification.md §10).",
        "",
    ]
    lines += ["Speed deviation, three readings (m/s): per step, the mean of |vx − v_d| (the paper's tables are "
              "compared with it); per episode, |mean vx − v_d|; signed, mean vx − v_d (> 0: faster than desired).",
              ""]
    variants = bool(grid.variants)
    headers = ["algorithm", "reward preset", "density (veh/km)", *(["variant"] if variants else []), "episodes",
               "runs", "collisions / episode", "speed deviation per step", "per episode", "signed"]
    lines += markdown.table(headers, [
        [str(row["algorithm"]), str(row["reward_preset"]), f"{row['density']:g}",
         *([str(row["variant"])] if variants else []), str(row["episodes"]),
         f"{row['n_runs']}/{row['runs_planned']}", _cell(row, "collisions", "paper_collisions"),
         _cell(row, "speed_dev_mps", "paper_speed_dev_mps"),
         interval_text(row["speed_dev_episode_mps_mean"], row["speed_dev_episode_mps_ci95_low"],
                       row["speed_dev_episode_mps_ci95_high"], 2),
         interval_text(row["speed_error_mps_mean"], row["speed_error_mps_ci95_low"],
                       row["speed_error_mps_ci95_high"], 2)]
        for _, row in table.iterrows()], drop_constant=True)
    if curves:
        lines += ["", "## Learning curves", ""]
        titles: dict[tuple[Path, ...], list[str]] = {}  # tables drawn by the same files share a line
        for group, paths in curves.items():
            titles.setdefault(tuple(paths), []).append(group)
        for shared, groups in titles.items():
            links = ", ".join(f"[{p.stem.split('_', 1)[1]}]({p.relative_to(out)})" for p in shared)
            lines.append(f"- {', '.join(groups)}: {links}")
    if runs is not None and len(runs):
        lines += _runs_markdown(runs, last)
    if incomplete:
        lines += ["", f"## Runs not (yet) in the table ({len(incomplete)})", ""]
        lines += [f"- `runs/{name}`: {state}" for name, state in incomplete]
    if notes:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in notes]
    return "\n".join(lines) + "\n"


def _plot(grid: Grid, groups: dict[Any, list[RunData]], folder: Path, smooth: int) -> tuple[dict[str, list[Path]],
                                                                                             list[str]]:
    """Curves per paper table (and ``other``); returns {group title: files} and notes."""
    by_table: dict[str, list[Setting]] = {}
    for setting in grid.settings:
        for table in setting.tables or ("other",):
            by_table.setdefault(f"Table {table}" if table != "other" else "other", []).append(setting)
    curves: dict[str, list[Path]] = {}
    drawn: dict[tuple[Any, ...], list[Path]] = {}  # the same settings in several tables: drawn once
    for title, settings in by_table.items():
        subset = {_key(s): groups[_key(s)] for s in settings if groups.get(_key(s))}
        if not subset:
            continue
        if tuple(subset) in drawn:
            curves[title] = drawn[tuple(subset)]
            continue
        stem = title.lower().replace(" ", "")
        folder.mkdir(parents=True, exist_ok=True)
        for column, name, ylabel in CURVE_METRICS:
            path = folder / f"{stem}_{name.removeprefix('curves_')}"
            try:
                plot_curves(subset, column, ylabel, path, smooth)
            except ReportError as exc:
                return curves, [f"learning curves skipped: {exc}"]
            curves.setdefault(title, []).append(path)
        drawn[tuple(subset)] = curves[title]
    return curves, []


def claimed_variant(grid: Grid) -> str:
    """The variant whose runs the paper's claims are checked on: :data:`DEFAULT_VARIANT`, or "" (the grid's own
    runs) in a grid without variants."""
    return "" if not grid.variants else DEFAULT_VARIANT


def paper_comparisons(grid: Grid) -> tuple[Comparison, ...]:
    """The paper's claims that compare two of the grid's settings of :func:`claimed_variant` on the paper's ring;
    none on another road."""
    claimed = claimed_variant(grid)
    return decidable((s.algorithm, s.preset, s.density) for s in grid.settings
                     if s.variant == claimed and grid.road(s) == "ring")


def verdict_page(grid: Grid, groups: dict[Any, list[RunData]], variant: str) -> str:
    """``variant`` against :data:`DEFAULT_VARIANT`, per setting of the grid, over every source."""
    comparisons = [Sides(setting_label(s.algorithm, s.preset, s.density), [r.path for r in groups.get(
        _key(s)[:3] + (variant,), [])], [r.path for r in groups.get(_key(s), [])])
        for s in grid.settings if s.variant == DEFAULT_VARIANT]
    return verdict_markdown(comparisons, grid.episodes, f"{variant} against {DEFAULT_VARIANT}: every source",
                            f"The complete runs of each setting of the grid {grid.name}", "`lanefree sweep --summary`",
                            variant, DEFAULT_VARIANT, "setting")


def _complete(info: RunInfo, path: Path, episodes: int) -> bool:
    """Whether the run in ``path`` counts in a summary: complete, or every episode of the budget on file (a
    copy of the results without models)."""
    return info.state == COMPLETE or episode_numbers(RunDir(path).episodes) == list(range(1, episodes + 1))


def complete_seeds(folder: Path) -> int:
    """How many of sweep folder ``folder``'s first seeds (0, 1, …) have a complete run in every setting: the N of
    ``lanefree sweep --summary DIR --seeds N`` whose tables have every run, while a sweep is extended."""
    sweep = SweepDir(folder)
    grid = read_manifest(folder).grid
    count = 0
    while count in grid.seeds and all(_complete(inspect_run(sweep.run(cell), grid.episodes), sweep.run(cell),
                                                grid.episodes)
                                      for cell in (Cell(setting, count) for setting in grid.settings)):
        count += 1
    return count


def summarize(folder: Path, last: int | None = None, smooth: int | None = None,
              seeds: int | None = None) -> SweepSummary:
    """Write ``summary.csv``, ``runs.csv``, ``summary.md``, ``curves/`` and (when a claim compares two of
    the grid's settings) ``claims.csv``/``claims.md`` of sweep folder ``folder`` from its complete runs
    (any time: during, after or without a driver); with ``seeds``, of seeds 0 … ``seeds`` − 1 only, as if the
    grid had those (a sweep extended to more seeds keeps the tables of its first ones). UsageError for a
    ``seeds`` above the grid's."""
    defaults = ReportConfig()
    last = defaults.last_episodes if last is None else last
    smooth = defaults.smooth_episodes if smooth is None else smooth
    sweep = SweepDir(folder)
    grid = read_manifest(folder).grid
    if seeds is not None:
        if not set(range(seeds)) <= set(grid.seeds):
            raise UsageError(f"{folder} has seeds {', '.join(map(str, grid.seeds))} per setting; --seeds {seeds} "
                             f"asks for seeds 0 … {seeds - 1} (give N ≤ {len(grid.seeds)})")
        grid = grid.with_budget(seeds=seeds)
    runs: list[tuple[Cell, RunData]] = []
    incomplete: list[tuple[str, str]] = []
    notes: list[str] = []
    for cell in grid.cells():
        path = sweep.run(cell)
        info = inspect_run(path, grid.episodes)
        if not _complete(info, path, grid.episodes):
            incomplete.append((cell.name, f"{info.state}, {info.episodes}/{grid.episodes} episodes"))
            continue
        try:
            runs.append((cell, read_run(path)))
        except Exception as exc:  # report's reader explains why a run is unusable
            incomplete.append((cell.name, f"unusable: {' '.join(str(exc).split())}"))
    if grid.episodes < last:
        notes.append(f"runs have {grid.episodes} episodes (< {last}); each run's mean uses all of them")
    groups: dict[Any, list[RunData]] = {}  # by the grid's own settings (its variants by name)
    for cell, run in runs:
        groups.setdefault(_key(cell.setting), []).append(run)
    table = _rows(grid, groups, last)
    order = {_key(setting): position for position, setting in enumerate(grid.settings)}  # the table's rows
    per_run, run_notes = _run_rows([run for _, run in sorted(runs, key=lambda cr: (
        order.get(_key(cr[0].setting), len(order)), cr[0].seed))], last, {run.path.name: cell.setting.variant
                                                                        for cell, run in runs})
    notes += run_notes
    try:
        curves, plot_notes = _plot(grid, groups, sweep.curves, smooth)
        table.to_csv(sweep.summary_csv, index=False)
        per_run.to_csv(sweep.runs_csv, index=False)
        write_atomic(sweep.summary_md, summary_markdown(grid, table, curves, folder, incomplete,
                                                        notes + plot_notes, last, per_run))
        files = list(dict.fromkeys(p for paths in curves.values() for p in paths)) + [
            sweep.summary_csv, sweep.runs_csv, sweep.summary_md]
        claimed = claimed_variant(grid)
        comparisons = paper_comparisons(grid)
        if comparisons:
            claimed_groups = {key[:3]: members for key, members in groups.items() if key[3] == claimed}
            claims = check_claims(claimed_groups, last, comparisons)
            claims.to_csv(sweep.claims_csv, index=False)
            write_atomic(sweep.claims_md, claims_markdown(
                claims, check_claims(claimed_groups, last, reading_comparisons(comparisons))))
            files += [sweep.claims_csv, sweep.claims_md]
        else:  # no claim compares two of this grid's settings (one written by an earlier version goes)
            sweep.claims_csv.unlink(missing_ok=True)
            sweep.claims_md.unlink(missing_ok=True)
        effects = None
        if DEFAULT_VARIANT in grid.variants:
            effects = effect_table(groups, last)
            effects.to_csv(sweep.effects_csv, index=False)
            write_atomic(sweep.effects_md, effects_markdown(effects, last))
            files += [sweep.effects_csv, sweep.effects_md]
        if grid.compare:
            write_atomic(sweep.verdict_md, "\n".join(verdict_page(grid, groups, variant) for variant in grid.compare))
            files.append(sweep.verdict_md)
        else:
            sweep.verdict_md.unlink(missing_ok=True)
    except OSError as exc:
        raise ReportError(f"cannot write the summary into {folder}: {exc.strerror or exc}") from None
    return SweepSummary(table, files, incomplete, notes + plot_notes, effects)


def summarize_study(folders: Sequence[Path], out: Path, last: int | None = None,
                    smooth: int | None = None) -> tuple[list[SweepSummary], Path]:
    """Several sweeps' summaries (:func:`summarize`, each written into its folder), then their effects on one
    page: ``out/effects.md`` (:func:`~lanefree_sumo.experiments.analysis.effects.study_markdown`: each choice's
    verdict in
    every cell, then each cell's figures) and ``out/effects.csv`` (the sweeps' rows); returns the summaries and
    the page. A cell may come from one sweep only; at least one sweep must have variants."""
    summaries = [summarize(folder, last, smooth) for folder in folders]
    tables = [s.effects for s in summaries if s.effects is not None]
    if not tables:
        raise ReportError("none of these sweeps has variants (a grid's `variants` with a `default`): there is no "
                          "effect to put side by side; report each sweep alone")
    seen: dict[tuple[str, str, float], Path] = {}
    for folder, summary in zip(folders, summaries):
        for cell in set(_cells(summary.effects)):
            if cell in seen:
                raise ReportError(f"the sweeps {seen[cell]} and {folder} both have the cell {cell[0]} / {cell[1]} / "
                                  f"{cell[2]:g} veh/km: each cell's variants are compared within one sweep")
            seen[cell] = folder
    table = pd.concat(tables, ignore_index=True)
    last = ReportConfig().last_episodes if last is None else last
    page = out / EFFECTS_MD
    try:
        out.mkdir(parents=True, exist_ok=True)
        table.to_csv(out / EFFECTS_CSV, index=False)
        write_atomic(page, study_markdown(table, last, [str(folder) for folder in folders]))
    except OSError as exc:
        raise ReportError(f"cannot write the study's effects into {out}: {exc.strerror or exc}") from None
    return summaries, page


def _cells(effects: pd.DataFrame | None) -> list[tuple[str, str, float]]:
    """The (algorithm, preset, density) cells of an effect table."""
    if effects is None or effects.empty:
        return []
    return list(zip(effects["algorithm"], effects["reward_preset"], effects["density"]))
