"""What every training session shares, SB3's loop and the batch alike: the provenance a run records
(:func:`versions`), the Ctrl-C/SIGTERM catcher (:class:`Stop`), a new run folder (:func:`new_run_folder`) and the
check of a run's episode rows before it continues (:func:`check_episode_rows`)."""

from __future__ import annotations

import contextlib
import itertools
import platform
import signal
import subprocess
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.errors import RunError
from lanefree_sumo.experiments.storage.episodes import EpisodeLog
from lanefree_sumo.experiments.storage.rundir import RunDir
from lanefree_sumo.sim.road import road_kind

# -- provenance ----------------------------------------------------------------------------------

def numpy_simd() -> str:
    """The SIMD kernel tiers numpy runs on (its baseline and the dispatched ones in use, as
    ``numpy.show_runtime`` lists them), e.g. ``X86_V2 X86_V3``; ``unknown`` if numpy does not say."""
    try:
        from numpy._core._multiarray_umath import (
            __cpu_baseline__,
            __cpu_dispatch__,
            __cpu_features__,
        )
    except ImportError:
        return "unknown"
    return " ".join([*__cpu_baseline__, *(f for f in __cpu_dispatch__ if __cpu_features__.get(f))])


def cpu_model() -> str:
    """The processor's model name (``/proc/cpuinfo``; elsewhere what :mod:`platform` says), e.g. ``AMD EPYC 9B14``:
    torch's BLAS picks its code paths per CPU model and vendor, so a run's later episodes repeat bit for bit only
    on a like CPU (docs/training.md)."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine() or "unknown"


def versions() -> dict[str, str]:
    """Versions of everything that shapes a result, with the SIMD kernels numpy and torch run on (they round
    differently from one CPU generation to the next: :mod:`lanefree_sumo.numerics`) and the CPU's model."""
    import gymnasium
    import stable_baselines3
    import torch

    try:  # a machine that trains on the numpy simulation or a GPU may have no SUMO
        from lanefree_sumo.sim.backends.sumo import sumo_version

        sumo = sumo_version()
    except ImportError:
        sumo = "not installed"
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=False,
            cwd=Path(__file__).resolve().parent,
        ).stdout.strip()
    except OSError:
        commit = ""
    from importlib.metadata import PackageNotFoundError, version

    try:
        package = version("lanefree_sumo")
    except PackageNotFoundError:  # run from a source tree on PYTHONPATH
        package = "not installed (source tree)"

    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "stable_baselines3": stable_baselines3.__version__,
        "gymnasium": gymnasium.__version__,
        "numpy": np.__version__,
        "numpy_simd": numpy_simd(),
        "torch_cpu": torch.backends.cpu.get_cpu_capability(),
        "cpu": cpu_model(),
        "sumo": sumo,
        "lanefree_sumo": package,
        "git_commit": commit or "unknown",
    }


# -- signals, run folders, episode rows --------------------------------------------------------------

class Stop:
    """Set by SIGINT/SIGTERM; the callback ends learning at the next step."""

    def __init__(self) -> None:
        self.requested = False
        self.signal_name = ""

    def __call__(self, signum: int, _frame: Any) -> None:
        self.requested = True
        self.signal_name = signal.Signals(signum).name


def run_name(cfg: LaneFreeConfig) -> str:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    agents = f"_k{cfg.scenario.agents}" if cfg.scenario.agents > 1 else ""
    tag = road_kind(cfg).tag
    road = f"_{tag}" if tag else ""
    return (f"{stamp}_{cfg.train.algo}_{cfg.reward.preset}{road}_d{cfg.scenario.density_veh_per_km:g}{agents}"
            f"_s{cfg.seed}{'_shield' if cfg.shield.enabled else ''}")


def new_run_folder(cfg: LaneFreeConfig, run: Path | None, restart: bool = False) -> Path:
    """Create the run folder atomically: ``run`` (refused if it holds anything but a new run that never reached
    its first checkpoint, :meth:`RunDir.never_checkpointed`, which the caller clears under the writer lock; with
    ``restart``, a run of a batch that cannot go on, which the caller clears too), else a
    fresh ``runs/<date-time>_...`` (``-2``, ``-3``, … when two runs start in the same second)."""
    if run is not None:
        if run.exists() and (not run.is_dir() or any(run.iterdir())) and not restart \
                and not RunDir(run).never_checkpointed():
            raise RunError(f"run folder {run} exists; resume it with --resume {run} or choose another --out")
        run.mkdir(parents=True, exist_ok=True)
        return run
    base = Path("runs") / run_name(cfg)
    for k in itertools.count(1):
        candidate = base if k == 1 else base.with_name(f"{base.name}-{k}")
        try:
            candidate.mkdir(parents=True)
            return candidate
        except FileExistsError:
            continue
    raise AssertionError("unreachable")


def check_episode_rows(folder: RunDir, done: int, agents: int) -> None:
    """Refuse to continue a run whose ``episodes.csv`` lacks rows of the checkpoint's episodes (or holds one
    twice): continuing would hide the gap in every report."""
    missing = EpisodeLog.missing(folder.episodes, done, agents)
    if missing:
        span = f"{missing[0]}" if len(missing) == 1 else f"{missing[0]}–{missing[-1]} ({len(missing)} episodes)"
        raise RunError(f"{folder.episodes} does not hold episode {span} of the {done} its newest checkpoint "
                       "has learned (once each); restore the file, or start the run again")
