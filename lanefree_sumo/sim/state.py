"""Vehicle state arrays shared by the physics, the backends and the environment.

Coordinates (specification §0): ``x`` is the longitudinal position along the ring's centre line in
[0, L) (m), ``y`` the lateral position of the vehicle's centre from the right road edge (m),
``vx``/``vy`` the speeds along x/y (m/s).  Row ``i`` is vehicle ``ids[i]`` in every array.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class VehicleState:
    """Kinematic state and fixed attributes of all vehicles on the road (one row each)."""

    ids: list[str]
    x: np.ndarray
    y: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    length: np.ndarray
    """Vehicle length (m)."""
    width: np.ndarray
    """Vehicle width (m)."""
    v_desired: np.ndarray
    """Desired longitudinal speed (m/s)."""
    controlled: np.ndarray
    """True where the force-based driver model controls the vehicle (background traffic)."""

    @property
    def n(self) -> int:
        return len(self.ids)

    def copy(self) -> VehicleState:
        return VehicleState(
            list(self.ids),
            self.x.copy(),
            self.y.copy(),
            self.vx.copy(),
            self.vy.copy(),
            self.length.copy(),
            self.width.copy(),
            self.v_desired.copy(),
            self.controlled.copy(),
        )


def wrap(dx: np.ndarray | float, ring_length: float) -> np.ndarray:
    """Map longitudinal differences onto [−L/2, L/2) on a ring of length ``ring_length`` (m)."""
    d = np.asarray(dx, dtype=float)
    return d - ring_length * np.floor(d / ring_length + 0.5)


def pairwise_offsets(state: VehicleState, ring_length: float) -> tuple[np.ndarray, np.ndarray]:
    """(dx, dy) matrices with ``dx[i, j] = wrap(x_j − x_i)`` and ``dy[i, j] = y_j − y_i`` (m)."""
    dx = wrap(state.x[None, :] - state.x[:, None], ring_length)
    dy = state.y[None, :] - state.y[:, None]
    return dx, dy
