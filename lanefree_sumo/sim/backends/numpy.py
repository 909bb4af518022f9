"""The protocol every backend follows, and the SUMO-free backend of the open road (the ring's runs as the
batched core, :mod:`lanefree_sumo.sim.world`)."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.sim.dynamics import StepCommand, ballistic_distance
from lanefree_sumo.sim.network import (
    onramp_edge_lengths,
    onramp_edge_offsets,
    onramp_lane_centre,
)
from lanefree_sumo.sim.state import VehicleState


class Backend(Protocol):
    """Executes steps; positions and speeds are always read back from it."""

    def reset(self, state: VehicleState) -> None: ...

    def step(self, cmd: StepCommand) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def close(self) -> None: ...


class OpenRoadNumpyBackend:
    """SUMO-free execution on the on-ramp, kept the way SUMO keeps it — edge, lane, position on the edge,
    lateral offset from the lane's centre — and updated with SUMO's arithmetic (the ballistic distance,
    the hand-over to the next edge, a lane change once the centre leaves its lane, small lateral moves set
    rather than driven), so both backends give the same trajectories from the same commands.

    Vehicles enter with :meth:`add` (placed at once, they move in the next :meth:`step`) and leave with
    :meth:`remove`."""

    def __init__(self, cfg: LaneFreeConfig) -> None:
        self.cfg = cfg
        self._step = cfg.sim.step_s
        self._offsets = np.array(onramp_edge_offsets(cfg))
        self._lengths = np.array(onramp_edge_lengths(cfg))
        self._ramp_half = 0.5 * cfg.road.onramp.ramp_width_m
        self._lane_shift = 0.5 * cfg.road.onramp.ramp_width_m + 0.5 * cfg.road.width_m
        self._min_lateral_move = cfg.sim.sumo_min_lateral_speed_mps * cfg.sim.step_s
        self._edge = self._lane = np.zeros(0, dtype=int)
        self._pos = self._lat = self._vx = self._y = np.zeros(0)

    def _place(self, rows: VehicleState) -> tuple[np.ndarray, ...]:
        """(edge, lane, position, lateral offset) of vehicles at ``rows``' x and y."""
        edge = np.searchsorted(self._offsets, rows.x, side="right") - 1
        lane = np.where((edge == 1) & (rows.y < 0.0), 0, np.where(edge == 1, 1, 0))
        centre = np.array([onramp_lane_centre(self.cfg, int(e), int(k)) for e, k in zip(edge, lane)])
        return edge, lane, rows.x - self._offsets[edge], rows.y - centre

    def reset(self, state: VehicleState) -> None:
        self._edge, self._lane, self._pos, self._lat = self._place(state)
        self._vx, self._y = state.vx.copy(), state.y.copy()

    def add(self, rows: VehicleState) -> None:
        """Vehicles entering the road where ``rows`` place them (appended, in order)."""
        edge, lane, pos, lat = self._place(rows)
        self._edge, self._lane = np.concatenate([self._edge, edge]), np.concatenate([self._lane, lane])
        self._pos, self._lat = np.concatenate([self._pos, pos]), np.concatenate([self._lat, lat])
        self._vx, self._y = np.concatenate([self._vx, rows.vx]), np.concatenate([self._y, rows.y])

    def remove(self, keep: np.ndarray) -> None:
        """Keep only the vehicles where ``keep`` is True (the others left the road)."""
        for name in ("_edge", "_lane", "_pos", "_lat", "_vx", "_y"):
            setattr(self, name, getattr(self, name)[keep])

    def step(self, cmd: StepCommand) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        pos = self._pos + ballistic_distance(self._vx, cmd.vx_next, self._step)
        passed = (pos > self._lengths[self._edge]) & (self._edge < len(self._offsets) - 1)
        self._pos = np.where(passed, pos - self._lengths[self._edge], pos)
        leaving_merge = passed & (self._edge == 1)
        self._edge = np.where(passed, self._edge + 1, self._edge)
        self._lane = np.where(passed & ~leaving_merge, 1, np.where(leaving_merge, 0, self._lane))
        self._lane = np.where(self._edge == 1, self._lane, 0)
        centre = self._centres()
        tiny = np.abs(cmd.dy) < self._min_lateral_move
        moved = np.where(tiny, (self._y + cmd.dy) - centre, self._lat + cmd.dy)
        lat = np.where(cmd.dy == 0.0, self._lat, moved)
        onto_main = (self._edge == 1) & (self._lane == 0) & (lat > self._ramp_half)
        self._lat = np.where(onto_main, lat - self._lane_shift, lat)
        self._lane = np.where(onto_main, 1, self._lane)
        self._vx = cmd.vx_next.copy()
        x = self._offsets[self._edge] + self._pos
        self._y = self._centres() + self._lat
        return x, self._y.copy(), self._vx.copy()

    def _centres(self) -> np.ndarray:
        """y (m) of the centre of every vehicle's lane."""
        return np.where((self._edge == 1) & (self._lane == 0), -self._ramp_half, 0.5 * self.cfg.road.width_m)

    def close(self) -> None:
        pass
