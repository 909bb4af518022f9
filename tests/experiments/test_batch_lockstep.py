"""Batched training with the lockstep loop (what ``--device cuda`` runs, here on the CPU without graphs): ordinary
run folders whose models SB3 loads, a stop and --resume continue with the uninterrupted episodes, a run with a
non-finite action stops alone."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from typing import Any

import pytest
import torch as th

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.experiments.runners.batch import BATCH_CHECKPOINTS, resume_batch, train_batch
from lanefree_sumo.rl.algorithms import get_algorithm
from lanefree_sumo.rl.lockstep import Lockstep
from tests.experiments.test_batch import rows

pytestmark = [pytest.mark.slow]

LOCKSTEP = {"sim": {"episode_steps": 20},
            "train": {"episodes": 3, "checkpoint_every_episodes": 1, "device": "torch-cpu",
                      "actor_critic": {"learning_starts_steps": 15, "buffer_size": 200},
                      "dqn": {"learning_starts_steps": 15, "buffer_size": 200, "target_update_steps": 10}}}
"""3 episodes of 20 steps; updates from step 16 on."""


def tiny(algo: str, seed: int, density: float = 70.0) -> LaneFreeConfig:
    return merge_config(LaneFreeConfig(), {**LOCKSTEP, "seed": seed, "scenario": {"density_veh_per_km": density},
                                           "train": {**LOCKSTEP["train"], "algo": algo}})


@pytest.mark.parametrize("algo", ["ddpg", "dqn", "per"])
def test_a_lockstep_batch_writes_ordinary_run_folders(tmp_path: Path, algo: str) -> None:
    cfgs = [tiny(algo, 0), tiny(algo, 1, density=90.0)]
    results = train_batch(cfgs, tmp_path / "batch", progress=False, command="test", lockstep=True)
    assert [done for _, done in results] == [3, 3]
    for folder, _ in results:
        got = rows(folder / "episodes.csv")
        assert [int(r["episode"]) for r in got] == [1, 2, 3]
        assert [int(r["timesteps"]) for r in got] == [20, 40, 60] and all(r["steps"] == "20" for r in got)
        model = get_algorithm(algo).cls.load(folder / "model.zip", device="cpu")
        assert model.num_timesteps == 60 and model._n_updates == 60 - 15 - 1  # none at the last step, as SB3
        session = json.loads((folder / "last_session.json").read_text())
        assert session["stopped_by"] is None and session["episodes_done"] == 3
    assert rows(results[0][0] / "episodes.csv") != rows(results[1][0] / "episodes.csv")


def test_a_lockstep_batch_trains_the_set_observation(tmp_path: Path) -> None:
    """DDPG on the set observation in the lockstep loop (the encoder over every row, as on a GPU): run folders
    whose models load with the paper encoder."""
    cfgs = [merge_config(tiny("ddpg", seed), {"observation": {"kind": "set", "encoder": "paper"}}) for seed in (0, 1)]
    results = train_batch(cfgs, tmp_path / "batch", progress=False, command="test", lockstep=True)
    assert [done for _, done in results] == [3, 3]
    for folder, _ in results:
        model = get_algorithm("ddpg").cls.load(folder / "model.zip", device="cpu")
        assert model.actor.features_extractor.encoder_name == "paper" and model._n_updates == 60 - 15 - 1
    assert rows(results[0][0] / "episodes.csv") != rows(results[1][0] / "episodes.csv")


@pytest.mark.parametrize("algo", ["ddpg", "per"])
def test_a_stopped_lockstep_batch_resumes_with_the_uninterrupted_episodes(tmp_path: Path, algo: str,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGTERM in the middle of episode 2: the batch saves after that iteration; --resume continues with the
    device streams' state (DDPG's noise; prioritised replay's priorities), and every run's episodes equal an
    uninterrupted batch's."""
    cfgs = [tiny(algo, 0), tiny(algo, 1)]
    whole = train_batch(cfgs, tmp_path / "whole", progress=False, command="test", lockstep=True)
    iterate = Lockstep.iterate

    def interrupted(self: Lockstep, update: bool = True) -> None:
        iterate(self, update)
        if self.learner.num_timesteps == 27:
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(Lockstep, "iterate", interrupted)
    out = tmp_path / "interrupted"
    stopped = train_batch(cfgs, out, progress=False, command="test", lockstep=True)
    monkeypatch.undo()
    assert [done for _, done in stopped] == [1, 1]
    assert [p.name for p in (out / BATCH_CHECKPOINTS).glob("step_*.pt")][-1] == "step_0000000027.pt"
    resumed = resume_batch(out, progress=False, command="test", lockstep=True)
    assert [done for _, done in resumed] == [3, 3]
    for (a, _), (b, _) in zip(resumed, whole):
        assert rows(a / "episodes.csv") == rows(b / "episodes.csv")


def test_a_lockstep_run_with_a_non_finite_action_stops_alone(tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """Run 1's actions turn NaN in episode 2: at that episode's end run 1 is stopped (no row for it, no model,
    its session says why); run 0 trains on to the end."""
    from lanefree_sumo.rl.algorithms.batched import BatchedDDPG

    act = BatchedDDPG.act_on_device

    def diverging(self: BatchedDDPG, obs: th.Tensor, random: bool) -> Any:
        actions, stored = act(self, obs, random)
        if self.num_timesteps >= 25:
            actions = actions.clone()
            actions[1] = float("nan")
        return actions, stored

    monkeypatch.setattr(BatchedDDPG, "act_on_device", diverging)
    (run0, done0), (run1, done1) = train_batch([tiny("ddpg", 0), tiny("ddpg", 1)], tmp_path / "batch",
                                               progress=False, command="test", lockstep=True)
    assert (done0, done1) == (3, 1)
    assert (run0 / "model.zip").is_file() and not (run1 / "model.zip").exists()
    assert [int(r["episode"]) for r in rows(run1 / "episodes.csv")] == [1]
    session = json.loads((run1 / "last_session.json").read_text())
    assert "not finite in episode 2" in session["stopped_by"] and session["episodes_done"] == 1
