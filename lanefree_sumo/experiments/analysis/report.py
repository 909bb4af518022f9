"""Reports over training runs: learning curves and the paper-style results table.

``report(runs, out)`` reads run folders written by ``lanefree train`` (layout in
:mod:`lanefree_sumo.experiments.storage.rundir`), groups them by (algorithm, reward preset, density) and
writes into ``out``::

    curves_return.png       episode return per training episode
    curves_collisions.png   agent collisions per episode
    curves_speed_dev.png    speed deviation mean |vx − v_d| per episode (m/s)
    summary.csv             one row per group: last-``last``-episode means, std over seeds, paper values
    summary.md              the same as a Markdown table, cells ``0.520 ± 0.100 (paper 0.449)``
    claims.csv, claims.md   the paper's claims two of the groups decide (their complete default runs; a sweep's
                            claims table, :func:`paper_claims`); not written when no claim compares two groups

Definitions (specification §8, §10):

* **Grouping.** The group key is read from each run's ``config.yaml``: ``train.algo``,
  ``reward.preset``, ``scenario.density_veh_per_km`` (veh/km) and the *variant*: every other
  setting where the run differs from the defaults (``shield.enabled=True``,
  ``scenario.agent_max_speed_mps=40.0``, …; empty for a default run), so a shielded run or a
  changed parameter never averages with default runs. Keys that do not change what is learned
  (:data:`.rundata.NOT_VARIANT`: seed, checkpoint interval, torch threads, learner path, gui) are not
  part of it; the planned number of episodes is. The run's seed is ``seed``. (The ``seed``
  column of ``episodes.csv`` is the per-episode environment seed, not the run seed.)
* **Table cells.** For each run, the mean of a metric over its last ``last`` episodes (by episode
  number; all episodes if the run has fewer — the ``episodes_min`` column and a note say so). The
  cell is the mean of these per-run values over the group's runs, ± their *sample* standard
  deviation over runs (``ddof=1``; undefined — NaN in the CSV, ``n/a`` in Markdown — for a
  single run). ``n_seeds`` counts the runs in the group.
* **Curves.** Each run's per-episode series is smoothed with a *trailing* moving average of
  ``smooth`` episodes (the value at episode e is the mean of episodes e−smooth+1 … e; the first
  episodes average over what exists), then the mean over the group's runs is drawn as a line and
  ± the sample std over runs (``ddof=1``) as a shaded band, at every episode that at least one
  run reached. Where the paper has a reference value, it is drawn as a dashed horizontal line in
  the group's colour.
* **Paper values.** :data:`PAPER_REFERENCE` holds specification §10 (paper Tables 5–8): collisions per
  episode and speed deviation (m/s), keyed by (algorithm, preset, density).

Damaged runs never crash a report. A run folder is *skipped* — listed in
:attr:`ReportResult.skipped` and in ``summary.md`` with the reason — when ``config.yaml`` or
``episodes.csv`` is missing or unreadable, the config lacks the group keys, the CSV misses one of
:data:`.rundata.REQUIRED_COLUMNS`, any row has a different number of fields than the header (this includes
a last line cut in the middle by a killed writer: the whole run is skipped, not just that line,
so that no table silently mixes complete and damaged files — ``lanefree train --resume``
rewrites the CSV cleanly), a required value is not a finite number, or an episode number repeats.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.errors import ReportError, RunError
from lanefree_sumo.experiments.analysis import markdown
from lanefree_sumo.experiments.analysis.claims import check_claims, claims_markdown, decidable, reading_comparisons
from lanefree_sumo.experiments.analysis.comparison import Sides, against_defaults, verdict_markdown
from lanefree_sumo.experiments.analysis.curves import (
    CURVE_METRICS,
    EVALUATION_FIGURES,
    group_label,
    plot_curves,
    plot_evaluations,
)
from lanefree_sumo.experiments.analysis.paper import paper_reference
from lanefree_sumo.experiments.storage.rundata import RunData, RunKey, UnusableRunError, read_run
from lanefree_sumo.experiments.storage.rundir import check_writable, fresh_output
from lanefree_sumo.rl.algorithms import ALGORITHM_NAMES

# -- constants -----------------------------------------------------------------------------------

TABLE_METRICS: tuple[tuple[str, str, str], ...] = (
    # (column, Markdown header, number format)
    ("collisions", "collisions / episode", ".3f"),
    ("speed_dev_mps", "speed deviation (m/s)", ".3f"),
    ("return", "return", ".2f"),
    ("overtakes", "overtakes / episode", ".2f"),
)
"""Metrics of the summary table, in column order."""

PLANNED_EPISODES = LaneFreeConfig().train.episodes
"""Training episodes of a default run (its planned length is part of a variant): a run with all of them is
complete, for the paper's claims."""


