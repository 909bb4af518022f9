"""Per-step trajectory files: one CSV row per vehicle and step.

Columns: ``t`` (s, end of the step; 0 = the initial state), ``id`` (SUMO vehicle id; the agent
is ``agent``), ``x`` (m along the ring's centre line, [0, L)), ``y`` (m from the right road
edge), ``vx``, ``vy`` (m/s), ``ax``, ``ay`` (m/s², realised during the step ending at t), and
with ``overlap=True`` a column ``overlap`` (1 when the vehicle's body overlaps another's at t),
with ``shield=True`` a column ``shielded`` (1 in an agent's row when the safety shield changed
that agent's action in the step ending at t).
On an open road (the on-ramp; x from the main road's upstream end, y < 0 on the ramp) vehicles come
and go: a vehicle's rows run from its entry — a row at the start of the step it entered in, as it was
placed, with zero accelerations — to the last step before it left.
Values are rounded to 1 µm, 1 µm/s; the file is flushed every simulated second.
"""

from __future__ import annotations

import csv
from collections.abc import Collection
from pathlib import Path

import numpy as np

from lanefree_sumo.sim.simulation import StepResult
from lanefree_sumo.sim.state import VehicleState

COLUMNS = ("t", "id", "x", "y", "vx", "vy", "ax", "ay")
DECIMALS = 6


class TrajectoryWriter:
    """Appends the state of every vehicle after each step to a CSV file.

    With ``vehicles`` a path, :meth:`close` writes there the fixed attributes of every vehicle that
    appeared in a row — id, length, width (m), v_desired (m/s) — in the order they first appeared
    (on an open road vehicles come and go; on the ring they are the initial state's)."""

    def __init__(self, path: Path, step_s: float, overlap: bool = False, shield: bool = False,
                 vehicles: Path | None = None) -> None:
        self._vehicles_path = vehicles
        self._attributes: dict[str, tuple[float, float, float]] = {}
        self._fh = open(path, "w", newline="")
        self._writer = csv.writer(self._fh)
        self._overlap = overlap
        self._shield = shield
        self._writer.writerow(COLUMNS + (("overlap",) if overlap else ()) + (("shielded",) if shield else ()))
        self._flush_every = max(1, int(round(1.0 / step_s)))
        self._step_s = step_s
        self._steps = 0

    def write(self, step: int, state: VehicleState, result: StepResult | None,
              shielded: Collection[str] = ()) -> None:
        """Rows for the state after ``step`` steps (``result`` None for the initial state);
        ``shielded``: the ids of the agents whose action the shield changed in this step. Vehicles that
        entered the road at the start of the step (an open road) get a row at the step's start too, as they
        were placed, before the rows of its end; vehicles taken off the road after it keep their row of it."""
        if result is not None and result.entered is not None:
            self._rows_of(step - 1, result.entered, None, None, None, ())
        if result is None:
            self._rows_of(step, state, None, None, None, shielded)
        else:
            self._rows_of(step, state, result.ax, result.ay, np.asarray(result.overlap.any(axis=1)), shielded)
        if result is not None and result.departed is not None:
            gone = result.departed
            self._rows_of(step, gone.state, gone.ax, gone.ay, gone.overlapping, shielded)
        self._steps += 1
        if self._steps % self._flush_every == 0:
            self._fh.flush()

    def _rows_of(self, step: int, state: VehicleState, ax: np.ndarray | None, ay: np.ndarray | None,
                 overlapping: np.ndarray | None, shielded: Collection[str]) -> None:
        """One row per vehicle of ``state`` at the end of ``step`` (accelerations and overlap None: zeros)."""
        n = state.n
        zeros = np.zeros(n)
        if any(len(values) != n for values in (ax, ay, overlapping) if values is not None):
            raise ValueError(f"the step's values do not have one entry per vehicle ({n}) of the state")
        cols = [
            [round(step * self._step_s, DECIMALS)] * n, state.ids,
            *(np.round(v, DECIMALS) for v in (state.x, state.y, state.vx, state.vy,
                                               zeros if ax is None else ax, zeros if ay is None else ay)),
        ]
        if self._overlap:
            cols.append(np.zeros(n, dtype=int) if overlapping is None else overlapping.astype(int))
        if self._shield:
            cols.append([int(vid in shielded) for vid in state.ids])
        self._writer.writerows(zip(*cols))
        if self._vehicles_path is not None and any(vid not in self._attributes for vid in state.ids):
            for i, vid in enumerate(state.ids):
                self._attributes.setdefault(vid, (float(state.length[i]), float(state.width[i]),
                                                  round(float(state.v_desired[i]), 9)))

    def close(self) -> None:
        """Close the trajectory file and write the vehicles' attributes (when asked for)."""
        self._fh.close()
        if self._vehicles_path is not None:
            with open(self._vehicles_path, "w", newline="") as fh:
                writer = csv.writer(fh)
                writer.writerow(("id", "length", "width", "v_desired"))
                writer.writerows((vid, *attrs) for vid, attrs in self._attributes.items())
