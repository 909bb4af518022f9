"""Runs of several agents end to end: train (DDPG and PPO) with per-agent rows, resume, report, evaluate with a
recording, shielded rollout, replay in SUMO, and the mixed-autonomy measurement."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.experiments.runners.evaluate import evaluate
from lanefree_sumo.experiments.runners.replay import replay
from lanefree_sumo.experiments.runners.rollout import rollout
from lanefree_sumo.experiments.runners.train import train
from lanefree_sumo.experiments.storage.episodes import EPISODE_COLUMNS, MULTI_AGENT_COLUMNS
from lanefree_sumo.experiments.storage.rundata import read_episodes

from conftest import TINY_TRAINING, lanefree

pytestmark = [pytest.mark.slow]

AGENTS = ["agent", "agent1", "agent2"]


def rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def config(algo: str, **extra) -> LaneFreeConfig:
    return merge_config(LaneFreeConfig(), {**TINY_TRAINING, "scenario": {"agents": 3}, **extra,
                                           "train": {**TINY_TRAINING["train"], "algo": algo}})


@pytest.mark.parametrize("algo", ["ddpg", "ppo"])
def test_a_shared_policy_run_has_a_row_per_agent_and_episode(tmp_path, algo):
    run, done = train(config(algo), run=tmp_path / algo, progress=False, command="test")
    assert done == 2 and (run / "model.zip").is_file()
    table = rows(run / "episodes.csv")
    assert list(table[0]) == list(EPISODE_COLUMNS + MULTI_AGENT_COLUMNS)
    assert [(r["episode"], r["agent"]) for r in table] == [(e, a) for e in ("1", "2") for a in AGENTS]
    assert all(int(r["steps"]) == 100 for r in table)
    # the report averages the agents of an episode
    frame = read_episodes(run / "episodes.csv")
    assert list(frame.index) == [1, 2]
    first = [float(r["collisions"]) for r in table[:3]]
    assert frame.loc[1, "collisions"] == pytest.approx(sum(first) / 3)


def test_resume_extends_a_multi_agent_run_without_gaps(tmp_path):
    run, _ = train(config("ddpg"), run=tmp_path / "run", progress=False)
    run, done = train(LaneFreeConfig(), run=run, resume=True, episodes=3, progress=False)
    assert done == 3
    assert [(r["episode"], r["agent"]) for r in rows(run / "episodes.csv")] == [
        (e, a) for e in ("1", "2", "3") for a in AGENTS]


@pytest.mark.sumo
def test_evaluate_record_replay_rollout_and_mixed_autonomy(tmp_path):
    run, _ = train(config("ddpg", shield={"enabled": True}), run=tmp_path / "run", progress=False)
    out = evaluate(run, episodes=2, record=True, progress=False).out
    table = rows(out / "episodes.csv")
    assert [(r["episode"], r["agent"]) for r in table] == [(e, a) for e in ("1", "2") for a in AGENTS]
    assert json.loads((out / "recording.json").read_text())["agent_ids"] == AGENTS
    trajectory = rows(out / "trajectories" / "episode_0001.csv")
    assert {r["id"] for r in trajectory} >= set(AGENTS) and "shielded" in trajectory[0]
    shielded_ids = {r["id"] for r in trajectory if r["shielded"] == "1"}
    assert shielded_ids <= set(AGENTS)
    result = replay(run, episode=1, gui=False)
    assert result.steps == 100 and result.max_dx_m < 1e-3

    cfg = merge_config(LaneFreeConfig(), {"sim": {"episode_steps": 50}, "backend": "numpy",
                                          "scenario": {"agents": 4}, "shield": {"enabled": True}})
    summary = rollout(cfg, "random", 2, seed=3)
    assert summary["episodes"] == 2 and summary["agents"] == 4 and not summary["interrupted"]

    done = lanefree("mixed-autonomy", str(run), "--agents", "0,2", "--episodes", "2")
    assert done.returncode == 0, done.stderr
    measured = rows(run / "mixed_autonomy" / "episodes.csv")
    assert [(r["agents"], r["episode"]) for r in measured] == [("0", "1"), ("0", "2"), ("2", "1"), ("2", "2")]
    assert {r["vehicles"] for r in measured} == {"35"}  # the run's 70 veh/km on 500 m, kept fixed
    assert all(r["agent_collisions"] == "0" for r in measured if r["agents"] == "0")
    speeds = [float(r["mean_speed_mps"]) for r in measured]
    throughput = [float(r["throughput_veh_per_h"]) for r in measured]
    # flow = density × speed: 35 vehicles on 0.5 km at v m/s cross x = 0 about 70 · 3.6 v times an hour
    # (over the four 25-s episodes together: a single one counts only a dozen crossings)
    assert np.mean(throughput) == pytest.approx(70 * 3.6 * np.mean(speeds), rel=0.3)
    assert (run / "mixed_autonomy" / "mixed_autonomy.png").is_file()
    again = lanefree("mixed-autonomy", str(run), "--agents", "0", "--episodes", "1")
    assert again.returncode == 2 and "exists" in again.stderr
    for args, needle in ((("--agents", "0,0"), "distinct"), (("--agents", "0,40"), "cannot replace 40 of 35"),
                         (("--agents", "x"), "whole numbers")):
        bad = lanefree("mixed-autonomy", str(run), *args, "--overwrite")
        assert bad.returncode == 2 and needle in bad.stderr and bad.stderr.count("\n") == 1, bad.stderr


@pytest.mark.parametrize(("args", "needle"), [
    (("--agents", "0"), "--agents"),
    (("--agents", "3", "--envs", "2"), "use --envs 1 with it"),
    (("--agents", "3", "--overlap"), "--overlap was removed"),
    (("--agents", "65"), "scenario.agents"),
    (("--agents", "60", "--density", "300"), "does not fit"),
])
def test_bad_agent_counts_are_one_line_and_write_nothing(tmp_path, args, needle):
    res = lanefree("train", *args, "--out", str(tmp_path / "run"))
    assert res.returncode == 2 and needle in res.stderr and res.stderr.count("\n") == 1, res.stderr
    assert not (tmp_path / "run").exists()