# -- results -------------------------------------------------------------------------------------

@dataclass
class ReportResult:
    """What :func:`report` produced."""

    table: pd.DataFrame
    """One row per group (per evaluation and group, with an ``evaluation`` column first, from
    :func:`evaluations_report`), the columns of ``summary.csv`` (see :func:`summary_table`)."""
    files: list[Path]
    """Files written, in order: the three curve PNGs (the two evaluation figures of
    :func:`evaluations_report`), ``summary.csv``, ``summary.md``, then ``claims.csv``, ``claims.md`` and
    ``verdict.md`` where written."""
    skipped: list[tuple[Path, str]]
    """Run folders left out, each with the reason."""
    notes: list[str] = field(default_factory=list)
    """Things worth knowing that did not stop a run being used (short runs, repeated seeds)."""


# -- reading runs --------------------------------------------------------------------------------
def _one_line(text: object) -> str:
    return " ".join(str(text).split())


# -- tables --------------------------------------------------------------------------------------

def _sort_key(key: RunKey) -> tuple[int, str, str, float, str]:
    algo, preset, density, variant = key
    return (ALGORITHM_NAMES.index(algo) if algo in ALGORITHM_NAMES else len(ALGORITHM_NAMES), algo, preset, density,
            variant)


def group_runs(runs: Sequence[RunData]) -> dict[RunKey, list[RunData]]:
    """Runs by (algorithm, preset, density, variant), groups in a stable order (algorithm as in the
    registry, the default variant first), runs within a group by seed."""
    groups: dict[RunKey, list[RunData]] = {}
    for run in runs:
        groups.setdefault(run.key, []).append(run)
    return {k: sorted(groups[k], key=lambda r: (r.seed, str(r.path))) for k in sorted(groups, key=_sort_key)}


def summary_table(groups: dict[RunKey, list[RunData]], last: int = 50) -> pd.DataFrame:
    """One row per group with columns::

        algorithm, reward_preset, density_veh_per_km, variant, n_seeds, seeds, episodes_min,
        <m>_mean, <m>_std  for m in collisions, speed_dev_mps, return, overtakes,
        collisions_paper, speed_dev_mps_paper, paper_source

    ``<m>_mean`` is the mean over runs of each run's mean over its last ``last`` episodes,
    ``<m>_std`` the sample std over runs (ddof=1, NaN for one run). ``episodes_min`` is the
    fewest episodes any run of the group has. Paper columns are NaN / "" where specification §10 has no
    value. Units: collisions and overtakes per episode, speed deviation m/s.
    """
    records = []
    for (algo, preset, density, variant), runs in groups.items():
        per_run = pd.DataFrame([r.episodes.tail(last).mean() for r in runs])
        rec: dict[str, Any] = {
            "algorithm": algo, "reward_preset": preset, "density_veh_per_km": density, "variant": variant,
            "n_seeds": len(runs), "seeds": ";".join(str(r.seed) for r in runs),
            "episodes_min": min(len(r.episodes) for r in runs),
        }
        for col, _, _ in TABLE_METRICS:
            rec[f"{col}_mean"] = float(per_run[col].mean())
            rec[f"{col}_std"] = float(per_run[col].std(ddof=1)) if len(runs) > 1 else math.nan
        ref = paper_reference(algo, preset, density, runs[0].road)  # a group's runs share their config
        rec["collisions_paper"] = ref.collisions if ref else math.nan
        rec["speed_dev_mps_paper"] = ref.speed_dev_mps if ref else math.nan
        rec["paper_source"] = ref.source if ref else ""
        records.append(rec)
    return pd.DataFrame.from_records(records)


