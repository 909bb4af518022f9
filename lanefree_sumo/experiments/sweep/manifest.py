"""``DIR/sweep.yaml``, the sweep's manifest, THE place that knows a sweep folder's file names,
and the driver lock (one driver per sweep folder).

The manifest holds the resolved grid (every run of the sweep follows from it), its budget against
the paper's (a reduced one is shown on every report), and one line per session that worked on the
sweep. What each run has done is never stored here: the run folders are the truth
(:mod:`.state`). Only the driver writes the manifest, atomically, while it holds the lock.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import socket
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import yaml

from lanefree_sumo.errors import ConfigError, RunError, UsageError
from lanefree_sumo.experiments.storage.rundir import BATCH_FILE, write_atomic
from lanefree_sumo.experiments.sweep.grid import Cell, Grid

MANIFEST = "sweep.yaml"
RUNS = "runs"
BATCHES = "batches"
"""Batched training's folders (:mod:`.batches`): ``batch.json`` and the batch checkpoints, the runs in ``runs/``."""
LOGS = "logs"
STATE = ".sweep"
SUMMARY_CSV = "summary.csv"
SUMMARY_MD = "summary.md"
CLAIMS_CSV = "claims.csv"
CLAIMS_MD = "claims.md"
EFFECTS_CSV = "effects.csv"
EFFECTS_MD = "effects.md"
VERDICT_MD = "verdict.md"
"""Each variant against the grid's ``default`` (:mod:`lanefree_sumo.experiments.analysis.effects`), in a grid with
variants."""
RUNS_CSV = "runs.csv"
CURVES = "curves"
FORMAT = 1
"""Version of the manifest layout."""


@dataclass(frozen=True)
class SweepDir:
    """A sweep folder and the paths inside it."""

    path: Path

    @property
    def manifest(self) -> Path:
        return self.path / MANIFEST

    @property
    def runs(self) -> Path:
        return self.path / RUNS

    def run(self, cell: Cell | str) -> Path:
        return self.runs / (cell if isinstance(cell, str) else cell.name)

    @property
    def batches(self) -> Path:
        return self.path / BATCHES

    def batch(self, name: str) -> Path:
        return self.batches / name

    def log(self, name: str) -> Path:
        return self.path / LOGS / f"{name}.log"

    @property
    def state(self) -> Path:
        return self.path / STATE

    def heartbeat(self, name: str) -> Path:
        """Exists while a worker trains run ``name``; its mtime is refreshed every few seconds."""
        return self.state / "running" / f"{name}.json"

    def failure(self, name: str) -> Path:
        """Why the latest attempt at run ``name`` failed (one line); removed when it is retried."""
        return self.state / "failed" / f"{name}.txt"

    def run_lock(self, name: str) -> Path:
        return self.state / "locks" / f"{name}.lock"

    @property
    def driver_lock(self) -> Path:
        return self.state / "driver.lock"

    @property
    def driver_info(self) -> Path:
        return self.state / "driver.json"

    @property
    def summary_csv(self) -> Path:
        return self.path / SUMMARY_CSV

    @property
    def summary_md(self) -> Path:
        return self.path / SUMMARY_MD

    @property
    def runs_csv(self) -> Path:
        return self.path / RUNS_CSV

    @property
    def claims_csv(self) -> Path:
        return self.path / CLAIMS_CSV

    @property
    def claims_md(self) -> Path:
        return self.path / CLAIMS_MD

    @property
    def effects_csv(self) -> Path:
        return self.path / EFFECTS_CSV

    @property
    def effects_md(self) -> Path:
        return self.path / EFFECTS_MD

    @property
    def verdict_md(self) -> Path:
        return self.path / VERDICT_MD

    @property
    def curves(self) -> Path:
        return self.path / CURVES


@dataclass
class Manifest:
    """What ``sweep.yaml`` holds."""

    grid: Grid
    created: str = field(default_factory=lambda: datetime.now().isoformat(timespec="seconds"))
    sessions: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"lanefree_sweep": FORMAT, "created": self.created, "runs": len(self.grid.cells()),
                "budget": self.grid.budget(), "grid": self.grid.to_dict(), "sessions": self.sessions}


