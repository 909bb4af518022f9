"""Vehicle state arrays shared by the physics, the backends and the environment.

Coordinates (specification §0): ``x`` is the longitudinal position along the ring's centre line in
[0, L) (m), ``y`` the lateral position of the vehicle's centre from the right road edge (m),
``vx``/``vy`` the speeds along x/y (m/s).  Row ``i`` is vehicle ``ids[i]`` in every array.

The physics (:mod:`.forces`, :mod:`.dynamics`, :mod:`.collisions`) takes arrays of shape ``[..., N]``: one
simulation's ``[N]`` (a :class:`VehicleState`) or a batch of runs' ``[K, N]`` (:class:`~lanefree_sumo.sim.world.World`,
whose runs are padded to a common N and masked by ``present``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from lanefree_sumo.sim.xp import namespace


class Bodies(Protocol):
    """What the physics reads of the vehicles: arrays of shape ``[..., N]`` (one row per vehicle)."""

    x: np.ndarray
    y: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    length: np.ndarray
    width: np.ndarray
    v_desired: np.ndarray


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


def wrap(dx: np.ndarray | float, ring_length: np.ndarray | float) -> np.ndarray:
    """Map longitudinal differences onto [−L/2, L/2) on a ring of length ``ring_length`` (m; a scalar, or one
    per run broadcastable against ``dx``)."""
    xp = namespace(dx)
    d = xp.asarray(dx, dtype=float)
    return d - ring_length * xp.floor(d / ring_length + 0.5)


def per_pair(value: np.ndarray | float) -> np.ndarray | float:
    """A per-run value of shape ``[..., 1]`` (broadcasting against ``[..., N]``) as ``[..., 1, 1]`` for ``[..., N, N]``
    pair matrices; a scalar stays a scalar."""
    return value if isinstance(value, (float, int)) or not value.ndim else value[..., None]


def pairwise_offsets(state: Bodies, ring_length: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """(dx, dy) matrices ``[..., N, N]`` with ``dx[i, j] = wrap(x_j − x_i)`` and ``dy[i, j] = y_j − y_i`` (m);
    ``ring_length``: a scalar or one per run, shape ``[..., 1]``."""
    dx = wrap(state.x[..., None, :] - state.x[..., :, None], per_pair(ring_length))
    dy = state.y[..., None, :] - state.y[..., :, None]
    return dx, dy


def take_rows(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``a[..., index]`` row by row: ``a`` ``[..., N]``, ``index`` ``[..., M]`` → ``[..., M]`` (numpy's
    ``take_along_axis`` with less overhead for one simulation's or one batch's rows)."""
    xp = namespace(a)
    if a.ndim == 1:
        return a[index]
    if a.ndim == 2 and xp.is_numpy:
        return a[np.arange(a.shape[0])[:, None], index]
    return xp.take_along_axis(a, index, -1)


def pair_mask(present: np.ndarray) -> np.ndarray:
    """``[..., N, N]``: True where both vehicles of a pair are present and they are two (the diagonal is False)."""
    xp = namespace(present)
    both = present[..., :, None] & present[..., None, :]
    xp.fill_diagonal(both, False)
    return both


