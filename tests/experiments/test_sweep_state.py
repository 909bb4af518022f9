"""What makes a sweep run complete, partial, stale or damaged: read from the run folder alone
(:mod:`lanefree_sumo.experiments.sweep.state`; files written by hand, no training, no Ray)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lanefree_sumo.experiments.sweep import state
from lanefree_sumo.experiments.sweep.manifest import SweepDir
from lanefree_sumo.experiments.sweep.state import (
    BUSY,
    COMPLETE,
    DAMAGED,
    FAILED,
    PARTIAL,
    PENDING,
    RUNNING,
    STALE,
    STALE_S,
    RunInfo,
    clear_failure,
    count_rows,
    episode_numbers,
    failure_reason,
    heartbeat_age,
    inspect_run,
    open_files,
    overlay,
    read_heartbeat,
    record_failure,
    writers_elsewhere,
)


def write_run(folder: Path, episodes: list[int] | None, model: bool = False, checkpoint: int | None = None,
              done: int | None = None) -> Path:
    """A run folder with an episodes.csv holding ``episodes`` (in that order), and optionally a final model,
    one complete checkpoint after ``checkpoint`` episodes and a last session that ended with ``done``."""
    folder.mkdir(parents=True)
    (folder / "config.yaml").write_text("{}\n")
    if episodes is not None:
        (folder / "episodes.csv").write_text("episode,return\n" + "".join(f"{e},1.0\n" for e in episodes))
    if model:
        (folder / "model.zip").write_bytes(b"model")
    if checkpoint is not None:
        ckpt = folder / "checkpoints" / f"ep_{checkpoint:05d}"
        ckpt.mkdir(parents=True)
        (ckpt / "model.zip").write_bytes(b"model")
        (ckpt / "state.json").write_text(json.dumps({"episodes": checkpoint, "timesteps": 10 * checkpoint}))
    if done is not None:
        (folder / "last_session.json").write_text(json.dumps({"episodes_done": done}))
    return folder


def test_with_a_model_complete_means_exactly_episodes_one_to_n(tmp_path):
    assert inspect_run(write_run(tmp_path / "a", [1, 2, 3], model=True), 3) == RunInfo(COMPLETE, 3)
    # three rows are not enough: they must be episodes 1, 2, 3, each once, in order
    for name, rows in (("gap", [1, 2, 4]), ("twice", [1, 2, 2]), ("order", [1, 3, 2]), ("from0", [0, 1, 2]),
                       ("extra", [1, 2, 3, 3]), ("more", [1, 2, 3, 4])):
        info = inspect_run(write_run(tmp_path / name, rows, model=True), 3)
        assert (info.state, info.episodes) == (DAMAGED, len(rows)), name
        assert "episodes 1…3" in info.detail
        assert "inspect it (restore the CSV or delete the folder to retrain)" in info.detail  # what to do
    # fewer, and exactly 1..k: a finished shorter run, extended
    info = inspect_run(write_run(tmp_path / "short", [1, 2], model=True), 3)
    assert info == RunInfo(PARTIAL, 2, "finished at 2 episodes; will be extended to 3")
    # fewer, not 1..k: damaged
    assert inspect_run(write_run(tmp_path / "shortgap", [2, 3], model=True), 3).state == DAMAGED


def test_a_cut_line_is_damaged_and_rows_are_counted_from_the_file(tmp_path):
    folder = write_run(tmp_path / "cut", [1, 2], model=True)
    with open(folder / "episodes.csv", "a") as fh:
        fh.write("3.5,1.0\n\n")  # not a whole episode number, then a blank line
    assert episode_numbers(folder / "episodes.csv") is None
    assert count_rows(folder / "episodes.csv") == 3  # non-blank lines after the header
    assert inspect_run(folder, 3) == RunInfo(DAMAGED, 3, inspect_run(folder, 3).detail)
    assert episode_numbers(tmp_path / "missing.csv") == [] and count_rows(tmp_path / "missing.csv") == 0
    blank = tmp_path / "blank.csv"
    blank.write_text("episode,return\n\n 7 ,1\n\n")
    assert episode_numbers(blank) == [7] and count_rows(blank) == 1
    header_only = tmp_path / "header.csv"
    header_only.write_text("episode,return\n")
    assert episode_numbers(header_only) == [] and count_rows(header_only) == 0
    assert count_rows(tmp_path) == 0  # a folder cannot be read as a file


def test_without_a_model_the_last_session_and_the_episode_numbers_decide(tmp_path):
    # committed results: episodes 1..N and a session that ended at N, no model, no checkpoints
    info = inspect_run(write_run(tmp_path / "done", [1, 2, 3], done=3), 3)
    assert info == RunInfo(COMPLETE, 3, "complete; its model is not here (results copied without models)")
    assert inspect_run(write_run(tmp_path / "cut", [1, 2, 3], done=2), 3).state == STALE  # ended earlier
    assert inspect_run(write_run(tmp_path / "more", [1, 2, 3], done=4), 3).state == STALE
    assert inspect_run(write_run(tmp_path / "gap", [1, 2, 4], done=3), 3).state == STALE  # rows, not 1..N
    assert inspect_run(write_run(tmp_path / "nosession", [1, 2, 3]), 3).state == STALE
    broken = write_run(tmp_path / "broken", [1, 2, 3])
    (broken / "last_session.json").write_text("[3]")
    assert inspect_run(broken, 3).state == STALE
    # a checkpoints folder without a usable checkpoint: a run that died, not committed results
    died = write_run(tmp_path / "died", [1, 2, 3], done=3)
    (died / "checkpoints").mkdir()
    info = inspect_run(died, 3)
    assert info == RunInfo(STALE, 3, "no checkpoint yet; restarts from scratch")


def test_a_checkpoint_makes_a_run_resumable(tmp_path):
    info = inspect_run(write_run(tmp_path / "a", [1, 2], checkpoint=2), 5)
    assert info == RunInfo(PARTIAL, 2, "resumable from episode 2")
    # a checkpoint without its model or state is not usable
    bad = write_run(tmp_path / "b", [1], checkpoint=1)
    (bad / "checkpoints" / "ep_00001" / "model.zip").unlink()
    assert inspect_run(bad, 5).state == STALE


def test_pending_means_no_folder_or_an_empty_one(tmp_path):
    assert inspect_run(tmp_path / "none", 3) == RunInfo(PENDING, 0)
    (tmp_path / "empty").mkdir()
    assert inspect_run(tmp_path / "empty", 3) == RunInfo(PENDING, 0)


def test_overlay_running_busy_failed_on_top_of_the_folder_state(tmp_path):
    sweep = SweepDir(tmp_path)
    name = "r"
    write_run(sweep.run(name), [1], checkpoint=1)
    info = inspect_run(sweep.run(name), 3)
    assert overlay(sweep, name, info, {}) == info  # nothing on top
    # a failure on file
    record_failure(sweep, name, "out of\n memory ")
    assert failure_reason(sweep, name) == "out of memory"
    assert overlay(sweep, name, info, {}) == RunInfo(FAILED, 1, "out of memory")
    damaged = RunInfo(DAMAGED, 1, "x")
    assert overlay(sweep, name, damaged, {}) == damaged  # damaged stays damaged
    complete = RunInfo(COMPLETE, 3)
    assert overlay(sweep, name, complete, {}) == complete  # complete stays complete
    # another process holding the episodes.csv open
    csv_path = str((sweep.run(name) / "episodes.csv").resolve())
    assert writers_elsewhere(sweep.run(name) / "episodes.csv", {csv_path: [42, 7, 42]}) == [7, 42]
    assert writers_elsewhere(sweep.run(name) / "nothing.csv", {csv_path: [42]}) == []
    busy = overlay(sweep, name, info, {csv_path: [42]})
    assert busy.state == BUSY and "process 42" in busy.detail and busy.episodes == 1
    # a fresh heartbeat of a live process here: running, whatever else
    beat = sweep.heartbeat(name)
    beat.parent.mkdir(parents=True, exist_ok=True)
    beat.write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}))
    assert read_heartbeat(sweep, name)["pid"] == os.getpid()
    running = overlay(sweep, name, info, {csv_path: [42]})
    assert running == RunInfo(RUNNING, 1, f"pid {os.getpid()} on {socket.gethostname()}")
    beat.write_text("{}")  # fresh but unreadable as a worker: trusted, named by question marks
    assert overlay(sweep, name, info, {}) == RunInfo(RUNNING, 1, "pid ? on ?")
    # the same heartbeat of a process that is gone: not running
    beat.write_text(json.dumps({"pid": 2**22 + 12345, "host": socket.gethostname()}))
    assert overlay(sweep, name, info, {}).state == FAILED
    # a heartbeat from another host is trusted while fresh, not once older than STALE_S
    beat.write_text(json.dumps({"pid": 1, "host": "elsewhere"}))
    assert overlay(sweep, name, info, {}).state == RUNNING
    old = time.time() - STALE_S - 5
    os.utime(beat, (old, old))
    assert heartbeat_age(sweep, name) == pytest.approx(STALE_S + 5, abs=2)
    assert overlay(sweep, name, info, {}).state == FAILED
    clear_failure(sweep, name)
    assert failure_reason(sweep, name) is None and overlay(sweep, name, info, {}) == info
    assert heartbeat_age(sweep, "other") is None and read_heartbeat(sweep, "other") == {}


def test_a_heartbeat_names_its_worker_is_refreshed_and_removed(tmp_path, monkeypatch):
    monkeypatch.setattr(state, "HEARTBEAT_S", 0.01)
    sweep = SweepDir(tmp_path)
    beat = state.Heartbeat(sweep, "r", {"episodes": 3})
    try:
        assert beat._thread.daemon  # a worker that dies without stop() is not kept alive by its heartbeat
        data = read_heartbeat(sweep, "r")
        assert (data["pid"], data["host"], data["episodes"]) == (os.getpid(), socket.gethostname(), 3)
        assert time.strptime(data["started"], "%Y-%m-%dT%H:%M:%S")
        old = time.time() - 60
        os.utime(beat.path, (old, old))
        deadline = time.monotonic() + 30
        while heartbeat_age(sweep, "r") > 30 and time.monotonic() < deadline:
            time.sleep(0.01)  # polling the state the thread changes
        assert heartbeat_age(sweep, "r") < 30  # refreshed by the thread
    finally:
        beat.stop()
    assert not beat.path.exists()
    beat._thread.join(timeout=30)  # stop() waits 2 × HEARTBEAT_S only; a loaded machine may need longer
    assert not beat._thread.is_alive()  # the thread ended: the stop event was set


def test_open_files_lists_the_files_other_processes_hold(tmp_path):
    path = tmp_path / "episodes.csv"
    path.write_text("episode\n")
    holder = subprocess.Popen([sys.executable, "-c", f"f = open({str(path)!r}); print('open', flush=True); "
                               "import sys; sys.stdin.read()"],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "open"
        opened = open_files()
        assert holder.pid in opened[str(path.resolve())]
        assert os.getpid() not in {pid for pids in opened.values() for pid in pids}  # never this process
        assert writers_elsewhere(path) == [holder.pid]
    finally:
        holder.stdin.close()
        holder.wait()
    assert writers_elsewhere(path) == []


def test_a_session_without_its_episode_count_finishes_nothing(tmp_path):
    # the default of a missing "episodes_done" must not equal any budget: one episode and {} is not complete
    assert inspect_run(write_run(tmp_path / "one", [1], done=None), 1).state == STALE
    (tmp_path / "one" / "last_session.json").write_text("{}")
    assert inspect_run(tmp_path / "one", 1).state == STALE


def test_rows_that_are_not_text_are_still_counted(tmp_path):
    path = tmp_path / "episodes.csv"
    path.write_bytes(b"episode,return\n1,1.0\n\xff\xfe,2\n")  # a row of bytes that are not UTF-8
    assert count_rows(path) == 2 and episode_numbers(path) is None


def test_an_empty_failure_reason_reads_failed(tmp_path):
    sweep = SweepDir(tmp_path)
    record_failure(sweep, "r", "  ")
    assert failure_reason(sweep, "r") == "failed"


def test_checking_a_worker_sends_it_no_signal_and_another_users_process_is_alive(tmp_path, monkeypatch):
    # the child restores the default action of SIGHUP (nohup ignores it), which ends a process
    child = subprocess.Popen([sys.executable, "-c", "import signal, sys\n"
                              "signal.signal(signal.SIGHUP, signal.SIG_DFL)\n"
                              "print('ready', flush=True); sys.stdin.read()"],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "ready"
        assert state._alive(child.pid) and state._alive(str(child.pid))
    finally:
        child.stdin.close()
        child.wait()
    assert child.returncode == 0  # it ended on its own: signal 0 only (a SIGHUP would have ended it first)
    assert not state._alive(child.pid) and not state._alive(None) and not state._alive("pid")

    def denied(pid: int, sig: int) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(state.os, "kill", denied)
    assert state._alive(1)  # not ours to signal, but there


def test_clearing_or_stopping_twice_is_harmless(tmp_path, monkeypatch):
    sweep = SweepDir(tmp_path)
    clear_failure(sweep, "never-failed")  # nothing on file: nothing to do
    monkeypatch.setattr(state, "HEARTBEAT_S", 0.01)
    beat = state.Heartbeat(sweep, "r", {})
    beat.path.unlink()  # removed under it (a sweep cleaning up): the beats go on, stop() does not fail
    misses = []
    real_utime = os.utime

    def utime(path, *args, **kwargs):
        if Path(path) == beat.path:
            misses.append(path)
        return real_utime(path, *args, **kwargs)

    monkeypatch.setattr(state.os, "utime", utime)
    deadline = time.monotonic() + 30
    while len(misses) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)  # polling the state the thread changes
    assert len(misses) >= 2 and beat._thread.is_alive()  # a beat on a missing file did not end the thread
    beat.stop()
    assert not beat.path.exists()


def test_a_heartbeat_from_the_future_is_zero_seconds_old(tmp_path):
    sweep = SweepDir(tmp_path)
    beat = sweep.heartbeat("r")
    beat.parent.mkdir(parents=True)
    beat.write_text("{}")
    ahead = time.time() + 100  # written on a host whose clock runs ahead
    os.utime(beat, (ahead, ahead))
    assert heartbeat_age(sweep, "r") == 0.0


def test_the_episode_number_is_the_first_of_many_columns(tmp_path):
    path = tmp_path / "episodes.csv"
    path.write_text("episode,return,speed\n1,1.0,20\n2,1.5,21\n")
    assert episode_numbers(path) == [1, 2]
