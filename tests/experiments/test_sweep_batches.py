"""The helpers of batched sweeps (experiments/sweep/batches.py) at values worked out by hand: the plan's line, a
batch's name, what a batch folder says of its runs, each run's result after its batch's session, and the batch task
itself (run_batch, train_batch_task) in this process on a tiny numpy batch. Packing grids and the task under the
embedded Ray are tested in test_sweep_batch.py."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from lanefree_sumo.experiments.runners.batch import BATCH_CHECKPOINTS, BATCH_FILE
from lanefree_sumo.experiments.sweep.batches import (
    Batch,
    Packing,
    _outcome,
    _result,
    batch_name,
    has_checkpoint,
    members,
    trained_in_batch,
)
from lanefree_sumo.experiments.sweep.grid import Cell, make_setting
from lanefree_sumo.experiments.sweep.manifest import SweepDir


def test_the_plans_line_counts_batches_resumed_ones_and_single_runs_with_their_reasons():
    packing = Packing(batches=[Batch("a", ("r1", "r2", "r3")), Batch("b", ("r4", "r5"), resumed=True),
                               Batch("c", ("r6", "r7"), resumed=True)],
                      sequential=[Cell(make_setting("ppo", "collision", 70), s) for s in range(3)],
                      reasons={"not batchable": 2, "alone in its batch": 1})
    assert packing.describe() == ("7 run(s) in 3 batch(es) of at most 3 (2 interrupted batch(es) continued as "
                                  "batches), 3 run(s) one per task (not batchable: 2; alone in its batch: 1)")
    assert Packing(batches=[Batch("a", ("r1", "r2"))]).describe() == "2 run(s) in 1 batch(es) of at most 2"
    assert Packing(sequential=packing.sequential[:1]).describe() == "1 run(s) one per task"
    assert Packing().describe() == "" and Packing().size == 1


def test_a_batchs_name_is_its_algorithms_size_and_a_digest_of_its_runs():
    digest = hashlib.sha1(b"run_a\nrun_b").hexdigest()[:8]
    assert batch_name(["dqn", "ddqn", "dqn"], ["run_a", "run_b"]) == f"batch_ddqn+dqn_k2_{digest}"
    three = hashlib.sha1(b"x\ny\nz").hexdigest()[:8]
    assert batch_name(["ddpg"] * 3, ["x", "y", "z"]) == f"batch_ddpg_k3_{three}"
    assert batch_name(["ddpg"], ["run_b", "run_a"]) != batch_name(["ddpg"], ["run_a", "run_b"])  # order counts


def test_a_batch_folder_names_its_runs_and_says_whether_it_has_a_checkpoint(tmp_path):
    folder = tmp_path / "batch"
    assert members(folder) == [] and not has_checkpoint(folder)
    folder.mkdir()
    for text in ("not json", json.dumps({"other": 1}), json.dumps({"runs": 3}), json.dumps([1])):
        (folder / BATCH_FILE).write_text(text)
        assert members(folder) == [], text
    (folder / BATCH_FILE).write_text(json.dumps({"runs": ["../../runs/run_a", "/abs/path/run_b"]}))
    assert members(folder) == ["run_a", "run_b"]
    (folder / BATCH_CHECKPOINTS).mkdir()
    (folder / BATCH_CHECKPOINTS / "step_0000000100.pt.tmp").write_bytes(b"")
    (folder / BATCH_CHECKPOINTS / "notes.txt").write_text("")
    assert not has_checkpoint(folder)
    (folder / BATCH_CHECKPOINTS / "step_0000000100.pt").write_bytes(b"")
    assert has_checkpoint(folder)


def test_a_run_trained_in_a_batch_of_several_is_told_from_a_batch_of_one(tmp_path):
    run = tmp_path / "run"
    assert not trained_in_batch(run)
    run.mkdir()
    for text in ("{", json.dumps(["batch"]), json.dumps({"episodes_done": 3})):
        (run / "last_session.json").write_text(text)
        assert not trained_in_batch(run), text
    (run / "last_session.json").write_text(json.dumps({"batch": {"run": 0}}))
    assert trained_in_batch(run)
    (run / BATCH_FILE).write_text(json.dumps({"runs": ["."]}))  # lanefree train --seed: a batch of one
    assert not trained_in_batch(run)
    (run / BATCH_FILE).write_text(json.dumps({"runs": ["../a", "../b"]}))
    assert trained_in_batch(run)


def _run(sweep: SweepDir, name: str, episodes: int, model: bool = False, session: dict | None = None) -> Path:
    folder = sweep.run(name)
    folder.mkdir(parents=True)
    (folder / "episodes.csv").write_text("episode,return\n" + "".join(f"{e},0.0\n" for e in range(1, episodes + 1)))
    if model:
        (folder / "model.zip").write_bytes(b"model")
    if session is not None:
        (folder / "last_session.json").write_text(json.dumps(session))
    return folder


def test_each_runs_result_after_its_batchs_session(tmp_path):
    sweep = SweepDir(tmp_path)
    here = {"host": socket.gethostname(), "pid": os.getpid(), "wall_s": 0.0}
    assert _result("r", "busy") == {"name": "r", "status": "busy", "episodes": 0, "detail": "", **here}
    _run(sweep, "done", 3, model=True)
    assert _outcome(sweep, "done", 3, ("failed", "boom")) == {**_result("done", "complete", 3)}
    _run(sweep, "short", 2)
    assert _outcome(sweep, "short", 3, ("failed", "boom")) == _result("short", "failed", 2, "boom")
    assert _outcome(sweep, "short", 3, ("interrupted", "stopped before training began")) == _result(
        "short", "interrupted", 2, "stopped before training began")
    assert _outcome(sweep, "short", 3, None) == _result("short", "interrupted", 2, "stopped at 2/3 episodes")
    _run(sweep, "nan", 1, session={"stopped_by": "a non-finite action at step 7"})
    assert _outcome(sweep, "nan", 3, None) == _result("nan", "failed", 1, "a non-finite action at step 7")
    for signal_name in ("SIGINT", "SIGTERM"):
        name = f"stopped_{signal_name}"
        _run(sweep, name, 1, session={"stopped_by": signal_name})
        assert _outcome(sweep, name, 3, None) == _result(name, "interrupted", 1, "stopped at 1/3 episodes")
    _run(sweep, "odd", 1, session={"stopped_by": None})
    (sweep.run("odd") / "last_session.json").write_text("[1]")  # not a mapping
    assert _outcome(sweep, "odd", 3, None)["status"] == "interrupted"
    assert _outcome(sweep, "missing", 3, None) == _result("missing", "interrupted", 0, "stopped at 0/3 episodes")


def _grid(seeds: int, **extra):
    from lanefree_sumo.experiments.sweep.grid import parse_grid

    return parse_grid({"reward_presets": ["collision"], "seeds": list(range(seeds)), "episodes": 2, **extra},
                      "g", "g.yaml")


def _pending(grid) -> dict:
    from lanefree_sumo.experiments.sweep.state import PENDING, RunInfo

    return {c.name: RunInfo(PENDING, 0) for c in grid.cells()}


def test_split_counts_splits_the_group_with_the_largest_batches_first():
    from lanefree_sumo.experiments.sweep.batches import split_counts

    # 6 runs in 1 batch (6 each) against 7 in 2 (3.5 each): the 6 are split first, though the 7 are more runs
    assert split_counts([6, 7], 6, 3) == [1, 2] and split_counts([6, 7], 6, 4) == [2, 2]
    assert split_counts([5], 8, 3) == [2]  # a third batch would hold fewer than 2 runs
    assert split_counts([6], 8, 3) == [3] and split_counts([7], 8, 4) == [3]


def test_pack_says_its_size_and_why_runs_go_alone(tmp_path):
    from lanefree_sumo.experiments.sweep.batches import pack
    from lanefree_sumo.experiments.sweep.state import PARTIAL, RunInfo

    grid = _grid(3, algorithms=["ddpg", "dqn", "dueling"])
    cells = list(grid.cells())
    sweep = SweepDir(tmp_path / "sweep")
    # one run of each algorithm: each alone in its batch, counted
    first = [c for c in cells if c.seed == 0]
    packing = pack(sweep, grid, first, _pending(grid), 8, workers=2)
    assert packing.size == 8 and not packing.batches and packing.sequential == first
    assert packing.reasons == {"alone in its batch": 3}
    assert pack(sweep, grid, first, _pending(grid), 5).size == 5
    # a run resumed from its own checkpoint trains alone, under that reason
    ddpg = [c for c in cells if c.setting.algorithm == "ddpg"]
    states = {**_pending(grid), ddpg[0].name: RunInfo(PARTIAL, 1, "resumable from episode 1")}
    packing = pack(sweep, grid, ddpg, states, 8)
    assert packing.reasons == {"resumed from its own checkpoint": 1} and packing.sequential == ddpg[:1]
    assert [b.runs for b in packing.batches] == [tuple(c.name for c in ddpg[1:])]
    # --batch 1 beside workers: every run alone, for the given reason
    single = pack(sweep, grid, ddpg, _pending(grid), 1, why_single="--batch 1", workers=4)
    assert single.reasons == {"--batch 1": 3} and not single.batches


def test_a_stale_run_with_a_batch_session_is_packed_afresh(tmp_path):
    """Only a PARTIAL run trained in a batch is refused: a stale one (its batch killed before its first
    checkpoint) starts again in a new batch."""
    from lanefree_sumo.experiments.sweep.batches import pack
    from lanefree_sumo.experiments.sweep.state import STALE, RunInfo

    grid = _grid(2)
    sweep = SweepDir(tmp_path / "sweep")
    cells = list(grid.cells())
    _run(sweep, cells[0].name, 1, session={"batch": {"run": 0}})
    packing = pack(sweep, grid, cells, {**_pending(grid), cells[0].name: RunInfo(STALE, 1)}, 2)
    assert [b.runs for b in packing.batches] == [tuple(c.name for c in cells)] and not packing.sequential


def test_an_interrupted_batch_holding_runs_of_another_grid_is_refused_by_name(tmp_path):
    import pytest

    from lanefree_sumo.errors import RunError
    from lanefree_sumo.experiments.sweep.batches import interrupted_batches

    grid = _grid(2)
    sweep = SweepDir(tmp_path / "sweep")
    names = [c.name for c in grid.cells()]
    folder = sweep.batch("old")
    (folder / BATCH_CHECKPOINTS).mkdir(parents=True)
    (folder / BATCH_CHECKPOINTS / "step_0000000100.pt").write_bytes(b"")
    (folder / BATCH_FILE).write_text(json.dumps({"runs": [f"../../runs/{n}" for n in (names[0], "zz", "aa")]}))
    with pytest.raises(RunError) as err:
        interrupted_batches(sweep, grid, list(grid.cells()), _pending(grid))
    assert str(err.value) == (f"batch {folder} holds aa, not a run of this sweep's grid; move the batch folder away "
                              "to train its other runs afresh")
    # a batch whose runs are all done or elsewhere is not this session's to continue, strangers or not
    assert interrupted_batches(sweep, grid, [c for c in grid.cells() if c.name == names[1]], _pending(grid)) == []


def test_a_dead_batch_folder_goes_even_when_its_runs_have_no_state(tmp_path):
    """A batch folder without a checkpoint naming runs the states do not list (no longer in the plan) is deleted."""
    from lanefree_sumo.experiments.sweep.batches import interrupted_batches

    grid = _grid(2)
    sweep = SweepDir(tmp_path / "sweep")
    folder = sweep.batch("dead")
    folder.mkdir(parents=True)
    (folder / BATCH_FILE).write_text(json.dumps({"runs": ["../../runs/gone_a", "../../runs/gone_b"]}))
    assert interrupted_batches(sweep, grid, list(grid.cells()), {}) == [] and not folder.exists()


# -- the batch task (run_batch, train_batch_task) in this process, on a tiny numpy batch ------------------------

TINY_BATCH = {"reward_presets": ["collision"], "seeds": [0, 1], "episodes": 2, "overrides": {
    "sim": {"episode_steps": 30}, "train": {"checkpoint_every_episodes": 1, "actor_critic": {
        "learning_starts_steps": 20, "batch_size": 8, "buffer_size": 200}}}}
"""Two DDPG runs of 2 episodes of 30 steps: a real batch that trains in a few seconds."""


@contextlib.contextmanager
def worker_output() -> Iterator[None]:
    """Inside: ``sys.stdout``/``sys.stderr`` write to file descriptors 1 and 2, as in a Ray worker (the task sends
    those to its log); after: the descriptors and pytest's streams as they were."""
    import sys

    streams = sys.stdout, sys.stderr
    streams[0].flush()
    streams[1].flush()
    saved = os.dup(1), os.dup(2)
    sys.stdout, sys.stderr = open(1, "w", closefd=False), open(2, "w", closefd=False)
    try:
        yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        sys.stdout, sys.stderr = streams
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])


