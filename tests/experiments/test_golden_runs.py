"""Golden files: the single-run ``episodes.csv`` of every batchable algorithm on a small config, frozen, so that
a rewrite of the trainers (one trainer for K ≥ 1) must reproduce them, and batched run k equals them too.

``LANEFREE_WRITE_GOLDEN=1 pytest tests/experiments/test_golden_runs.py`` rewrites them (only on purpose: say why
in the commit)."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import pytest

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.experiments.runners.batch import train_batch
from lanefree_sumo.experiments.runners.train import train

pytestmark = [pytest.mark.slow]

GOLDEN = Path(__file__).resolve().parents[1] / "golden"
SMALL = {"sim": {"episode_steps": 50}, "scenario": {"density_veh_per_km": 90},
         "train": {"episodes": 3, "checkpoint_every_episodes": 1,
                   "actor_critic": {"learning_starts_steps": 40, "buffer_size": 500},
                   "dqn": {"learning_starts_steps": 40, "buffer_size": 500, "target_update_steps": 30}}}
ALGORITHMS = ("ddpg", "td3", "dqn", "ddqn", "dueling", "per")


def config(algo: str, seed: int = 3) -> LaneFreeConfig:
    return merge_config(LaneFreeConfig(), {**SMALL, "seed": seed, "train": {**SMALL["train"], "algo": algo}})


def rows(path: Path, columns: Path | None = None) -> list[dict[str, str]]:
    """The rows of an episodes.csv but wall time; ``columns``: only the columns of that file (a golden file: the
    columns it froze must be reproduced, a metric added later may stand beside them)."""
    with open(path, newline="") as fh:
        table = list(csv.DictReader(fh))
    keep = None
    if columns is not None:
        with open(columns, newline="") as fh:
            keep = set(next(csv.reader(fh)))
    return [{k: v for k, v in row.items() if k != "wall_s" and (keep is None or k in keep)} for row in table]


@pytest.mark.parametrize("algo", ALGORITHMS)
def test_a_single_run_reproduces_its_golden_episodes(tmp_path, algo):
    run, done = train(config(algo), run=tmp_path / "run", progress=False)
    assert done == 3
    golden = GOLDEN / f"{algo}_episodes.csv"
    if os.environ.get("LANEFREE_WRITE_GOLDEN") == "1":
        golden.write_text((run / "episodes.csv").read_text())
    assert rows(run / "episodes.csv", golden) == rows(golden)


@pytest.mark.parametrize("algo", ["ddpg", "dqn", "per"])
def test_batched_run_k_reproduces_the_golden_single_run(tmp_path, algo):
    runs = train_batch([config(algo, seed=7), config(algo, seed=3)], tmp_path / "batch", progress=False,
                       command="test")
    assert rows(runs[1][0] / "episodes.csv", GOLDEN / f"{algo}_episodes.csv") == rows(GOLDEN / f"{algo}_episodes.csv")


SCENES = {"shield": {"shield": {"enabled": True}},
          "onramp": {"road": {"kind": "onramp"}, "scenario": {"density_veh_per_km": 40}}}
"""Single runs the ring's batched world does not hold: frozen from SB3's loop, which trained them before the one
trainer did."""


@pytest.mark.parametrize(("algo", "scene"), [("ddpg", "shield"), ("ddpg", "onramp"), ("dqn", "shield"),
                                             ("dqn", "onramp")])
def test_a_single_run_off_the_ring_or_shielded_reproduces_its_golden_episodes(tmp_path, algo, scene):
    run, done = train(merge_config(config(algo), SCENES[scene]), run=tmp_path / "run", progress=False)
    assert done == 3
    golden = GOLDEN / f"{algo}_{scene}_episodes.csv"
    if os.environ.get("LANEFREE_WRITE_GOLDEN") == "1":
        golden.write_text((run / "episodes.csv").read_text())
    assert rows(run / "episodes.csv", golden) == rows(golden)


@pytest.mark.parametrize("scene", list(SCENES))
def test_batched_run_k_with_the_shield_or_on_the_on_ramp_reproduces_the_golden_single_run(tmp_path, scene):
    runs = train_batch([merge_config(config("ddpg", seed=7), SCENES[scene]),
                        merge_config(config("ddpg", seed=3), SCENES[scene])], tmp_path / "batch", progress=False,
                       command="test")
    golden = GOLDEN / f"ddpg_{scene}_episodes.csv"
    assert rows(runs[1][0] / "episodes.csv", golden) == rows(golden)
