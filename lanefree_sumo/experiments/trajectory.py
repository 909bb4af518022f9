"""Per-step trajectory files: one CSV row per vehicle and step.

Columns: ``t`` (s, end of the step; 0 = the initial state), ``id`` (SUMO vehicle id; the agent
is ``agent``), ``x`` (m along the ring's centre line, [0, L)), ``y`` (m from the right road
edge), ``vx``, ``vy`` (m/s), ``ax``, ``ay`` (m/s², realised during the step ending at t), and
with ``overlap=True`` a column ``overlap`` (1 when the vehicle's body overlaps another's at t),
with ``shield=True`` a column ``shielded`` (1 in an agent's row when the safety shield changed
that agent's action in the step ending at t).
Values are rounded to 1 µm, 1 µm/s; the file is flushed every simulated second.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from lanefree_sumo.sim.simulation import StepResult
from lanefree_sumo.sim.state import VehicleState

COLUMNS = ("t", "id", "x", "y", "vx", "vy", "ax", "ay")
DECIMALS = 6


def write_vehicles(path: Path, state: VehicleState) -> None:
    """The fixed attributes of a recording's vehicles: id, length, width (m), v_desired (m/s)."""
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(("id", "length", "width", "v_desired"))
        writer.writerows(zip(state.ids, state.length, state.width, np.round(state.v_desired, 9)))


class TrajectoryWriter:
    """Appends the state of every vehicle after each step to a CSV file."""

    def __init__(self, path: Path, step_s: float, overlap: bool = False, shield: bool = False) -> None:
        self._fh = open(path, "w", newline="")
        self._writer = csv.writer(self._fh)
        self._overlap = overlap
        self._shield = shield
        self._writer.writerow(COLUMNS + (("overlap",) if overlap else ()) + (("shielded",) if shield else ()))
        self._flush_every = max(1, int(round(1.0 / step_s)))
        self._step_s = step_s
        self._rows = 0

    def write(self, step: int, state: VehicleState, result: StepResult | None,
              shielded: bool | np.ndarray = False) -> None:
        """Rows for the state after ``step`` steps (``result`` None for the initial state);
        ``shielded``: the shield changed the agents' action in this step (one flag for every agent, or
        one per row of the state)."""
        n = state.n
        zeros = np.zeros(n)
        ax = zeros if result is None else result.ax
        ay = zeros if result is None else result.ay
        cols = [
            [round(step * self._step_s, DECIMALS)] * n, state.ids,
            *(np.round(v, DECIMALS) for v in (state.x, state.y, state.vx, state.vy, ax, ay)),
        ]
        if self._overlap:
            hit = np.zeros(n, dtype=int) if result is None else result.overlap.any(axis=1).astype(int)
            cols.append(hit)
        if self._shield:
            cols.append((~state.controlled & shielded).astype(int))
        self._writer.writerows(zip(*cols))
        self._rows += 1
        if self._rows % self._flush_every == 0:
            self._fh.flush()

    def close(self) -> None:
        self._fh.close()
