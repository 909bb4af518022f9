"""Batched training: run k of a batch equals ``lanefree train --seed k`` (episodes.csv, every column but wall_s),
a run with a non-finite action stops alone, Ctrl-C/SIGTERM and --resume continue a batch exactly, CLI errors."""

from __future__ import annotations

import csv
import json
import os
import signal
from pathlib import Path
from typing import Any

import pytest

from lanefree_sumo.commands.train import report_batch
from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.experiments.runners.batch import BATCH_CHECKPOINTS, batch_name, resume_batch, train_batch
from lanefree_sumo.experiments.runners.train import train
from lanefree_sumo.experiments.storage.episodes import EPISODE_COLUMNS
from lanefree_sumo.rl.algorithms import get_algorithm

from conftest import lanefree_popen, wait_for

pytestmark = [pytest.mark.slow]

SMALL = {"sim": {"episode_steps": 60},
         "train": {"episodes": 3, "checkpoint_every_episodes": 1,
                   "actor_critic": {"learning_starts_steps": 40, "buffer_size": 500},
                   "dqn": {"learning_starts_steps": 40, "buffer_size": 500, "target_update_steps": 30}}}
"""3 episodes of 60 steps; updates from step 41 on."""


def small(algo: str, seed: int, density: float = 90.0, **extra: dict) -> LaneFreeConfig:
    return merge_config(LaneFreeConfig(), {**SMALL, **extra, "seed": seed,
                                           "scenario": {"density_veh_per_km": density},
                                           "train": {**SMALL["train"], "algo": algo}})


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return [{k: v for k, v in row.items() if k != "wall_s"} for row in csv.DictReader(fh)]


@pytest.mark.parametrize("algo", ["ddpg", "td3", "dqn", "ddqn", "dueling", "per"])
def test_batched_runs_equal_sequential_runs(tmp_path: Path, algo: str) -> None:
    """Run k of a batch (seeds 0 and 1, run 1 at another density) writes the sequential run's episodes.csv."""
    cfgs = [small(algo, 0), small(algo, 1, density=120.0)]
    results = train_batch(cfgs, tmp_path / "batch", progress=False, command="test")
    assert [done for _, done in results] == [3, 3]
    for cfg, (folder, _) in zip(cfgs, results):
        run, _ = train(cfg, run=tmp_path / f"seq_{cfg.seed}", progress=False, command="test")
        with open(folder / "episodes.csv", newline="") as fh:
            assert next(csv.reader(fh)) == list(EPISODE_COLUMNS)
        batched, sequential = rows(folder / "episodes.csv"), rows(run / "episodes.csv")
        assert len(batched) == 3 and batched == sequential
        for name in ("config.yaml", "command.txt", "versions.json", "last_session.json", "sessions.jsonl"):
            assert (folder / name).is_file(), name
        model = get_algorithm(algo).cls.load(folder / "model.zip", device="cpu")
        assert model.observation_space.shape == (24,)
    assert results[1][0].name == batch_name(cfgs[1]) == f"{algo}_{cfgs[1].reward.preset}_d120_s1"


# the open modelling choices, each in a batch of two runs: per run where the batch allows it, else for both
OPEN_CHOICES = {
    "overtake_bonus": ("ddpg", [{"reward": {"overtake_bonus": "once_per_vehicle"}},
                                {"reward": {"overtake_bonus": "net_passes"}}]),
    "agent_limits": ("dqn", [{"scenario": {"agent_max_speed_mps": 24.0, "agent_lateral_speed_ratio": 0.3}}, {}]),
    "discrete_sizes": ("ddqn", [{"action": {"discrete_ax_mps2": 3.0, "discrete_ay_mps2": 0.5}}] * 2),
    "kerasrl_ddpg": ("ddpg", [{"train": {"profile": "kerasrl"}}] * 2),
    "kerasrl_dqn": ("dqn", [{"train": {"profile": "kerasrl"}}] * 2),
    "pre_tanh_penalty": ("ddpg", [{"train": {"actor_critic": {"pre_tanh_penalty": 0.01}}}, {}]),
}