def _cell(mean: float, std: float, fmt: str, paper: float | None) -> str:
    text = f"{mean:{fmt}} ± {std:{fmt}}" if math.isfinite(std) else f"{mean:{fmt}} ± n/a"
    if paper is not None and math.isfinite(paper):
        text += f" (paper {paper:g})"
    return text


def summary_markdown(table: pd.DataFrame, last: int, skipped: Sequence[tuple[Path, str]] = (),
                     notes: Sequence[str] = (), source: str = "") -> str:
    """The summary table as Markdown, with a short explanation, skipped runs and notes."""
    headers = ["algorithm", "reward preset", "density (veh/km)", "variant", "seeds"] + [h for _, h, _ in TABLE_METRICS]
    lines = [
        "# lanefree_sumo training report",
        "",
        (f"Means over the last {last} episodes of each run, then mean ± sample std (ddof=1) over runs "
         "(seeds); paper values from docs/specification.md §10 in parentheses." if not source else
         f"**Evaluation** (`RUN/{source}/episodes.csv`, the deterministic policy; density = the evaluated one): "
         f"means over the last {last} evaluation episodes of each run, then mean ± sample std (ddof=1) over "
         "runs; paper values (training, last 50 episodes) in parentheses."),
        "",
    ]
    rows = []
    for _, row in table.iterrows():
        cells = [str(row["algorithm"]), str(row["reward_preset"]), f"{row['density_veh_per_km']:g}",
                 str(row["variant"]) or "default", str(int(row["n_seeds"]))]
        for col, _, fmt in TABLE_METRICS:
            paper = row.get(f"{col}_paper")
            cells.append(_cell(row[f"{col}_mean"], row[f"{col}_std"], fmt,
                               None if paper is None or pd.isna(paper) else float(paper)))
        rows.append(cells)
    lines += markdown.table(headers, rows, drop_constant=True)
    return "\n".join(lines + _skipped_and_notes(skipped, notes)) + "\n"


def evaluations_markdown(table: pd.DataFrame, last: int, skipped: Sequence[tuple[Path, str]] = (),
                         notes: Sequence[str] = ()) -> str:
    """The table of :func:`evaluations_report` as Markdown: one row per evaluation and group."""
    headers = ["evaluation", "algorithm", "reward preset", "density (veh/km)", "variant", "seeds",
               *[h for _, h, _ in TABLE_METRICS]]
    rows = []
    for _, row in table.iterrows():
        cells = [f"`{row['evaluation']}`", str(row["algorithm"]), str(row["reward_preset"]),
                 f"{row['density_veh_per_km']:g}", str(row["variant"]) or "default", str(int(row["n_seeds"]))]
        cells += [_cell(row[f"{col}_mean"], row[f"{col}_std"], fmt, None) for col, _, fmt in TABLE_METRICS]
        rows.append(cells)
    lines = ["# lanefree_sumo evaluations, side by side", "",
             f"Each evaluation (`RUN/<evaluation>/episodes.csv`, the policy without exploration noise; density = "
             f"the evaluated one): means over the last {last} evaluation episodes of each run, then mean ± sample "
             "std (ddof=1) over runs. Figures: `evaluations_collisions.png`, `evaluations_speed_dev.png`.", "",
             *markdown.table(headers, rows, drop_constant=True)]
    return "\n".join(lines + _skipped_and_notes(skipped, notes)) + "\n"