def row_sum(a: np.ndarray, count: np.ndarray | None = None) -> np.ndarray:
    """Σ over the last axis, bit for bit numpy's own ``a.sum(axis=-1)`` over each row's first ``count`` entries.

    ``count`` (broadcastable to ``a.shape[:-1]``): how many entries of each row are real, the rest being padding
    equal to 0.0; None: every entry. numpy sums a row pairwise (eight running sums over blocks of eight, combined
    as a tree, then the remainder one by one; halves first beyond 128 entries), so the grouping depends on the
    row's length: a padded row summed by numpy would round differently from the same row unpadded. This
    reproduces numpy's grouping for each row's own length, so a run padded in a batch sums as it does alone. On a
    GPU (the torch namespace's ``numpy_order_sums`` off) the row is summed in torch's order: equal to rounding."""
    xp = namespace(a)
    if xp.is_numpy:  # numpy's own sum where it is the one wanted
        if count is None:
            return a.sum(axis=-1)
        if a.shape[-1] < 8:  # numpy adds such rows one by one: trailing +0.0 padding changes no sum but -0.0's
            total = a.sum(axis=-1)
            if (total != 0.0).all():
                return total
        count = np.broadcast_to(count, a.shape[:-1])
        if (count == a.shape[-1]).all():
            return a.sum(axis=-1)
    elif not xp.numpy_order_sums:  # torch's own order (a GPU's): the padding is 0.0, so the same sum to rounding
        return xp.sum(a, axis=-1)
    else:  # other libraries sum in their own order: numpy's order, formed step by step
        count = xp.broadcast_to(a.shape[-1] if count is None else count, a.shape[:-1])
    return _pairwise(a, None, count, a.shape[-1])


_BLOCK = 128
"""numpy's pairwise block: rows up to this long are summed with eight running sums, longer ones halved first."""


def _pairwise(a: np.ndarray, start: np.ndarray | None, count: np.ndarray, width: int) -> np.ndarray:
    """numpy's pairwise sum of ``a[..., start:start + count]`` per row (:func:`row_sum`; ``start`` None: 0);
    ``count`` ≤ ``width``."""
    xp = namespace(a)
    if start is not None and (not xp.is_numpy or start.any()):
        index = xp.minimum(start[..., None] + xp.arange(width), a.shape[-1] - 1)
        window = xp.take_along_axis(a, index, -1)
    else:
        start = xp.zeros(count.shape, dtype=int)
        window = a[..., :width]
    if width <= _BLOCK:
        return _block_sum(window, count)
    # rows longer than a block are summed as two halves (numpy's split: n/2 rounded down to a multiple of 8)
    half = count // 2
    half = half - half % 8
    split = (_pairwise(a, start, half, width // 2)
             + _pairwise(a, start + half, count - half, min(width, width - width // 2 + 8)))
    return xp.where(count > _BLOCK, split, _block_sum(window[..., :_BLOCK], xp.minimum(count, _BLOCK)))


def _block_sum(a: np.ndarray, count: np.ndarray) -> np.ndarray:
    """numpy's sum of ``a[..., :count]`` (count ≤ 128 per row): below 8 entries one by one; else eight running sums
    over whole blocks of eight, combined pairwise, then the remaining entries one by one."""
    xp = namespace(a)
    width = a.shape[-1]
    if not width:
        return xp.zeros(a.shape[:-1])
    blocked = xp.where(count >= 8, count - count % 8, 0)
    padded = -(-width // 8) * 8
    lanes = xp.where(xp.arange(width) < blocked[..., None], a, 0.0)
    if padded > width:
        lanes = xp.concatenate([lanes, xp.zeros(a.shape[:-1] + (padded - width,))], axis=-1)
    blocks = lanes.reshape(a.shape[:-1] + (-1, 8))
    # the eight running sums, adding the blocks one after another (numpy's reduction over a non-innermost axis)
    if xp.is_numpy:
        acc = blocks.sum(axis=-2)
    else:
        acc = blocks[..., 0, :]
        for b in range(1, blocks.shape[-2]):
            acc = acc + blocks[..., b, :]
    tree = ((acc[..., 0] + acc[..., 1]) + (acc[..., 2] + acc[..., 3])) + ((acc[..., 4] + acc[..., 5])
                                                                           + (acc[..., 6] + acc[..., 7]))
    total = xp.where(count >= 8, tree, 0.0)
    rest = xp.arange(7)
    tail = xp.take_along_axis(a, xp.minimum(blocked[..., None] + rest, width - 1), -1)
    tail = xp.where(rest < (count - blocked)[..., None], tail, 0.0)
    for t in range(7):
        total = total + tail[..., t]
    return total
