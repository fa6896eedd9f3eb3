"""Running mean and variance of observations, exact under batching and merging.

Usage::

    rms = RunningMeanStd(shape=(17,))
    rms.update(obs_rows)                 # [N, 17]; any N, in any order of batches
    rms.merge(stats_from_another_actor)  # same result as one pass over both streams
    x_norm = rms.normalize(x)            # (x - mean) / sqrt(var + eps), clipped to [-5, 5]

Batches are combined with the parallel algorithm of Chan, Golub and LeVeque (1979) in float64
(https://en.wikipedia.org/wiki/Algorithms_for_calculating_variance#Parallel_algorithm): each update
adds the batch's own mean and sum of squared deviations, so the result does not depend on how the
stream was cut. ``var`` is the population variance (divide by ``count``), as in SB3/Gymnasium.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class RunningMeanStd:
    """Per-feature running statistics of a ``shape``-shaped vector (float64 inside)."""

    def __init__(self, shape: tuple[int, ...], epsilon: float = 1e-8) -> None:
        self.shape = tuple(int(d) for d in shape)
        self.epsilon = float(epsilon)
        self.count = 0
        self.mean = np.zeros(self.shape, dtype=np.float64)
        self._m2 = np.zeros(self.shape, dtype=np.float64)  # sum of squared deviations from the mean

    @property
    def var(self) -> np.ndarray:
        """Population variance; zeros before any data."""
        return self._m2 / self.count if self.count else np.zeros(self.shape, dtype=np.float64)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(self.var + self.epsilon)

    def update(self, batch: np.ndarray) -> None:
        """Add ``batch`` of shape ``[N, *shape]`` (N may be 0); non-finite values are an error."""
        x = np.asarray(batch, dtype=np.float64)
        if x.shape[1:] != self.shape:
            raise ValueError(f"RunningMeanStd.update: expected [N, *{self.shape}], got {x.shape}")
        n = x.shape[0]
        if n == 0:
            return
        if not np.isfinite(x).all():
            raise ValueError("RunningMeanStd.update: batch has non-finite values")
        mean = x.mean(axis=0)
        m2 = np.square(x - mean).sum(axis=0)
        self._combine(n, mean, m2)

    def merge(self, other: RunningMeanStd) -> None:
        """Fold in the statistics of ``other`` (same shape), as if its data had been seen here."""
        if other.shape != self.shape:
            raise ValueError(f"RunningMeanStd.merge: shapes differ, {self.shape} vs {other.shape}")
        if other.count:
            self._combine(other.count, other.mean, other._m2)

    def _combine(self, n: int, mean: np.ndarray, m2: np.ndarray) -> None:
        total = self.count + n
        delta = mean - self.mean
        self.mean = self.mean + delta * (n / total)
        self._m2 = self._m2 + m2 + np.square(delta) * (self.count * n / total)
        self.count = total

    def normalize(self, x: np.ndarray, clip: float = 5.0) -> np.ndarray:
        """``(x - mean) / sqrt(var + epsilon)`` clipped to ``[-clip, clip]``, as float32."""
        out = (np.asarray(x, dtype=np.float64) - self.mean) / self.std
        return np.clip(out, -clip, clip).astype(np.float32)

    def copy(self) -> RunningMeanStd:
        new = RunningMeanStd(self.shape, self.epsilon)
        new.load_state_dict(self.state_dict())
        return new

    def state_dict(self) -> dict[str, Any]:
        """``{"count": int, "mean": float64 array, "var": float64 array}`` (copies)."""
        return {"count": self.count, "mean": self.mean.copy(), "var": self.var.copy()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned; shapes must match, count >= 0, var >= 0."""
        count = int(state["count"])
        mean = np.asarray(state["mean"], dtype=np.float64)
        var = np.asarray(state["var"], dtype=np.float64)
        if mean.shape != self.shape or var.shape != self.shape:
            raise ValueError(f"RunningMeanStd state: expected shape {self.shape}, got {mean.shape}/{var.shape}")
        if count < 0 or not (np.isfinite(mean).all() and np.isfinite(var).all()) or (var < 0).any():
            raise ValueError("RunningMeanStd state: count must be >= 0 and mean/var finite, var >= 0")
        self.count = count
        self.mean = mean.copy()
        self._m2 = var * count