def _skipped_and_notes(skipped: Sequence[tuple[Path, str]], notes: Sequence[str]) -> list[str]:
    lines: list[str] = []
    if skipped:
        lines += ["", "## Skipped runs", ""] + [f"- `{p}`: {reason}" for p, reason in skipped]
    if notes:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in notes]
    return lines


# -- the report ----------------------------------------------------------------------------------

def _check_writable(folder: Path) -> None:
    """The run-folder module's writability check of ``folder``, as a ReportError (before any figure is drawn)."""
    try:
        check_writable(folder, folder=True)
    except RunError as exc:
        raise ReportError(str(exc)) from None


def _read_usable(runs: Sequence[Path], source: str,
                 first: int | None = None) -> tuple[list[RunData], list[tuple[Path, str]], list[str]]:
    """(usable runs, skipped runs with the reason, notes) of the folders given, each read once (``first``: as
    :func:`~.rundata.read_run`)."""
    usable: list[RunData] = []
    skipped: list[tuple[Path, str]] = []
    notes: list[str] = []
    seen: set[Path] = set()
    for raw in runs:
        run = Path(raw)
        resolved = run.resolve()
        if resolved in seen:
            notes.append(f"{run} given more than once; counted once")
            continue
        seen.add(resolved)
        try:
            usable.append(read_run(run, source, first))
        except UnusableRunError as exc:
            skipped.append((run, _one_line(str(exc))))
    if first is not None:
        notes.append(f"every run read over its first {first} training episodes only (--first): longer runs are cut "
                     "there, and the planned number of episodes does not separate variants")
    return usable, skipped, notes


def _group_notes(groups: dict[RunKey, list[RunData]], last: int, where: str = "") -> list[str]:
    """What a reader of the table must know about its groups: runs (or evaluations, ``where`` naming them)
    with fewer than ``last`` episodes, and groups holding a seed twice."""
    notes = []
    for key, members in groups.items():
        for member in members:
            if len(member.episodes) < last:
                notes.append(f"{member.path}{where} has {markdown.count(len(member.episodes), 'episode')} (< {last}); "
                             "its mean uses all of them")
        seeds = [r.seed for r in members]
        if len(set(seeds)) < len(seeds):
            notes.append(f"group {group_label(key)}{where} has runs with the same seed ({seeds}); each counts "
                         "separately")
    return notes


def _no_usable_run(skipped: Sequence[tuple[Path, str]]) -> ReportError:
    if not skipped:
        return ReportError("no run folders given; pass the folders that 'lanefree train' made")
    reasons = "; ".join(f"{p.name}: {r}" for p, r in skipped[:5])
    more = f"; and {len(skipped) - 5} more" if len(skipped) > 5 else ""
    return ReportError(f"no usable run among {len(skipped)} folder(s) ({reasons}{more})")


def _write_report(out: Path, files: dict[str, Any]) -> list[Path]:
    """Write ``files`` (name -> text, DataFrame for CSV, or a callable drawing into the path given) into
    ``out`` through the safe-output mechanism of every verb: a new folder, or an earlier report (its marker)
    replaced whole once the new one is complete; never a folder of anything else."""
    _check_writable(out.parent)
    try:
        with fresh_output(out, overwrite=True, verb="report") as tmp:
            for name, content in files.items():
                if isinstance(content, str):
                    (tmp / name).write_text(content, encoding="utf-8")
                elif isinstance(content, pd.DataFrame):
                    content.to_csv(tmp / name, index=False)
                else:
                    content(tmp / name)
    except RunError as exc:
        raise ReportError(str(exc)) from None
    except OSError as exc:
        raise ReportError(f"cannot write the report to {out}: {_one_line(exc)}") from None
    return [out / name for name in files]