def test_batched_set_observation_runs_agree_with_sequential_runs(tmp_path: Path) -> None:
    """The set observation (the paper encoder): run k of a batch agrees with ``lanefree train --seed k --obs set``
    to float tolerance (the batched encoder sums rows in another order: tests/rl/test_batched_set.py): the
    same episodes, counts equal, the other columns within 1e-4 relative; the model loads with its set encoder."""
    extra = {"observation": {"kind": "set", "encoder": "paper"}, "train": {"episodes": 2}}
    cfgs = [merge_config(small("ddpg", seed), extra) for seed in (0, 1)]
    results = train_batch(cfgs, tmp_path / "batch", progress=False, command="test")
    for cfg, (folder, done) in zip(cfgs, results):
        run, _ = train(cfg, run=tmp_path / f"seq_{cfg.seed}", progress=False, command="test")
        batched, sequential = rows(folder / "episodes.csv"), rows(run / "episodes.csv")
        assert done == 2 and len(batched) == len(sequential) == 2
        for mine, theirs in zip(batched, sequential):
            for column, value in theirs.items():
                try:
                    assert float(mine[column]) == pytest.approx(float(value), rel=1e-4, abs=1e-6), column
                except ValueError:  # a text column
                    assert mine[column] == value, column
        model = get_algorithm("ddpg").cls.load(folder / "model.zip", device="cpu")
        assert model.actor.features_extractor.encoder_name == "paper"


@pytest.mark.parametrize("choice", list(OPEN_CHOICES))
def test_batched_runs_equal_sequential_runs_under_the_open_choices(tmp_path: Path, choice: str) -> None:
    """Each open choice: run k of the batch writes ``lanefree train``'s episodes.csv (2 episodes of 60 steps)."""
    algo, extras = OPEN_CHOICES[choice]
    cfgs = []
    for seed, extra in enumerate(extras):
        cfg = merge_config(merge_config(small(algo, seed), extra), {"train": {"episodes": 2}})
        # the profile's warm-up is 1000 steps: shortened as every test run's, the profile's other keys kept
        cfgs.append(merge_config(cfg, {"train": {section: {"learning_starts_steps": 40}
                                                 for section in ("dqn", "actor_critic")}}))
    if choice.startswith("kerasrl"):
        assert (cfgs[0].train.dqn.loss, cfgs[0].train.dqn.max_grad_norm,
                cfgs[0].train.actor_critic.warmup_actions) == ("squared", None, "policy")
    results = train_batch(cfgs, tmp_path / "batch", progress=False, command="test")
    for cfg, (folder, done) in zip(cfgs, results):
        run, _ = train(cfg, run=tmp_path / f"seq_{cfg.seed}", progress=False, command="test")
        assert done == 2 and rows(folder / "episodes.csv") == rows(run / "episodes.csv")


