"""Training runs end to end: every algorithm's run folder, interruption and resume of a real
training subprocess, evaluation of a saved model, broken checkpoints."""

from __future__ import annotations

import csv
import json
import signal
import time
import zipfile
from pathlib import Path

import pytest
import yaml

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.errors import RunError
from lanefree_sumo.experiments.runners.batch import is_single_run
from lanefree_sumo.experiments.runners.evaluate import evaluate
from lanefree_sumo.experiments.runners.train import train
from lanefree_sumo.experiments.storage.episodes import EPISODE_COLUMNS
from lanefree_sumo.rl.algorithms import ALGORITHM_NAMES, get_algorithm
from lanefree_sumo.rl.models import episode_seed

from conftest import TINY_TRAINING, lanefree_popen, wait_for

pytestmark = [pytest.mark.sumo, pytest.mark.slow]


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def tiny_config(algo: str, **extra) -> LaneFreeConfig:
    return merge_config(LaneFreeConfig(), {**TINY_TRAINING, **extra, "train": {**TINY_TRAINING["train"], "algo": algo}})


@pytest.mark.parametrize("algo", ALGORITHM_NAMES)
def test_every_algorithm_makes_a_complete_run_folder(tmp_path, algo):
    run, done = train(tiny_config(algo), run=tmp_path / algo, progress=False, command="test")
    assert done == 2
    for name in ("config.yaml", "command.txt", "versions.json", "episodes.csv", "model.zip"):
        assert (run / name).is_file(), name
    assert any((run / "tb").rglob("events.out.tfevents*"))
    table = rows(run / "episodes.csv")
    assert list(table[0]) == list(EPISODE_COLUMNS)
    assert [int(r["episode"]) for r in table] == [1, 2]
    assert all(r["algorithm"] == algo and int(r["steps"]) == 100 for r in table)
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["train"]["algo"] == algo
    assert config["action"]["kind"] == ("discrete" if algo in ("dqn", "ddqn", "dueling", "per") else "continuous")
    versions = json.loads((run / "versions.json").read_text())
    assert {"python", "torch", "stable_baselines3", "sumo", "lanefree_sumo", "git_commit"} <= set(versions)
    ckpt = run / "checkpoints" / "ep_00001"
    assert (ckpt / "model.zip").is_file() and (ckpt / "state.json").is_file()
    spec = get_algorithm(algo)
    # the batchable algorithms train as a batch of one: the replay buffer is in the batch checkpoint, and the
    # run folder is its own batch; SB3's (sac) keeps it beside each checkpoint's model
    assert (ckpt / "replay_buffer.pkl").is_file() == (spec.off_policy and not spec.batched)
    assert is_single_run(run) == spec.batched
    assert any((run / "batch_checkpoints").glob("step_*.pt")) == spec.batched
    # stock SB3's class loads every run's model, which names no class of the project's but the dueling policy
    data = json.loads(zipfile.ZipFile(run / "model.zip").read("data"))
    modules = {v["__module__"] for v in data.values() if isinstance(v, dict) and "__module__" in v}
    assert modules and all(m.startswith("stable_baselines3.") for m in modules - {
        "lanefree_sumo.rl.algorithms.q_networks"}), modules
    assert ("lanefree_sumo.rl.algorithms.q_networks" in modules) == (algo == "dueling")
    model = spec.cls.load(run / "model.zip", device="cpu")
    assert (type(getattr(model, "q_net", None)).__name__ == "DuelingQNetwork") == (algo == "dueling")


