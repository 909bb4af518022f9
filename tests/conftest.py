"""Shared test helpers: the repository root, the ``lanefree`` command in a subprocess, tiny
training configs, and a private Xvfb display for sumo-gui.

Markers (registered in pyproject.toml): ``sumo`` — runs the real SUMO; ``gui`` — sumo-gui under
Xvfb; ``slow`` — trains or runs long (seconds or more). ``make test-fast`` runs what has none.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from lanefree_sumo.experiments.analysis.markdown import TABLE_BEGIN, TABLE_END

ROOT = Path(__file__).resolve().parent.parent
"""The repository root (the CLI runs from here)."""

CLI_ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def lanefree(*args: str, cwd: Path | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run ``lanefree ARGS`` to completion in a subprocess; stdout/stderr captured as text."""
    return subprocess.run([sys.executable, "-m", "lanefree_sumo.cli", *args], capture_output=True, text=True,
                          cwd=cwd or ROOT, timeout=timeout, env=CLI_ENV)


def _default_sigint() -> None:
    """In the child: Ctrl-C as a terminal gives it, also when the suite itself runs with SIGINT ignored (a
    background job inherits SIG_IGN, and Python then installs no KeyboardInterrupt handler)."""
    signal.signal(signal.SIGINT, signal.default_int_handler)


def lanefree_popen(*args: str, **kwargs) -> subprocess.Popen:
    """Start ``lanefree ARGS`` in the background (to interrupt it)."""
    return subprocess.Popen([sys.executable, "-m", "lanefree_sumo.cli", *args], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=CLI_ENV,
                            preexec_fn=_default_sigint, **kwargs)


def wait_for(condition, proc: subprocess.Popen, what: str = "the state", limit_s: float = 300) -> None:
    """Wait for a state (``condition()`` true), not a time; fail at once if ``proc`` ends first, and after
    ``limit_s`` only as a safety net against a hung process."""
    deadline = time.monotonic() + limit_s
    while not condition():
        assert proc.poll() is None, (f"the process ended before {what}", proc.communicate())
        assert time.monotonic() < deadline, f"no {what} within {limit_s:g} s"
        time.sleep(0.05)


TINY_TRAINING = {
    "sim": {"episode_steps": 100},
    "train": {
        "episodes": 2, "checkpoint_every_episodes": 1,
        "actor_critic": {"learning_starts_steps": 50, "buffer_size": 1000, "ppo_n_steps": 100},
        "dqn": {"learning_starts_steps": 50, "buffer_size": 1000, "target_update_steps": 50},
    },
}
"""Config overrides for a 2-episode run of 100 steps that still learns."""


@pytest.fixture(scope="session")
def display() -> Iterator[str]:
    """A private Xvfb server for sumo-gui; the tests need it, so a missing Xvfb is a failure
    (``make test`` installs it through ``make system-deps``). Xvfb picks a free display number itself and
    writes it to a pipe once it accepts connections (``-displayfd``): parallel test workers never race
    for one number, and the fixture waits for that state, not for a time."""
    xvfb = shutil.which("Xvfb")
    assert xvfb, "Xvfb is not installed: run 'make system-deps' (make test does)"
    read_end, write_end = os.pipe()
    proc = subprocess.Popen([xvfb, "-displayfd", str(write_end), "-screen", "0", "1280x1024x24", "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, pass_fds=(write_end,))
    os.close(write_end)
    with os.fdopen(read_end) as announced:
        number = announced.readline().strip()  # "" if Xvfb ended without a display
    assert number.isdigit(), f"Xvfb did not start (exit code {proc.poll()})"
    old = os.environ.get("DISPLAY")
    os.environ["DISPLAY"] = f":{number}"
    yield f":{number}"
    if old is None:
        os.environ.pop("DISPLAY", None)
    else:
        os.environ["DISPLAY"] = old
    proc.terminate()
    proc.wait(timeout=10)


@pytest.fixture(scope="session", autouse=True)
def _sb3_logs_in_the_test_tmp(tmp_path_factory) -> Iterator[None]:
    """SB3 makes a log folder in /tmp for every model without a log dir; keep them in pytest's tmp."""
    old = os.environ.get("SB3_LOGDIR")
    os.environ["SB3_LOGDIR"] = str(tmp_path_factory.mktemp("sb3-logs"))
    yield
    if old is None:
        os.environ.pop("SB3_LOGDIR", None)
    else:
        os.environ["SB3_LOGDIR"] = old


@pytest.fixture(scope="module")
def one_torch_thread() -> Iterator[None]:
    """Tiny networks: one intra-op thread is much faster (and avoids contention on shared CPUs)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def fenced_rows(text: str) -> list[str]:
    """The table lines between the markers of ``text`` (exactly one fenced table expected)."""
    lines = text.splitlines()
    assert lines.count(TABLE_BEGIN) == 1 and lines.count(TABLE_END) == 1
    inside = lines[lines.index(TABLE_BEGIN) + 1:lines.index(TABLE_END)]
    return [line for line in inside if line]
