"""``make bench-gpu`` runs on the CPU too: tiny sizes, every printed row parses."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

pytestmark = [pytest.mark.slow]


def test_the_gpu_bench_runs_on_the_cpu_and_prints_rows_that_parse():
    res = subprocess.run([sys.executable, "-m", "lanefree_sumo.tools.bench", "--gpu", "--device", "torch-cpu",
                          "--env-sizes", "1,3", "--train-sizes", "1,2", "--dqn-sizes", "1,2", "--per-sizes", "2",
                          "--env-steps", "3", "--train-steps", "2"],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert re.match(r"device: cpu — .+; torch \S+; CUDA \S+", lines[0])
    assert lines[1].startswith("host reads inside an iteration: not checked")
    assert lines[2] == "compiled ring step against the step as written: not compiled on this device"
    env = [re.fullmatch(r"\| env \| (\d+) \| (\d+) \| ([\d.]+) \|", line) for line in lines]
    assert [(int(m[1]), int(m[2])) for m in env if m] == [(1, 3), (3, 3)] and all(float(m[3]) > 0 for m in env if m)
    train = [re.fullmatch(r"\| train \| (\w+) \| (\d+) \| (\d+) \| ([\d.]+) \| ([\d.]+) \|", line) for line in lines]
    measured = [(m[1], int(m[2]), int(m[3]), float(m[4]), float(m[5])) for m in train if m]
    assert [(algo, k, n) for algo, k, n, _, _ in measured] == [("ddpg", 1, 2), ("ddpg", 2, 2), ("dqn", 1, 2),
                                                               ("dqn", 2, 2), ("per", 2, 2)]
    # ms/iteration is 1000 / the rate before the rate was rounded to 0.1
    assert all(rate > 0.05 and 1000 / (rate + 0.05) - 0.01 <= ms <= 1000 / (rate - 0.05) + 0.01
               for *_, rate, ms in measured)
    single = next(line for line in lines if line.startswith("one 625-episode DDPG run"))
    minutes = float(re.search(r": ([\d.]+) min$", single)[1])  # type: ignore[index]
    assert minutes == pytest.approx(625 * 800 / measured[0][3] / 60, rel=0.1)
    assert any(line.startswith("projected grid: not measured") for line in lines)  # K = 110 and 10 not run here


def test_the_gpu_bench_without_a_gpu_is_one_line():
    pytest.importorskip("torch")
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    res = subprocess.run([sys.executable, "-m", "lanefree_sumo.tools.bench", "--gpu"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode != 0 and len(res.stderr.strip().splitlines()) == 1 and "cuda" in res.stderr


def test_the_drift_of_a_traced_step_is_zero_and_measured_along_the_ring():
    """The bench's drift line, with the step traced but not fused (``aot_eager``, the CPU's bit-for-bit trace):
    both gaps 0 after 1 and after 5 steps; and a gap across the ring's seam counts as the distance along it."""
    import torch

    from lanefree_sumo.sim.state import wrap
    from lanefree_sumo.tools.bench_gpu import compiled_drift

    gaps = wrap(torch.tensor([0.1, 250.0, 10.0], dtype=torch.float64)
                - torch.tensor([499.9, 0.0, 12.5], dtype=torch.float64), 500.0).abs()
    assert torch.allclose(gaps, torch.tensor([0.2, 250.0, 2.5], dtype=torch.float64))

    line = compiled_drift("torch-cpu", runs=2, steps=5, compile="aot_eager")
    assert line == ("aot_eager, K = 2: after 1 step(s) |Δx| ≤ 0.0e+00 m (along the ring), |Δvx| ≤ 0.0e+00 m/s; "
                    "after 5 step(s) |Δx| ≤ 0.0e+00 m (along the ring), |Δvx| ≤ 0.0e+00 m/s")
