"""Golden files: the single-run ``episodes.csv`` of every batchable algorithm on a small config, frozen, so that
a rewrite of the trainers (one trainer for K ≥ 1) must reproduce them, and batched run k equals them too.

The learners' float32 products are torch's CPU kernels, whose last bits depend on the CPU (measured: the same
code on an Intel Xeon and on an AMD EPYC, both AVX-512, agrees to 4e-6 relative after three DDPG episodes, and
PER's sampling there takes another path): each CPU has its own set, ``tests/golden/<cpu>-<torch's capability>/``
(:func:`kernels`), frozen from one program, reproduced bit for bit on that CPU.

``LANEFREE_WRITE_GOLDEN=1 pytest tests/experiments/test_golden_runs.py`` writes this CPU's set (only on purpose:
a new CPU's set from a commit that reproduces another CPU's set there; say why in the commit)."""

from __future__ import annotations

import csv
import os
import re
from pathlib import Path

import pytest

from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.experiments.runners.batch import train_batch
from lanefree_sumo.experiments.runners.session import versions
from lanefree_sumo.experiments.runners.train import train

pytestmark = [pytest.mark.slow]



def kernels() -> str:
    """This machine's CPU and torch's kernel level (the run's ``versions.json``) as a folder name, e.g.
    ``amd-epyc-avx512``."""
    found = versions()
    return re.sub(r"[^a-z0-9]+", "-", f"{found['cpu']} {found['torch_cpu']}".lower()).strip("-")


GOLDEN = Path(__file__).resolve().parents[1] / "golden" / kernels()
WRITE = os.environ.get("LANEFREE_WRITE_GOLDEN") == "1"


def golden_file(name: str) -> Path:
    """This CPU's golden file ``name``; a missing set fails, saying how to freeze it."""
    path = GOLDEN / name
    if not WRITE and not path.is_file():
        pytest.fail(f"no golden file {path.name} for this CPU ({GOLDEN.name}) under tests/golden/: freeze this CPU's "
                    "set with LANEFREE_WRITE_GOLDEN=1 from a commit that reproduces another CPU's set on its CPU")
    return path


def freeze(run_csv: Path, golden: Path) -> None:
    """With ``LANEFREE_WRITE_GOLDEN=1``: write ``run_csv`` as this CPU's golden file."""
    if WRITE:
        golden.parent.mkdir(parents=True, exist_ok=True)
        golden.write_text(run_csv.read_text())
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
    golden = golden_file(f"{algo}_episodes.csv")
    freeze(run / "episodes.csv", golden)
    assert rows(run / "episodes.csv", golden) == rows(golden)


@pytest.mark.sumo
@pytest.mark.parametrize(("algo", "backend"), [("ddpg", "libsumo"), ("per", "libsumo"), ("td3", "traci")])
def test_a_run_inside_sumo_reproduces_the_golden_episodes(tmp_path, algo, backend):
    """A single run inside SUMO trains in the one trainer too (a batch of one, its environment LaneFree-v0 on that
    backend) and gives the numpy run's golden episodes, bit for bit."""
    cfg = merge_config(config(algo), {"train": {"backend": backend}})
    run, done = train(cfg, run=tmp_path / "run", progress=False)
    assert done == 3 and (run / "batch.json").is_file()
    golden = golden_file(f"{algo}_episodes.csv")
    assert rows(run / "episodes.csv", golden) == rows(golden)


@pytest.mark.parametrize("algo", ["ddpg", "dqn", "per"])
def test_batched_run_k_reproduces_the_golden_single_run(tmp_path, algo):
    runs = train_batch([config(algo, seed=7), config(algo, seed=3)], tmp_path / "batch", progress=False,
                       command="test")
    golden = golden_file(f"{algo}_episodes.csv")
    assert rows(runs[1][0] / "episodes.csv", golden) == rows(golden)


CHOICES = {"kerasrl": {"train": {"profile": "kerasrl", "actor_critic": {"learning_starts_steps": 40},
                                  "dqn": {"learning_starts_steps": 40}}},
           "kerasrl_penalty": {"train": {"profile": "kerasrl", "actor_critic": {"learning_starts_steps": 40,
                                                                                "pre_tanh_penalty": 0.05}}}}
"""The learner choices SB3's classes lack (Keras-RL's profile: DDPG acting from the first step; the DQN family's
½·δ² loss without a gradient clip, importance-weighted under PER; DDPG's pre-tanh penalty): frozen from SB3's
loop with the project's subclasses of SB3's DDPG and DQN, before those stopped training."""


@pytest.mark.parametrize(("algo", "choice"), [("ddpg", "kerasrl_penalty"), ("dqn", "kerasrl"), ("per", "kerasrl"),
                                              ("dueling", "kerasrl")])
