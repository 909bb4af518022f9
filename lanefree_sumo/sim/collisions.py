"""Collisions (specification §4): rectangle overlaps on the ring, counted as events.

Two vehicles overlap when ``|dx| < (l_i + l_j)/2`` and ``|dy| < (w_i + w_j)/2``.  A collision
*event* starts on the first step of an overlap of a pair; a contact lasting many steps is one
event.  Vehicles are never removed.
"""

from __future__ import annotations

import numpy as np

from lanefree_sumo.sim.state import Bodies, pair_mask, pairwise_offsets
from lanefree_sumo.sim.xp import namespace


def overlap_matrix(
    state: Bodies, ring_length: np.ndarray | float, offsets: tuple[np.ndarray, np.ndarray] | None = None,
    present: np.ndarray | None = None,
) -> np.ndarray:
    """Symmetric boolean matrices ``[..., N, N]``: ``[i, j]`` is True when vehicles i ≠ j overlap.
    ``offsets`` = (dx, dy) from :func:`~lanefree_sumo.sim.state.pairwise_offsets` if already computed;
    ``ring_length``: a scalar or one per run (``[..., 1]``); ``present`` (``[..., N]``, None: all): padded rows
    (False) overlap nobody."""
    dx, dy = pairwise_offsets(state, ring_length) if offsets is None else offsets
    half_len = 0.5 * (state.length[..., :, None] + state.length[..., None, :])
    half_wid = 0.5 * (state.width[..., :, None] + state.width[..., None, :])
    xp = namespace(dx)
    overlap = (xp.abs(dx) < half_len) & (xp.abs(dy) < half_wid)
    if present is None:
        xp.fill_diagonal(overlap, False)
        return overlap
    return overlap & pair_mask(present)


def started_overlaps(overlap: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """``[..., N, N]``, True at the pairs (i < j) whose overlap started now: collision events (module docstring)."""
    return namespace(overlap).triu(overlap & ~previous, k=1)


def count_events(pairs: np.ndarray, row: int, agents: np.ndarray) -> tuple[int, int, int]:
    """Of one step's collision events ``pairs`` (``[k, 2]`` rows, as :meth:`CollisionTracker.update` returns):
    (the events of vehicle ``row``, those of them with another agent, those between two background vehicles).
    ``agents``: the rows of every agent vehicle, ``row`` among them."""
    if not len(pairs):
        return 0, 0, 0
    mine = (pairs == row).any(axis=1)
    of_agents = np.isin(pairs, agents)
    return (int(np.count_nonzero(mine)), int(np.count_nonzero(mine & of_agents.all(axis=1))),
            int(np.count_nonzero(~of_agents.any(axis=1))))


class CollisionTracker:
    """Counts overlap events per pair: a pair that keeps overlapping is counted once.

    ``update`` takes this step's overlap matrix and returns the pairs (i < j) whose overlap
    started on this step.
    """

    def __init__(self, n_vehicles: int) -> None:
        self._previous = np.zeros((n_vehicles, n_vehicles), dtype=bool)

    def reset(self, n_vehicles: int) -> None:
        self._previous = np.zeros((n_vehicles, n_vehicles), dtype=bool)

    def keep(self, keep: np.ndarray) -> None:
        """Forget the vehicles where ``keep`` is False (they left the road); the others keep their pairs."""
        self._previous = self._previous[np.ix_(keep, keep)]

    def add(self, count: int) -> None:
        """Vehicles appended to the state: they overlap nobody yet."""
        self._previous = np.pad(self._previous, ((0, count), (0, count)))

    def update(self, overlap: np.ndarray) -> np.ndarray:
        """Return an array of shape (k, 2) of the pairs (i < j) that started overlapping now."""
        started = started_overlaps(overlap, self._previous)
        self._previous = overlap.copy()
        return np.argwhere(started)
