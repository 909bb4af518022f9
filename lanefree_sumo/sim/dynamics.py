"""Vehicle dynamics (specification §2): a double integrator with the ballistic update, on a ring.

    x' = x + vx·T + ½·ax·T²      vx' = vx + ax·T
    y' = y + vy·T + ½·ay·T²      vy' = vy + ay·T

``vx'`` is floored at 0 (no reversing).  A lateral move that would put the body closer than
``clearance`` to a road edge is clipped there and ``vy'`` set to 0: a *boundary contact*.
SUMO rejects lateral targets at or past the lane border, so the clearance is strictly positive.

Every function is element-wise (numpy, or torch through :mod:`.xp`):
arrays ``[N]`` of one simulation or ``[K, N]`` of a batch of runs
(:mod:`~lanefree_sumo.sim.world`); the road width and bounds are scalars or broadcast against them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from lanefree_sumo.config import AccelerationBounds
from lanefree_sumo.sim.xp import namespace


@dataclass
class StepCommand:
    """What one step asks of every vehicle; exactly what a backend needs to execute it."""

    vx_next: np.ndarray
    """Speed at the end of the step (m/s), commanded with ``setSpeed``."""
    dy: np.ndarray
    """Lateral displacement during the step (m), commanded with ``changeSublane``."""
    vy_next: np.ndarray
    """Lateral speed at the end of the step (m/s); kept on the Python side."""
    ax: np.ndarray
    """Realised longitudinal acceleration (m/s²) after the vx ≥ 0 floor."""
    ay: np.ndarray
    """Realised lateral acceleration (m/s²) after the road-edge clip."""
    boundary_contact: np.ndarray
    """True where the lateral move was clipped at a road edge."""


def plan_step(
    x: np.ndarray,
    y: np.ndarray,
    vx: np.ndarray,
    vy: np.ndarray,
    width: np.ndarray,
    ax: np.ndarray,
    ay: np.ndarray,
    step_s: float,
    road_width: np.ndarray | float,
    clearance: float,
    contact_tolerance: float = 0.0,
    bounds: tuple[np.ndarray | float, np.ndarray | float] | None = None,
) -> StepCommand:
    """Integrate one ballistic step laterally and longitudinally (speeds), with the edge clip.

    Overshoots of the clip line up to ``contact_tolerance`` (m) are clipped without counting
    as a contact or zeroing vy (they are floating-point rounding of a driver that stops at the
    line). ``bounds`` = (lowest, highest) lateral position each body may reach (m; scalars or one per
    vehicle); None: 0 and ``road_width``."""
    xp = namespace(vx)
    t = step_s
    vx_next = xp.maximum(vx + ax * t, 0.0)
    ax_real = (vx_next - vx) / t
    y_target = y + vy * t + 0.5 * ay * t * t
    if bounds is None:
        lo = 0.5 * width + clearance
        hi = road_width - 0.5 * width - clearance
    else:
        lo = bounds[0] + 0.5 * width + clearance
        hi = bounds[1] - 0.5 * width - clearance
    y_next = xp.clip(y_target, lo, hi)
    contact = xp.abs(y_target - y_next) > contact_tolerance
    dy = y_next - y
    vy_next = xp.where(contact, 0.0, vy + ay * t)
    # realised lateral acceleration: the one that yields the clipped displacement
    ay_real = xp.where(contact, 2.0 * (dy - vy * t) / (t * t), ay)
    return StepCommand(vx_next, dy, vy_next, ax_real, ay_real, contact)


def clip_accelerations(
    ax: ArrayLike, ay: ArrayLike, bounds: AccelerationBounds, vx: ArrayLike, max_speed: Any, step_s: float,
    vy: np.ndarray | float = 0.0, lateral_ratio: Any = None, lateral_bounded: Any = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Clip agents' accelerations (m/s², element-wise) to their bounds and so that each speed ``vx`` (m/s) does
    not exceed ``max_speed`` (m/s; a number or an array broadcast with ``vx``) at the end of the step; with
    ``lateral_ratio`` r also so that |vy| ≤ r·vx after the step (vy in m/s), as the driver model bounds the
    background's; ``lateral_bounded`` (an array broadcast with ``vx``, or None: all) where that bound applies."""
    xp = namespace(vx, ax, ay)
    speed: np.ndarray = xp.asarray(vx, dtype=float)
    ax_top = xp.minimum(bounds.ax_max, (max_speed - speed) / step_s)
    ay_clipped = xp.clip(xp.asarray(ay, dtype=float), bounds.ay_min, bounds.ay_max)
    if lateral_ratio is not None:
        bounded = xp.maximum(xp.minimum(ay_clipped, (lateral_ratio * speed - vy) / step_s),
                             -(lateral_ratio * speed + vy) / step_s)
        bounded = xp.clip(bounded, bounds.ay_min, bounds.ay_max)
        ay_clipped = bounded if lateral_bounded is None else xp.where(lateral_bounded, bounded, ay_clipped)
    return xp.minimum(xp.maximum(xp.asarray(ax, dtype=float), bounds.ax_min), ax_top), ay_clipped


def clip_acceleration(
    ax: float, ay: float, bounds: AccelerationBounds, vx: float, max_speed: float, step_s: float,
    vy: float = 0.0, lateral_ratio: float | None = None,
) -> tuple[float, float]:
    """:func:`clip_accelerations` of one agent, as floats."""
    ax_c, ay_c = clip_accelerations(ax, ay, bounds, vx, max_speed, step_s, vy, lateral_ratio)
    return float(ax_c), float(ay_c)


def ballistic_distance(vx: np.ndarray, vx_next: np.ndarray, step_s: float) -> np.ndarray:
    """Distance travelled in one ballistic step, (v + ½·(v' − v))·T  =  v·T + ½·a·T² (m).

    Evaluated in the order SUMO's ballistic update uses, so that the SUMO-free backend
    reproduces SUMO's positions bit for bit."""
    return (vx + 0.5 * (vx_next - vx)) * step_s
