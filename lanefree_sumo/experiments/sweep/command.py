"""``lanefree sweep``: the command line of sweeps (``add_parser`` registers it, ``run`` executes it).

Exit codes: 0 every run complete (with ``--only``, every run it asked for); 1 some run failed, is damaged or busy
elsewhere; 2 bad input (one line on stderr, nothing written); 130 interrupted (checkpoints saved; rerun to
continue).
"""

from __future__ import annotations

import argparse
import fnmatch
import os
import shlex
import socket
import sys
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

from lanefree_sumo import argtypes
from lanefree_sumo.config import nested_overrides
from lanefree_sumo.errors import EXIT_INTERRUPTED, LaneFreeError, UsageError
from lanefree_sumo.experiments.storage.rundir import EPISODES, read_sessions
from lanefree_sumo.experiments.sweep.batches import DEFAULT_BATCH, PER_RUN_KEYS, members
from lanefree_sumo.experiments.sweep.grid import BUILTIN_GRIDS, Cell, Grid, builtin_descriptions, load_grid
from lanefree_sumo.experiments.sweep.manifest import (
    Manifest,
    SweepDir,
    check_same_grid,
    driver_lock,
    driver_running,
    read_manifest,
    write_manifest,
)
from lanefree_sumo.experiments.sweep.state import (
    BUSY,
    COMPLETE,
    DAMAGED,
    FAILED,
    PARTIAL,
    PENDING,
    RUNNING,
    STALE,
    RunInfo,
    inspect_run,
    open_files,
    overlay,
    read_heartbeat,
    writers_elsewhere,
)
from lanefree_sumo.options import Option, add_options

EXIT_OK, EXIT_INCOMPLETE = 0, 1
DEFAULT_RETRIES = 3


def default_workers() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


