"""Batched sweeps (``lanefree sweep --batch K``): runs packed into batches, each trained in one Ray task.

A batch is :mod:`lanefree_sumo.experiments.runners.batch`'s: K runs of one algorithm (dqn and ddqn as one) in one
process (the
batched simulation and learners), run k bit for bit the sequential ``lanefree train`` of its config on CPU. Its run
folders stay ``DIR/runs/<name>/``, the same folders with the same contents a sequential sweep writes; the batch's own
files (``batch.json``, ``batch_checkpoints/``) live in ``DIR/batches/<batch>/`` and its log is
``DIR/logs/<batch>.log``. The batch checkpoints (every member's replay buffer among them) are deleted once every
member is complete.

Packing (:func:`pack`): the runs to start whose configs differ only in what a batch may differ in
(:data:`PER_RUN_KEYS`) go together, in grid order, split into batches of at most K (:data:`DEFAULT_BATCH` without
``--batch``) of near equal size — into more, smaller ones (2 runs at least) while the new batches are fewer than
the workers, so that none idles (:func:`split_counts`; 14 runs at K = 16 on 2 workers: 7 + 7). A run the batched
path cannot train (:func:`batch_key`'s reason) goes one run per task. An interrupted batch (a batch folder with a
batch checkpoint and an unfinished member) continues as that batch, whatever K is now: its members' checkpoints
hold no replay buffer of their own. A batch folder without a checkpoint (killed before its first) is deleted and
its runs are packed afresh.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import shutil
import socket
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lanefree_sumo.config import LaneFreeConfig, config_to_dict
from lanefree_sumo.errors import ConfigError, LaneFreeError, RunError
from lanefree_sumo.experiments.sweep.grid import Cell, Grid
from lanefree_sumo.experiments.sweep.manifest import SweepDir
from lanefree_sumo.experiments.sweep.state import (
    BUSY,
    COMPLETE,
    PARTIAL,
    PENDING,
    STALE,
    Heartbeat,
    RunInfo,
    clear_failure,
    held_elsewhere,
    inspect_run,
    record_failure,
    run_lock,
    writers_elsewhere,
)

DEFAULT_BATCH = 8
"""The most runs a batch takes when ``--batch`` is not given."""

PER_RUN_KEYS = ("seed", "scenario.density_veh_per_km", "reward.preset", "reward.overtake_bonus",
                "scenario.agent_max_speed_mps", "scenario.agent_lateral_speed_ratio",
                "train.actor_critic.pre_tanh_penalty")
"""The config keys (dotted) the runs of one batch may differ in (:class:`~lanefree_sumo.rl.batched_env.
BatchedRingEnv`); every other key they share, but ``train.algo`` only up to its batch group (dqn and ddqn
mix: :func:`~lanefree_sumo.rl.algorithms.batched.dqn.batch_group`)."""


@dataclass(frozen=True)
class Batch:
    """One batch task: its folder name under ``DIR/batches/`` and its runs (their names under ``DIR/runs/``)."""

    name: str
    runs: tuple[str, ...]
    resumed: bool = False
    """It continues an interrupted batch from its newest batch checkpoint."""


@dataclass
class Packing:
    """How a sweep session trains its runs."""

    batches: list[Batch] = field(default_factory=list)
    sequential: list[Cell] = field(default_factory=list)
    """Runs trained one per task."""
    reasons: dict[str, int] = field(default_factory=dict)
    """Why runs go one per task (the batched path's reason → how many runs)."""
    size: int = 1
    """The most runs per new batch (K; an interrupted batch continues with its own runs)."""

    def describe(self) -> str:
        """One line for the sweep's plan."""
        parts = []
        if self.batches:
            resumed = sum(b.resumed for b in self.batches)
            runs = sum(len(b.runs) for b in self.batches)
            largest = max(len(b.runs) for b in self.batches)
            parts.append(f"{runs} run(s) in {len(self.batches)} batch(es) of at most {largest}"
                         + (f" ({resumed} interrupted batch(es) continued as batches)" if resumed else ""))
        if self.sequential:
            why = "; ".join(f"{r}: {n}" for r, n in self.reasons.items())
            parts.append(f"{len(self.sequential)} run(s) one per task" + (f" ({why})" if why else ""))
        return ", ".join(parts)


def batch_key(cfg: LaneFreeConfig) -> str:
    """What the runs of one batch share, as text (the config without :data:`PER_RUN_KEYS`); ConfigError (one
    line, the reason) for a run the batched path cannot train."""
    from lanefree_sumo.experiments.runners.batch import check_batchable
    from lanefree_sumo.rl.algorithms.batched.dqn import batch_group

    check_batchable(cfg)
    data = config_to_dict(cfg)
    for key in PER_RUN_KEYS:
        *path, last = key.split(".")
        section = data
        for part in path:
            section = section[part]
        section.pop(last)
    data["train"]["algo"] = batch_group(cfg.train.algo)  # dqn and ddqn runs share batches
    return json.dumps(data, sort_keys=True, default=str)


def batch_name(algos: Sequence[str], runs: list[str]) -> str:
    """A batch folder's name: its runs' algorithms (``ddqn+dqn`` where they mix), size and a digest of its runs
    (the same runs, the same name)."""
    digest = hashlib.sha1("\n".join(runs).encode()).hexdigest()[:8]
    return f"batch_{'+'.join(sorted(set(algos)))}_k{len(runs)}_{digest}"


def members(folder: Path) -> list[str]:
    """The names of the runs of batch ``folder`` (its ``batch.json``); empty when it has none or it is unreadable."""
    from lanefree_sumo.experiments.runners.batch import BATCH_FILE

    try:
        return [Path(p).name for p in json.loads((folder / BATCH_FILE).read_text())["runs"]]
    except (OSError, ValueError, KeyError, TypeError):
        return []


def has_checkpoint(folder: Path) -> bool:
    from lanefree_sumo.experiments.storage.rundir import BATCH_CHECKPOINTS

    return any((folder / BATCH_CHECKPOINTS).glob("step_*.pt"))


def trained_in_batch(run: Path) -> bool:
    """Whether run folder ``run``'s last session was a batch's of several runs (a single run trained as a batch of
    one, :func:`~lanefree_sumo.experiments.runners.batch.is_single_run`, is extended as a run is)."""
    from lanefree_sumo.experiments.runners.batch import is_single_run

    try:
        session = json.loads((run / "last_session.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(session, dict) and "batch" in session and not is_single_run(run)


def interrupted_batches(sweep: SweepDir, grid: Grid, todo: list[Cell], states: dict[str, RunInfo]) -> list[Batch]:
    """The batches of ``sweep`` to continue: those with a batch checkpoint and a run in ``todo``. Deletes the
    batch folders without a checkpoint (killed before their first: their runs start afresh; or finished) that no
    process is training: their ``batch.json`` names their runs (a batch writes it after claiming them), none of
    which is busy elsewhere (``states``: its episodes.csv open in another process) or has its lock held by another
    process (a sweep's batch between its start and its first checkpoint)."""
    found: list[Batch] = []
    if not sweep.batches.is_dir():
        return found
    wanted, known = {c.name for c in todo}, {c.name for c in grid.cells()}
    busy = {name for name, info in states.items() if info.state == BUSY}
    for folder in sorted(p for p in sweep.batches.iterdir() if p.is_dir()):
        runs = members(folder)
        if not has_checkpoint(folder):
            idle = all(name not in busy and not held_elsewhere(sweep, name) for name in runs)
            if runs and idle:
                shutil.rmtree(folder)
        elif wanted.intersection(runs):
            strangers = sorted(set(runs) - known)
            if strangers:
                raise RunError(f"batch {folder} holds {strangers[0]}, not a run of this sweep's grid; move the "
                               "batch folder away to train its other runs afresh")
            found.append(Batch(folder.name, tuple(runs), resumed=True))
    return found


def _single_reason(sweep: SweepDir, grid: Grid, cell: Cell, info: RunInfo, size: int,
                   why_single: str) -> str | None:
    """Why ``cell`` trains one run per task (None: it may be batched). RunError for a finished batched run the
    grid would extend."""
    if info.state == PARTIAL and trained_in_batch(sweep.run(cell)):
        raise RunError(f"{sweep.run(cell)} was trained in a batch ({info.detail}); a batch is not extended: "
                       f"keep the grid's episodes or use another --out")
    if size < 2:
        return why_single
    if info.state not in (PENDING, STALE):
        return "resumed from its own checkpoint"
    try:
        batch_key(grid.config(cell))
    except ConfigError as exc:
        return str(exc).split(";")[0]
    return None


def split_counts(groups: Sequence[int], size: int, workers: int | None) -> list[int]:
    """How many batches each group of ``groups`` (their run counts) is split into: enough for at most ``size``
    runs each, then — while the new batches are fewer than ``workers`` — one more for the group with the largest
    batches, as long as each keeps 2 runs (``workers`` None: unknown, no such split)."""
    counts = [math.ceil(n / size) for n in groups]
    while workers and sum(counts) < workers:
        fits = [i for i, n in enumerate(groups) if n >= 2 * (counts[i] + 1)]
        if not fits:
            break
        widest = max(fits, key=lambda i: groups[i] / counts[i])
        counts[widest] += 1
    return counts


def pack(sweep: SweepDir, grid: Grid, todo: list[Cell], states: dict[str, RunInfo], size: int,
         why_single: str = "--batch 1", workers: int | None = None) -> Packing:
    """Batches of at most ``size`` and single runs for ``todo`` (module docstring; ``why_single``: the plan's
    reason when ``size`` is 1; ``workers``: the workers the new batches share, see :func:`split_counts`);
    deletes batch folders without a checkpoint. RunError for a finished batched run the grid asks to extend (a
    batch is not extended)."""
    packing = Packing(batches=interrupted_batches(sweep, grid, todo, states), size=size)
    claimed = {name for batch in packing.batches for name in batch.runs}
    groups: dict[str, list[Cell]] = {}
    for cell in todo:
        if cell.name in claimed:
            continue
        reason = _single_reason(sweep, grid, cell, states[cell.name], size, why_single)
        if reason is None:
            groups.setdefault(batch_key(grid.config(cell)), []).append(cell)
        else:
            packing.sequential.append(cell)
            packing.reasons[reason] = packing.reasons.get(reason, 0) + 1
    counts = split_counts([len(cells) for cells in groups.values()], size, workers)  # size 1: no groups
    for cells, count in zip(groups.values(), counts):
        start = 0
        for i in range(count):  # near equal sizes: 10 runs at K = 8 are 5 + 5, not 8 + 2
            n = len(cells) // count + (i < len(cells) % count)
            chunk = cells[start:start + n]
            start += n
            if len(chunk) == 1:
                packing.sequential.append(chunk[0])
                packing.reasons["alone in its batch"] = packing.reasons.get("alone in its batch", 0) + 1
            else:
                names = [c.name for c in chunk]
                packing.batches.append(Batch(batch_name([c.setting.algorithm for c in chunk], names), tuple(names)))
    return packing


# -- the Ray task --------------------------------------------------------------------------------------------

def _result(name: str, status: str, episodes: int = 0, detail: str = "") -> dict[str, Any]:
    return {"name": name, "status": status, "episodes": episodes, "detail": detail, "host": socket.gethostname(),
            "pid": os.getpid(), "wall_s": 0.0}


def train_batch_task(sweep: SweepDir, batch: str, runs: list[str], configs: list[dict[str, Any]], target: int,
                     command: str) -> None:
    """Bring batch ``batch``'s runs to ``target`` episodes: continue it from its newest batch checkpoint, or start
    it (a run folder left by a start killed before its first checkpoint is cleared)."""
    from lanefree_sumo.config import merge_config
    from lanefree_sumo.experiments.runners.batch import resume_batch, train_batch

    folder = sweep.batch(batch)
    if has_checkpoint(folder):
        print(f"continuing batch {batch} from its newest batch checkpoint", flush=True)
        resume_batch(folder, progress=False, command=command)
        return
    for name in runs:
        info = inspect_run(sweep.run(name), target)
        if info.state == STALE:
            print(f"{name}: no checkpoint ({info.episodes} episode rows); starting from scratch", flush=True)
            shutil.rmtree(sweep.run(name))
        elif info.state != PENDING:
            detail = f" ({info.detail})" if info.detail else ""
            raise RunError(f"{sweep.run(name)} is {info.state}{detail}; a new batch starts only new runs")
    train_batch([merge_config(LaneFreeConfig(), c) for c in configs], folder, [sweep.run(n) for n in runs],
                progress=False, command=command)


def run_batch(out: str, batch: str, runs: list[str], configs: list[dict[str, Any]], target: int,
              command: str) -> list[dict[str, Any]]:
    """Ray task: train batch ``batch`` of sweep folder ``out`` (runs ``runs`` with configs ``configs``). Returns
    one :func:`~.worker.run_cell` result per run: ``complete``, ``interrupted``, ``failed`` (a run stopped for a
    non-finite action, or the batch's error) or ``busy``."""
    from lanefree_sumo.experiments.storage.rundir import BATCH_CHECKPOINTS
    from lanefree_sumo.experiments.sweep.worker import _node_id, _redirect_output

    sweep = SweepDir(Path(out))
    t0 = time.monotonic()
    _redirect_output(sweep.log(batch))
    node = _node_id()
    print(f"\n=== {time.strftime('%Y-%m-%d %H:%M:%S')} batch {batch} ({len(runs)} runs: {', '.join(runs)}) on host "
          f"{socket.gethostname()} pid {os.getpid()} node {node}", flush=True)
    with contextlib.ExitStack() as stack:
        held = [stack.enter_context(run_lock(sweep, name)) for name in runs]
        holders = [h for name in runs for h in writers_elsewhere(sweep.run(name) / "episodes.csv")]
        if not all(held) or holders:
            who = f"process {holders[0]}" if holders else "another sweep worker"
            print(f"a run of batch {batch} is being trained by {who}", flush=True)
            return [_result(name, "busy", detail=f"{sweep.run(name)} (batch {batch}) is being trained by {who}")
                    for name in runs]
        beats = [Heartbeat(sweep, name, {"node": node, "batch": batch}) for name in runs]
        failure = None
        try:
            for name in runs:
                clear_failure(sweep, name)
            train_batch_task(sweep, batch, runs, configs, target,
                             f"{command}  # sweep batch {batch} on {socket.gethostname()} pid {os.getpid()}")
        except KeyboardInterrupt:
            failure = ("interrupted", "stopped before training began")
        except LaneFreeError as exc:
            failure = ("failed", " ".join(str(exc).split()))
        except Exception as exc:  # a bug or a broken environment: the traceback goes to the log
            traceback.print_exc()
            failure = ("failed", f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]} (see {sweep.log(batch)})")
        finally:
            for beat in beats:
                beat.stop()
        results = [_outcome(sweep, name, target, failure) for name in runs]
        for result in results:
            result["wall_s"] = round(time.monotonic() - t0, 1)
            if result["status"] == "failed":
                record_failure(sweep, result["name"], result["detail"])
        if all(r["status"] == "complete" for r in results):
            shutil.rmtree(sweep.batch(batch) / BATCH_CHECKPOINTS, ignore_errors=True)  # nothing left to resume
        print(f"=== batch {batch}: " + ", ".join(f"{r['name']} {r['status']}" for r in results)
              + f" ({round(time.monotonic() - t0, 1)} s)", flush=True)
        return results
    raise AssertionError("unreachable")


def _outcome(sweep: SweepDir, name: str, target: int, failure: tuple[str, str] | None) -> dict[str, Any]:
    """Run ``name``'s result after its batch's session: its folder's state, the batch's failure, or the reason
    its run was stopped (``last_session.json``'s ``stopped_by``: a non-finite action)."""
    info = inspect_run(sweep.run(name), target)
    if info.state == COMPLETE:
        return _result(name, "complete", info.episodes)
    if failure is not None:
        return _result(name, failure[0], info.episodes, failure[1])
    try:
        stopped = json.loads((sweep.run(name) / "last_session.json").read_text()).get("stopped_by")
    except (OSError, ValueError, AttributeError):
        stopped = None
    if stopped and stopped not in ("SIGINT", "SIGTERM"):
        return _result(name, "failed", info.episodes, str(stopped))
    return _result(name, "interrupted", info.episodes, f"stopped at {info.episodes}/{target} episodes")