def test_training_on_numpy_and_libsumo_gives_the_same_episodes(tmp_path):
    """The default training backend (numpy) changes no number: whole DDPG training episodes, learning
    included, give the same episodes.csv rows (all but the wall time) as in SUMO; both train in the one trainer (a
    batch of one)."""
    tables = {}
    for backend in ("numpy", "libsumo"):
        cfg = merge_config(tiny_config("ddpg", scenario={"density_veh_per_km": 120}), {"train": {"backend": backend}})
        run, _ = train(cfg, run=tmp_path / backend, progress=False)
        assert yaml.safe_load((run / "config.yaml").read_text())["backend"] == backend
        assert json.loads((run / "batch.json").read_text()) == {"runs": ["."]}
        tables[backend] = [{k: v for k, v in r.items() if k != "wall_s"} for r in rows(run / "episodes.csv")]
    assert len(tables["numpy"]) == 2
    assert tables["numpy"] == tables["libsumo"]


def test_set_observation_trains_with_the_encoder(tmp_path):
    run, done = train(tiny_config("dueling", observation={"kind": "set"}), run=tmp_path / "set", progress=False)
    assert done == 2 and (run / "model.zip").is_file()


EPISODES = 30
"""The interrupted run's episodes (test_sigint_checkpoints_and_resume_continues_without_gaps)."""


def test_sigint_checkpoints_and_resume_continues_without_gaps(tmp_path):
    # 30 short episodes: a fast machine trains one in ~50 ms, so SIGINT after the second lands long before the last
    run = tmp_path / "run"
    proc = lanefree_popen("train", "--algo", "dqn", "--episodes", str(EPISODES), "--episode-steps", "100",
                          "--out", str(run), "--checkpoint-every", "100")
    csv_path = run / "episodes.csv"
    deadline = time.time() + 240
    while time.time() < deadline:
        if csv_path.exists() and len(rows(csv_path)) >= 2:
            break
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Resume with: lanefree train --resume" in err and "Traceback" not in err
    first = [int(r["episode"]) for r in rows(csv_path)]
    assert 2 <= len(first) < EPISODES and first == list(range(1, len(first) + 1))
    state = json.loads(next((run / "checkpoints").glob("ep_*/state.json")).read_text())
    assert state["episodes"] == len(first)

    resumed = lanefree_popen("train", "--resume", str(run))
    out, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err
    episodes = [int(r["episode"]) for r in rows(csv_path)]
    assert episodes == list(range(1, EPISODES + 1))
    timesteps = [int(r["timesteps"]) for r in rows(csv_path)]
    assert timesteps == sorted(timesteps)
    # the traffic continues: episode k's seed depends on the run's seed and k only, as if never interrupted
    assert [int(r["seed"]) for r in rows(csv_path)] == [episode_seed(0, 0, k) for k in range(1, EPISODES + 1)]
    assert (run / "model.zip").is_file()
    assert len((run / "command.txt").read_text().splitlines()) == 2
    # each session's episodes, end and versions (the kernels too), as one line each
    sessions = [json.loads(line) for line in (run / "sessions.jsonl").read_text().splitlines()]
    assert [(s["first_episode"], s["episodes_done"], s["stopped_by"]) for s in sessions] == [
        (1, len(first), "SIGINT"), (len(first) + 1, EPISODES, None)]
    assert all(s["versions"]["numpy_simd"] and s["versions"]["git_commit"] for s in sessions)
    assert json.loads((run / "last_session.json").read_text()) == sessions[-1]


def test_evaluate_a_saved_model_with_recording(tmp_path):
    import torch

    run, _ = train(tiny_config("ddpg"), run=tmp_path / "run", progress=False)
    torch.set_num_threads(2)  # torch's default on two cores; the policy runs on the run's torch_threads
    out = evaluate(run, episodes=2, record=True, progress=False).out
    assert torch.get_num_threads() == 1
    assert out == run / "eval"
    table = rows(out / "episodes.csv")
    assert [r["episode"] for r in table] == ["1", "2"]
    assert {r["seed"] for r in table} == {"100001", "100002"}
    traj = rows(out / "trajectories" / "episode_0001.csv")
    assert list(traj[0]) == ["t", "id", "x", "y", "vx", "vy", "ax", "ay", "overlap"]
    agent = [r for r in traj if r["id"] == "agent"]
    assert len(agent) == 101 and agent[0]["t"] == "0.0"
    with pytest.raises(RunError, match="exists; choose another --out or pass --overwrite"):
        evaluate(run, episodes=1, progress=False)
    other = evaluate(run, episodes=1, density=120, progress=False).out
    assert other.name == "eval_d120" and rows(other / "episodes.csv")[0]["density"] == "120.0"


