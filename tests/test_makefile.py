"""The Makefile's shortcuts pass what their variables say (``make -n``: the commands, nothing run)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="needs make")


def make_n(*args: str) -> str:
    """The last command ``make -n ARGS`` would run (the target's own, after the venv's)."""
    res = subprocess.run(["make", "-n", "-s", *args], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    return res.stdout.strip().splitlines()[-1]


def test_replay_runs_under_xvfb_without_a_display_and_on_the_display_with_one():
    assert make_n("replay", "RUN=runs/r", "DISPLAY=").startswith("xvfb-run -a ")
    assert not make_n("replay", "RUN=runs/r", "DISPLAY=:0").startswith("xvfb-run")


def test_evaluate_passes_overwrite_only_when_asked():
    assert make_n("evaluate", "RUN=runs/r", "OVERWRITE=1").endswith("evaluate runs/r --record --overwrite")
    assert "--overwrite" not in make_n("evaluate", "RUN=runs/r")
