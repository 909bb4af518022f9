"""Batched training on a torch device: the same functions as the numpy batch (CPU here; CI has no GPU), and the
one-line error for a GPU that is not there."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from lanefree_sumo.cli import main
from lanefree_sumo.config import LaneFreeConfig, merge_config
from lanefree_sumo.experiments.runners.batch import train_batch
from lanefree_sumo.sim.xp_torch import numpy_transcendentals
from tests.experiments.test_batch import rows, small

pytestmark = [pytest.mark.slow]


def on_torch(cfgs: list[LaneFreeConfig]) -> list[LaneFreeConfig]:
    """The same runs on ``train.device = torch-cpu`` (the GPU's torch program, here on the CPU)."""
    return [merge_config(c, {"train": {"device": "torch-cpu"}}) for c in cfgs]


@pytest.mark.parametrize("algo", ["ddpg", "dqn"])
def test_a_batch_on_a_torch_device_equals_the_numpy_batch(tmp_path: Path, algo: str) -> None:
    """Simulation, observations, rewards and books as torch tensors on the device, the learners there too: with
    numpy's transcendental functions (tests/sim/test_world_torch.py) every episode row equals the numpy batch's."""
    cfgs = [small(algo, 0), small(algo, 1, density=120.0)]
    reference = train_batch(cfgs, tmp_path / "numpy", progress=False, command="test")
    with numpy_transcendentals():
        on_device = train_batch(on_torch(cfgs), tmp_path / "torch", progress=False, command="test")
    assert [done for _, done in on_device] == [3, 3]
    for (mine, _), (theirs, _) in zip(on_device, reference):
        got, want = rows(mine / "episodes.csv"), rows(theirs / "episodes.csv")
        assert len(got) == 3 and got == want
        assert (mine / "model.zip").is_file()


def test_a_batch_on_a_torch_device_with_torchs_own_functions_trains(tmp_path: Path) -> None:
    """With torch's own sqrt/erfc/pow (what a GPU computes: a few ulp apart per step) the first episode's
    figures agree with the numpy batch's to 1e-6 relative (the learning starts at step 41 of 60, so the
    traffic has not yet parted); every run finishes."""
    cfgs = [small("ddpg", 0), small("ddpg", 1, density=120.0)]
    reference = train_batch(cfgs, tmp_path / "numpy", progress=False, command="test")
    on_device = train_batch(on_torch(cfgs), tmp_path / "torch", progress=False, command="test")
    assert [done for _, done in on_device] == [3, 3]
    for (mine, _), (theirs, _) in zip(on_device, reference):
        got, want = rows(mine / "episodes.csv")[0], rows(theirs / "episodes.csv")[0]
        for column in ("return", "mean_speed_mps", "speed_dev_mps", "mean_c_x", "mean_c_f"):
            assert float(got[column]) == pytest.approx(float(want[column]), rel=1e-6), column


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA GPU")
def test_cuda_without_a_gpu_is_one_line_and_a_nonzero_exit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) \
        -> None:
    code = main(["train", "--seeds", "0-1", "--device", "cuda", "--out", str(tmp_path / "b")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "cuda" in err and "--device cpu" in err
    assert not (tmp_path / "b").exists()  # refused before anything was written
    code = main(["train", "--seed", "0", "--device", "cuda", "--out", str(tmp_path / "one")])  # a batch of one
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "cuda" in err and "--device cpu" in err
    assert not (tmp_path / "one").exists()
    code = main(["train", "--algo", "sac", "--device", "cuda", "--out", str(tmp_path / "sac")])  # SB3's loop
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and "does not support the sac algorithm" in err
    assert not (tmp_path / "sac").exists()



@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA GPU")
def test_a_sweep_on_cuda_without_a_gpu_is_one_line_before_anything_is_written(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["sweep", "table5", "--seeds", "1", "--episodes", "1", "--set", "train.device=cuda",
                 "--out", str(tmp_path / "sweep")])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1 and ("no CUDA GPU" in err or "CPU-only build" in err)
    assert not (tmp_path / "sweep").exists()
