"""The in-process prioritized replay table: trajectory chunks in, priority-weighted windows out.

Usage (see :class:`~algorithm.replay.base.ReplayTable` for the contract)::

    table = PrioritizedTable.from_config(cfg.replay_config, env_spec.sensors, env_spec.action.size,
                                         window=burn_in_step + n_step, seed=0)
    keys = table.insert(chunk)                    # T new keys; the chunk also fills one bootstrap row
    table.insert_once(chunks, ChunkIds(producer, seqs, acked_below))  # a re-sent chunk is not stored twice
    batch = table.sample(256, timeout=1.0)        # [B, L] windows, keys, probabilities, table size
    table.update_priorities(batch.keys, td_abs)   # raw |TD|; evicted keys are ignored
    table.save(path); other.load(path)            # atomic; sampling continues identically

Storage is a ring of ``capacity`` rows; key ``k`` lives in row ``k % capacity``. A chunk of ``T``
steps takes ``T + 1`` consecutive keys: ``T`` step rows and one *bootstrap row* holding only
``obs[T]`` (its per-step fields are zeros and its priority is 0, so it never starts a window). Every
row remembers the key of its chunk's bootstrap row (``end``). A window of ``L`` steps starting at key
``s`` reads observation ``k`` from key ``min(s + k, end)`` and step ``k`` from the same key, with
``mask[k] = s + k < end``: past the chunk's end it repeats the final observation and reads the
bootstrap row's zeros, and it never reads another chunk. Eviction is FIFO by key (a row is evicted
when a new key overwrites it); because keys increase, a stored step row's whole chunk tail is
still stored, so every sampleable window is intact.

The ring's arrays and the windows read from them are :class:`~algorithm.replay.ring.ChunkRing`'s; the
checks of what callers hand in are algorithm/replay/checks.py's; saving and loading the whole table are
algorithm/replay/snapshot.py's; this class adds priorities, the rate limiter, duplicate detection and
normalizer statistics.

Priorities are ``clip(raw, td_error_min, td_error_max) ** alpha`` in a float64 :class:`SumTree`.
All operations run under one lock (the rate limiter's condition, so that admission and action are
atomic); the hot paths are vectorised numpy plus compiled tree loops, with no per-item Python loops.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, cast

import numpy as np

from algorithm.normalizer import RunningMeanStd
from algorithm.replay.base import NormalizerStats, ReplayInfo
from algorithm.replay.checks import check_chunk, check_priorities, check_table_args, keys_int64
from algorithm.replay.dedup import FORGOTTEN, MAX_PRODUCERS, ChunkIds, ChunkLedger, Inserted
from algorithm.replay.rate_limiter import InsertTimeout, RateLimiter
from algorithm.replay.ring import ChunkRing
from algorithm.replay.snapshot import TableSnapshot
from algorithm.replay.sum_tree import SumTree
from algorithm.spaces import SensorSpec
from algorithm.types import Batch, Chunk


class ReplayConfigLike(Protocol):
    """The ``replay_config`` fields :meth:`PrioritizedTable.from_config` reads."""

    capacity: int
    alpha: float
    td_error_min: float
    td_error_max: float
    samples_per_insert: float | None
    batch_size: int
    samples_per_insert_tolerance: float
    min_size_to_sample: int
    max_producers: int


class PrioritizedTable(TableSnapshot):
    """Prioritized (``alpha > 0``) or uniform (``alpha == 0``) table of fixed-length windows.

    Args:
        capacity: rows stored, steps plus one bootstrap row per chunk (so a chunk may hold at
            most ``capacity - 1`` steps).
        sensors: observation sensors in order; each is stored with its own dtype (uint8 images
            stay uint8). Vector (non-image) sensors get a running normalizer.
        action_size: width of the flat action vector.
        window: ``L = burn_in_step + n_step`` steps per sampled window.
        burn_in: the first ``burn_in`` steps of a window look *back* from the sampled step: a
            window for key ``k`` covers steps ``k - burn_in .. k + n_step - 1`` of ``k``'s chunk,
            so step ``burn_in`` of the window is the sampled one. Look-back rows before the chunk's
            first stored row are zeros with ``mask`` False (the zero rows the original system
            prepended at episode start; docs/architecture.md section 5), and ``rnn_state`` is the
            stored state at the window's first valid row.
        alpha, td_error_min, td_error_max: priority transform (``alpha == 0``: uniform).
        rnn_state_size: width of the stored recurrent state (0: none; chunks must then have
            ``rnn_state=None``).
        rate_limiter: one per table; default: ratio not enforced, ``min_size_to_sample=1``.
        seed: seeds the table's numpy Generator (saved and restored with the table).
        max_producers: producers whose chunk ids :meth:`insert_once` keeps (a new one past it is
            refused with :class:`~algorithm.replay.dedup.ProducerLimitReached`; see
            algorithm/replay/dedup.py).
    """

    def __init__(
        self,
        capacity: int,
        sensors: tuple[SensorSpec, ...],
        action_size: int,
        window: int,
        alpha: float = 0.9,
        td_error_min: float = 0.01,
        td_error_max: float = 1.0,
        rnn_state_size: int = 0,
        rate_limiter: RateLimiter | None = None,
        seed: int | None = None,
        burn_in: int = 0,
        max_producers: int = MAX_PRODUCERS,
    ) -> None:
        check_table_args(
            capacity, sensors, action_size, window, burn_in, rnn_state_size, alpha, td_error_min, td_error_max
        )
        self.capacity = int(capacity)
        self.sensors = tuple(sensors)
        self.action_size = int(action_size)
        self.window = int(window)
        self.burn_in = int(burn_in)
        self.alpha = float(alpha)
        self.td_error_min = float(td_error_min)
        self.td_error_max = float(td_error_max)
        self.rnn_state_size = int(rnn_state_size)
        self.rate_limiter = rate_limiter or RateLimiter(1.0, 1, enforce_ratio=False)
        if self.rate_limiter.min_size_to_sample > self.capacity - 1:
            raise ValueError(
                f"min_size_to_sample {self.rate_limiter.min_size_to_sample} can never be reached "
                f"with capacity {self.capacity} (at most capacity - 1 steps are stored)"
            )
        self._lock = self.rate_limiter.condition
        self._rng = np.random.default_rng(seed)

        self._ring = ChunkRing(
            self.capacity, self.sensors, self.action_size, self.rnn_state_size, self.window, self.burn_in
        )
        self._tree = SumTree(self.capacity)  # the rows' priorities
        self._normalizers = {s.name: RunningMeanStd(s.shape) for s in self.sensors if not s.is_image}
        self.max_producers = int(max_producers)
        self._ledger = ChunkLedger(self.max_producers)  # which producers' chunks are stored (insert_once)
        self._max_priority = float(self._transform(np.ones(1))[0])
        self._counters = dict.fromkeys(
            (
                "inserted_chunks",
                "evicted_rows",
                "sample_calls",
                "priority_updates",
                "priority_updates_ignored",
                "rnn_state_updates",
                "duplicates",
                "stored_past_limiter",
            ),
            0,
        )

    @classmethod
    def from_config(
        cls,
        replay_config: ReplayConfigLike,
        sensors: tuple[SensorSpec, ...],
        action_size: int,
        window: int,
        rnn_state_size: int = 0,
        enforce_ratio: bool = False,
        seed: int | None = None,
        burn_in: int = 0,
    ) -> PrioritizedTable:
        """Build a table and its rate limiter from ``replay_config``.

        ``enforce_ratio=False`` (the single-process loop, which decides itself how many updates to
        run per env step): inserts never block and sampling waits only for ``min_size_to_sample``.
        ``True`` (a replay shared by separate actor and learner processes): inserts and samples
        also wait to keep ``samples_per_insert`` within ``samples_per_insert_tolerance``.
        """
        limiter = RateLimiter(
            samples_per_insert=replay_config.samples_per_insert or replay_config.batch_size,
            min_size_to_sample=replay_config.min_size_to_sample,
            tolerance=replay_config.samples_per_insert_tolerance,
            enforce_ratio=enforce_ratio,
        )
        return cls(
            capacity=replay_config.capacity,
            sensors=sensors,
            action_size=action_size,
            window=window,
            alpha=replay_config.alpha,
            td_error_min=replay_config.td_error_min,
            td_error_max=replay_config.td_error_max,
            rnn_state_size=rnn_state_size,
            rate_limiter=limiter,
            seed=seed,
            burn_in=burn_in,
            max_producers=replay_config.max_producers,
        )

    # ------------------------------------------------------------------ public interface

    def insert(self, chunk: Chunk, priorities: np.ndarray | None = None, timeout: float | None = None) -> np.ndarray:
        """Store ``chunk`` contiguously and return its ``T`` step keys (uint64, increasing).

        New rows get the highest priority seen so far unless raw ``priorities`` ``[T]`` are given.
        Blocks while the rate limiter says the learner is behind (only when it enforces the
        ratio); raises :class:`~algorithm.replay.rate_limiter.InsertTimeout` after ``timeout`` s.
        A chunk that does not match the table's specs raises ``ValueError`` and stores nothing.
        """
        t = self._check_chunk(chunk)
        new_p = None if priorities is None else self._transform(check_priorities(priorities, t, "insert"))
        with self._lock:
            self.rate_limiter.await_insert(t, timeout)
            return self._store(chunk, t, new_p)

    def insert_many(
        self,
        chunks: Sequence[Chunk],
        priorities: Sequence[np.ndarray | None] | None = None,
        timeout: float | None = None,
    ) -> list[np.ndarray]:
        """Store several chunks as one request, all or nothing; returns each chunk's keys.

        Every chunk (and its optional raw ``priorities``) is validated before any is stored, the
        rate limiter admits their total steps at once, and no other operation runs between them:
        either all are stored, with consecutive keys in order, or none (``ValueError`` naming
        ``chunks[i]``, or :class:`~algorithm.replay.rate_limiter.InsertTimeout`). For callers
        that hand over several chunks at a time, such as the replay server.
        """
        return self._insert(self._check_many(chunks, priorities), None, timeout).keys

    def insert_once(
        self,
        chunks: Sequence[Chunk],
        ids: ChunkIds,
        priorities: Sequence[np.ndarray | None] | None = None,
        timeout: float | None = None,
        producer_stopping: bool = False,
    ) -> Inserted:
        """:meth:`insert_many` for a producer that sends a chunk again when it missed the answer:
        a chunk already stored under ``(ids.producer, ids.seqs[i])`` is not stored again but
        answered with the keys it got (counted in ``info()["duplicates"]``); the new ones are
        stored all or nothing. The ids are saved with the table (algorithm/replay/dedup.py says
        what that guarantees and how little it keeps). A request of duplicates only is never held
        back by the rate limiter. Bad ``ids`` raise ``ValueError`` and store nothing; a new producer
        that would exceed ``max_producers`` raises
        :class:`~algorithm.replay.dedup.ProducerLimitReached` and stores nothing.

        ``producer_stopping``: these are the producer's last tries (it is stopping). When the rate
        limiter still holds them back after ``timeout`` they are stored anyway (their steps counted
        in ``info()["stored_past_limiter"]``) instead of raising ``InsertTimeout``: at a Ctrl-C of a
        whole run the learner stops first and draws no more, and what the actors collected is worth
        more in the table (for a resumed run) than thrown away. The overshoot is bounded by what a
        stopping producer holds (``ds/actor/sink.py``)."""
        checked = self._check_many(chunks, priorities)
        ids.check(len(checked))
        return self._insert(checked, ids, timeout, producer_stopping)

    def _check_many(
        self, chunks: Sequence[Chunk], priorities: Sequence[np.ndarray | None] | None
    ) -> list[tuple[Chunk, int, np.ndarray | None]]:
        """Validate every chunk and its raw priorities; returns ``(chunk, T, transformed priorities)``."""
        if priorities is not None and len(priorities) != len(chunks):
            raise ValueError(f"insert: {len(priorities)} priority arrays for {len(chunks)} chunks")
        checked: list[tuple[Chunk, int, np.ndarray | None]] = []
        for i, chunk in enumerate(chunks):
            p = None if priorities is None else priorities[i]
            try:
                t = self._check_chunk(chunk)
                new_p = None if p is None else self._transform(check_priorities(p, t, "insert"))
            except ValueError as e:
                raise ValueError(f"chunks[{i}]: {e}") from e
            checked.append((chunk, t, new_p))
        return checked

    def _insert(
        self,
        checked: list[tuple[Chunk, int, np.ndarray | None]],
        ids: ChunkIds | None,
        timeout: float | None,
        producer_stopping: bool = False,
    ) -> Inserted:
        with self._lock:
            known: list[int | None] = [None] * len(checked)
            if ids is not None:
                self._ledger.settle(ids)
                known = self._ledger.lookup(ids)
            steps = sum(t for (_, t, _), first in zip(checked, known, strict=True) if first is None)
            if steps:
                try:
                    self.rate_limiter.await_insert(steps, timeout)
                except InsertTimeout:
                    if not producer_stopping:
                        raise
                    self._counters["stored_past_limiter"] += steps
                if ids is not None:  # the wait released the lock: a copy of this request may have been
                    self._ledger.settle(ids)  # stored, or (nothing of it stored) its producer forgotten
                    known = self._ledger.lookup(ids)
            keys, duplicate = [], []
            for i, ((chunk, t, new_p), first) in enumerate(zip(checked, known, strict=True)):
                if first is None:
                    keys.append(self._store(chunk, t, new_p))
                    if ids is not None:
                        self._ledger.record(ids, ids.seqs[i], int(keys[-1][0]))
                else:  # the keys it was stored under; none if they are forgotten
                    known_keys = np.arange(first, first + t) if first != FORGOTTEN else np.empty(0)
                    keys.append(known_keys.astype(np.uint64))
                    self._counters["duplicates"] += 1
                duplicate.append(first is not None)
            return Inserted(keys, duplicate, self.rate_limiter.inserted)

    def _store(self, chunk: Chunk, t: int, new_p: np.ndarray | None) -> np.ndarray:
        """Write a validated, admitted chunk into the ring (the caller holds the lock)."""
        first = self._ring.next_key
        rows, evicted_steps, evicted_rows = self._ring.write(chunk, t)
        if new_p is None:
            new_p = np.full(t, self._max_priority)
        else:
            self._max_priority = max(self._max_priority, float(new_p.max()))
        self._tree.set(rows, np.append(new_p, 0.0))
        # Each observation counts once: a chunk cut mid-episode hands its last observation on
        # as the next chunk's first, so it is only counted here when the episode ended.
        ended = bool(chunk.terminated[-1] or chunk.truncated[-1])
        for spec, data in zip(self.sensors, chunk.obs, strict=True):
            if spec.name in self._normalizers:
                self._normalizers[spec.name].update(data if ended else data[:-1])

        self._counters["inserted_chunks"] += 1
        self._counters["evicted_rows"] += evicted_rows
        self.rate_limiter.record_insert(t, evicted_steps)
        return np.arange(first, first + t, dtype=np.uint64)

    def sample(self, batch_size: int, timeout: float | None = None) -> Batch:
        """Draw ``batch_size`` windows with probability ``priority / total`` (stratified).

        If every stored priority is 0, draws uniformly among sampleable rows. Waits for the rate
        limiter; raises :class:`~algorithm.replay.base.SampleTimeout` after ``timeout`` seconds.
        """
        b = int(batch_size)
        if b < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        with self._lock:
            self.rate_limiter.await_sample(b, timeout)
            size = self.rate_limiter.size
            total = self._tree.total
            if total > 0.0:
                rows = self._tree.sample_stratified(b, self._rng)
                probabilities = self._tree.get(rows) / total
            else:
                rows = self._ring.uniform_rows(b, self._rng)
                probabilities = np.full(b, 1.0 / size)
            batch = self._ring.gather(rows, probabilities, size)
            self._counters["sample_calls"] += 1
            self.rate_limiter.record_sample(b)
        return batch

    def windows_after(self, key: int, limit: int) -> Batch | None:
        """The windows starting at the oldest ``limit`` stored steps whose keys are ``>= key``, in key
        order, or None when there are none: what a learner scores to give new data its |TD| as
        priority (``sac_config.insert_td_priorities``). Not a sample: the rate limiter does not count
        it and it never waits. ``probabilities`` are the windows' current sampling probabilities."""
        if int(limit) < 1:
            raise ValueError(f"windows_after: limit must be >= 1, got {limit}")
        if int(key) < 0:
            raise ValueError(f"windows_after: key must be >= 0, got {key}")
        with self._lock:
            rows = self._ring.live_rows_from(int(key), int(limit))
            if not rows.shape[0]:
                return None
            total = self._tree.total
            size = self.rate_limiter.size
            probabilities = self._tree.get(rows) / total if total > 0.0 else np.full(rows.shape[0], 1.0 / size)
            return self._ring.gather(rows, probabilities, size)

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> None:
        """Set raw priorities (e.g. mean |TD| over heads) of ``keys``; keys that are evicted,
        bootstrap rows or never issued are ignored. Shapes must match; values finite and >= 0."""
        k64 = keys_int64(keys, "update_priorities")
        p = self._transform(check_priorities(priorities, k64.shape[0], "update_priorities"))
        rows = k64 % self.capacity
        with self._lock:
            valid = self._ring.live(k64, rows)
            n_valid = int(np.count_nonzero(valid))
            if n_valid:
                self._tree.set(rows[valid], p[valid])
                self._max_priority = max(self._max_priority, float(p[valid].max()))
            self._counters["priority_updates"] += n_valid
            self._counters["priority_updates_ignored"] += k64.shape[0] - n_valid

    def update_rnn_states(self, keys: np.ndarray, states: np.ndarray) -> None:
        """Overwrite the stored recurrent state of the steps ``keys`` with ``states [N, S]``
        (``sac_config.refresh_rnn_states``); evicted keys, bootstrap rows and keys never issued are
        ignored, as in :meth:`update_priorities`. States must be finite float32."""
        if not self.rnn_state_size:
            raise ValueError("update_rnn_states: this table stores no recurrent state (rnn_state_size=0)")
        k64 = keys_int64(keys, "update_rnn_states")
        s = np.asarray(states)
        if s.shape != (k64.shape[0], self.rnn_state_size) or s.dtype != np.float32:
            raise ValueError(
                f"update_rnn_states: states must be float32 [{k64.shape[0]}, {self.rnn_state_size}], "
                f"got {s.dtype} {list(s.shape)}"
            )
        if not np.isfinite(s).all():
            raise ValueError("update_rnn_states: states hold non-finite values")
        rows = k64 % self.capacity
        with self._lock:
            valid = self._ring.live(k64, rows)
            assert self._ring.rnn is not None
            self._ring.rnn[rows[valid]] = s[valid]
            self._counters["rnn_state_updates"] += int(np.count_nonzero(valid))

    def info(self) -> ReplayInfo:
        """Flat ``replay/*`` numbers plus ``"normalizer"``: ``{sensor name: {count, mean, var}}``."""
        with self._lock:
            lim = self.rate_limiter
            out: dict[str, Any] = {
                "size": lim.size,
                "capacity": self.capacity,
                "stored_rows": self._ring.stored_rows,
                "inserted_steps": lim.inserted,
                "evicted_steps": lim.evicted,
                "sampled_windows": lim.sampled,
                "samples_per_insert_actual": lim.sampled / lim.inserted if lim.inserted else 0.0,
                "next_key": self._ring.next_key,
                "max_priority": self._max_priority,
                "total_priority": self._tree.total,
                "producers": len(self._ledger),
                **self._counters,
                **lim.info(),
            }
            out["normalizer"] = self._normalizer_state()
        return cast(ReplayInfo, out)

    def normalizer_stats(self) -> dict[str, NormalizerStats]:
        """``{sensor name: {"count", "mean", "var"}}`` over every inserted observation of each vector
        sensor (rows ``0..T`` of every chunk); load into a :class:`RunningMeanStd` to normalize."""
        with self._lock:
            return self._normalizer_state()

    # ------------------------------------------------------------------ internals

    def _transform(self, raw: np.ndarray) -> np.ndarray:
        return np.power(np.clip(raw, self.td_error_min, self.td_error_max), self.alpha)

    def _normalizer_state(self) -> dict[str, NormalizerStats]:
        return {name: cast(NormalizerStats, rms.state_dict()) for name, rms in self._normalizers.items()}

    def _check_chunk(self, chunk: Chunk) -> int:
        return check_chunk(chunk, self.sensors, self.action_size, self.rnn_state_size, self.capacity)