OPTIONS: tuple[Option, ...] = (
    Option("grid", extra={"nargs": "?", "metavar": "GRID"}, note="built-in grid name or YAML grid file"),
    Option("--out", type=Path, extra={"metavar": "DIR"},
           note="sweep folder (default runs/sweep_<grid>); on a cluster, storage every node mounts"),
    Option("--resume", type=Path, extra={"metavar": "DIR"}, note="continue the sweep in DIR"),
    Option("--status", type=Path, extra={"metavar": "DIR"},
           note="print the state of the sweep in DIR (also while it runs elsewhere) and exit"),
    Option("--list", extra={"action": "store_true"}, note="list the built-in grids with what each is, and exit"),
    Option("--summary", type=Path, extra={"metavar": "DIR"},
           note="(re)write DIR/summary.csv, summary.md and curves/ from the complete runs and exit"),
    Option("--seeds", type=argtypes.positive(int, "seeds"), extra={"metavar": "N"},
           note="seeds 0 … N−1 instead of the grid's (a reduced budget is recorded and reported); with --resume "
           "DIR, add seeds to DIR's sweep until it has N per setting (its runs are kept); with --summary DIR, "
           "summarise seeds 0 … N−1 only"),
    Option("--episodes", "train.episodes", unit="episodes", default=None, extra={"metavar": "N"},
           note="for every run of GRID instead of the grid's (paper: 625)"),
    Option("--episode-steps", "sim.episode_steps", unit="steps", default=None, extra={"metavar": "N"},
           note="for every run of GRID instead of the grid's (paper: 800; fewer for quick tests)"),
    Option("--workers", type=argtypes.positive(int, "workers"), extra={"metavar": "N"},
           note=f"runs at a time on the embedded local Ray (default: the cores, {default_workers()} here)"),
    Option("--address", extra={"metavar": "HOST:PORT"},
           note="join the Ray cluster at HOST:PORT instead of starting a local one (default: $RAY_ADDRESS if set)"),
    Option("--retries", type=argtypes.nonnegative(int, "retries"), default=DEFAULT_RETRIES, extra={"metavar": "N"},
           note=f"times Ray retries a run whose worker process died (default {DEFAULT_RETRIES})"),
    Option("--batch", type=argtypes.positive(int, "batch"), extra={"metavar": "K"},
           note="train runs of one algorithm (dqn and ddqn count as one) whose configs differ only in "
           f"{', '.join(PER_RUN_KEYS)} as batches of at most K (default {DEFAULT_BATCH}) in one task each (the same "
           "episodes as one run per task, bit for bit on CPU), smaller ones while that keeps more workers busy; "
           "--batch 1 trains one run per task"),
    Option("--only", default=[], extra={"action": "append", "metavar": "GLOB"},
           note="train only the runs whose folder names match GLOB (a shell pattern, e.g. "
           "'*_fields_zones_overtake_collision_d70_*': Table 8 before the rest; repeatable), leaving the others for "
           "a later run of the sweep; an interrupted batch holding a matching run continues whole"),
    Option("--no-progress", extra={"action": "store_true"}, note="no progress bar"),
    Option("--no-ray", extra={"action": "store_true"},
           note="train the batches and runs one after another in this process, without Ray (a machine without Ray, "
           "such as one GPU: each batch then has it alone); not with --workers, --address or --retries"),
    Option("--set", type=argtypes.setting, default=[], extra={"action": "append", "metavar": "KEY=VALUE",
                                                              "dest": "settings"},
           note="a config value for every run of GRID, added to its overrides, e.g. --set "
           "reward.broad_stretch=absolute (repeatable; not the keys the grid sets per run)"),
)
"""``lanefree sweep``'s options: the run-folder options, then the budget, then Ray's."""


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``sweep`` on the CLI's subparsers."""
    sw = subparsers.add_parser(
        "sweep",
        help="train a grid of runs (the paper's tables) on Ray, resumable",
        description="Train every (algorithm, reward preset, density, seed) run of GRID on Ray, one CPU per task, "
        "runs of one algorithm (dqn and ddqn as one) packed K to a task (--batch), into "
        "DIR/runs/<algo>_<preset>_d<density>_s<seed>/ (ordinary run folders, the same as one run per task would "
        "write), "
        "then write DIR/summary.csv and summary.md (last-50-episode means with 95 % bootstrap CIs over runs, the "
        "paper's values) and learning curves per table. GRID: a built-in grid, " + ", ".join(BUILTIN_GRIDS) +
        " (--list says what each is; 10 seeds and 625 episodes each, --seeds N for fewer), or a YAML file (keys "
        "algorithms, reward_presets, densities or tables, seeds or n_seeds, episodes, overrides, variants, "
        "compare). Rerunning the same command (or --resume DIR) skips complete runs, resumes "
        "interrupted ones from their newest checkpoint and retries failed ones; existing run folders with the same "
        "config are adopted. Ctrl-C stops every run with a checkpoint.",
    )
    add_options(sw, OPTIONS)
    return sw


def _check_args(args: argparse.Namespace) -> tuple[str, Path]:
    """(mode, folder) after checking which options go together; UsageError otherwise."""
    given: set[str] = getattr(args, "given", set())
    if args.list:
        if args.grid is not None or len(given - {"--list"}) > 0:
            raise UsageError("lanefree sweep: --list goes alone")
        return "list", Path()
    modes = [m for m in ("resume", "status", "summary") if getattr(args, m) is not None]
    if len(modes) > 1 or (modes and args.grid is not None):
        raise UsageError("lanefree sweep: give one of GRID, --resume DIR, --status DIR, --summary DIR")
    if not modes and args.grid is None:
        raise UsageError("lanefree sweep: give a GRID (" + ", ".join(BUILTIN_GRIDS) + " or a YAML file), "
                         "--resume DIR, --status DIR or --summary DIR (see 'lanefree sweep --help')")
    budget = [o for o in ("--seeds", "--episodes", "--episode-steps", "--set") if o in given]
    ray_opts = [o for o in ("--workers", "--address", "--retries", "--batch", "--only", "--no-progress", "--no-ray")
                if o in given]
    if modes:
        mode = modes[0]
        extra = [o for o in budget if not (mode in ("resume", "summary") and o == "--seeds")]
        if args.out is not None or extra:
            bad = "--out" if args.out is not None else extra[0]
            raise UsageError(f"lanefree sweep: {bad} goes with GRID, not with --{mode} (the grid is in DIR/sweep.yaml)")
        if mode != "resume" and ray_opts:
            raise UsageError(f"lanefree sweep: {ray_opts[0]} does not go with --{mode}")
        folder = getattr(args, mode)
    else:
        mode, folder = "grid", args.out
    if args.no_ray:
        clash = [o for o in ("--workers", "--address", "--retries") if o in given]
        if clash:
            raise UsageError(f"lanefree sweep: {clash[0]} sizes or joins Ray; --no-ray trains without it")
    if args.workers is not None and (args.address is not None or (os.environ.get("RAY_ADDRESS") and mode != "status")):
        raise UsageError("lanefree sweep: --workers sizes the embedded local Ray; a cluster (--address or RAY_ADDRESS) "
                         "runs as many runs at once as it has CPUs")
    return mode, folder