def report(runs: Sequence[Path], out: Path, last: int = 50, smooth: int = 20,
           source: str | Sequence[str] = "", compare: bool = False, first: int | None = None,
           against: Sequence[Path] | None = None) -> ReportResult:
    """Learning curves and the last-``last``-episode summary table of training runs.

    ``runs``: run folders of ``lanefree train``; unusable ones are skipped with the reason.
    ``out``: folder for ``curves_return.png``, ``curves_collisions.png``, ``curves_speed_dev.png``,
    ``summary.csv``, ``summary.md`` (and ``claims.csv``/``claims.md`` where the runs decide a paper's claim:
    :func:`paper_claims`, training episodes read whole): a new folder, or the folder of an earlier report (its
    ``.lanefree-output`` marker), replaced whole when the new report is complete; any other existing
    folder is refused (a user's notes, a sweep folder, a run folder).
    ``last``: episodes per run averaged for the table (paper: 50).
    ``smooth``: width in episodes of the trailing moving average of the curves.
    ``source``: ``""`` for the training episodes, else an evaluation folder name inside each run
    (``eval``, ``eval_d120``, ``eval_shield``, …): its episodes instead, at the evaluated density.
    Several names: :func:`evaluations_report` (the evaluations side by side, no learning curves).
    ``compare``: also ``verdict.md`` (training episodes only): each way the runs differ from the defaults against
    the default runs of the same setting, over training windows and every evaluation the runs have
    (:func:`~lanefree_sumo.experiments.analysis.comparison.verdict_markdown`).
    ``first``: read every run over its training episodes 1 … ``first`` only (runs of different lengths compared
    over the same episodes; a run with fewer is skipped), the planned number of episodes then not part of a
    run's variant; not with evaluations.
    ``against``: run folders of one group (e.g. DDPG's, to set TD3 against them): ``verdict.md`` then compares
    every other group with that group — the ``against`` runs and any of ``runs`` in it — instead of each variant
    with the defaults of its setting (as ``compare`` does, which it implies); the group is in the table and curves.

    Raises :class:`ReportError` when ``last``, ``smooth`` or ``first`` < 1, when ``first`` or ``against`` is given
    with evaluations, when no usable run remains, when ``compare`` finds no variant with default runs of its setting,
    when ``against`` is empty, an ``against`` run is unusable, the ``against`` runs are of several groups, no other
    group remains, or (without ``first``) the runs compared have different numbers of episodes, or when ``out``
    cannot be written.
    """
    if against is not None and source:
        raise ReportError("against compares training episodes; evaluations are tabulated without it: drop one")
    if against is not None and not against:
        raise ReportError("against needs at least one run folder to compare with")
    if first is not None:
        if isinstance(first, bool) or not isinstance(first, int) or first < 1:
            raise ReportError(f"first must be a whole number of episodes ≥ 1, got {first!r}")
        if source:
            raise ReportError("first cuts the training episodes; evaluations are of the final models: drop one")
    if not isinstance(source, str):
        if len(source) != 1:
            return evaluations_report(runs, out, source, last)
        source = source[0]
    if isinstance(last, bool) or not isinstance(last, int) or last < 1:
        raise ReportError(f"last must be a whole number of episodes ≥ 1, got {last!r}")
    if isinstance(smooth, bool) or not isinstance(smooth, int) or smooth < 1:
        raise ReportError(f"smooth must be a whole number of episodes ≥ 1, got {smooth!r}")
    out = Path(out)
    baseline = {Path(run).resolve(): Path(run) for run in against or ()}
    given = {Path(run).resolve() for run in runs}  # a baseline run given as RUN too is read once, without a note
    usable, skipped, notes = _read_usable([*runs, *(run for path, run in baseline.items() if path not in given)],
                                          source, first)
    bad = next(((run, why) for run, why in skipped if run.resolve() in baseline), None)
    if bad is not None:
        raise ReportError(f"--against {bad[0]} is unusable: {bad[1]}")
    if not usable:
        raise _no_usable_run(skipped)

    groups = group_runs(usable)
    notes += _group_notes(groups, last)
    table = summary_table(groups, last)
    files: dict[str, Any] = {
        name: (lambda path, column=column, ylabel=ylabel: plot_curves(groups, column, ylabel, path, smooth))
        for column, name, ylabel in CURVE_METRICS}
    claim_files = _claim_files(groups, last, notes) if not source and first is None else {}
    files["summary.csv"] = table
    files["summary.md"] = summary_markdown(table, last, skipped, notes, source)
    files.update(claim_files)
    if baseline:
        files["verdict.md"] = _against_page(groups, set(baseline), skipped, first)
    elif compare:
        files["verdict.md"] = _verdict_page(groups, first)
    return ReportResult(table=table, files=_write_report(out, files), skipped=skipped, notes=notes)


