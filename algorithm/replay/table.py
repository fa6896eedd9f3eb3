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

Priorities are ``clip(raw, td_error_min, td_error_max) ** alpha`` in a float64 :class:`SumTree`.
All operations run under one lock (the rate limiter's condition, so that admission and action are
atomic); the hot paths are vectorised numpy plus compiled tree loops, with no per-item Python loops.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol, cast

import numpy as np

from algorithm.normalizer import RunningMeanStd
from algorithm.replay import persistence
from algorithm.replay.base import NormalizerStats, ReplayInfo
from algorithm.replay.dedup import FORGOTTEN, MAX_PRODUCERS, ChunkIds, ChunkLedger, Inserted
from algorithm.replay.rate_limiter import InsertTimeout, RateLimiter
from algorithm.replay.sum_tree import SumTree
from algorithm.spaces import SensorSpec
from algorithm.types import Batch, Chunk

_EMPTY = -1  # row key of a row that has never been written


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


class PrioritizedTable:
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
        if int(capacity) < 2:
            raise ValueError(f"replay capacity must be >= 2 rows, got {capacity}")
        if int(window) < 1:
            raise ValueError(f"replay window (burn_in_step + n_step) must be >= 1, got {window}")
        if not 0 <= int(burn_in) < int(window):
            raise ValueError(f"replay burn_in must be in [0, window), got burn_in={burn_in}, window={window}")
        if int(action_size) < 1:
            raise ValueError(f"action_size must be >= 1, got {action_size}")
        if int(rnn_state_size) < 0:
            raise ValueError(f"rnn_state_size must be >= 0, got {rnn_state_size}")
        if not 0.0 <= alpha <= 1.0:
            raise ValueError(f"replay alpha must be in [0, 1], got {alpha}")
        if not 0.0 <= td_error_min <= td_error_max or not np.isfinite(td_error_max):
            raise ValueError(f"need 0 <= td_error_min <= td_error_max < inf, got {td_error_min}, {td_error_max}")
        names = [s.name for s in sensors]
        if not sensors or len(set(names)) != len(names):
            raise ValueError(f"replay needs at least one sensor and unique sensor names, got {names}")
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

        cap, a = self.capacity, self.action_size
        self._obs = [np.zeros((cap, *s.shape), dtype=s.dtype) for s in self.sensors]
        self._steps = {  # per-step fields, named as in Chunk and Batch
            "actions": np.zeros((cap, a), dtype=np.float32),
            "prev_actions": np.zeros((cap, a), dtype=np.float32),
            "rewards": np.zeros(cap, dtype=np.float32),
            "terminated": np.zeros(cap, dtype=bool),
            "truncated": np.zeros(cap, dtype=bool),
            "behaviour_logp": np.zeros(cap, dtype=np.float32),
        }
        self._rnn = np.zeros((cap, self.rnn_state_size), dtype=np.float32) if self.rnn_state_size else None
        self._row_key = np.full(cap, _EMPTY, dtype=np.int64)
        self._end_key = np.full(cap, _EMPTY, dtype=np.int64)
        self._start_key = np.full(cap, _EMPTY, dtype=np.int64)  # key of the chunk's first row
        self._tree = SumTree(cap)
        self._normalizers = {s.name: RunningMeanStd(s.shape) for s in self.sensors if not s.is_image}
        self._next_key = 0
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
        new_p = None if priorities is None else self._transform(self._check_priorities(priorities, t, "insert"))
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
                new_p = None if p is None else self._transform(self._check_priorities(p, t, "insert"))
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
        first = self._next_key
        keys = np.arange(first, first + t + 1, dtype=np.int64)
        rows = keys % self.capacity
        old = self._row_key[rows]
        stored = old != _EMPTY
        evicted_steps = int(np.count_nonzero(stored & (old != self._end_key[rows])))

        # Plain slices when the chunk does not wrap the ring: much cheaper than index arrays.
        wraps = rows[t] < rows[0]
        span = rows if wraps else slice(rows[0], rows[t] + 1)
        steps = rows[:t] if wraps else slice(rows[0], rows[t])
        boot = rows[t]
        for store, data in zip(self._obs, chunk.obs, strict=True):
            store[span] = data
        for name, store in self._steps.items():
            store[steps] = getattr(chunk, name)
            store[boot] = 0  # masked window steps read these zeros
        if self._rnn is not None:
            self._rnn[steps] = chunk.rnn_state
        self._row_key[span] = keys
        self._end_key[span] = first + t
        self._start_key[span] = first

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

        self._next_key = first + t + 1
        self._counters["inserted_chunks"] += 1
        self._counters["evicted_rows"] += int(np.count_nonzero(stored))
        self.rate_limiter.record_insert(t, evicted_steps)
        return keys[:t].astype(np.uint64)

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
                rows = self._uniform_rows(b)
                probabilities = np.full(b, 1.0 / size)
            batch = self._gather(rows, probabilities, size)
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
            low = max(int(key), self._next_key - self.capacity)
            # Bootstrap rows are at most one in two rows, so 2 * limit candidates hold limit steps.
            candidates = np.arange(low, min(self._next_key, low + 2 * int(limit)), dtype=np.int64)
            rows = candidates % self.capacity
            rows = rows[self._live(candidates, rows)][: int(limit)]
            if not rows.shape[0]:
                return None
            total = self._tree.total
            size = self.rate_limiter.size
            probabilities = self._tree.get(rows) / total if total > 0.0 else np.full(rows.shape[0], 1.0 / size)
            return self._gather(rows, probabilities, size)

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> None:
        """Set raw priorities (e.g. mean |TD| over heads) of ``keys``; keys that are evicted,
        bootstrap rows or never issued are ignored. Shapes must match; values finite and >= 0."""
        k64 = _keys_int64(keys, "update_priorities")
        p = self._transform(self._check_priorities(priorities, k64.shape[0], "update_priorities"))
        rows = k64 % self.capacity
        with self._lock:
            valid = self._live(k64, rows)
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
        if self._rnn is None:
            raise ValueError("update_rnn_states: this table stores no recurrent state (rnn_state_size=0)")
        k64 = _keys_int64(keys, "update_rnn_states")
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
            valid = self._live(k64, rows)
            self._rnn[rows[valid]] = s[valid]
            self._counters["rnn_state_updates"] += int(np.count_nonzero(valid))

    def _live(self, k64: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Which keys still name a stored step (not evicted, not a bootstrap row, issued). Under the lock."""
        return (k64 >= 0) & (self._row_key[rows] == k64) & (self._end_key[rows] != k64)

    def info(self) -> ReplayInfo:
        """Flat ``replay/*`` numbers plus ``"normalizer"``: ``{sensor name: {count, mean, var}}``."""
        with self._lock:
            lim = self.rate_limiter
            out: dict[str, Any] = {
                "size": lim.size,
                "capacity": self.capacity,
                "stored_rows": int(min(self._next_key, self.capacity)),
                "inserted_steps": lim.inserted,
                "evicted_steps": lim.evicted,
                "sampled_windows": lim.sampled,
                "samples_per_insert_actual": lim.sampled / lim.inserted if lim.inserted else 0.0,
                "next_key": self._next_key,
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
                "next_key": self._next_key,
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
            for name, value in attributes.items():
                setattr(self, name, value)

    # ------------------------------------------------------------------ internals

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
        arrays = {f"obs_{i}": store for i, store in enumerate(self._obs)}
        arrays.update(self._steps)
        arrays.update(
            row_key=self._row_key,
            end_key=self._end_key,
            start_key=self._start_key,
            priorities=self._tree.leaves,
        )
        if self._rnn is not None:
            arrays["rnn_state"] = self._rnn
        for i, s in enumerate(self.sensors):
            if s.name in self._normalizers:
                state = self._normalizers[s.name].state_dict()
                arrays[f"norm_mean_{i}"], arrays[f"norm_var_{i}"] = state["mean"], state["var"]
        return {name: arr.copy() for name, arr in arrays.items()} if copy else arrays

    def _validated_state(
        self, data: dict[str, np.ndarray], meta: dict[str, Any]
    ) -> tuple[dict[str, Any], dict[str, int]]:
        """Check a loaded file's internal consistency; return the attributes to install and the
        rate limiter's counters."""
        cap, next_key = self.capacity, int(meta["next_key"])
        row_key, end_key, leaves = data["row_key"], data["end_key"], data["priorities"]
        start_key = data["start_key"]
        stored = row_key != _EMPTY
        rk, ek = row_key[stored], end_key[stored]
        if not (
            (rk % cap == np.flatnonzero(stored)).all()
            and (rk >= next_key - cap).all()
            and (ek >= rk).all()
            and (ek < next_key).all()
            and (row_key[ek % cap] == ek).all()
            and (end_key[~stored] == _EMPTY).all()
            and (start_key[stored] <= rk).all()
            and (start_key[~stored] == _EMPTY).all()
        ):
            raise ValueError("row keys are not a ring of consecutive chunks")
        is_step = stored & (row_key != end_key)
        if not np.isfinite(leaves).all() or (leaves < 0).any() or (leaves[~is_step] != 0).any():
            raise ValueError("priorities must be finite, >= 0, and 0 on bootstrap and empty rows")
        lim = {k: int(meta["rate_limiter"][k]) for k in ("inserted", "evicted", "sampled")}
        if min(lim.values()) < 0 or lim["inserted"] - lim["evicted"] != int(np.count_nonzero(is_step)):
            raise ValueError(f"rate limiter counters {lim} disagree with the stored rows")
        # A counter added after the snapshot was written (rnn_state_updates) starts at 0.
        counters = {name: int(meta["counters"].get(name, 0)) for name in self._counters}
        max_priority = float(meta["max_priority"])
        if not 0.0 <= max_priority < np.inf:
            raise ValueError(f"max_priority must be finite and >= 0, got {max_priority}")
        tree = SumTree(cap)
        tree.set_all(leaves)
        rng = np.random.default_rng()
        rng.bit_generator.state = meta["rng"]
        ledger = ChunkLedger.from_state(meta.get("ledger", []), next_key, self.max_producers)  # old files: none
        normalizers = {}
        for i, s in enumerate(self.sensors):
            if s.name in self._normalizers:
                rms = RunningMeanStd(s.shape)
                rms.load_state_dict(
                    {
                        "count": meta["normalizer_counts"][s.name],
                        "mean": data[f"norm_mean_{i}"],
                        "var": data[f"norm_var_{i}"],
                    }
                )
                normalizers[s.name] = rms
        attributes = {
            "_obs": [data[f"obs_{i}"] for i in range(len(self.sensors))],
            "_steps": {name: data[name] for name in self._steps},
            "_rnn": data.get("rnn_state"),
            "_row_key": row_key,
            "_end_key": end_key,
            "_start_key": start_key,
            "_tree": tree,
            "_normalizers": normalizers,
            "_next_key": next_key,
            "_max_priority": max_priority,
            "_counters": counters,
            "_rng": rng,
            "_ledger": ledger,
        }
        return attributes, lim

    def _transform(self, raw: np.ndarray) -> np.ndarray:
        return np.power(np.clip(raw, self.td_error_min, self.td_error_max), self.alpha)

    def _normalizer_state(self) -> dict[str, NormalizerStats]:
        return {name: cast(NormalizerStats, rms.state_dict()) for name, rms in self._normalizers.items()}

    def _uniform_rows(self, n: int) -> np.ndarray:
        """``n`` rows drawn uniformly among stored step rows (rejecting bootstrap rows; at most
        half of the stored rows are bootstrap rows, so a few vectorised rounds suffice)."""
        low = max(0, self._next_key - self.capacity)
        picked = np.empty(0, dtype=np.int64)
        while picked.shape[0] < n:
            keys = self._rng.integers(low, self._next_key, size=2 * n)
            rows = keys % self.capacity
            picked = np.concatenate([picked, rows[self._end_key[rows] != keys]])
        return picked[:n]

    def _gather(self, rows: np.ndarray, probabilities: np.ndarray, size: int) -> Batch:
        keys = self._row_key[rows]
        ends = self._end_key[rows][:, None]
        pos = (keys - self.burn_in)[:, None] + np.arange(self.window + 1, dtype=np.int64)
        if not self.burn_in:
            read = np.minimum(pos, ends) % self.capacity  # [B, L+1]; clamped to the bootstrap row
            step = read[:, :-1]  # bootstrap rows hold zeros, so masked steps come out zero/False
            return Batch(
                keys=keys.astype(np.uint64),
                probabilities=probabilities,
                table_size=int(size),
                obs=[store[read] for store in self._obs],
                mask=pos[:, :-1] < ends,
                rnn_state=None if self._rnn is None else self._rnn[rows],
                **{name: store[step] for name, store in self._steps.items()},
            )
        # Look-back: rows before the chunk's first live row (evicted ones included) read as zeros.
        starts = np.maximum(self._start_key[rows], self._next_key - self.capacity)[:, None]
        read = np.clip(pos, starts, ends) % self.capacity
        before = pos < starts
        step = read[:, :-1]
        mask = ~before[:, :-1] & (pos[:, :-1] < ends)

        def zero_before(x: np.ndarray, where: np.ndarray) -> np.ndarray:
            return np.where(where.reshape(where.shape + (1,) * (x.ndim - 2)), np.zeros((), x.dtype), x)

        return Batch(
            keys=keys.astype(np.uint64),
            probabilities=probabilities,
            table_size=int(size),
            obs=[zero_before(store[read], before) for store in self._obs],
            mask=mask,
            rnn_state=None if self._rnn is None else self._rnn[read[:, 0]],
            **{name: zero_before(store[step], before[:, :-1]) for name, store in self._steps.items()},
        )

    def _check_priorities(self, priorities: np.ndarray, n: int, where: str) -> np.ndarray:
        p = np.asarray(priorities, dtype=np.float64)
        if p.shape != (n,):
            raise ValueError(f"{where}: priorities must have shape ({n},), got {p.shape}")
        if not np.isfinite(p).all() or (p < 0).any():
            raise ValueError(f"{where}: priorities must be finite and >= 0")
        return p

    def _check_chunk(self, chunk: Chunk) -> int:
        """Validate ``chunk`` against the table's specs; returns ``T``. Raises ``ValueError``."""
        rewards = np.asarray(chunk.rewards)
        if rewards.ndim != 1 or rewards.shape[0] < 1:
            raise ValueError(f"chunk.rewards must have shape [T] with T >= 1, got {rewards.shape}")
        t = rewards.shape[0]
        if t + 1 > self.capacity:
            raise ValueError(f"chunk of {t} steps needs {t + 1} rows but replay capacity is {self.capacity}")
        if len(chunk.obs) != len(self.sensors):
            raise ValueError(f"chunk has {len(chunk.obs)} observation sensors, the table expects {len(self.sensors)}")
        a = self.action_size
        fields: list[tuple[str, Any, tuple[int, ...], np.dtype]] = [
            (f"obs[{i}] ({s.name})", chunk.obs[i], (t + 1, *s.shape), np.dtype(s.dtype))
            for i, s in enumerate(self.sensors)
        ]
        fields += [
            ("actions", chunk.actions, (t, a), np.dtype(np.float32)),
            ("prev_actions", chunk.prev_actions, (t, a), np.dtype(np.float32)),
            ("rewards", chunk.rewards, (t,), np.dtype(np.float32)),
            ("terminated", chunk.terminated, (t,), np.dtype(bool)),
            ("truncated", chunk.truncated, (t,), np.dtype(bool)),
            ("behaviour_logp", chunk.behaviour_logp, (t,), np.dtype(np.float32)),
        ]
        if self.rnn_state_size:
            fields.append(("rnn_state", chunk.rnn_state, (t, self.rnn_state_size), np.dtype(np.float32)))
        elif chunk.rnn_state is not None:
            raise ValueError("chunk.rnn_state is set but the table was built with rnn_state_size=0")
        for name, arr, shape, dtype in fields:
            if not isinstance(arr, np.ndarray):
                raise ValueError(f"chunk.{name} must be a numpy array, got {type(arr).__name__}")
            if arr.shape != shape or arr.dtype != dtype:
                raise ValueError(f"chunk.{name}: expected {dtype} {shape}, got {arr.dtype} {arr.shape}")
            if dtype.kind == "f" and not np.isfinite(arr).all():
                raise ValueError(f"chunk.{name} has non-finite values")
        for name in ("terminated", "truncated"):
            if getattr(chunk, name)[:-1].any():
                raise ValueError(f"chunk.{name}: only the last step of a chunk may be terminated or truncated")
        return t


def _keys_int64(keys: np.ndarray, what: str) -> np.ndarray:
    """``keys`` (a 1-D integer array) as int64; uint64 keys >= 2**63 wrap to negatives, which were
    never issued and so are ignored like evicted ones."""
    k = np.asarray(keys)
    if k.ndim != 1 or (k.size and k.dtype.kind not in "ui"):
        raise ValueError(f"{what}: keys must be a 1-D integer array, got {k.dtype} {k.shape}")
    return k.astype(np.int64)
