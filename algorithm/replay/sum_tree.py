"""A float64 sum tree over ``capacity`` leaves, with batched, compiled updates and descents.

Usage::

    tree = SumTree(capacity)
    tree.set(indices, priorities)          # leaves >= 0; parents recomputed from their children
    idx = tree.sample_stratified(256, rng)  # leaf indices drawn proportionally to their values
    p = tree.get(idx) / tree.total

Layout: a 1-based binary heap over ``P`` leaves, ``P`` the smallest power of two >= ``capacity``;
leaf ``i`` lives at ``P + i`` and the padding leaves stay 0, so any capacity works and the padding
is never drawn. Every parent is *recomputed* as ``left + right`` whenever a leaf below it changes
(never adjusted by a delta), so the tree is always a pure function of its leaves: no drift can
accumulate however many updates run, and ``total`` differs from an exact sum of the leaves only by
the rounding of one pairwise summation (relative error <= ~log2(P) * 2**-53).

Zero leaves are never returned: the descent only enters a child whose sum is positive, so float
rounding at a segment boundary cannot land on an empty leaf. The loops are compiled with numba
(measured in ``bench/replay.py``: several times faster than a vectorised numpy descent at 1M leaves).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True)
def _set_leaves(tree: np.ndarray, base: int, indices: np.ndarray, values: np.ndarray) -> None:
    for j in range(indices.shape[0]):
        node = base + indices[j]
        tree[node] = values[j]
        node >>= 1
        while node >= 1:
            tree[node] = tree[2 * node] + tree[2 * node + 1]
            node >>= 1


@numba.njit(cache=True)
def _descend(tree: np.ndarray, base: int, targets: np.ndarray) -> np.ndarray:
    # Level by level over the whole batch rather than one root-to-leaf walk per target: the loads
    # of one level are independent, so the CPU overlaps their cache misses (about 2x at 1M leaves).
    n = targets.shape[0]
    node = np.ones(n, dtype=np.int64)
    u = targets.copy()
    level = 1
    while level < base:
        for j in range(n):
            left = tree[2 * node[j]]
            # Go right only when u is past the left sum *and* the right subtree holds mass: after
            # `u -= left` rounding can leave u >= right, and an empty right child must not be entered.
            if u[j] >= left and tree[2 * node[j] + 1] > 0.0:
                u[j] -= left
                node[j] = 2 * node[j] + 1
            else:
                node[j] = 2 * node[j]
        level *= 2
    return node - base


@numba.njit(cache=True)
def _rebuild(tree: np.ndarray, base: int) -> None:
    for node in range(base - 1, 0, -1):
        tree[node] = tree[2 * node] + tree[2 * node + 1]


class SumTree:
    """Non-negative float64 leaves with O(log n) updates and proportional sampling.

    Not thread-safe on its own: the replay table calls it under its lock.
    """

    def __init__(self, capacity: int) -> None:
        if int(capacity) < 1:
            raise ValueError(f"SumTree capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self._base = 1 << max(0, (self.capacity - 1).bit_length())
        self._tree = np.zeros(2 * self._base, dtype=np.float64)

    @property
    def total(self) -> float:
        """Sum of all leaves (the root)."""
        return float(self._tree[1])

    @property
    def leaves(self) -> np.ndarray:
        """Read-only view of the ``capacity`` leaf values."""
        view = self._tree[self._base : self._base + self.capacity]
        view.flags.writeable = False
        return view

    def get(self, indices: np.ndarray) -> np.ndarray:
        """Leaf values at ``indices`` (float64 copy)."""
        return self._tree[self._base + np.asarray(indices, dtype=np.int64)]

    def set(self, indices: np.ndarray, values: np.ndarray) -> None:
        """Set leaves ``indices`` to ``values`` (finite, >= 0); the last write wins on duplicates."""
        idx = np.ascontiguousarray(indices, dtype=np.int64).reshape(-1)
        val = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
        if idx.shape != val.shape:
            raise ValueError(f"SumTree.set: {idx.shape[0]} indices but {val.shape[0]} values")
        if idx.size == 0:
            return
        if idx.min() < 0 or idx.max() >= self.capacity:
            raise IndexError(f"SumTree.set: indices must be in [0, {self.capacity}), got {idx.min()}..{idx.max()}")
        if not np.isfinite(val).all() or val.min() < 0.0:
            raise ValueError("SumTree.set: values must be finite and >= 0")
        _set_leaves(self._tree, self._base, idx, val)

    def set_all(self, values: np.ndarray) -> None:
        """Replace every leaf at once and rebuild all parents (used when loading a table)."""
        val = np.asarray(values, dtype=np.float64)
        if val.shape != (self.capacity,):
            raise ValueError(f"SumTree.set_all: expected shape ({self.capacity},), got {val.shape}")
        if not np.isfinite(val).all() or (val.size and val.min() < 0.0):
            raise ValueError("SumTree.set_all: values must be finite and >= 0")
        self._tree[:] = 0.0
        self._tree[self._base : self._base + self.capacity] = val
        _rebuild(self._tree, self._base)

    def find(self, targets: np.ndarray) -> np.ndarray:
        """Leaf index whose cumulative range contains each target in ``[0, total)``.

        Targets at or beyond ``total`` (float rounding) map to the last positive leaf; the result is
        always a leaf with a positive value. Requires ``total > 0``.
        """
        if not self._tree[1] > 0.0:
            raise ValueError("SumTree.find: the tree is empty (total is 0)")
        return _descend(self._tree, self._base, np.ascontiguousarray(targets, dtype=np.float64))

    def sample_stratified(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Draw ``n`` leaves proportionally to value: one uniform draw in each of ``n`` equal
        segments of ``[0, total)`` (stratified, as in Schaul et al. 2016, appendix B.2.1)."""
        total = self._tree[1]
        targets = (np.arange(n, dtype=np.float64) + rng.random(n)) * (total / n)
        return self.find(targets)
