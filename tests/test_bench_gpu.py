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
    res = subprocess.run([sys.executable, "-m", "lanefree_sumo.tools.bench", "--gpu", "--device", "cpu",
                          "--env-sizes", "1,3", "--train-sizes", "1,2", "--env-steps", "3", "--train-steps", "2"],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert re.match(r"device: cpu — .+; torch \S+; CUDA \S+", lines[0])
    rows = [re.fullmatch(r"\| (env|train) \| (\d+) \| (\d+) \| ([\d.]+) \|", line) for line in lines]
    measured = [(m[1], int(m[2]), int(m[3]), float(m[4])) for m in rows if m]
    assert [(section, k) for section, k, _, _ in measured] == [("env", 1), ("env", 3), ("train", 1), ("train", 2)]
    assert all(rate > 0 for *_, rate in measured) and [s for _, _, s, _ in measured] == [3, 3, 2, 2]
    grid = next(line for line in lines if line.startswith("projected grid:"))
    minutes = float(re.search(r": ([\d.]+) min$", grid)[1])  # type: ignore[index]
    train_2 = measured[3][3]
    assert minutes == pytest.approx(75 * 625 * 800 / train_2 / 60, rel=0.1)  # 150 runs in batches of 2 (rate rounded)


def test_the_gpu_bench_without_a_gpu_is_one_line():
    pytest.importorskip("torch")
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    res = subprocess.run([sys.executable, "-m", "lanefree_sumo.tools.bench", "--gpu"], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode != 0 and len(res.stderr.strip().splitlines()) == 1 and "cuda" in res.stderr
