"""What a sweep's run folders hold, read from the folders themselves (they are the truth).

A run is **complete** when its ``model.zip`` exists and ``episodes.csv`` holds exactly episodes
1 … N of the grid's budget N (each once), or when a folder without model and checkpoints holds those
episodes and the ``last_session.json`` of a finished session (committed results: git keeps no models);
**partial** when it has a usable checkpoint to resume
from (or is a finished shorter run to extend); **stale** when its folder has no checkpoint yet
(a worker died before the first one: it restarts from scratch); **pending** without a folder;
**damaged** when ``model.zip`` exists but the CSV does not hold exactly its episodes (never
touched automatically). On top of that a run is **running** while a worker's heartbeat is fresh,
**failed** while the latest attempt's failure reason is on file, and **busy** while a process
outside the sweep (a standalone ``lanefree train``) has its ``episodes.csv`` open.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from lanefree_sumo.errors import RunError
from lanefree_sumo.experiments.storage.rundir import RunDir, write_atomic
from lanefree_sumo.experiments.sweep.manifest import SweepDir

HEARTBEAT_S = 10.0
"""A worker refreshes its heartbeat this often (s)."""
STALE_S = 90.0
"""A heartbeat older than this (s) belongs to a worker that is gone."""

COMPLETE, PARTIAL, STALE, PENDING, DAMAGED = "complete", "partial", "stale", "pending", "damaged"
RUNNING, FAILED, BUSY = "running", "failed", "busy"


def episode_numbers(csv_path: Path) -> list[int] | None:
    """Episode numbers of the rows of an ``episodes.csv`` in file order; None when a row has no
    whole episode number (a line cut mid-row)."""
    if not csv_path.is_file():
        return []
    try:
        lines = csv_path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return None
    numbers = []
    for line in lines[1:]:
        if not line.strip():
            continue
        first = line.split(",", 1)[0].strip()
        if not first.isdigit():
            return None
        numbers.append(int(first))
    return numbers


def count_rows(csv_path: Path) -> int:
    """Finished episodes in an ``episodes.csv`` (its non-blank lines after the header)."""
    try:
        with open(csv_path, "rb") as fh:
            return max(0, sum(1 for line in fh if line.strip()) - 1)
    except OSError:
        return 0


@dataclass(frozen=True)
class RunInfo:
    """The state of one run folder."""

    state: str
    episodes: int
    """Rows in its episodes.csv (episodes finished so far)."""
    detail: str = ""


def inspect_run(folder: Path, target: int) -> RunInfo:
    """What ``folder`` holds against a budget of ``target`` episodes (see the module docstring)."""
    if not folder.is_dir() or not any(folder.iterdir()):
        return RunInfo(PENDING, 0)
    run = RunDir(folder)
    numbers = episode_numbers(run.episodes)
    rows = len(numbers) if numbers is not None else count_rows(run.episodes)
    if run.model.is_file():
        if numbers == list(range(1, target + 1)):
            return RunInfo(COMPLETE, rows)
        if numbers is not None and numbers == list(range(1, len(numbers) + 1)) and len(numbers) < target:
            return RunInfo(PARTIAL, rows, f"finished at {len(numbers)} episodes; will be extended to {target}")
        return RunInfo(DAMAGED, rows, f"model.zip exists but episodes.csv does not hold exactly episodes 1…{target}; "
                                      "inspect it (restore the CSV or delete the folder to retrain)")
    try:
        ckpt = run.newest_checkpoint()
    except RunError:
        if numbers == list(range(1, target + 1)) and not run.checkpoints.exists() and _finished(run, target):
            return RunInfo(COMPLETE, rows, "complete; its model is not here (results copied without models)")
        return RunInfo(STALE, rows, "no checkpoint yet; restarts from scratch")
    return RunInfo(PARTIAL, rows, f"resumable from episode {ckpt.episodes}")


def _finished(run: RunDir, target: int) -> bool:
    """The run's last session says it ended with ``target`` episodes done."""
    try:
        return int(json.loads(run.last_session.read_text()).get("episodes_done", -1)) == target
    except (OSError, ValueError, TypeError, AttributeError):
        return False


def heartbeat_age(sweep: SweepDir, name: str) -> float | None:
    """Seconds since the heartbeat of run ``name`` was refreshed; None without one."""
    try:
        return max(0.0, time.time() - sweep.heartbeat(name).stat().st_mtime)
    except OSError:
        return None