def test_a_run_with_the_learner_choices_reproduces_its_golden_episodes(tmp_path, algo, choice):
    run, done = train(merge_config(config(algo), CHOICES[choice]), run=tmp_path / "run", progress=False)
    assert done == 3
    golden = golden_file(f"{algo}_{choice}_episodes.csv")
    freeze(run / "episodes.csv", golden)
    assert rows(run / "episodes.csv", golden) == rows(golden)


SCENES = {"shield": {"shield": {"enabled": True}},
          "onramp": {"road": {"kind": "onramp"}, "scenario": {"density_veh_per_km": 40}}}
"""Single runs the ring's batched world does not hold: frozen from SB3's loop, which trained them before the one
trainer did."""


@pytest.mark.parametrize(("algo", "scene"), [("ddpg", "shield"), ("ddpg", "onramp"), ("dqn", "shield"),
                                             ("dqn", "onramp")])
def test_a_single_run_off_the_ring_or_shielded_reproduces_its_golden_episodes(tmp_path, algo, scene):
    run, done = train(merge_config(config(algo), SCENES[scene]), run=tmp_path / "run", progress=False)
    assert done == 3
    golden = golden_file(f"{algo}_{scene}_episodes.csv")
    freeze(run / "episodes.csv", golden)
    assert rows(run / "episodes.csv", golden) == rows(golden)


SHARED = {"agents2": {"scenario": {"agents": 2}}, "envs2": {"train": {"envs": 2}}}
"""Single runs of several learning vehicles (one shared policy) or several environments (one process each): SB3's
loop trains them; frozen as the guard before the one trainer takes them over."""


@pytest.mark.parametrize(("algo", "scene"), [("ddpg", "agents2"), ("dqn", "agents2"), ("td3", "agents2"),
                                             ("ddqn", "agents2"), ("dueling", "agents2"), ("per", "agents2"),
                                             ("ddpg", "envs2"), ("dqn", "envs2")])
def test_a_single_run_of_several_agents_or_environments_reproduces_its_golden_episodes(tmp_path, algo, scene):
    run, done = train(merge_config(config(algo), SHARED[scene]), run=tmp_path / "run", progress=False)
    assert done >= 3
    golden = golden_file(f"{algo}_{scene}_episodes.csv")
    freeze(run / "episodes.csv", golden)
    assert rows(run / "episodes.csv", golden) == rows(golden)


@pytest.mark.sumo
@pytest.mark.parametrize(("algo", "backend"), [("ddpg", "libsumo"), ("dqn", "traci")])
def test_a_run_of_several_agents_inside_sumo_reproduces_the_golden_episodes(tmp_path, algo, backend):
    """Two agents of one SUMO simulation train in the one trainer too (a batch of one whose run has two slots, the
    multi-agent env on that backend) and give the numpy run's golden episodes, frozen from SB3's loop."""
    cfg = merge_config(merge_config(config(algo), SHARED["agents2"]), {"train": {"backend": backend}})
    run, done = train(cfg, run=tmp_path / "run", progress=False)
    assert done == 3 and (run / "batch.json").is_file()
    golden = golden_file(f"{algo}_agents2_episodes.csv")
    assert rows(run / "episodes.csv", golden) == rows(golden)


@pytest.mark.parametrize(("algo", "scene"), [("ddpg", "agents2"), ("dqn", "envs2")])
def test_batched_run_k_of_several_agents_or_environments_reproduces_the_golden_single_run(tmp_path, algo, scene):
    """Two runs of two slots each (two agents of one simulation, or two environments) as one batch: run k's
    episodes are its single run's, frozen from SB3's loop."""
    runs = train_batch([merge_config(config(algo, seed=7), SHARED[scene]),
                        merge_config(config(algo, seed=3), SHARED[scene])], tmp_path / "batch", progress=False,
                       command="test")
    golden = golden_file(f"{algo}_{scene}_episodes.csv")
    assert rows(runs[1][0] / "episodes.csv", golden) == rows(golden)
    assert rows(runs[0][0] / "episodes.csv", golden) != rows(golden)  # run 0 is another seed's


@pytest.mark.parametrize("scene", list(SCENES))
def test_batched_run_k_with_the_shield_or_on_the_on_ramp_reproduces_the_golden_single_run(tmp_path, scene):
    runs = train_batch([merge_config(config("ddpg", seed=7), SCENES[scene]),
                        merge_config(config("ddpg", seed=3), SCENES[scene])], tmp_path / "batch", progress=False,
                       command="test")
    golden = golden_file(f"ddpg_{scene}_episodes.csv")
    assert rows(runs[1][0] / "episodes.csv", golden) == rows(golden)
