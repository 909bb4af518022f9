"""The helpers of batched sweeps (experiments/sweep/batches.py) at values worked out by hand: the plan's line, a
batch's name, what a batch folder says of its runs, and each run's result after its batch's session. The packing
itself and the Ray task are tested in test_sweep_batch.py."""

from __future__ import annotations

import hashlib
import json
import os
import socket
from pathlib import Path

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