def test_a_run_with_a_non_finite_action_stops_alone(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Run 1's policy gives NaN in episode 2: run 1 stops there (its folder's session says why, no model.zip),
    run 0 finishes as it would have alone."""
    from lanefree_sumo.rl.algorithms.batched import BatchedDDPG

    act = BatchedDDPG.act

    def diverging(self: BatchedDDPG, obs, explore: bool = True):
        actions = act(self, obs, explore)
        if self.num_timesteps >= 70:
            actions[1] = float("nan")
        return actions

    monkeypatch.setattr(BatchedDDPG, "act", diverging)
    cfgs = [small("ddpg", 0), small("ddpg", 1)]
    (run0, done0), (run1, done1) = train_batch(cfgs, tmp_path / "batch", progress=False, command="test")
    assert (done0, done1) == (3, 1)
    monkeypatch.undo()
    alone, _ = train_batch([cfgs[0]], tmp_path / "alone", progress=False, command="test")[0]
    assert rows(run0 / "episodes.csv") == rows(alone / "episodes.csv")
    assert (run0 / "model.zip").is_file() and not (run1 / "model.zip").exists()
    assert [int(r["episode"]) for r in rows(run1 / "episodes.csv")] == [1]
    session = json.loads((run1 / "last_session.json").read_text())
    assert "not finite" in session["stopped_by"] and session["episodes_done"] == 1
    assert json.loads((run0 / "last_session.json").read_text())["stopped_by"] is None
    assert report_batch([(run0, done0), (run1, done1)]) == 1  # not an interruption: nothing to resume
    out = capsys.readouterr()
    assert f"stopped after 1/3 episodes -> {run1} (run 1: action" in out.out and "--resume" not in out.err


@pytest.mark.parametrize(("algo", "obs"), [("td3", "vector"), ("ddpg", "set"), ("td3", "set")])
def test_a_stopped_batch_resumes_exactly_with_td3_and_the_set_observation(tmp_path: Path, algo: str, obs: str,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGTERM in the middle of episode 2 (after the first batch checkpoint): --resume continues TD3's target-noise
    streams and the set observation's batch, and every run's episodes equal an uninterrupted batch's."""
    from lanefree_sumo.experiments.runners import batch

    extra = {"observation": {"kind": "set", "encoder": "paper"}} if obs == "set" else {}
    cfgs = [merge_config(small(algo, seed), extra) for seed in (0, 1)]
    whole = train_batch(cfgs, tmp_path / "whole", progress=False, command="test")
    step = batch._Batch._step

    def interrupted(self: Any, env: Any, learner: Any, *args: Any) -> bool:
        checkpoint = step(self, env, learner, *args)
        if learner.num_timesteps == 90:
            os.kill(os.getpid(), signal.SIGTERM)
        return checkpoint

    monkeypatch.setattr(batch._Batch, "_step", interrupted)
    out = tmp_path / "interrupted"
    stopped = train_batch(cfgs, out, progress=False, command="test")
    monkeypatch.undo()
    assert [done for _, done in stopped] == [1, 1]
    resumed = resume_batch(out, progress=False, command="test")
    assert [done for _, done in resumed] == [3, 3]
    for (a, _), (b, _) in zip(resumed, whole):
        assert rows(a / "episodes.csv") == rows(b / "episodes.csv")


def test_a_batch_stopped_by_sigterm_resumes_with_the_uninterrupted_episodes(tmp_path: Path) -> None:
    """SIGTERM once the first batch checkpoint exists; --resume BATCH finishes it; every run's episodes.csv then
    equals an uninterrupted batch's."""
    args = ["--algo", "dqn", "--episodes", "4", "--episode-steps", "60", "--checkpoint-every", "1",
            "--set", "train.dqn.learning_starts_steps=40", "--set", "train.dqn.buffer_size=500",
            "--set", "train.dqn.target_update_steps=30"]
    out = tmp_path / "interrupted"
    proc = lanefree_popen("train", "--seeds", "0-1", "--out", str(out), *args)
    wait_for(lambda: any((out / BATCH_CHECKPOINTS).glob("step_*.pt")), proc, "the first batch checkpoint")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    assert "lanefree train --resume" in err
    short = [len(rows(p / "episodes.csv")) for p in sorted(out.glob("dqn_*"))]
    assert len(short) == 2 and min(short) < 4
    cfgs = [merge_config(LaneFreeConfig(), {"seed": s, "sim": {"episode_steps": 60}, "train": {
        "algo": "dqn", "episodes": 4, "checkpoint_every_episodes": 1,
        "dqn": {"learning_starts_steps": 40, "buffer_size": 500, "target_update_steps": 30}}}) for s in (0, 1)]
    whole = train_batch(cfgs, tmp_path / "whole", progress=False, command="test")
    resumed = resume_batch(out, progress=False, command="test")
    assert [done for _, done in resumed] == [4, 4]
    for (a, _), (b, _) in zip(resumed, whole):
        assert a.name == b.name and rows(a / "episodes.csv") == rows(b / "episodes.csv")
        assert (a / "model.zip").is_file()
    sessions = [json.loads(line) for line in (resumed[0][0] / "sessions.jsonl").read_text().splitlines()]
    assert [s["stopped_by"] for s in sessions] == ["SIGTERM", None] and sessions[1]["first_episode"] > 1