def paper_claims(groups: dict[RunKey, list[RunData]], last: int) -> tuple[pd.DataFrame | None, list[str]]:
    """(the paper's claims (:mod:`~lanefree_sumo.experiments.analysis.claims`) that two of the groups decide — None
    when no claim compares two of them —; the runs left out for being unfinished, ``NAME (done/planned episodes)``). A
    claim is checked on the complete runs of default groups (no variant: the paper's settings, on its ring, another
    road being a variant, and its :data:`PLANNED_EPISODES` episodes), as a sweep checks it on its complete runs."""
    default: dict[tuple[str, str, float], list[RunData]] = {}
    unfinished: list[str] = []
    for key, members in groups.items():
        if key[3] != "":
            continue
        for run in members:
            if list(run.episodes.index) == list(range(1, PLANNED_EPISODES + 1)):
                default.setdefault(key[:3], []).append(run)
            else:
                unfinished.append(f"{run.path.name} ({len(run.episodes)}/{PLANNED_EPISODES} episodes)")
    comparisons = decidable({key[:3] for key, members in groups.items() if key[3] == ""})
    if not comparisons:
        return None, []
    return check_claims(default, last, comparisons), unfinished


def reading_claims(groups: dict[RunKey, list[RunData]], last: int) -> pd.DataFrame:
    """The speed claims the default complete runs decide, under the other readings (:func:`reading_comparisons`)."""
    default: dict[tuple[str, str, float], list[RunData]] = {}
    for key, members in groups.items():
        if key[3] == "":
            default.setdefault(key[:3], []).extend(run for run in members
                                                   if list(run.episodes.index) == list(range(1, PLANNED_EPISODES + 1)))
    comparisons = decidable({key[:3] for key in groups if key[3] == ""})
    return check_claims(default, last, reading_comparisons(comparisons))


def _claim_files(groups: dict[RunKey, list[RunData]], last: int, notes: list[str]) -> dict[str, Any]:
    """``claims.csv`` and ``claims.md`` of :func:`paper_claims` (none when no claim compares two groups); a note
    in ``notes`` names the unfinished runs left out."""
    claims, unfinished = paper_claims(groups, last)
    if claims is None:
        return {}
    if unfinished:
        notes.append(f"the paper's claims count complete runs only (every one of the {PLANNED_EPISODES} planned "
                     f"episodes); left out of claims.md: {', '.join(unfinished)}")
    return {"claims.csv": claims, "claims.md": claims_markdown(claims, reading_claims(groups, last))}


def _verdict_page(groups: dict[RunKey, list[RunData]], first: int | None = None) -> str:
    """``verdict.md`` of ``report(..., compare=True)``: one table per variant against the defaults (``first``: as
    :func:`report`)."""
    pages = against_defaults(groups)
    if not pages:
        kinds = "; ".join(sorted({variant or "the defaults" for (*_, variant) in groups}))
        raise ReportError(f"--compare needs runs of the defaults and runs that differ from them, of the same "
                          f"algorithm, reward preset and density; these runs are of: {kinds}")
    episodes = max(int(run.episodes.index.max()) for runs in groups.values() for run in runs)
    return "\n".join(verdict_markdown(sides, episodes, f"{variant} against the defaults: every source",
                                      "The runs given, by setting", "`lanefree report --compare`",
                                      "variant", "default", "setting", first) for variant, sides in pages.items())