def read_manifest(folder: Path) -> Manifest:
    """The manifest of sweep folder ``folder``; RunError naming the problem."""
    path = SweepDir(folder).manifest
    if not path.is_file() and (folder / BATCH_FILE).is_file():
        raise RunError(f"{folder} is a 'lanefree train --seeds' batch, not a sweep folder; its runs: "
                       f"'lanefree report {folder}', and 'lanefree train --resume {folder}' continues it while "
                       "unfinished")
    if not path.is_file():
        raise RunError(f"{folder} is not a sweep folder (no {MANIFEST}); start one with "
                       f"'lanefree sweep GRID --out {folder}'")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
        if not isinstance(data, dict) or data.get("lanefree_sweep") != FORMAT:
            raise ConfigError(f"not a lanefree sweep manifest of format {FORMAT}")
        grid = Grid.from_dict(data["grid"], str(path))
        sessions = list(data.get("sessions") or [])
    except (OSError, UnicodeDecodeError, yaml.YAMLError, ConfigError, KeyError, TypeError) as exc:
        reason = " ".join(str(exc).split())[:300]
        raise RunError(f"{path} is unusable ({reason}); restore it or start the sweep in another folder") from None
    return Manifest(grid, str(data.get("created", "")), sessions)


SELF = "<sweep folder>"
"""How a manifest names the folder it is in."""


def write_manifest(folder: Path, manifest: Manifest) -> None:
    """Write ``sweep.yaml`` atomically (a reader never sees half a file). The sweep folder's own path in
    the recorded commands is written ``<sweep folder>``: the manifest is committed and moved between
    machines, and the folder may sit elsewhere there."""
    path = SweepDir(folder).manifest
    here = re.compile(re.escape(str(folder.resolve())) + r"(?=/|\s|$)")  # the folder, not a longer name it starts
    data = manifest.to_dict()
    data["sessions"] = [{**s, "command": here.sub(SELF, str(s.get("command", "")))} if isinstance(s, dict) else s
                        for s in data["sessions"]]
    text = ("# lanefree sweep manifest: the grid of this sweep folder. Resume with 'lanefree sweep --resume "
            f"{SELF}'.\n" + yaml.safe_dump(data, sort_keys=False))
    write_atomic(path, text)


def grid_difference(saved: Grid, asked: Grid) -> str | None:
    """The first difference between two grids, as ``key: saved vs asked``; None when equal."""
    a, b = saved.to_dict(), asked.to_dict()
    for key in ("settings", "seeds", "episodes", "overrides"):
        if a[key] != b[key]:
            if key == "settings":
                return (f"settings: {', '.join(s.label for s in saved.settings)} vs "
                        f"{', '.join(s.label for s in asked.settings)}")
            return f"{key}: {a[key]} vs {b[key]}"
    return None


def check_same_grid(folder: Path, saved: Grid, asked: Grid) -> None:
    """UsageError when ``folder`` holds a sweep of another grid than the one asked for."""
    diff = grid_difference(saved, asked)
    if diff is not None:
        raise UsageError(f"{folder} holds a sweep of another grid ({diff}, in {MANIFEST} vs asked now); "
                         f"continue it with 'lanefree sweep --resume {folder}' or choose another --out")


# -- the driver lock ------------------------------------------------------------------------------

def driver_running(folder: Path) -> dict[str, Any] | None:
    """The driver working on ``folder`` now (its pid, host, start), or None when there is none."""
    sweep = SweepDir(folder)
    if not sweep.driver_lock.exists():
        return None
    try:
        with open(sweep.driver_lock, "a+") as fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                try:
                    return dict(json.loads(sweep.driver_info.read_text()))
                except (OSError, ValueError, TypeError):
                    return {"pid": "?", "host": "?"}
            fcntl.flock(fh, fcntl.LOCK_UN)
    except OSError:
        return None
    return None


@contextlib.contextmanager
def driver_lock(folder: Path, command: str) -> Iterator[None]:
    """Hold the sweep folder's driver lock; UsageError when another driver holds it."""
    sweep = SweepDir(folder)
    try:
        sweep.state.mkdir(parents=True, exist_ok=True)
        fh = open(sweep.driver_lock, "a+")
    except OSError as exc:
        raise RunError(f"cannot write {folder}: {exc.strerror or exc}") from None
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            other = driver_running(folder) or {}
            raise UsageError(f"{folder} is being run by another 'lanefree sweep' (pid {other.get('pid', '?')} on "
                             f"{other.get('host', '?')}); watch it with 'lanefree sweep --status {folder}'") from None
        write_atomic(sweep.driver_info, json.dumps({
            "pid": os.getpid(), "host": socket.gethostname(), "command": command,
            "started": datetime.now().isoformat(timespec="seconds")}) + "\n")
        yield
    finally:
        fh.close()  # releases the lock
