"""The SUMO-free backend, and the protocol every backend follows."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from lanefree_sumo.config import LaneFreeConfig
from lanefree_sumo.sim.dynamics import StepCommand, ballistic_distance
from lanefree_sumo.sim.network import EDGES, edge_length, edge_to_ring, ring_to_edge
from lanefree_sumo.sim.state import VehicleState


class Backend(Protocol):
    """Executes steps; positions and speeds are always read back from it."""

    def reset(self, state: VehicleState) -> None: ...

    def step(self, cmd: StepCommand) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

    def close(self) -> None: ...


class NumpyBackend:
    """SUMO-free execution of the same commands.

    Positions are kept the way SUMO keeps them — edge index plus position on the edge, lateral
    offset from the lane centre — and updated with the same arithmetic (ballistic distance,
    edge hand-over, small lateral moves set rather than driven), so that both backends produce
    bit-identical trajectories from the same commands.
    """

    def __init__(self, cfg: LaneFreeConfig) -> None:
        self._length = cfg.road.length_m
        self._segment = edge_length(cfg.road.length_m)
        self._step = cfg.sim.step_s
        self._half_width = 0.5 * cfg.road.width_m
        self._min_lateral_move = cfg.sim.sumo_min_lateral_speed_mps * cfg.sim.step_s
        self._edge = np.zeros(0, dtype=int)
        self._pos = self._pos_lat = self._vx = self._y = np.zeros(0)

    def reset(self, state: VehicleState) -> None:
        self._edge, self._pos = ring_to_edge(state.x, self._length)
        self._pos_lat = state.y - self._half_width
        self._vx = state.vx.copy()
        self._y = state.y.copy()

    def step(self, cmd: StepCommand) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        pos = self._pos + ballistic_distance(self._vx, cmd.vx_next, self._step)
        passed = pos > self._segment
        self._pos = np.where(passed, pos - self._segment, pos)
        self._edge = np.where(passed, (self._edge + 1) % EDGES, self._edge)
        tiny = np.abs(cmd.dy) < self._min_lateral_move
        moved = np.where(tiny, (self._y + cmd.dy) - self._half_width, self._pos_lat + cmd.dy)
        self._pos_lat = np.where(cmd.dy == 0.0, self._pos_lat, moved)
        self._vx = cmd.vx_next.copy()
        x = edge_to_ring(self._edge, self._pos, self._length)
        self._y = self._pos_lat + self._half_width
        return x, self._y.copy(), self._vx.copy()

    def close(self) -> None:
        pass


class OpenRoadNumpyBackend:
    """SUMO-free execution on an open road (the on-ramp), whose vehicles enter (:meth:`add`) and leave
    (:meth:`remove`): positions advance by the ballistic distance, lateral moves are added."""

    def __init__(self, cfg: LaneFreeConfig) -> None:
        self._step = cfg.sim.step_s
        self._x = self._y = self._vx = np.zeros(0)

    def reset(self, state: VehicleState) -> None:
        self._x, self._y, self._vx = state.x.copy(), state.y.copy(), state.vx.copy()

    def add(self, rows: VehicleState) -> None:
        """Vehicles entering the road (appended, in order)."""
        self._x = np.concatenate([self._x, rows.x])
        self._y = np.concatenate([self._y, rows.y])
        self._vx = np.concatenate([self._vx, rows.vx])

    def remove(self, keep: np.ndarray) -> None:
        """Keep only the vehicles where ``keep`` is True (the others left the road)."""
        self._x, self._y, self._vx = self._x[keep], self._y[keep], self._vx[keep]

    def step(self, cmd: StepCommand) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        self._x = self._x + ballistic_distance(self._vx, cmd.vx_next, self._step)
        self._y = self._y + cmd.dy
        self._vx = cmd.vx_next.copy()
        return self._x.copy(), self._y.copy(), self._vx.copy()

    def close(self) -> None:
        pass