def test_broken_checkpoints_give_clear_errors(tmp_path):
    run, _ = train(tiny_config("sac"), run=tmp_path / "run", progress=False)  # SB3's loop: checkpoints/ep_N
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    (run / "checkpoints" / "ep_00002" / "model.zip").write_bytes(b"not a zip")
    with pytest.raises(RunError, match="is corrupt"):
        train(LaneFreeConfig(), run=run, resume=True, progress=False, episodes=4)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(RunError, match="no config.yaml"):
        train(LaneFreeConfig(), run=empty, resume=True, progress=False)
    (empty / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(RunError, match="no usable checkpoint"):
        train(LaneFreeConfig(), run=empty, resume=True, progress=False)


def _sb3_loop_run(folder: Path, algo: str) -> Path:
    """A run as an earlier version left it: ``algo`` trained in SB3's loop with stock SB3's class (checkpoints with
    SB3's replay buffer beside the model, no batch.json)."""
    from lanefree_sumo.experiments.runners import train as runner
    from lanefree_sumo.experiments.storage.rundir import RunDir, write_config
    from lanefree_sumo.rl.models import training_config

    cfg = training_config(tiny_config(algo))
    folder.mkdir()
    write_config(folder, cfg)
    assert runner._train_session(cfg, RunDir(folder), None, 0, 2, False, "test") == (folder, 2)
    return folder


@pytest.mark.parametrize("case", ["sb3-loop", "no-batch-json", "sweep-batch"])
def test_an_earlier_versions_run_of_sb3s_loop_is_refused_in_one_line_and_left_as_it_is(tmp_path, case):
    """A run folder of a batchable algorithm with no batch of its own is not resumed: one that SB3's loop trained
    (an earlier version's: its checkpoints keep SB3's replay buffer), a batch of one that lost its batch.json, a run
    of a sweep's batch (continued with its batch). The error says what still works; nothing in the folder changes."""
    if case == "sb3-loop":
        run = _sb3_loop_run(tmp_path / "old", "dqn")
        assert any(run.glob("checkpoints/ep_*/replay_buffer.pkl"))
        expected = "was trained in SB3's loop by an earlier version, where dqn no longer trains; its model"
    else:
        run, _ = train(tiny_config("ddpg"), run=tmp_path / "runs" / "one", progress=False)
        if case == "no-batch-json":
            (run / "batch.json").unlink()
            expected = "was trained as a batch of one but has no batch.json, so its batch checkpoint cannot be found"
        else:  # as a sweep's batch leaves its runs: its last session names the batch's folder, no batch.json
            session = json.loads((run / "last_session.json").read_text())
            session["batch"] = {"folder": "../../batches/b", "run": 1, "runs": 2}
            (run / "last_session.json").write_text(json.dumps(session))
            (run / "batch.json").unlink()
            expected = (f"is a run of the batch {tmp_path / 'batches' / 'b'}; continue the whole batch: lanefree "
                        "sweep --resume SWEEP for a sweep's")
    before = {p: p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}
    with pytest.raises(RunError, match=expected.replace("(", r"\(").replace(")", r"\)")) as caught:
        train(LaneFreeConfig(), run=run, resume=True, progress=False, episodes=4)
    assert "\n" not in str(caught.value)
    assert {p: p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()} == before


def test_cli_refuses_an_existing_run_folder(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "keep").write_text("x")
    proc = lanefree_popen("train", "--episodes", "1", "--out", str(run))
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2 and "exists; resume it" in err and err.count("\n") == 1


def test_parallel_environments_in_separate_processes(tmp_path):
    cfg = merge_config(tiny_config("ddpg"), {"train": {"envs": 2, "episodes": 4}})
    run, done = train(cfg, run=tmp_path / "par", progress=False)
    table = rows(run / "episodes.csv")
    assert done == 4 and [int(r["episode"]) for r in table] == [1, 2, 3, 4]
    # two environments with different traffic seeds ran side by side
    assert len({r["seed"] for r in table}) == 4


@pytest.mark.parametrize("state", ["config.yaml", "command.txt"])
def test_a_new_run_stopped_before_its_first_episode_leaves_nothing_behind(tmp_path, state):
    """SIGTERM (as Ctrl-C) while the run folder is being set up, or while the first (long) episode runs: exit
    130, no folder left, and the same command then simply runs."""
    run = tmp_path / "run"
    command = ("train", "--episodes", "1", "--episode-steps", "20000", "--out", str(run), "--backend", "numpy")
    proc = lanefree_popen(*command)
    wait_for(lambda: (run / state).exists(), proc, f"{state} in the new run folder")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "interrupted" in err and "Traceback" not in err, err
    assert not run.exists()
    again = lanefree_popen(*command[:4], "40", *command[5:])  # the same command, a short episode
    _, err = again.communicate(timeout=300)
    assert again.returncode == 0, err
    assert len(rows(run / "episodes.csv")) == 1


def test_resume_trains_every_remaining_episode_and_refuses_a_gap_in_the_episode_log(tmp_path):
    """The budget of a resumed run comes from its episodes: a checkpoint whose step count includes part of an
    unfinished episode (as one taken at Ctrl-C does) still leads to every episode asked for. A log that lacks
    an episode the checkpoint learned is refused, and left as it is."""
    run, _ = train(tiny_config("ddpg"), run=tmp_path / "run", progress=False)
    state = run / "checkpoints" / "ep_00002" / "state.json"
    saved = json.loads(state.read_text())
    saved["timesteps"] += 150  # one and a half episodes of 100 steps that were never logged
    state.write_text(json.dumps(saved))
    run, done = train(LaneFreeConfig(), run=run, resume=True, episodes=4, progress=False)
    assert done == 4 and [r["episode"] for r in rows(run / "episodes.csv")] == ["1", "2", "3", "4"]

    log = run / "episodes.csv"
    whole = log.read_text()
    kept = [line for line in whole.splitlines(keepends=True) if not line.startswith("2,")]
    log.write_text("".join(kept))
    before = log.read_text()
    with pytest.raises(RunError, match="does not hold episode 2 of the 4"):
        train(LaneFreeConfig(), run=run, resume=True, episodes=5, progress=False)
    assert log.read_text() == before
    lines = whole.splitlines(keepends=True)  # a row cut in the middle (a crash while writing it)
    log.write_text("".join(lines[:-1]) + lines[-1][: len(lines[-1]) // 3])
    with pytest.raises(RunError, match="does not hold episode 4 of the 4"):
        train(LaneFreeConfig(), run=run, resume=True, episodes=5, progress=False)


@pytest.mark.parametrize(("algo", "slots"), [("ddpg", {"scenario": {"agents": 2}}), ("dqn", {"train": {"envs": 2}}),
                                            ("ddpg", {"scenario": {"agents": 2}, "train": {"backend": "libsumo"}})],
                         ids=["ddpg-agents2", "dqn-envs2", "ddpg-agents2-libsumo"])
def test_a_run_of_several_agents_or_environments_resumed_equals_the_uninterrupted_run(tmp_path, monkeypatch, algo,
                                                                                     slots):
    """A run of two learning vehicles (one shared policy) or of two environments trains in the one trainer too (a
    batch of one whose run has two slots): SIGTERM at step 150, in the middle of an episode and after a checkpoint,
    and --resume give the uninterrupted run's episodes.csv (every column but wall time). (Inside SUMO the stop keeps
    the checkpoint taken between episodes; the resume starts the simulation again from its episode's seed.)"""
    import os

    from lanefree_sumo.experiments.runners import batch

    def table(run: Path) -> list[dict[str, str]]:
        return [{k: v for k, v in r.items() if k != "wall_s"} for r in rows(run / "episodes.csv")]

    cfg = merge_config(merge_config(tiny_config(algo), {"train": {"episodes": 4}}), slots)
    whole, done = train(cfg, run=tmp_path / "whole", progress=False, command="test")
    assert done == 4 and (whole / "batch.json").is_file()
    step = batch._Batch._step

    def interrupted(self, env, learner, *args):
        checkpoint = step(self, env, learner, *args)
        if learner.num_timesteps == 300:  # step 150 of two slots
            os.kill(os.getpid(), signal.SIGTERM)
        return checkpoint

    monkeypatch.setattr(batch._Batch, "_step", interrupted)
    cut, done = train(cfg, run=tmp_path / "cut", progress=False, command="test")
    monkeypatch.undo()
    assert done == (1 if "scenario" in slots else 2) and not (cut / "model.zip").exists()
    assert train(LaneFreeConfig(), run=cut, resume=True, progress=False, command="test") == (cut, 4)
    assert table(cut) == table(whole) and len(table(whole)) == (8 if "scenario" in slots else 4)


@pytest.mark.parametrize("scene", [{}, {"shield": {"enabled": True}, "road": {"kind": "onramp"},
                                        "scenario": {"density_veh_per_km": 40}}, {"train": {"backend": "libsumo"}}],
                         ids=["ring", "shield-onramp", "libsumo"])
def test_a_single_run_resumed_or_extended_equals_the_uninterrupted_run(tmp_path, monkeypatch, scene):
    """One trainer: a single DDPG run is a batch of one in its own folder (on the ring its batched world, with the
    shield on the on-ramp LaneFree-v0 itself, in SUMO LaneFree-v0 on libsumo), so SIGTERM in the middle of episode
    2 and --resume, and a finished 2-episode run extended with --episodes 3, give the uninterrupted 3-episode run's
    episodes.csv (every column but wall time) and TensorBoard events in the run folder. (Inside SUMO the stop keeps
    the checkpoint of episode 1, taken between episodes, and the resume trains episode 2 again.)"""
    import os

    from lanefree_sumo.experiments.runners import batch

    def table(run: Path) -> list[dict[str, str]]:
        return [{k: v for k, v in r.items() if k != "wall_s"} for r in rows(run / "episodes.csv")]

    cfg = merge_config(merge_config(tiny_config("ddpg"), {"train": {"episodes": 3}}), scene)
    whole, done = train(cfg, run=tmp_path / "whole", progress=False, command="test")
    assert (whole / "batch.json").is_file()
    assert done == 3 and any((whole / "tb").rglob("events.out.tfevents*"))
    step = batch._Batch._step

    def interrupted(self, env, learner, *args):
        checkpoint = step(self, env, learner, *args)
        if learner.num_timesteps == 150:  # half way through episode 2, after episode 1's checkpoint
            os.kill(os.getpid(), signal.SIGTERM)
        return checkpoint

    monkeypatch.setattr(batch._Batch, "_step", interrupted)
    cut, done = train(cfg, run=tmp_path / "cut", progress=False, command="test")
    monkeypatch.undo()
    assert done == 1 and not (cut / "model.zip").exists()
    assert train(LaneFreeConfig(), run=cut, resume=True, progress=False, command="test") == (cut, 3)
    assert table(cut) == table(whole)

    short, _ = train(merge_config(cfg, {"train": {"episodes": 2}}), run=tmp_path / "short", progress=False)
    with pytest.raises(RunError, match="is finished .*--episodes N with N > 2"):
        train(LaneFreeConfig(), run=short, resume=True, progress=False)
    assert train(LaneFreeConfig(), run=short, resume=True, episodes=3, progress=False) == (short, 3)
    assert table(short) == table(whole) and yaml.safe_load((short / "config.yaml").read_text())["train"][
        "episodes"] == 3
