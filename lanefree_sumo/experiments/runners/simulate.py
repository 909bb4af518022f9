"""``lanefree simulate``: background traffic alone, written to an output folder.

Writes ``trajectory.csv`` (flushed every simulated second), ``summary.json``, ``config.yaml`` and
``command.txt`` (names in :mod:`lanefree_sumo.experiments.storage.rundir`).
"""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path
from typing import Any

from lanefree_sumo.config import LaneFreeConfig, SimulationConfig
from lanefree_sumo.errors import ConfigError
from lanefree_sumo.experiments.storage.rundir import (
    SIM_SUMMARY,
    SIM_TRAJECTORY,
    append_command,
    fresh_output,
    write_config,
)
from lanefree_sumo.experiments.storage.trajectory import TrajectoryWriter
from lanefree_sumo.sim.simulation import run_simulation
from lanefree_sumo.sim.spawn import check_fits

MAX_STEPS: int = next(f for f in fields(SimulationConfig) if f.name == "episode_steps").metadata["range"][1]
"""The most steps one simulation runs: the longest episode the config allows."""


def simulate(
    cfg: LaneFreeConfig,
    seconds: float,
    out: Path,
    command: str,
    overwrite: bool = False,
    write_trajectory: bool = True,
    progress: bool = False,
) -> dict[str, Any]:
    """Simulate ``seconds`` (s) of traffic into ``out``; return the summary (also in summary.json).
    Ctrl-C (and SIGTERM, which ``lanefree`` turns into Ctrl-C) stops early and keeps what was simulated,
    marked ``interrupted``."""
    most = MAX_STEPS * cfg.sim.step_s
    if not seconds <= most:
        raise ConfigError(f"--seconds {seconds:g} is longer than a simulation may run ({MAX_STEPS} steps of "
                          f"{cfg.sim.step_s:g} s, {most:g} s)")
    steps = int(round(seconds / cfg.sim.step_s))
    if steps < 1:
        raise ConfigError(f"--seconds {seconds:g} is shorter than one step of {cfg.sim.step_s:g} s")
    check_fits(cfg)  # before anything is written
    with fresh_output(out, overwrite, "simulate") as folder:
        append_command(folder, command)
        write_config(folder, cfg)
        writer = TrajectoryWriter(folder / SIM_TRAJECTORY, cfg.sim.step_s) if write_trajectory else None
        try:
            summary = run_simulation(cfg, steps, on_step=writer.write if writer else None, progress=progress)
        finally:
            if writer:
                writer.close()
        (folder / SIM_SUMMARY).write_text(json.dumps(summary, indent=2) + "\n")
    return summary