def _task(tmp_path: Path, **overrides):
    """The sweep folder, grid, run names and configs of one batch of :data:`TINY_BATCH`'s two runs."""
    from lanefree_sumo.config import config_to_dict
    from lanefree_sumo.experiments.sweep.grid import parse_grid

    grid = parse_grid({**TINY_BATCH, **overrides}, "tiny", "tiny.yaml")
    cells = list(grid.cells())
    return (SweepDir(tmp_path / "sweep"), [c.name for c in cells],
            [config_to_dict(grid.config(c)) for c in cells])


def test_a_batch_task_trains_its_runs_clears_their_failures_and_keeps_no_checkpoint(tmp_path):
    import re
    import time

    from lanefree_sumo.experiments.sweep.batches import run_batch
    from lanefree_sumo.experiments.sweep.state import failure_reason, record_failure

    sweep, names, configs = _task(tmp_path)
    record_failure(sweep, names[0], "an earlier session's failure")
    _run(sweep, names[1], 1)  # a start killed before its first checkpoint: restarted from scratch
    t0 = time.monotonic()
    with worker_output():
        results = run_batch(str(sweep.path), "batch_t", names, configs, 2, "lanefree sweep tiny.yaml")
    elapsed = time.monotonic() - t0
    host, pid = socket.gethostname(), os.getpid()
    assert [{k: v for k, v in r.items() if k != "wall_s"} for r in results] == [
        {"name": n, "status": "complete", "episodes": 2, "detail": "", "host": host, "pid": pid} for n in names]
    for r in results:  # seconds since the task began, to a tenth
        assert isinstance(r["wall_s"], float) and 0 <= r["wall_s"] <= elapsed + 0.05
        assert r["wall_s"] == round(r["wall_s"], 1)
    assert failure_reason(sweep, names[0]) is None  # cleared when its batch started
    for name in names:
        assert len((sweep.run(name) / "episodes.csv").read_text().splitlines()) == 3
        command = (sweep.run(name) / "command.txt").read_text()
        assert f"lanefree sweep tiny.yaml  # sweep batch batch_t on {host} pid {pid}" in command
    assert not (sweep.batch("batch_t") / BATCH_CHECKPOINTS).exists()  # complete: nothing left to resume
    log = sweep.log("batch_t").read_text()
    assert re.search(rf"\n=== \d{{4}}-\d\d-\d\d \d\d:\d\d:\d\d batch batch_t \(2 runs: {names[0]}, {names[1]}\) "
                     rf"on host {host} pid {pid} node -\n", log)
    assert f"{names[1]}: no checkpoint (1 episode rows); starting from scratch\n" in log
    took = re.search(rf"=== batch batch_t: {names[0]} complete, {names[1]} complete \((\d+\.\d) s\)\n", log)
    assert took is not None and float(took.group(1)) <= elapsed + 0.05
    # a new batch of runs that are complete: each says so, and the batch, which never checkpointed, leaves no folder
    with worker_output():
        again = run_batch(str(sweep.path), "batch_u", names, configs, 2, "c")
    assert [(r["name"], r["status"], r["episodes"]) for r in again] == [(n, "complete", 2) for n in names]
    assert not (sweep.batch("batch_u") / BATCH_CHECKPOINTS).exists()


