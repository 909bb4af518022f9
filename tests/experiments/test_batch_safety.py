"""A batch claims its folder (never writes into a user's, a run's or another batch's), resume refuses a damaged
episodes.csv, and the CLI's batch mistakes are one line before anything is written."""

from __future__ import annotations

import csv
import os
import re
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.errors import RunError
from lanefree_sumo.experiments.runners import batch
from lanefree_sumo.experiments.runners.batch import resume_batch, train_batch
from lanefree_sumo.experiments.storage.rundir import claim
from lanefree_sumo.rl.batched_env import BatchedRingEnv

from conftest import lanefree

TINY = {"sim": {"episode_steps": 30},
        "train": {"algo": "dqn", "episodes": 2, "checkpoint_every_episodes": 1,
                  "dqn": {"learning_starts_steps": 20, "buffer_size": 200, "target_update_steps": 20}}}


def tiny(seed: int) -> LaneFreeConfig:
    return merge_config(LaneFreeConfig(), {**TINY, "seed": seed})


def stop_after_first_checkpoint(monkeypatch: pytest.MonkeyPatch) -> None:
    """The next batch is stopped by SIGTERM at its 45th step, after its first batch checkpoint (episode 1 of 30
    steps; checkpoint_every_episodes 1); ``monkeypatch.undo()`` restores the loop."""
    step = batch._Batch._step

    def stopped(self: Any, env: Any, learner: Any, *args: Any) -> bool:
        checkpoint = step(self, env, learner, *args)
        if learner.num_timesteps == 45:
            os.kill(os.getpid(), signal.SIGTERM)
        return checkpoint

    monkeypatch.setattr(batch._Batch, "_step", stopped)


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("holds,named", [("user", "2 file(s) or folder(s), e.g. notes.txt"), ("run", "a run")])
def test_a_batch_never_writes_into_a_folder_that_holds_something(tmp_path, holds, named):
    out = tmp_path / "out"
    out.mkdir()
    if holds == "user":
        (out / "notes.txt").write_text("mine")
        (out / "zz").mkdir()
    else:
        (out / "config.yaml").write_text("seed: 0\n")
    before = snapshot(out)
    with pytest.raises(RunError, match=re.escape(f"holds {named}; a batch writes into a new or empty folder")):
        train_batch([tiny(0), tiny(1)], out, progress=False, command="test")
    assert snapshot(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_second_batch_is_refused_while_one_writes_and_after_it_stopped(tmp_path, monkeypatch):
    out = tmp_path / "batch"
    with claim(out, "train"):  # another process's batch holds the folder: flock is per open file, as across processes
        with pytest.raises(RunError, match="is being written by process"):
            train_batch([tiny(0), tiny(1)], out, progress=False, command="test")
    assert not out.exists()
    stop_after_first_checkpoint(monkeypatch)
    first = train_batch([tiny(0), tiny(1)], out, progress=False, command="test")
    monkeypatch.undo()
    assert [done for _, done in first] == [1, 1]
    before = snapshot(out)
    with pytest.raises(RunError, match="holds a batch already; resume it with --resume"):
        train_batch([tiny(5), tiny(6)], out, progress=False, command="test")
    assert snapshot(out) == before
    resumed = resume_batch(out, progress=False, command="test")  # the first batch is whole and resumes
    assert [done for _, done in resumed] == [2, 2]
    with pytest.raises(RunError, match="holds a finished batch"):
        train_batch([tiny(5), tiny(6)], out, progress=False, command="test")


@pytest.mark.parametrize("damage", ["rows", "file"])
def test_resuming_a_batch_whose_episodes_csv_lost_rows_is_refused(tmp_path, monkeypatch, damage):
    out = tmp_path / "batch"
    stop_after_first_checkpoint(monkeypatch)
    runs = train_batch([tiny(0), tiny(1)], out, progress=False, command="test")
    monkeypatch.undo()
    episodes = runs[1][0] / "episodes.csv"
    if damage == "rows":
        episodes.write_text(episodes.read_text().splitlines()[0] + "\n")
    else:
        episodes.unlink()
    with pytest.raises(RunError, match=r"episodes.csv does not hold episode 1 of the 1 its newest checkpoint"):
        resume_batch(out, progress=False, command="test")
    assert (episodes.read_text().count("\n") if episodes.exists() else 0) <= 1  # left as it was, not rewritten


@pytest.mark.parametrize("seeds,said", [
    ("0-99999999999999999999", "out of range; allowed 0 … 2147483647"),
    ("0-100000", "100001 seeds in '0-100000'; a batch trains at most 4096"),
    ("0-2147483647", "a batch trains at most 4096"),
])
def test_seed_ranges_beyond_a_batch_are_one_line_and_write_nothing(tmp_path, seeds, said):
    res = lanefree("train", "--seeds", seeds, "--out", str(tmp_path / "b"), timeout=120)
    assert res.returncode == 2 and said in res.stderr and res.stderr.count("\n") == 1
    assert not (tmp_path / "b").exists()


def test_a_batch_whose_replay_buffers_do_not_fit_is_one_line_naming_how_many_runs_fit(tmp_path):
    """64 DDPG runs with 10⁸-transition buffers (≈ 20 GiB of replay each): more than a machine has; the line says
    how much they need and how many such runs fit here (computed as the batch allocates them: replay_bytes equals
    the batched replay's bytes), and nothing is written."""
    from lanefree_sumo.experiments.runners.batch import available_memory, replay_bytes
    from lanefree_sumo.rl.env import action_space, observation_space
    from lanefree_sumo.rl.models import build_batched, training_config

    small = training_config(merge_config(LaneFreeConfig(), {"train": {"actor_critic": {"buffer_size": 1000}}}))
    learner = build_batched([small, small], [0, 1], observation_space(small), action_space(small))
    held = sum(v.nbytes for v in learner.replay.state_dict().values() if isinstance(v, torch.Tensor))
    assert 2 * replay_bytes(small) == held == 2 * 1000 * (2 * 4 * 24 + 2 * 4 + 3 * 4)
    per_run = 100_000_000 * (2 * 4 * 24 + 2 * 4 + 3 * 4)
    assert 64 * per_run > available_memory("cpu")
    res = lanefree("train", "--seeds", "0-63", "--set", "train.actor_critic.buffer_size=100000000",
                   "--out", str(tmp_path / "b"), timeout=120)
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    need = f"64 runs need ≈ {64 * per_run / 2**30:.1f} GiB of replay memory ({per_run / 2**20:,.0f} MiB each)"
    assert need in res.stderr
    fit = re.search(r"at most (\d+) such runs fit here; train fewer seeds per batch", res.stderr)
    assert fit is not None and int(fit.group(1)) < 64  # (the available memory moves between the two processes)
    assert not (tmp_path / "b").exists()


def test_set_seed_with_seeds_is_refused(tmp_path):
    res = lanefree("train", "--seeds", "0-1", "--set", "seed=7", "--out", str(tmp_path / "b"), timeout=120)
    assert res.returncode != 0 and "--set seed=… and --seeds exclude each other" in res.stderr
    assert not (tmp_path / "b").exists()


def test_a_grid_whose_overrides_are_not_a_mapping_is_one_line(tmp_path):
    grid = tmp_path / "g.yaml"
    grid.write_text("algorithms: [ddpg]\nreward_presets: [collision]\noverrides: [1, 2]\n")
    res = lanefree("sweep", str(grid), "--out", str(tmp_path / "s"), "--no-ray", timeout=120)
    assert res.returncode != 0 and "overrides must be a mapping of config keys" in res.stderr
    assert "internal error" not in res.stderr and not (tmp_path / "s").exists()


@pytest.mark.parametrize("actions,named", [(np.zeros((2, 3)), r"shape \(3, 2\)"), (np.zeros(5), r"shape \(3, 2\)"),
                                           (np.zeros((1, 2)), r"shape \(3, 2\)")])
def test_the_batched_env_validates_its_actions(actions, named):
    env = BatchedRingEnv([{"seed": s, "backend": "numpy"} for s in range(3)])
    env.reset()
    with pytest.raises(ValueError, match=named):
        env.step(actions)


@pytest.mark.parametrize("runs", [[5], [2], [-1], [0, 0], [True]])
def test_the_batched_env_validates_the_runs_it_resets(runs):
    env = BatchedRingEnv([{"seed": s, "backend": "numpy"} for s in range(2)])
    env.reset()
    with pytest.raises(ValueError, match=r"runs are distinct indices 0 … 1"):
        env.reset(runs=runs)


def test_a_full_disk_at_a_batch_checkpoint_is_one_line_and_the_previous_one_resumes(tmp_path, monkeypatch):
    import torch

    from lanefree_sumo.errors import OperatingSystemError

    cfgs = [merge_config(tiny(s), {"train": {"episodes": 3}}) for s in (0, 1)]
    whole = train_batch(cfgs, tmp_path / "whole", progress=False, command="test")
    save, calls = torch.save, []

    def full_disk(obj: Any, path: Any, *args: Any, **kwargs: Any) -> None:
        if not str(path).endswith(".pt.tmp"):  # a model.zip's parts, written by SB3
            return save(obj, path, *args, **kwargs)
        calls.append(path)
        if len(calls) == 2:  # what torch.save raises when the disk fills mid-write
            Path(path).write_bytes(b"half")
            raise RuntimeError("[enforce fail at inline_container.cc:672] . PytorchStreamWriter failed writing file")
        save(obj, path, *args, **kwargs)

    monkeypatch.setattr(torch, "save", full_disk)
    out = tmp_path / "batch"
    with pytest.raises(OperatingSystemError, match=r"could not write the batch checkpoint .*PytorchStreamWriter failed "
                       r"writing file\); the previous one \(step_\d+\.pt\) is kept: free some space and resume") as err:
        train_batch(cfgs, out, progress=False, command="test")
    assert "\n" not in str(err.value)
    monkeypatch.undo()
    assert [p.name for p in (out / "batch_checkpoints").iterdir()] == [Path(calls[0]).name.removesuffix(".tmp")]
    resumed = resume_batch(out, progress=False, command="test")
    assert [done for _, done in resumed] == [3, 3]

    def rows(path: Path) -> list[dict[str, str]]:
        with open(path, newline="") as fh:
            return [{k: v for k, v in row.items() if k != "wall_s"} for row in csv.DictReader(fh)]

    for (a, _), (b, _) in zip(resumed, whole):
        assert rows(a / "episodes.csv") == rows(b / "episodes.csv")


def test_the_verbs_understand_a_batch_folder(tmp_path):
    out = tmp_path / "batch"
    train = lanefree("train", "--seeds", "0-1", "--algo", "dqn", "--episodes", "1", "--set", "sim.episode_steps=30",
                     "--set", "train.dqn.learning_starts_steps=20", "--out", str(out), timeout=300)
    assert train.returncode == 0, train.stderr
    report = lanefree("report", str(out), "--out", str(tmp_path / "report"), timeout=300)
    assert report.returncode == 0, report.stderr
    assert "| 2 |" in (tmp_path / "report" / "summary.md").read_text()  # one group of the batch's two runs
    rollout = lanefree("rollout", "--run", str(out), "--episodes", "1", timeout=300)
    assert rollout.returncode == 2 and rollout.stderr.count("\n") == 1
    assert "is a batch of 'lanefree train --seeds' (2 runs); pass one of its run folders, e.g." in rollout.stderr
    evaluate = lanefree("evaluate", str(out), "--episodes", "2", timeout=300)  # every finished run of the batch
    assert evaluate.returncode == 0, evaluate.stderr
    assert f"{out}: 2 run(s) evaluated, 0 already complete, 0 without a final model" in evaluate.stdout
    for run in sorted(p for p in out.iterdir() if (p / "config.yaml").is_file()):
        assert len((run / "eval" / "episodes.csv").read_text().splitlines()) == 3
    again = lanefree("evaluate", str(out), "--episodes", "2", timeout=300)  # nothing missing: nothing redone
    assert again.returncode == 0 and "0 run(s) evaluated, 2 already complete" in again.stdout
    shielded = lanefree("evaluate", str(out), "--episodes", "1", "--shield", timeout=300)
    assert shielded.returncode == 0 and "2 run(s) evaluated" in shielded.stdout
    assert all((p / "eval_shield" / "episodes.csv").is_file() for p in out.iterdir() if (p / "config.yaml").is_file())
    with_out = lanefree("evaluate", str(out), "--out", str(tmp_path / "e"), timeout=120)
    assert with_out.returncode == 2 and "each run of" in with_out.stderr and not (tmp_path / "e").exists()
    missing = lanefree("evaluate", str(tmp_path / "nowhere"), timeout=120)
    assert missing.returncode != 0 and missing.stderr.count("\n") == 1


def test_every_run_of_a_batch_writes_its_tensorboard_log(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    runs = train_batch([tiny(0), tiny(1)], tmp_path / "batch", progress=False, command="test")
    for run, done in runs:
        events = EventAccumulator(str(run / "tb" / "batch"))
        events.Reload()
        returns = events.Scalars("episode/return")
        assert [e.step for e in returns] == [30, 60] and done == 2
        with open(run / "episodes.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        for event, row in zip(returns, rows):  # each episode's own return (TensorBoard keeps float32)
            assert event.value == pytest.approx(float(row["return"]), rel=1e-6)


@pytest.mark.parametrize("args,said", [
    (["--algo", "td3", "--set", "train.profile=kerasrl"],
     "(what train.profile = kerasrl sets) is built for ddpg only; td3 takes SB3's uniform warm-up; add --set "
     "train.actor_critic.warmup_actions=uniform beside the profile"),
    (["--seeds", "0-1", "--algo", "td3", "--set", "train.actor_critic.pre_tanh_penalty=0.01"],
     "pre_tanh_penalty = 0.01 is built into the project's ddpg only; set it to 0 for td3"),
    (["--set", "train.actor_critic.pre_tanh_penalty=0.01", "--algo", "td3"],
     "pre_tanh_penalty = 0.01 is built into the project's ddpg only; set it to 0 for td3"),
])
def test_one_validation_for_one_run_and_a_batch(tmp_path, args, said):
    res = lanefree("train", *args, "--episodes", "1", "--out", str(tmp_path / "x"), timeout=120)
    assert res.returncode == 2 and said in res.stderr and res.stderr.count("\n") == 1
    assert not (tmp_path / "x").exists()


def test_a_grid_whose_runs_cannot_train_is_refused_before_it_starts(tmp_path):
    grid = tmp_path / "g.yaml"
    grid.write_text("algorithms: [td3]\nreward_presets: [collision]\nn_seeds: 1\nvariants:\n"
                    "  keras: {train.profile: kerasrl}\n")
    res = lanefree("sweep", str(grid), "--out", str(tmp_path / "s"), "--no-ray", timeout=120)
    assert res.returncode == 2 and res.stderr.count("\n") == 1
    assert "td3 / collision / d70 / keras: train.actor_critic.warmup_actions = policy" in res.stderr
    assert not (tmp_path / "s").exists()


def test_a_finished_batch_gets_advice_that_leads_somewhere(tmp_path):
    out = tmp_path / "batch"
    runs = train_batch([tiny(0), tiny(1)], out, progress=False, command="test")
    extend = lanefree("train", "--resume", str(runs[0][0]), "--episodes", "5", timeout=120)
    assert extend.returncode == 2 and "is a finished run of the batch" in extend.stderr
    assert "train more episodes as a new batch" in extend.stderr and "--resume" not in extend.stderr.split(";")[1]
    status = lanefree("sweep", "--status", str(out), timeout=120)
    assert status.returncode != 0 and status.stderr.count("\n") == 1
    assert "is a 'lanefree train --seeds' batch, not a sweep folder" in status.stderr


def test_books_load_from_a_dict_and_from_a_checkpoint_of_the_former_module_path(monkeypatch):
    """A batch checkpoint keeps its books as a dict; one written while the batch module was
    ``lanefree_sumo.experiments.batch`` (its pickled books name that module) still resumes."""
    import dataclasses
    import pickle
    import sys
    import types

    from lanefree_sumo.experiments.runners.batch import _Books, _load_books

    books = _Books(done=[3, 1], target=[5, 5], finished=[False, False], stopped={1: "not finite"}, steps=240)
    assert _load_books(dataclasses.asdict(books)) == books
    former = types.ModuleType("lanefree_sumo.experiments.batch")
    old = dataclasses.make_dataclass("_Books", [(f.name, f.type) for f in dataclasses.fields(_Books)])
    old.__module__ = former.__name__
    former._Books = old
    monkeypatch.setitem(sys.modules, former.__name__, former)
    saved = pickle.dumps(old(**dataclasses.asdict(books)))
    monkeypatch.delitem(sys.modules, former.__name__)
    assert _load_books(saved) == books
    with pytest.raises(TypeError, match="the books are a dict"):
        _load_books(pickle.dumps({"done": [1]}))


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return [{k: v for k, v in row.items() if k != "wall_s"} for row in csv.DictReader(fh)]


@pytest.mark.parametrize("single", [False, True])
def test_a_batch_whose_checkpoints_are_all_damaged_starts_afresh_with_the_same_command(tmp_path, monkeypatch, single):
    """A batch (or a single run, its own batch) stopped after its first checkpoint, its two batch checkpoints then
    damaged: --resume says to delete the newest and resume from the older; that one unusable too, it says to start
    afresh with the command that made it, and that command trains the runs again — to the episodes of an
    uninterrupted batch (the runs of a batch finish together: none of them had finished)."""
    from lanefree_sumo.experiments.runners.train import train

    cfgs = [merge_config(tiny(seed), {"train": {"episodes": 2}}) for seed in ((0,) if single else (0, 1))]

    def start(out: Path) -> list[tuple[Path, int]]:
        return [train(cfgs[0], run=out, progress=False, command="test")] if single else \
            train_batch(cfgs, out, progress=False, command="test")

    def resume(out: Path) -> Any:
        return train(LaneFreeConfig(), run=out, resume=True, progress=False, command="test") if single else \
            resume_batch(out, progress=False, command="test")

    whole = start(tmp_path / "whole")
    out = tmp_path / "batch"
    stop_after_first_checkpoint(monkeypatch)
    assert [done for _, done in start(out)] == [1] * len(cfgs)
    monkeypatch.undo()
    older, newest = sorted((out / "batch_checkpoints").glob("step_*.pt"))
    for path in (older, newest):
        path.write_bytes(b"damaged")
    with pytest.raises(RunError, match=r"is unusable .*delete it to resume from the older one"):
        resume(out)
    newest.unlink()
    afresh = (rf"it was the run's only one: start it afresh with 'lanefree train … --out {re.escape(str(out))}' "
              r"\(no --resume\)" if single else r"it was the batch's only one: start the batch afresh with the command "
              rf"that made it \(its --out {re.escape(str(out))}, no --resume\)")
    with pytest.raises(RunError, match=afresh):
        resume(out)
    again = start(out)
    assert [done for _, done in again] == [2] * len(cfgs)
    for (a, _), (b, _) in zip(again, whole):
        assert _rows(a / "episodes.csv") == _rows(b / "episodes.csv")
    assert not (out / "batch_checkpoints" / older.name).read_bytes().startswith(b"damaged")
