"""Segment trees for prioritised replay (Schaul et al. 2016, proportional variant).

A :class:`SumTree` gives the total priority mass and finds the leaf holding a cumulative mass; a
:class:`MinTree` gives the smallest priority (for the largest importance weight). Both are numpy,
vectorised over batches of indices.
"""


from typing import ClassVar

import numpy as np


class _SegmentTree:
    """Complete binary tree over ``capacity`` leaves stored in one flat array.

    Node 1 is the root, node ``k`` has children ``2k`` and ``2k+1``; leaf ``i``
    is node ``size + i`` where ``size`` is the next power of two ≥ capacity.
    Subclasses define the associative operation and its neutral element.
    """

    neutral: ClassVar[float] = 0.0

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self.size = 1 << (self.capacity - 1).bit_length()  # next power of two
        self.depth = self.size.bit_length() - 1  # log2(size)
        self.tree = np.full(2 * self.size, self.neutral, dtype=np.float64)

    @staticmethod
    def _combine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _check(self, indices: np.ndarray | int) -> np.ndarray:
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= self.capacity):
            raise IndexError(f"tree index out of range [0, {self.capacity}): {idx.min()}..{idx.max()}")
        return idx

    @staticmethod
    def _combine_two(a: float, b: float) -> float:
        """:meth:`_combine` of two numbers (the same result, without array overhead)."""
        raise NotImplementedError

    def update(self, indices: np.ndarray | int, values: np.ndarray | float) -> None:
        """Set leaves ``indices`` to ``values`` and recompute their ancestors, each node from its two children
        (one leaf, as a new transition sets: node by node; several: level by level)."""
        idx = self._check(indices)
        if idx.size == 0:
            return
        vals = np.broadcast_to(np.asarray(values, dtype=np.float64).reshape(-1), idx.shape)
        nodes = idx + self.size
        tree = self.tree
        tree[nodes] = vals  # duplicate indices: last value wins
        if nodes.size == 1:
            node = int(nodes[0]) >> 1
            while node:
                tree[node] = self._combine_two(tree[2 * node], tree[2 * node + 1])
                node >>= 1
            return
        for _ in range(self.depth):  # a node listed twice gets the same value twice: its children are final
            tree[nodes >> 1] = self._combine(tree[nodes & ~1], tree[nodes | 1])
            nodes = nodes >> 1

    def get(self, indices: np.ndarray | int) -> np.ndarray:
        """Leaf values at ``indices``."""
        return self.tree[self._check(indices) + self.size]

    def reduce(self) -> float:
        """Reduction (sum or min) over all leaves."""
        return float(self.tree[1])

    def clear(self) -> None:
        self.tree.fill(self.neutral)


class SumTree(_SegmentTree):
    """Sum-tree: O(log n) update, total mass and prefix-sum search (Schaul 2016)."""

    neutral: ClassVar[float] = 0.0

    @staticmethod
    def _combine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return a + b

    @staticmethod
    def _combine_two(a: float, b: float) -> float:
        return a + b

    def total(self) -> float:
        """Sum of all leaves."""
        return self.reduce()

    def find_prefixsum_idx(self, values: np.ndarray | float) -> np.ndarray:
        """For each ``v`` return the leaf ``i`` with ``sum(p[:i]) <= v < sum(p[:i+1])``.

        Never returns a zero-mass leaf while the tree has positive mass (values
        at or above the total, e.g. from rounding, map to the last non-empty leaf).
        """
        v = np.array(values, dtype=np.float64).reshape(-1)
        node = np.ones(v.shape, dtype=np.int64)
        for _ in range(self.depth):
            left = 2 * node
            left_mass = self.tree[left]
            go_right = (v >= left_mass) & (self.tree[left + 1] > 0.0)
            v = np.where(go_right, v - left_mass, v)
            node = np.where(go_right, left + 1, left)
        return node - self.size


class MinTree(_SegmentTree):
    """Min-tree: O(log n) update and global minimum (empty leaves are +inf)."""

    neutral: ClassVar[float] = float("inf")

    @staticmethod
    def _combine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.minimum(a, b)

    @staticmethod
    def _combine_two(a: float, b: float) -> float:
        return min(a, b)

    def min(self) -> float:
        """Minimum over all leaves (+inf when empty)."""
        return self.reduce()