def test_a_batch_task_whose_run_is_held_elsewhere_trains_nothing(tmp_path):
    import subprocess
    import sys

    from lanefree_sumo.experiments.sweep.batches import run_batch
    from lanefree_sumo.experiments.sweep.state import run_lock

    sweep, names, configs = _task(tmp_path)
    with run_lock(sweep, names[1]) as held, worker_output():
        assert held
        results = run_batch(str(sweep.path), "batch_t", names, configs, 2, "c")
    assert [(r["name"], r["status"], r["detail"]) for r in results] == [
        (n, "busy", f"{sweep.run(n)} (batch batch_t) is being trained by another sweep worker") for n in names]
    assert not any(sweep.run(n).exists() and any(sweep.run(n).iterdir()) for n in names)
    assert "a run of batch batch_t is being trained by another sweep worker" in sweep.log("batch_t").read_text()
    # another process writing a run's episodes.csv (a `lanefree train` of it): named by its id
    csv_path = sweep.run(names[1]) / "episodes.csv"
    csv_path.parent.mkdir(parents=True)
    csv_path.write_text("episode\n")
    hold = "import sys; f = open(sys.argv[1], 'a'); print('open', flush=True); sys.stdin.read()"
    writer = subprocess.Popen([sys.executable, "-c", hold, str(csv_path)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert writer.stdout is not None and writer.stdout.readline() == "open\n"  # the file is held open now
        with worker_output():
            results = run_batch(str(sweep.path), "batch_v", names, configs, 2, "c")
    finally:
        writer.communicate("")
    said = f"is being trained by process {writer.pid}"
    assert [(r["name"], r["status"]) for r in results] == [(n, "busy") for n in names]
    assert all(r["detail"] == f"{sweep.run(r['name'])} (batch batch_v) {said}" for r in results)
    assert f"a run of batch batch_v {said}" in sweep.log("batch_v").read_text()
    assert csv_path.read_text() == "episode\n"  # nothing trained into it


def test_a_batch_tasks_errors_fail_its_runs_in_one_line_and_an_interrupt_before_training_leaves_them(
        tmp_path, monkeypatch):
    import lanefree_sumo.experiments.sweep.batches as batches_module
    from lanefree_sumo.errors import ConfigError
    from lanefree_sumo.experiments.sweep.batches import run_batch
    from lanefree_sumo.experiments.sweep.state import failure_reason, read_heartbeat

    sweep, names, configs = _task(tmp_path)
    raised: list[BaseException | None] = []
    beats: list[list[dict]] = []

    def stand_in(*args, **kwargs):
        beats.append([read_heartbeat(sweep, n) for n in names])  # what the sweep's status reads meanwhile
        if raised[-1] is not None:
            raise raised[-1]

    monkeypatch.setattr(batches_module, "train_batch_task", stand_in)
    log = sweep.log("batch_t")
    for error, status, detail in (
            (ConfigError("a bad\n  value"), "failed", "a bad value"),
            (ValueError("broken\nenv " + "x" * 400), "failed",
             f"ValueError: {('broken env ' + 'x' * 400)[:300]} (see {log})"),
            (KeyboardInterrupt(), "interrupted", "stopped before training began"),
            (None, "interrupted", "stopped at 0/2 episodes")):  # returned without training: left for later
        raised.append(error)
        with worker_output():
            results = run_batch(str(sweep.path), "batch_t", names, configs, 2, "c")
        assert [(r["name"], r["status"], r["episodes"], r["detail"]) for r in results] == [
            (n, status, 0, detail) for n in names], error
        assert [failure_reason(sweep, n) for n in names] == [detail if status == "failed" else None] * 2
    text = log.read_text()
    assert "Traceback" in text and text.count("Traceback") == 1  # a bug's traceback goes to the log, once
    beat = {"node": "-", "batch": "batch_t", "pid": os.getpid(), "host": socket.gethostname()}
    assert [[{k: b.get(k) for k in beat} for b in each] for each in beats] == [[beat] * 2] * 4


def test_a_batch_task_continues_a_checkpointed_batch_and_restarts_stale_runs_but_refuses_finished_ones(
        tmp_path, monkeypatch, capsys):
    import lanefree_sumo.experiments.runners.batch as runner
    from lanefree_sumo.errors import RunError
    from lanefree_sumo.experiments.sweep.batches import train_batch_task

    sweep, names, configs = _task(tmp_path)
    calls: list[tuple] = []
    monkeypatch.setattr(runner, "resume_batch", lambda *a, **k: calls.append(("resume", a, k)))
    monkeypatch.setattr(runner, "train_batch", lambda *a, **k: calls.append(("train", a, k)))
    (sweep.batch("b") / BATCH_CHECKPOINTS).mkdir(parents=True)
    (sweep.batch("b") / BATCH_CHECKPOINTS / "step_0000000030.pt").write_bytes(b"")
    train_batch_task(sweep, "b", names, configs, 2, "cmd")
    assert calls == [("resume", (sweep.batch("b"),), {"progress": False, "command": "cmd"})]
    assert capsys.readouterr().out == "continuing batch b from its newest batch checkpoint\n"
    # no checkpoint: a stale run (rows, no checkpoint) is cleared and the batch starts with the grid's configs
    calls.clear()
    _run(sweep, names[0], 1)
    train_batch_task(sweep, "c", names, configs, 2, "cmd")
    assert not sweep.run(names[0]).exists()
    assert capsys.readouterr().out == f"{names[0]}: no checkpoint (1 episode rows); starting from scratch\n"
    [(kind, args, kwargs)] = calls
    assert kind == "train" and args[1:] == (sweep.batch("c"), [sweep.run(n) for n in names])
    assert kwargs == {"progress": False, "command": "cmd"}
    assert [(c.seed, c.train.algo, c.sim.episode_steps, c.train.episodes) for c in args[0]] == [
        (0, "ddpg", 30, 2), (1, "ddpg", 30, 2)]
    # a run that is further than pending is not started again by a new batch
    calls.clear()
    _run(sweep, names[1], 2, model=True)
    with pytest.raises(RunError) as err:
        train_batch_task(sweep, "d", names, configs, 2, "cmd")
    assert str(err.value) == f"{sweep.run(names[1])} is complete; a new batch starts only new runs"
    _run(sweep, names[0], 1, model=True)  # one episode of two, its model saved: a run to extend, not to restart
    with pytest.raises(RunError) as err:
        train_batch_task(sweep, "d", names, configs, 2, "cmd")
    assert str(err.value) == (f"{sweep.run(names[0])} is partial (finished at 1 episodes; will be extended to 2); "
                              "a new batch starts only new runs")
    assert calls == []