def read_heartbeat(sweep: SweepDir, name: str) -> dict[str, Any]:
    try:
        return dict(json.loads(sweep.heartbeat(name).read_text()))
    except (OSError, ValueError, TypeError):
        return {}


def failure_reason(sweep: SweepDir, name: str) -> str | None:
    try:
        return sweep.failure(name).read_text(encoding="utf-8").strip() or "failed"
    except OSError:
        return None


def record_failure(sweep: SweepDir, name: str, reason: str) -> None:
    write_atomic(sweep.failure(name), " ".join(reason.split()) + "\n")


def clear_failure(sweep: SweepDir, name: str) -> None:
    sweep.failure(name).unlink(missing_ok=True)


def open_files() -> dict[str, list[int]]:
    """Every file open in another process on this host → those processes' ids (Linux ``/proc``;
    empty elsewhere). Read once and passed to :func:`writers_elsewhere` when checking many runs."""
    proc = Path("/proc")
    found: dict[str, list[int]] = {}
    if not (proc / "self" / "fd").is_dir():
        return found
    me = os.getpid()
    for entry in proc.iterdir():
        if not entry.name.isdigit() or int(entry.name) == me:
            continue
        try:
            for fd in (entry / "fd").iterdir():
                with contextlib.suppress(OSError):
                    found.setdefault(os.readlink(fd), []).append(int(entry.name))
        except OSError:  # gone, or not ours to read
            continue
    return found


def writers_elsewhere(path: Path, opened: dict[str, list[int]] | None = None) -> list[int]:
    """Ids of other processes on this host that have ``path`` open. ``lanefree train`` keeps its
    run's episodes.csv open while it trains."""
    if not path.exists():
        return []
    return sorted(set((opened if opened is not None else open_files()).get(str(path.resolve()), [])))


def _alive(pid: Any) -> bool:
    try:
        os.kill(int(pid), 0)
    except (TypeError, ValueError, ProcessLookupError):
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def overlay(sweep: SweepDir, name: str, info: RunInfo, opened: dict[str, list[int]] | None = None) -> RunInfo:
    """``info`` with running / busy / failed on top (a complete run stays complete)."""
    if info.state == COMPLETE:
        return info
    age = heartbeat_age(sweep, name)
    if age is not None and age < STALE_S:
        beat = read_heartbeat(sweep, name)
        if beat.get("host") != socket.gethostname() or _alive(beat.get("pid")):
            return RunInfo(RUNNING, info.episodes, f"pid {beat.get('pid', '?')} on {beat.get('host', '?')}")
    holders = writers_elsewhere(RunDir(sweep.run(name)).episodes, opened)
    if holders:
        return RunInfo(BUSY, info.episodes, f"episodes.csv is open in process {holders[0]} outside this sweep")
    reason = failure_reason(sweep, name)
    if reason is not None and info.state != DAMAGED:
        return RunInfo(FAILED, info.episodes, reason)
    return info


# -- held by a worker while it trains a run -------------------------------------------------------

@contextlib.contextmanager
def run_lock(sweep: SweepDir, name: str) -> Iterator[bool]:
    """Yield True while this process holds run ``name``'s lock, False when another one does."""
    path = sweep.run_lock(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    fh: IO[str] = open(path, "a+")
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            yield False
            return
        yield True
    finally:
        fh.close()


def held_elsewhere(sweep: SweepDir, name: str) -> bool:
    """Whether another process (a sweep worker, a batch) holds run ``name``'s lock now."""
    with run_lock(sweep, name) as held:
        return not held


class Heartbeat:
    """``.sweep/running/<run>.json`` (host, pid, start) refreshed every :data:`HEARTBEAT_S` by a
    daemon thread while the worker trains; removed when it stops."""

    def __init__(self, sweep: SweepDir, name: str, extra: dict[str, Any]) -> None:
        self.path = sweep.heartbeat(name)
        self._stop = threading.Event()
        write_atomic(self.path, json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                            "started": time.strftime("%Y-%m-%dT%H:%M:%S"), **extra}) + "\n")
        self._thread = threading.Thread(target=self._beat, name="sweep-heartbeat", daemon=True)
        self._thread.start()

    def _beat(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            with contextlib.suppress(OSError):
                os.utime(self.path)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2 * HEARTBEAT_S)
        self.path.unlink(missing_ok=True)