def run(args: argparse.Namespace) -> int:
    """Execute ``lanefree sweep``; LaneFreeError for bad input (the CLI prints it as one line)."""
    mode, folder = _check_args(args)
    if mode == "list":
        for name, description in builtin_descriptions().items():
            print(f"{name:<8} {description}")
        return EXIT_OK
    if mode == "status":
        print(status_text(folder))
        return EXIT_OK
    if mode == "summary":
        from lanefree_sumo.experiments.sweep.summary import summarize

        result = summarize(folder, seeds=args.seeds)
        print(f"{len(result.table)} setting(s), {len(result.incomplete)} run(s) not complete -> "
              f"{folder / 'summary.md'}")
        print(SweepDir(folder).summary_md.read_text())
        return EXIT_OK
    command = shlex.join(["lanefree", *sys.argv[1:]])
    extend = False
    if mode == "resume":
        grid = read_manifest(folder).grid
        if args.seeds is not None:
            grid, extend = grid.with_more_seeds(args.seeds, str(folder)), True
    else:
        grid = load_grid(args.grid).with_budget(args.seeds, args.episodes, args.episode_steps,
                                                nested_overrides(args.settings))
        folder = folder if folder is not None else Path("runs") / f"sweep_{grid.name}"
    address = None if args.no_ray else args.address or os.environ.get("RAY_ADDRESS") or None
    return _drive(folder, grid, mode, command, args.workers, address, args.retries, not args.no_progress, extend,
                  args.batch, args.no_ray, args.only)


def plan(folder: Path, grid: Grid, extend: bool = False) -> dict[str, RunInfo]:
    """State of every run before starting; RunError/UsageError (nothing written) when a run folder
    cannot be adopted: not a run folder, another config, more episodes than the grid's. ``extend``:
    ``grid`` is the saved one with more seeds (``--resume DIR --seeds N``)."""
    from lanefree_sumo.experiments.sweep.worker import check_adoptable

    sweep = SweepDir(folder)
    if sweep.manifest.exists() and not extend:
        check_same_grid(folder, read_manifest(folder).grid, grid)
    elif folder.exists() and not folder.is_dir():
        raise UsageError(f"--out {folder} is a file; choose a folder")
    states = {}
    opened = open_files()
    for cell in grid.cells():
        info = inspect_run(sweep.run(cell), grid.episodes)
        if info.state != PENDING:
            check_adoptable(sweep.run(cell), grid.config(cell))
        if info.state not in (PENDING, COMPLETE):
            holders = writers_elsewhere(sweep.run(cell) / "episodes.csv", opened)
            if holders:
                info = RunInfo(BUSY, info.episodes, f"episodes.csv is open in process {holders[0]} outside this "
                                                    "sweep; rerun the sweep when it has stopped")
        states[cell.name] = info
    return states


def _ray_description(workers: int | None, address: str | None) -> str:
    if workers == 0:
        return "this process (no Ray)"
    return f"Ray cluster at {address}" if address else f"embedded local Ray, {workers} worker(s)"


