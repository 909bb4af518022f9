"""``lanefree sweep --batch K``: how runs are packed into batches (fast, no Ray), a batched sweep writes the run
folders of a sequential one (episodes.csv, config.yaml, the summary), and a batched sweep whose batch worker is
killed, then interrupted, resumes exactly beside a complete run (slow, the embedded Ray)."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from lanefree_sumo.errors import RunError
from lanefree_sumo.experiments.runners.batch import BATCH_CHECKPOINTS, BATCH_FILE, train_batch
from lanefree_sumo.experiments.sweep.batches import DEFAULT_BATCH, pack, split_counts
from lanefree_sumo.experiments.sweep.grid import load_grid
from lanefree_sumo.experiments.sweep.manifest import SweepDir, read_manifest
from lanefree_sumo.experiments.sweep.runner import stop_text
from lanefree_sumo.experiments.sweep.state import BUSY, COMPLETE, PARTIAL, PENDING, STALE, RunInfo, run_lock

from conftest import CLI_ENV, lanefree, lanefree_popen, wait_for


def write_grid(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return [{k: v for k, v in row.items() if k != "wall_s"} for row in csv.DictReader(fh)]


def pending(grid) -> dict[str, RunInfo]:
    return {c.name: RunInfo(PENDING, 0) for c in grid.cells()}


# -- packing (pure logic) -------------------------------------------------------------------------------------

def test_runs_that_differ_only_where_a_batch_may_are_packed_together(tmp_path):
    grid = load_grid(write_grid(tmp_path / "g.yaml", {
        "algorithms": ["ddpg", "dqn", "ppo"], "reward_presets": ["collision", "fields_collision"],
        "densities": [70, 90], "seeds": [0, 1], "episodes": 2,
        "variants": {"default": {}, "once": {"reward.overtake_bonus": "once_per_vehicle"},
                     "cap25": {"scenario.agent_max_speed_mps": 25.0},
                     "slow": {"train.actor_critic.learning_rate": 1e-4, "train.dqn.learning_rate": 1e-4}}}))
    sweep = SweepDir(tmp_path / "sweep")
    cells = list(grid.cells())
    packing = pack(sweep, grid, cells, pending(grid), 8)
    # per algorithm: default, once (overtake bonus per run) and cap25 (top speed per run) together, slow (another
    # learning rate) apart; 24 + 8 runs of each of ddpg and dqn, in batches of at most 8 of near equal size
    assert sorted(len(b.runs) for b in packing.batches) == [8] * 8
    for batch in packing.batches:
        algos = {name.split("_")[0] for name in batch.runs}
        slow = {"_slow_" in name for name in batch.runs}
        assert len(algos) == 1 and len(slow) == 1 and not batch.resumed
    mixed = [b for b in packing.batches if any("_once_" in n for n in b.runs) and any("_default_" in n for n in b.runs)]
    assert mixed  # the overtake bonus, the density and the preset differ within a batch
    assert [b for b in packing.batches if any("_cap25_" in n for n in b.runs) and
            any("_cap25_" not in n for n in b.runs)]  # and the top speed
    assert {c.name.split("_")[0] for c in packing.sequential} == {"ppo"} and len(packing.sequential) == 32
    assert list(packing.reasons) == ["batched training covers ddpg, td3, dqn, ddqn, dueling, per, not ppo"]
    assert "64 run(s) in 8 batch(es) of at most 8" in packing.describe()
    assert sorted([n for b in packing.batches for n in b.runs] + [c.name for c in packing.sequential]) == \
        sorted(c.name for c in cells)  # every run once
    # 10 runs at K = 4: 4 + 3 + 3; K = 1: one run per task
    ten = [c for c in cells if c.name.startswith("ddpg") and "_slow_" not in c.name][:10]
    assert [len(b.runs) for b in pack(sweep, grid, ten, pending(grid), 4).batches] == [4, 3, 3]
    single = pack(sweep, grid, ten, pending(grid), 1)
    assert not single.batches and len(single.sequential) == 10 and single.reasons == {"--batch 1": 10}


def test_dqn_and_ddqn_runs_share_batches_and_the_other_variants_do_not(tmp_path):
    """dqn and ddqn have one network (their targets differ run by run): their runs pack together, the batch named
    after both; dueling (another network) and per (trees on the host) stay in batches of their own."""
    grid = load_grid(write_grid(tmp_path / "g.yaml", {
        "algorithms": ["dqn", "ddqn", "dueling", "per"], "reward_presets": ["collision"], "densities": [70],
        "seeds": [0, 1, 2], "episodes": 2}))
    packing = pack(SweepDir(tmp_path / "sweep"), grid, list(grid.cells()), pending(grid), 8)
    together = {frozenset(name.split("_")[0] for name in b.runs): (len(b.runs), b.name.split("_")[1])
                for b in packing.batches}
    assert together == {frozenset({"dqn", "ddqn"}): (6, "ddqn+dqn"), frozenset({"dueling"}): (3, "dueling"),
                        frozenset({"per"}): (3, "per")}
    assert not packing.sequential


def test_a_run_with_a_switch_the_batched_learners_lack_goes_one_per_task(tmp_path):
    grid = load_grid(write_grid(tmp_path / "g.yaml", {
        "algorithms": ["dqn"], "reward_presets": ["collision"], "seeds": [0, 1], "episodes": 2,
        "variants": {"default": {}, "libsumo": {"train.backend": "libsumo"}}}))
    cells = list(grid.cells())
    packing = pack(SweepDir(tmp_path / "sweep"), grid, cells, pending(grid), 8)
    assert [sorted(b.runs) for b in packing.batches] == [sorted(c.name for c in cells if "_default_" in c.name)]
    assert sorted(c.name for c in packing.sequential) == sorted(c.name for c in cells if "_libsumo_" in c.name)
    assert list(packing.reasons) == ["batched training does not support the libsumo backend (--backend)"]


def test_the_dqn_familys_runs_on_the_set_observation_are_batched(tmp_path):
    grid = load_grid(write_grid(tmp_path / "g.yaml", {
        "algorithms": ["dqn", "per"], "reward_presets": ["collision"], "seeds": [0, 1], "episodes": 2,
        "variants": {"set": {"observation.kind": "set"}}}))
    cells = list(grid.cells())
    packing = pack(SweepDir(tmp_path / "sweep"), grid, cells, pending(grid), 8)
    assert not packing.sequential and len(packing.batches) == 2
    assert sorted(r for b in packing.batches for r in b.runs) == sorted(c.name for c in cells)


def test_runs_of_several_environments_or_agents_are_packed_by_their_count(tmp_path):
    grid = load_grid(write_grid(tmp_path / "g.yaml", {
        "algorithms": ["ddpg"], "reward_presets": ["collision"], "seeds": [0, 1], "episodes": 2,
        "variants": {"default": {}, "envs": {"train.envs": 2}, "agents": {"scenario.agents": 2}}}))
    cells = list(grid.cells())
    packing = pack(SweepDir(tmp_path / "sweep"), grid, cells, pending(grid), 8)
    assert not packing.sequential
    assert sorted(sorted(b.runs) for b in packing.batches) == sorted(
        sorted(c.name for c in cells if f"_{variant}_" in c.name) for variant in ("default", "envs", "agents"))


@pytest.mark.parametrize(("grid_name", "runs"), [("ddpg", 6), ("td3", 3)])
def test_the_set_encoder_remedy_grids_train_as_one_batch_each(tmp_path, grid_name, runs):
    """The committed remedy grids (the set observation; DDPG's two variants differ in the pre-tanh penalty, which
    a batch may hold per run) pack into one batch at --batch 6."""
    root = Path(__file__).resolve().parents[2]
    grid = load_grid(root / "results" / "varobs_remedies" / f"{grid_name}.yaml")
    packing = pack(SweepDir(tmp_path / "sweep"), grid, list(grid.cells()), pending(grid), 6)
    assert [len(b.runs) for b in packing.batches] == [runs] and not packing.sequential


def test_the_default_batch_keeps_every_worker_busy():
    """Without --batch: at most DEFAULT_BATCH runs per batch, split further while a worker would idle."""
    assert DEFAULT_BATCH == 8
    assert split_counts([4], DEFAULT_BATCH, 2) == [2] and split_counts([150], DEFAULT_BATCH, 2) == [19]
    assert split_counts([10], DEFAULT_BATCH, 2) == [2] and split_counts([10], DEFAULT_BATCH, None) == [2]
    assert split_counts([1], DEFAULT_BATCH, 4) == [1] and split_counts([6], DEFAULT_BATCH, 3) == [3]


def test_a_stop_counts_runs_and_the_tasks_holding_them():
    assert stop_text([("a",), ("b", "c", "d")]).startswith("4 run(s) in 2 task(s): those training save")
    assert stop_text([("a",), ("b",)]).startswith("2 run(s): those training save a checkpoint and stop")


def test_a_given_batch_size_is_split_further_while_a_worker_would_idle(tmp_path):
    """--batch K beside W workers: more, smaller batches while the new ones are fewer than W (2 runs at least),
    the largest split first; unknown workers (a cluster under --batch) or --no-ray (0): K alone decides."""
    assert split_counts([14], 16, 2) == [2] and split_counts([14], 16, None) == [1] and split_counts([14], 16, 0) == [1]
    assert split_counts([3], 16, 2) == [1] and split_counts([4], 16, 4) == [2]  # batches keep 2 runs
    assert split_counts([10, 4], 16, 3) == [2, 1] and split_counts([10, 4], 16, 4) == [3, 1]
    assert split_counts([43], 16, 2) == [3]  # already enough: K decides
    grid = load_grid(write_grid(tmp_path / "g.yaml", {"reward_presets": ["collision"], "seeds": list(range(14)),
                                                      "episodes": 2}))
    cells = list(grid.cells())
    packing = pack(SweepDir(tmp_path / "sweep"), grid, cells, pending(grid), 16, workers=2)
    assert [b.runs for b in packing.batches] == [tuple(c.name for c in cells[:7]), tuple(c.name for c in cells[7:])]
    assert [len(b.runs) for b in pack(SweepDir(tmp_path / "sweep"), grid, cells, pending(grid), 16).batches] == [14]


def test_an_interrupted_batch_continues_as_that_batch_and_one_without_a_checkpoint_is_packed_afresh(tmp_path):
    grid = load_grid(write_grid(tmp_path / "g.yaml", {"reward_presets": ["collision"], "seeds": [0, 1, 2, 3],
                                                      "episodes": 2}))
    sweep = SweepDir(tmp_path / "sweep")
    names = [c.name for c in grid.cells()]
    for folder, runs, checkpoint in (("old", names[:2], True), ("dead", names[2:], False)):
        (sweep.batch(folder) / BATCH_CHECKPOINTS).mkdir(parents=True)
        (sweep.batch(folder) / BATCH_FILE).write_text(json.dumps({"runs": [f"../../runs/{n}" for n in runs]}))
        if checkpoint:
            (sweep.batch(folder) / BATCH_CHECKPOINTS / "step_0000000100.pt").write_bytes(b"")
    states = {**pending(grid), names[0]: RunInfo(PARTIAL, 1), names[1]: RunInfo(STALE, 0)}
    packing = pack(sweep, grid, list(grid.cells()), states, 1)  # --batch 1: the interrupted batch is still one
    assert [(b.name, b.runs, b.resumed) for b in packing.batches] == [("old", tuple(names[:2]), True)]
    assert [c.name for c in packing.sequential] == names[2:] and not sweep.batch("dead").exists()
    # a finished batched run the grid would extend: refused, nothing can resume it
    run = sweep.run(names[2])
    run.mkdir(parents=True)
    (run / "last_session.json").write_text(json.dumps({"batch": {"run": 0}}))
    with pytest.raises(RunError, match="trained in a batch .* a batch is not extended"):
        pack(sweep, grid, list(grid.cells()), {**states, names[2]: RunInfo(PARTIAL, 1, "finished at 1")}, 2)


def test_a_batch_starting_elsewhere_before_its_first_checkpoint_is_left_alone(tmp_path):
    """A batch folder without a checkpoint is deleted only when nothing trains it: not while a process holds one of
    its runs' locks (a sweep's batch between its start and its first checkpoint), nor while one of its runs is busy
    elsewhere, nor before its batch.json names its runs; a finished batch's folder goes (it was deleted under a
    starting batch, which then failed at its first checkpoint)."""
    grid = load_grid(write_grid(tmp_path / "g.yaml", {"reward_presets": ["collision"], "seeds": [0, 1, 2, 3, 4],
                                                      "episodes": 2}))
    sweep = SweepDir(tmp_path / "sweep")
    names = [c.name for c in grid.cells()]
    for folder, runs in (("locked", names[:2]), ("busy", names[2:4]), ("finished", names[4:]), ("starting", None)):
        (sweep.batch(folder) / BATCH_CHECKPOINTS).mkdir(parents=True)
        if runs is not None:
            (sweep.batch(folder) / BATCH_FILE).write_text(json.dumps({"runs": [f"../../runs/{n}" for n in runs]}))
    states = {**pending(grid), names[3]: RunInfo(BUSY, 1, "episodes.csv is open in process 1"),
              names[4]: RunInfo(COMPLETE, 2)}
    todo = [c for c in grid.cells() if c.name in names[:3]]
    with run_lock(sweep, names[1]) as held:  # as a batch task holds it (another open file: another holder)
        assert held
        packing = pack(sweep, grid, todo, states, 2)
    assert [p.name for p in sorted(sweep.batches.iterdir())] == ["busy", "locked", "starting"]
    planned = [n for b in packing.batches for n in b.runs] + [c.name for c in packing.sequential]
    assert sorted(planned) == names[:3]  # a held run is planned (its task finds it busy); the busy one is not
    pack(sweep, grid, todo, {**states, names[3]: RunInfo(PENDING, 0)}, 2)  # nothing holds them now
    assert [p.name for p in sweep.batches.iterdir()] == ["starting"]


def test_bad_batch_options_are_one_line_errors(tmp_path):
    grid = write_grid(tmp_path / "g.yaml", {"reward_presets": ["collision"], "seeds": [0], "episodes": 2})
    for args, said in ((["--batch", "0"], "--batch"), (["--status", str(tmp_path), "--batch", "2"], "--batch"),
                       (["--no-ray", "--workers", "2"], "--workers sizes or joins Ray; --no-ray trains without it"),
                       (["--status", str(tmp_path), "--no-ray"], "--no-ray does not go with --status")):
        done = lanefree("sweep", *([] if args[0] == "--status" else [str(grid), "--out", str(tmp_path / "out")]),
                        *args, timeout=120)
        assert done.returncode == 2 and said in done.stderr and len(done.stderr.strip().splitlines()) == 1, \
            done.stderr
    assert not (tmp_path / "out").exists()


def test_no_ray_runs_the_tasks_in_turn_stops_after_an_interrupted_one_and_gets_its_output_back(
        tmp_path, monkeypatch, capfd):
    """``--no-ray``'s loop (the tasks replaced by stand-ins: the loop's logic alone): batches in turn, each task's
    redirected output back to the driver after it, and nothing started after an interrupted batch."""
    import lanefree_sumo.experiments.sweep.batches as batches_module
    from lanefree_sumo.experiments.sweep.runner import run_in_process
    from lanefree_sumo.experiments.sweep.worker import _redirect_output

    grid = load_grid(write_grid(tmp_path / "g.yaml", {"reward_presets": ["collision"], "seeds": [0, 1, 2, 3, 4, 5],
                                                       "episodes": 2}))
    sweep = SweepDir(tmp_path / "sweep")
    packing = pack(sweep, grid, list(grid.cells()), pending(grid), 2)
    assert len(packing.batches) == 3
    started = []

    def stand_in(out, batch, runs, configs, target, command):
        started.append(batch)
        _redirect_output(Path(out) / "logs" / f"{batch}.log")  # as the real task does
        os.write(1, b"inside the task\n")  # at the descriptor, as SUMO writes
        status = "interrupted" if len(started) == 2 else "complete"
        return [{"name": name, "status": status, "episodes": 1, "detail": ""} for name in runs]

    monkeypatch.setattr(batches_module, "run_batch", stand_in)
    outcome = run_in_process(sweep, grid, [], "lanefree sweep", packing.batches)
    print("the driver again")
    assert started == [b.name for b in packing.batches[:2]] and outcome.interrupted
    assert sorted(r["status"] for r in outcome.results.values()) == ["complete"] * 2 + ["interrupted"] * 2
    out = capfd.readouterr().out
    assert "the driver again" in out and "inside the task" not in out and "[1/3]" in out and "[2/3]" in out
    assert (sweep.path / "logs" / f"{started[0]}.log").read_text() == "inside the task\n"


# -- real sweeps on the embedded Ray ----------------------------------------------------------------------------

def test_an_embedded_ray_that_cannot_start_is_one_line_and_trains_nothing(tmp_path):
    """Ray's temp folder is a file here (a start that fails as an overloaded machine's does: no Ray)."""
    (tmp_path / "file").write_text("")
    grid = write_grid(tmp_path / "g.yaml", {"reward_presets": ["collision"], "seeds": [0], "episodes": 2})
    done = subprocess.run([sys.executable, "-m", "lanefree_sumo.cli", "sweep", str(grid), "--out",
                           str(tmp_path / "out"), "--workers", "1", "--no-progress"], capture_output=True, text=True,
                          timeout=300, env={**CLI_ENV, "RAY_TMPDIR": str(tmp_path / "file")})
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "the embedded Ray did not start" in done.stderr and "internal error" not in done.stderr
    assert not (tmp_path / "out" / "runs").exists()


TINY = {"algorithms": ["ddpg", "dqn"], "reward_presets": ["collision", "fields_collision"], "seeds": [0],
        "episodes": 2, "overrides": {"sim": {"episode_steps": 40}, "train": {
            "checkpoint_every_episodes": 1, "actor_critic": {"learning_starts_steps": 30},
            "dqn": {"learning_starts_steps": 30, "target_update_steps": 20}}}}
"""2 algorithms × 2 presets, 2 episodes of 40 steps, updates from step 31: two batches of two at --batch 2."""


@pytest.mark.slow
@pytest.mark.sumo
def test_a_batched_sweep_writes_the_run_folders_of_a_sequential_sweep(tmp_path):
    grid = write_grid(tmp_path / "tiny.yaml", TINY)
    batched, sequential = tmp_path / "batched", tmp_path / "sequential"
    done = lanefree("sweep", str(grid), "--out", str(batched), "--batch", "2", "--workers", "1", "--no-progress",
                    timeout=900)
    assert done.returncode == 0, done.stderr
    assert "4 run(s) in 2 batch(es) of at most 2" in done.stdout and "4/4 runs complete" in done.stdout
    # the runs one at a time, each its own batch (Ray hands a batch of one to a worker as it hands this one)
    alone = lanefree("sweep", str(grid), "--out", str(sequential), "--batch", "1", "--no-ray", "--no-progress",
                     timeout=900)
    assert alone.returncode == 0, alone.stderr
    assert "4 run(s) one per task (--batch 1: 4)" in alone.stdout
    names = sorted(p.name for p in (sequential / "runs").iterdir())
    assert sorted(p.name for p in (batched / "runs").iterdir()) == names and len(names) == 4
    for name in names:
        a, b = batched / "runs" / name, sequential / "runs" / name
        assert rows(a / "episodes.csv") == rows(b / "episodes.csv") and len(rows(a / "episodes.csv")) == 2
        assert (a / "config.yaml").read_text() == (b / "config.yaml").read_text()
        # the same files, a TensorBoard log in each (the batch's under tb/batch); a run of its own is its own batch
        # (batch.json, batch_checkpoints/), a batched run's batch files are the batch folder's
        assert sorted(p.name for p in a.iterdir()) == sorted(
            p.name for p in b.iterdir() if p.name not in ("batch.json", "batch_checkpoints"))
        assert (b / "batch.json").is_file() and not (a / "batch.json").exists()
        assert list((a / "tb" / "batch").glob("events.out.tfevents.*"))
    summary = [{k: v for k, v in r.items() if "wall" not in k} for r in csv.DictReader(open(batched / "summary.csv"))]
    assert summary == [{k: v for k, v in r.items() if "wall" not in k}
                       for r in csv.DictReader(open(sequential / "summary.csv"))]
    # --no-ray: the same batches one after another in the driver's process, the same run folders
    here = lanefree("sweep", str(grid), "--out", str(tmp_path / "here"), "--batch", "2", "--no-ray", "--no-progress",
                    timeout=900)
    assert here.returncode == 0, here.stderr
    assert "4 run(s) in this process (no Ray): 4 run(s) in 2 batch(es) of at most 2" in here.stdout
    assert here.stdout.count(": 2/2 run(s) complete") == 2 and "4/4 runs complete" in here.stdout
    for name in names:
        assert rows(tmp_path / "here" / "runs" / name / "episodes.csv") == rows(batched / "runs" / name /
                                                                                 "episodes.csv")
    assert read_manifest(tmp_path / "here").sessions[-1]["ray"] == "this process (no Ray)"
    # and no Ray was started on the way (asking an unstarted Ray for its node starts one)
    logs = sorted((tmp_path / "here" / "logs").glob("*.log"))
    assert len(logs) == 2 and all(" node -\n" in log.read_text() for log in logs)
    # a finished batch keeps no batch checkpoint (its replay buffers): nothing is left to resume
    assert not list((batched / "batches").glob(f"*/{BATCH_CHECKPOINTS}/*"))


@pytest.mark.slow
def test_only_trains_the_matching_runs_first_and_a_later_resume_the_rest(tmp_path):
    grid = write_grid(tmp_path / "tiny.yaml", TINY)
    out = tmp_path / "out"
    bad = lanefree("sweep", str(grid), "--out", str(out), "--only", "dqn_*_d90_*", "--no-ray", "--no-progress")
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and not out.exists()
    assert "--only dqn_*_d90_* matches no run of the grid; its runs are named like ddpg_collision_d70_s0" in bad.stderr
    first = lanefree("sweep", str(grid), "--out", str(out), "--only", "dqn_*", "--batch", "2", "--no-ray",
                     "--no-progress", timeout=900)
    assert first.returncode == 0, first.stderr  # every run asked for is complete
    assert "2 run(s) not matching --only left for a later run of the sweep" in first.stdout
    assert "2 run(s) in this process (no Ray): 2 run(s) in 1 batch(es)" in first.stdout
    assert sorted(p.name for p in (out / "runs").iterdir()) == ["dqn_collision_d70_s0", "dqn_fields_collision_d70_s0"]
    rest = lanefree("sweep", "--resume", str(out), "--batch", "2", "--no-ray", "--no-progress", timeout=900)
    assert rest.returncode == 0 and "2 complete, 0 to resume, 2 to start" in rest.stdout, rest.stderr
    assert "4/4 runs complete" in rest.stdout
    status = lanefree("sweep", "--status", str(out), "--only", "dqn_*")
    assert status.returncode == 2 and "--only does not go with --status" in status.stderr


@pytest.mark.slow
@pytest.mark.sumo
def test_a_batched_sweep_killed_and_interrupted_resumes_exactly_beside_a_complete_run(tmp_path):
    """Seed 0 complete (trained alone); seeds 1 and 2 added as a batch, whose worker is SIGKILLed after its first batch
    checkpoint (Ray's retry continues the batch), then the driver is interrupted; ``--resume --batch 1`` continues
    the batch as a batch, leaves seed 0 alone, and the batch's runs end with the episodes of an uninterrupted
    batch."""
    episodes, every = 100, 5
    grid = write_grid(tmp_path / "kill.yaml", {
        "reward_presets": ["collision"], "seeds": [0], "episodes": episodes,
        "overrides": {"sim": {"episode_steps": 25}, "train": {
            "checkpoint_every_episodes": every, "actor_critic": {"learning_starts_steps": 10**6}}}})
    out = tmp_path / "sweep"
    first = lanefree("sweep", str(grid), "--out", str(out), "--no-ray", "--no-progress", timeout=600)  # seed 0 alone
    assert first.returncode == 0, first.stderr
    sweep = SweepDir(out)
    before = {p: p.stat().st_mtime_ns for p in sweep.run("ddpg_collision_d70_s0").rglob("*") if p.is_file()}

    proc = lanefree_popen("sweep", "--resume", str(out), "--seeds", "3", "--batch", "2", "--workers", "1",
                          "--no-progress")
    try:
        wait_for(lambda: any(sweep.batches.glob(f"*/{BATCH_CHECKPOINTS}/step_*.pt")), proc, "a batch checkpoint")
        (batch,) = [p for p in sweep.batches.iterdir() if p.is_dir()]  # beside it: its claim, .<batch>.lock
        victim = json.loads(sweep.heartbeat("ddpg_collision_d70_s1").read_text())["pid"]
        os.kill(victim, signal.SIGKILL)
        log = sweep.log(batch.name)
        wait_for(lambda: log.read_text().count("continuing batch") == 1 and all(
            len(rows(sweep.run(f"ddpg_collision_d70_s{s}") / "episodes.csv")) >= 2 * every for s in (1, 2)),
            proc, "the retried batch's episodes")
        proc.send_signal(signal.SIGINT)
        said, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert "stopping: 2 run(s) in 1 task(s): those training save a checkpoint and stop" in said + err
    stopped = [len(rows(sweep.run(f"ddpg_collision_d70_s{s}") / "episodes.csv")) for s in (1, 2)]
    assert all(n < episodes for n in stopped)

    resumed = lanefree("sweep", "--resume", str(out), "--batch", "1", "--no-progress", timeout=900)
    assert resumed.returncode == 0, resumed.stderr
    assert "1 complete" in resumed.stdout and "1 interrupted batch(es) continued as batches" in resumed.stdout
    assert "3/3 runs complete" in resumed.stdout
    assert {p: p.stat().st_mtime_ns for p in before} == before  # the complete run was not touched
    saved = read_manifest(out).grid
    cfgs = [saved.config(c) for c in saved.cells() if c.seed in (1, 2)]
    whole = train_batch(cfgs, tmp_path / "whole", progress=False, command="test")
    for cfg, (folder, done) in zip(cfgs, whole):
        run = sweep.run(f"ddpg_collision_d70_s{cfg.seed}")
        assert done == episodes and rows(run / "episodes.csv") == rows(folder / "episodes.csv")
        assert (run / "model.zip").is_file()



@pytest.mark.slow
def test_resume_only_says_which_runs_continue_in_an_interrupted_batch(tmp_path):
    """An interrupted batch goes on whole: with --only naming one of its runs, the other is said to train too
    (not to be left for later), and it does."""
    grid = write_grid(tmp_path / "g.yaml", {
        "reward_presets": ["collision"], "seeds": [0, 1], "episodes": 40,
        "overrides": {"sim": {"episode_steps": 20}, "train": {
            "checkpoint_every_episodes": 2, "actor_critic": {"learning_starts_steps": 10**6}}}})
    out = tmp_path / "sweep"
    sweep = SweepDir(out)
    proc = lanefree_popen("sweep", str(grid), "--out", str(out), "--batch", "2", "--no-ray", "--no-progress")
    try:
        wait_for(lambda: any(sweep.batches.glob(f"*/{BATCH_CHECKPOINTS}/step_*.pt")), proc, "a batch checkpoint")
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130
    rest = lanefree("sweep", "--resume", str(out), "--only", "*_s0", "--no-ray", "--no-progress", timeout=900)
    assert rest.returncode == 0, rest.stderr
    assert "1 run(s) not matching --only train too: they continue in an interrupted batch" in rest.stdout
    assert "left for a later run" not in rest.stdout and "2/2 runs complete" in rest.stdout
