"""The replay table interface every implementation provides (in-process, gRPC client, fakes).

Usage, from an actor and a learner sharing one table::

    keys = table.insert(chunk)                      # actor: one chunk -> one key per step
    table.insert_once(chunks, ChunkIds(producer, seqs, acked_below))   # actor: safe to send again
    batch = table.sample(batch_size, timeout=1.0)   # learner: B windows, with keys and probabilities
    table.update_priorities(batch.keys, td_abs)     # learner: |TD| per sampled key; evicted keys ignored
    new = table.windows_after(cursor, 256)          # learner: new data to score (insert_td_priorities)
    stats = table.info()                            # anyone: sizes, counters, normalizer stats (ReplayInfo)

A remote table raises :class:`ReplayUnavailable` when it cannot be reached; other errors are the
same as in process (``ValueError`` for a bad request, :class:`SampleTimeout`, ...).

``update_priorities`` and ``insert(..., priorities=...)`` take raw magnitudes (mean |TD| over Q
heads); the table maps them to sampling priorities ``clip(p, td_error_min, td_error_max) ** alpha``
itself, so callers never need the replay's hyper-parameters.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Protocol, TypedDict

import numpy as np

from algorithm.replay.dedup import ChunkIds, Inserted
from algorithm.types import Batch, Chunk


class SampleTimeout(TimeoutError):
    """No batch could be sampled before the timeout (table too small or rate-limited)."""


class ReplayUnavailable(ConnectionError):
    """The table cannot be reached now (a remote table's server went away or did not answer within
    the call's deadline); the call may be repeated later. An in-process table never raises it, so a
    learner catches this one error whatever transport it has (ds/replay/client.py raises it)."""


class NormalizerStats(TypedDict):
    """Running statistics of one vector sensor over every inserted observation."""

    count: int
    mean: np.ndarray  # float64, the sensor's shape
    var: np.ndarray  # float64, the sensor's shape


class ReplayInfo(TypedDict):
    """What :meth:`ReplayTable.info` returns (over gRPC: ints as ints, the rest as floats)."""

    size: int  # sampleable step rows
    capacity: int
    stored_rows: int  # rows holding data, bootstrap rows included
    inserted_steps: int  # steps ever inserted (a run's env steps, distributed)
    evicted_steps: int
    sampled_windows: int
    samples_per_insert_actual: float
    next_key: int  # the key the next inserted step gets
    max_priority: float
    total_priority: float
    producers: int  # producers the dedup ledger keeps
    inserted_chunks: int
    evicted_rows: int
    sample_calls: int
    priority_updates: int
    priority_updates_ignored: int
    rnn_state_updates: int
    duplicates: int  # chunks sent again and answered without storing them twice
    stored_past_limiter: int  # steps of stopping producers stored while the rate limiter held inserts back
    rate_limiter_surplus: float  # windows the learner may still draw now (-1: no ratio)
    insert_waits: float
    sample_waits: float
    insert_wait_seconds: float
    sample_wait_seconds: float
    normalizer: dict[str, NormalizerStats]  # per vector sensor


class ReplayTable(Protocol):
    def insert(self, chunk: Chunk, priorities: np.ndarray | None = None) -> np.ndarray:
        """Store a chunk contiguously; returns its ``len(chunk)`` new uint64 keys (increasing,
        never reused). New rows get the current maximum priority unless ``priorities`` is given.
        May block while the rate limiter says the learner is behind, if the table was built to."""
        ...

    def insert_many(
        self,
        chunks: Sequence[Chunk],
        priorities: Sequence[np.ndarray | None] | None = None,
        timeout: float | None = None,
    ) -> list[np.ndarray]:
        """Store several chunks as one request, all or nothing; returns each chunk's keys."""
        ...

    def insert_once(
        self,
        chunks: Sequence[Chunk],
        ids: ChunkIds,
        priorities: Sequence[np.ndarray | None] | None = None,
        timeout: float | None = None,
        producer_stopping: bool = False,
    ) -> Inserted:
        """Store chunks all or nothing, except those already stored under their ids (producer,
        sequence number), which are answered with their keys and not stored again: a producer
        that missed an answer sends the same chunks again safely (algorithm/replay/dedup.py).
        ``producer_stopping``: its last tries; stored after ``timeout`` even if the rate limiter
        still holds inserts back."""
        ...

    def sample(self, batch_size: int, timeout: float | None = None) -> Batch:
        """Draw ``batch_size`` windows proportionally to priority. Blocks until the rate limiter
        allows it; raises :class:`SampleTimeout` after ``timeout`` seconds (None: wait forever)."""
        ...

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> None:
        """Set the priority of each key still stored; evicted or unknown keys are ignored."""
        ...

    def windows_after(self, key: int, limit: int) -> Batch | None:
        """The windows starting at the oldest ``limit`` stored steps with keys ``>= key`` (None: no
        such step), for scoring new data; not counted as sampling and never blocking."""
        ...

    def update_rnn_states(self, keys: np.ndarray, states: np.ndarray) -> None:
        """Overwrite the stored recurrent state ``[N, rnn_state_size]`` of each key still stored."""
        ...

    def info(self) -> ReplayInfo:
        """Sizes, counters, rates and the normalizer statistics (:class:`ReplayInfo`)."""
        ...

    def normalizer_stats(self) -> dict[str, NormalizerStats]:
        """``info()["normalizer"]`` alone: what a learner with ``use_normalization`` polls."""
        ...

    def save(self, path: str | Path) -> None:
        """Write the whole table atomically (temp file, fsync, rename)."""
        ...

    def load(self, path: str | Path) -> None:
        """Replace the contents with what :meth:`save` wrote; a bad file raises and changes nothing."""
        ...