def _drive(folder: Path, grid: Grid, mode: str, command: str, workers: int | None, address: str | None,
           retries: int, progress: bool, extend: bool = False, batch: int | None = None,
           in_process: bool = False, only: Sequence[str] = ()) -> int:
    from lanefree_sumo.experiments.storage.rundir import check_writable
    from lanefree_sumo.experiments.sweep.batches import pack
    from lanefree_sumo.experiments.sweep.runner import check_address, cluster_size, run_in_process, run_sweep
    from lanefree_sumo.experiments.sweep.summary import summarize

    workers = 0 if in_process else (workers or default_workers()) if address is None else None
    states = plan(folder, grid, extend)  # every check before the first write
    chosen = chosen_runs(grid, only)
    if address is not None:
        check_address(address)
    elif grid.on_cuda():
        from lanefree_sumo.experiments.runners.batch import check_device

        check_device("cuda")  # the embedded Ray's batches train on this machine's GPU
    check_writable(folder, folder=True)
    sweep = SweepDir(folder)
    cells: dict[str, Cell] = {c.name: c for c in grid.cells()}
    todo = [cells[n] for n, info in states.items() if info.state not in (COMPLETE, BUSY, DAMAGED) and n in chosen]
    with driver_lock(folder, command):
        cpus = workers if address is None or batch is not None or not todo else cluster_size(address)
        size = DEFAULT_BATCH if batch is None else batch
        packing = pack(sweep, grid, todo, states, size,
                       "--batch 1" if batch == 1 else "no more runs to train than workers", cpus)
        manifest = read_manifest(folder) if sweep.manifest.exists() else Manifest(grid)
        manifest.grid = grid  # the same, or with the seeds --seeds added
        manifest.sessions.append({"started": datetime.now().isoformat(timespec="seconds"), "command": command,
                                  "host": socket.gethostname(), "ray": _ray_description(workers, address),
                                  "batch": size})
        write_manifest(folder, manifest)
        busy = [(n, i) for n, i in states.items() if i.state in (BUSY, DAMAGED)]
        counts = {s: sum(1 for i in states.values() if i.state == s) for s in (COMPLETE, PARTIAL, STALE, PENDING)}
        budget = grid.budget()
        print(f"sweep {grid.name} -> {folder}: {len(cells)} runs ({len(grid.settings)} setting(s) × {len(grid.seeds)} "
              f"seed(s) × {grid.episodes} episodes of {grid.episode_steps} steps): {counts[COMPLETE]} complete, "
              f"{counts[PARTIAL]} to resume, {counts[STALE] + counts[PENDING]} to start, {len(busy)} left alone"
              + (f"; REDUCED BUDGET ({'; '.join(budget['notes'])})" if budget["reduced"] else ""), flush=True)
        for name, info in busy:
            print(f"  left alone: runs/{name}: {info.detail}", file=sys.stderr)
        trained = {n for b in packing.batches for n in b.runs} | {c.name for c in packing.sequential}
        waiting = [n for n, i in states.items() if n not in chosen and i.state not in (COMPLETE, BUSY, DAMAGED)]
        along = sum(1 for n in waiting if n in trained)
        if len(waiting) > along:
            print(f"  {len(waiting) - along} run(s) not matching --only left for a later run of the sweep", flush=True)
        if along:
            print(f"  {along} run(s) not matching --only train too: they continue in an interrupted batch with runs "
                  "that match (a batch goes on whole)", flush=True)
        interrupted = False
        if todo:
            print(f"  {len(todo)} run(s) {'in' if in_process else 'on the'} {_ray_description(workers, address)}: "
                  f"{packing.describe()}; logs in "
                  f"{folder / 'logs'}", flush=True)
            if in_process:
                interrupted = run_in_process(sweep, grid, packing.sequential, command, packing.batches).interrupted
            else:
                interrupted = run_sweep(sweep, grid, packing.sequential, workers, address, retries, command,
                                        progress, packing.batches).interrupted
        else:
            print("  nothing to train", flush=True)
        summarize(folder)
    opened = open_files()
    final = {n: overlay(sweep, n, inspect_run(sweep.run(n), grid.episodes), opened) for n in cells}
    complete = sum(1 for i in final.values() if i.state == COMPLETE)
    for name, info in final.items():
        if info.state in (FAILED, DAMAGED, BUSY):
            print(f"  {info.state}: runs/{name}: {info.detail}", file=sys.stderr)
    print(f"sweep {grid.name}: {complete}/{len(cells)} runs complete -> {sweep.summary_md}")
    if interrupted:
        print(f"lanefree: interrupted; checkpoints saved. Continue with: lanefree sweep --resume {folder}",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK if all(final[n].state == COMPLETE for n in chosen) else EXIT_INCOMPLETE


def chosen_runs(grid: Grid, only: Sequence[str]) -> set[str]:
    """The names of the grid's runs to train: every run, or those matching one of the ``--only`` patterns
    (:func:`fnmatch.fnmatchcase`); UsageError for a pattern matching none."""
    names = [c.name for c in grid.cells()]
    if not only:
        return set(names)
    for pattern in only:
        if not any(fnmatch.fnmatchcase(name, pattern) for name in names):
            raise UsageError(f"lanefree sweep: --only {pattern} matches no run of the grid; its runs are named like "
                             f"{names[0]} (algorithm_preset_d<density>_s<seed>)")
    return {name for name in names if any(fnmatch.fnmatchcase(name, pattern) for pattern in only)}


PARTIAL_PACE_EPISODES = 25
"""Episodes an unfinished run must have recorded before its pace counts."""

PACE_RUNS = 3
"""An algorithm's pace is the median over its this many most recent runs: machines and code change between
sessions, and the latest runs measure the ones the rest will run on."""


def _batch_size(session: dict[str, Any]) -> int:
    """How many runs a recorded training session trained together in one process (1 outside a batch, or when the
    record is not a whole number ≥ 1)."""
    batch = session.get("batch")
    runs = batch.get("runs") if isinstance(batch, dict) else None
    return runs if isinstance(runs, int) and not isinstance(runs, bool) and runs >= 1 else 1


def _pace_sample(run: Path, together: int | None = None) -> tuple[str | None, list[float]]:
    """(when the run's last recorded training session ended, ISO 8601 UTC, or None; the core-seconds of each
    episode of its latest session — the one in progress when ``together`` is given (the run is training now,
    batched with ``together`` − 1 others), else its last recorded one — or of all its episodes when that session
    has fewer than :data:`PARTIAL_PACE_EPISODES` or none is recorded). An episode's core-seconds are its wall
    time shared among the runs trained with it on one core (a batch's, ``sessions.jsonl``). A session's
    episodes measure the machine and code it ran on; a resumed run's earlier ones may not."""
    import numpy as np
    import pandas as pd

    sessions = read_sessions(run)
    last = sessions[-1] if sessions else {}
    ended = last.get("ended") if isinstance(last.get("ended"), str) else None
    try:
        table = pd.read_csv(run / EPISODES, usecols=["episode", "wall_s"])
        episode, wall = table["episode"].to_numpy(dtype=float), table["wall_s"].to_numpy(dtype=float)
    except (OSError, ValueError):
        return ended, []
    try:
        first = int(last["episodes_done"]) + 1 if together is not None else int(last["first_episode"])
    except (KeyError, TypeError, ValueError):
        first = 1
    valid = np.isfinite(wall) & (wall > 0)
    sample = wall[valid & (episode >= first)]
    if sample.size < PARTIAL_PACE_EPISODES:
        sample = wall[valid]
    share = together if together is not None else _batch_size(last)
    return ended, [float(x) / share for x in sample]


def time_left(grid: Grid, sweep: SweepDir, runs: dict[str, tuple[str, int]]) -> str:
    """One line: the core-hours the unfinished runs still need, at each algorithm's pace: the median over its
    :data:`PACE_RUNS` most recent runs of each run's median episode core-seconds in its latest session
    (:func:`_pace_sample`; a batch's wall time shared among its runs: for the runs training now, the runs of the
    batch their heartbeat names, its ``batch.json``). Most recent: the runs training now, then the others by the
    end of their last training session (``sessions.jsonl``; runs without one count as the oldest). A run counts
    once complete, or with :data:`PARTIAL_PACE_EPISODES` episodes. An algorithm without such a run is assumed to
    go at the median of the others' paces; the line says which. ``runs``: name -> (state, episodes)."""
    import numpy as np

    measured: dict[str, list[tuple[tuple[int, str], float]]] = {}  # algo -> [(recency, the run's pace)]
    training: set[str] = set()
    left: dict[str, int] = {}
    for cell in grid.cells():
        state, episodes = runs[cell.name]
        algo = cell.setting.algorithm
        if state != COMPLETE:
            left[algo] = left.get(algo, 0) + max(grid.episodes - episodes, 0)
        if state not in (COMPLETE, PARTIAL, RUNNING) or episodes == 0:  # not a stale, failed or damaged run's
            continue
        together = None
        if state == RUNNING:  # trained with the runs of the batch its heartbeat names (alone without one)
            batch = read_heartbeat(sweep, cell.name).get("batch")
            together = len(members(sweep.batch(batch))) or 1 if isinstance(batch, str) and batch else 1
        ended, walls = _pace_sample(sweep.run(cell), together)
        if not walls or (state != COMPLETE and len(walls) < PARTIAL_PACE_EPISODES):
            continue
        recency = (2, cell.name) if state == RUNNING else ((1, ended) if ended else (0, cell.name))
        measured.setdefault(algo, []).append((recency, float(np.median(walls))))
        if state == RUNNING:
            training.add(algo)
    if not left:
        return "time left: none, every run is complete"
    known = {algo: float(np.median([pace for _, pace in sorted(paces)[-PACE_RUNS:]]))
             for algo, paces in measured.items()}
    if not known:
        return (f"time left: unknown until a run completes or has {PARTIAL_PACE_EPISODES} episodes "
                "(its episodes' wall times set the pace)")
    every = float(np.median(list(known.values())))
    assumed = sorted(algo for algo in left if algo not in known)
    seconds = sum(n * known.get(algo, every) for algo, n in left.items())
    paces = ", ".join(f"{algo} {known[algo]:.1f}" + (" (with runs training now)" if algo in training else "")
                      for algo in sorted(known))
    note = f"; {', '.join(assumed)}: no run far enough yet, {every:.1f} assumed" if assumed else ""
    return (f"time left: ≈ {seconds / 3600:.1f} core-hours for {sum(left.values())} episodes at each algorithm's "
            f"pace (core-s per episode, a batch's shared among its runs; median of its {PACE_RUNS} latest runs' "
            f"latest sessions: {paces}{note}); divide by the workers running at once")


def status_text(folder: Path) -> str:
    """The state of every run of the sweep in ``folder`` (read from the folders; no Ray needed)."""
    manifest = read_manifest(folder)
    grid, sweep = manifest.grid, SweepDir(folder)
    opened = open_files()
    infos = {c.name: overlay(sweep, c.name, inspect_run(sweep.run(c), grid.episodes), opened) for c in grid.cells()}
    budget = grid.budget()
    driver = driver_running(folder)
    total = len(infos) * grid.episodes
    done = sum(min(i.episodes, grid.episodes) for i in infos.values())
    head = f"sweep {grid.name} in {folder}: {len(infos)} runs × {grid.episodes} episodes of {grid.episode_steps} steps"
    if budget["reduced"]:
        head += f" (REDUCED BUDGET: {'; '.join(budget['notes'])})"
    who = (f"running, pid {driver.get('pid')} on {driver.get('host')} since {driver.get('started', '?')}" if driver
           else f"not running (continue with 'lanefree sweep --resume {folder}')")
    lines = [head, f"driver: {who}",
             "runs: " + ", ".join(f"{sum(1 for i in infos.values() if i.state == s)} {s}"
                                  for s in (COMPLETE, RUNNING, PARTIAL, STALE, PENDING, FAILED, BUSY, DAMAGED)),
             f"episodes: {done}/{total} ({100.0 * done / max(total, 1):.1f} %)",
             time_left(grid, sweep, {name: (info.state, info.episodes) for name, info in infos.items()}), "",
             f"{'setting':60} {'complete':>9} {'episodes':>12}"]
    for setting in grid.settings:
        names = [Cell(setting, s).name for s in grid.seeds]
        n_done = sum(1 for n in names if infos[n].state == COMPLETE)
        eps = sum(min(infos[n].episodes, grid.episodes) for n in names)
        lines.append(f"{setting.label:60} {n_done:>4}/{len(names):<4} {eps:>6}/{len(names) * grid.episodes}")
    notable = [(n, i) for n, i in infos.items() if i.state in (RUNNING, FAILED, BUSY, DAMAGED)]
    if notable:
        lines.append("")
        lines += [f"{i.state:>8}: runs/{n} ({i.episodes}/{grid.episodes}): {i.detail}" for n, i in notable]
    return "\n".join(lines)


__all__ = ["add_parser", "run", "status_text", "plan", "LaneFreeError"]