def _against_page(groups: dict[RunKey, list[RunData]], baseline: set[Path], skipped: list[tuple[Path, str]],
                  first: int | None = None) -> str:
    """``verdict.md`` of ``report(..., against=...)``: every group against the group of the runs ``baseline``
    (resolved paths), in one table (``skipped``: the run folders left out, with why; ``first``: as
    :func:`report`)."""
    keys = sorted({key for key, runs in groups.items() for run in runs if run.path.resolve() in baseline},
                  key=_sort_key)
    if len(keys) != 1:
        raise ReportError(f"--against takes the runs of one group (algorithm, reward preset, density, variant); these "
                          f"are of {len(keys)}: {'; '.join(group_label(key) for key in keys)}")
    base = keys[0]
    sides = [Sides(group_label(key), [run.path for run in runs], [run.path for run in groups[base]])
             for key, runs in groups.items() if key != base]
    if not sides:
        left_out = f" ({skipped[0][0]} was left out: {skipped[0][1]})" if skipped else ""
        raise ReportError(f"--against: no run of another group than {group_label(base)} to compare with it{left_out}; "
                          "give the runs to set against it as RUN")
    lengths = {int(run.episodes.index.max()) for runs in groups.values() for run in runs}
    if first is None and len(lengths) > 1:
        raise ReportError(f"--against: the runs have {min(lengths)} to {max(lengths)} episodes, so their last 50 are "
                          f"different episodes; compare them over the same ones with --first {min(lengths)}")
    episodes = max(lengths)
    return verdict_markdown(sides, episodes, f"Each group against {group_label(base)}: every source",
                            "The runs given, by group", "`lanefree report --against`", "group", "baseline",
                            "group", first)


def evaluations_report(runs: Sequence[Path], out: Path, sources: Sequence[str], last: int = 50) -> ReportResult:
    """The evaluations ``sources`` (folder names inside each run, e.g. ``eval``, ``eval_d90``,
    ``eval_onramp``) of the same runs side by side: ``summary.csv``/``summary.md`` hold one row per
    (evaluation, group) — the group keyed as in :func:`report`, at the evaluated density — and
    ``evaluations_collisions.png``/``evaluations_speed_dev.png`` one bar per group and evaluation (mean
    over runs, ± sample std over runs as the error bar). A run lacking one of the evaluations is left out
    of that evaluation only (named in ``summary.md``).

    Raises :class:`ReportError` for no or repeated names, ``last`` < 1, no usable run in any evaluation,
    or an unwritable ``out``.
    """
    if isinstance(last, bool) or not isinstance(last, int) or last < 1:
        raise ReportError(f"last must be a whole number of episodes ≥ 1, got {last!r}")
    if not sources or len(set(sources)) < len(sources):
        raise ReportError(f"name each evaluation folder once, got {list(sources)}")
    out = Path(out)
    tables: list[pd.DataFrame] = []
    skipped: list[tuple[Path, str]] = []
    notes: list[str] = []
    for source in sources:
        usable, missing, said = _read_usable(runs, source)
        skipped += [entry for entry in missing if entry not in skipped]  # a broken run: named once
        notes += [note for note in said if note not in notes]
        if usable:
            groups = group_runs(usable)
            notes += _group_notes(groups, last, where=f" ({source})")
            tables.append(summary_table(groups, last).assign(evaluation=source))
    if not tables:
        if not skipped:
            raise _no_usable_run(skipped)
        raise ReportError(f"no run has any of the evaluations {', '.join(sources)} ({skipped[0][0].name}: "
                          f"{skipped[0][1]})")
    table = pd.concat(tables, ignore_index=True)
    table = table[["evaluation", *[c for c in table.columns if c != "evaluation"]]]
    files: dict[str, Any] = {
        f"evaluations_{name}.png": (lambda path, column=column, ylabel=ylabel:
                                    plot_evaluations(table, column, ylabel, path))
        for column, name, ylabel in EVALUATION_FIGURES}
    files["summary.csv"] = table
    files["summary.md"] = evaluations_markdown(table, last, skipped, notes)
    return ReportResult(table=table, files=_write_report(out, files), skipped=skipped, notes=notes)
