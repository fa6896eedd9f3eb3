"""Saving and loading a replay table whole: :class:`TableSnapshot` is the mixin of
:class:`algorithm.replay.table.PrioritizedTable` that writes its state to one file and reads it back,
so sampling continues exactly where it stopped. The file format and its checks are
:mod:`algorithm.replay.persistence`'s; :class:`~algorithm.replay.table.PrioritizedTable` owns the
attributes this reads.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from algorithm.normalizer import RunningMeanStd
from algorithm.replay import persistence
from algorithm.replay.dedup import ChunkLedger
from algorithm.replay.rate_limiter import RateLimiter
from algorithm.replay.ring import ChunkRing
from algorithm.replay.sum_tree import SumTree
from algorithm.spaces import SensorSpec


class TableSnapshot:
    """:meth:`save` and :meth:`load` of a :class:`~algorithm.replay.table.PrioritizedTable` (which provides
    these attributes)."""

    capacity: int
    sensors: tuple[SensorSpec, ...]
    action_size: int
    rnn_state_size: int
    alpha: float
    td_error_min: float
    td_error_max: float
    max_producers: int
    rate_limiter: RateLimiter
    _lock: threading.Condition
    _rng: np.random.Generator
    _ring: ChunkRing
    _tree: SumTree
    _normalizers: dict[str, RunningMeanStd]
    _ledger: ChunkLedger
    _max_priority: float
    _counters: dict[str, int]

    def save(self, path: str | Path, *, before_replace: Callable[[], object] | None = None) -> None:
        """Write the table to ``path`` (an ``.npz`` archive, no pickles) atomically: the state is
        copied under the lock, then written to a temp file beside ``path``, fsynced and renamed.
        The ids of :meth:`insert_once` are saved with the rows they name, so a table loaded from
        the file recognises exactly the chunks it holds. ``before_replace`` is called right before
        the rename; if it raises, ``path`` is left as it was (the replay server abandons a save
        past its call's deadline with it)."""
        with self._lock:
            arrays = self._state_arrays()
            meta = {
                **self._layout(),
                "next_key": self._ring.next_key,
                "max_priority": self._max_priority,
                "counters": dict(self._counters),
                "rate_limiter": self.rate_limiter.state_dict(),
                "rng": self._rng.bit_generator.state,
                "normalizer_counts": {name: rms.count for name, rms in self._normalizers.items()},
                "ledger": self._ledger.state_dict(),
            }
        persistence.write_atomic(Path(path), arrays, meta, before_replace)

    def load(
        self,
        path: str | Path,
        *,
        follow_symlinks: bool = True,
        before_install: Callable[[], object] | None = None,
    ) -> None:
        """Replace the contents with a file written by :meth:`save` of a table with the same
        capacity, sensors, action size, recurrent state size and priority transform. Everything
        is read and validated first; a bad or mismatched file raises ``ValueError`` naming the
        problem and leaves this table unchanged. Sampling then continues exactly as it would have
        in the saved table (same rows, priorities, counters and random state). Only a regular file
        is opened (a FIFO or device is a ``ValueError`` at once); ``follow_symlinks=False`` refuses
        a symlink at ``path`` too. ``before_install`` is called once the file is validated, right
        before the contents are replaced; if it raises, the table is left unchanged."""
        expected = {name: (arr.shape, arr.dtype) for name, arr in self._state_arrays(copy=False).items()}
        data, meta = persistence.read_checked(Path(path), self._layout(), expected, follow_symlinks)
        try:
            attributes, limiter_state = self._validated_state(data, meta)
        except (KeyError, TypeError, ValueError, AttributeError, IndexError, ArithmeticError) as e:
            raise ValueError(f"{path}: inconsistent replay file ({type(e).__name__}: {e})") from e
        if before_install is not None:
            before_install()
        with self._lock:
            self.rate_limiter.load_state_dict(limiter_state)
            self._ring.install(data, int(meta["next_key"]))
            for name, value in attributes.items():
                setattr(self, name, value)

    def _layout(self) -> dict[str, Any]:
        """What a saved file must match to be loaded here (JSON-friendly)."""
        return {
            "capacity": self.capacity,
            "sensors": [[s.name, list(s.shape), np.dtype(s.dtype).str] for s in self.sensors],
            "action_size": self.action_size,
            "rnn_state_size": self.rnn_state_size,
            "alpha": self.alpha,
            "td_error_min": self.td_error_min,
            "td_error_max": self.td_error_max,
        }

    def _state_arrays(self, copy: bool = True) -> dict[str, np.ndarray]:
        normalized = {i: self._normalizers[s.name] for i, s in enumerate(self.sensors) if s.name in self._normalizers}
        arrays = {**self._ring.arrays(), "priorities": self._tree.leaves, **persistence.normalizer_arrays(normalized)}
        return {name: arr.copy() for name, arr in arrays.items()} if copy else arrays

    def _validated_state(
        self, data: dict[str, np.ndarray], meta: dict[str, Any]
    ) -> tuple[dict[str, Any], dict[str, int]]:
        """Check a loaded file's internal consistency (:func:`persistence.restored_state`); return the
        attributes to install besides the ring's arrays, and the rate limiter's counters."""
        next_key = int(meta["next_key"])
        state = persistence.restored_state(
            data, meta, self._ring.checked_step_rows(data, next_key), tuple(self._counters),
            {i: s for i, s in enumerate(self.sensors) if s.name in self._normalizers},
        )  # fmt: skip
        tree = SumTree(self.capacity)
        tree.set_all(state.priorities)
        attributes = {
            "_tree": tree,
            "_normalizers": state.normalizers,
            "_max_priority": state.max_priority,
            "_counters": state.counters,
            "_rng": state.rng,
            "_ledger": ChunkLedger.from_state(meta.get("ledger", []), next_key, self.max_producers),  # old files: none
        }
        return attributes, state.limiter
