"""The replay table's storage: a ring of rows holding trajectory chunks, and the windows read from it.

:class:`ChunkRing` knows the layout described in algorithm/replay/table.py's docstring (keys, rows,
bootstrap rows, look-back) and nothing about priorities, rate limits or locking: the table holds
its lock around every call and keeps the priorities of the rows in its sum tree.
"""

from __future__ import annotations

import numpy as np

from algorithm.spaces import SensorSpec
from algorithm.types import Batch, Chunk

EMPTY = -1  # row key of a row that has never been written


class ChunkRing:
    """``capacity`` rows; key ``k`` lives in row ``k % capacity``; a chunk of ``T`` steps takes ``T + 1``
    consecutive keys (``T`` step rows and its bootstrap row). Windows are ``window`` steps, the first
    ``burn_in`` of them looking back from the sampled step."""

    def __init__(
        self,
        capacity: int,
        sensors: tuple[SensorSpec, ...],
        action_size: int,
        rnn_state_size: int,
        window: int,
        burn_in: int,
    ) -> None:
        self.capacity, self.window, self.burn_in = capacity, window, burn_in
        cap = capacity
        self.obs = [np.zeros((cap, *s.shape), dtype=s.dtype) for s in sensors]
        self.steps = {  # per-step fields, named as in Chunk and Batch
            "actions": np.zeros((cap, action_size), dtype=np.float32),
            "prev_actions": np.zeros((cap, action_size), dtype=np.float32),
            "rewards": np.zeros(cap, dtype=np.float32),
            "terminated": np.zeros(cap, dtype=bool),
            "truncated": np.zeros(cap, dtype=bool),
            "behaviour_logp": np.zeros(cap, dtype=np.float32),
        }
        self.rnn = np.zeros((cap, rnn_state_size), dtype=np.float32) if rnn_state_size else None
        self.row_key = np.full(cap, EMPTY, dtype=np.int64)
        self.end_key = np.full(cap, EMPTY, dtype=np.int64)  # key of the chunk's bootstrap row
        self.start_key = np.full(cap, EMPTY, dtype=np.int64)  # key of the chunk's first row
        self.next_key = 0

    @property
    def stored_rows(self) -> int:
        return int(min(self.next_key, self.capacity))

    def write(self, chunk: Chunk, t: int) -> tuple[np.ndarray, int, int]:
        """Store a validated chunk of ``t`` steps at the next keys; returns its ``t + 1`` rows (the step
        rows, then the bootstrap row) and how many step rows and rows in all it overwrote."""
        first = self.next_key
        keys = np.arange(first, first + t + 1, dtype=np.int64)
        rows = keys % self.capacity
        old = self.row_key[rows]
        stored = old != EMPTY
        evicted_steps = int(np.count_nonzero(stored & (old != self.end_key[rows])))

        # Plain slices when the chunk does not wrap the ring: much cheaper than index arrays.
        wraps = rows[t] < rows[0]
        span = rows if wraps else slice(rows[0], rows[t] + 1)
        steps = rows[:t] if wraps else slice(rows[0], rows[t])
        boot = rows[t]
        for store, data in zip(self.obs, chunk.obs, strict=True):
            store[span] = data
        for name, store in self.steps.items():
            store[steps] = getattr(chunk, name)
            store[boot] = 0  # masked window steps read these zeros
        if self.rnn is not None:
            self.rnn[steps] = chunk.rnn_state
        self.row_key[span] = keys
        self.end_key[span] = first + t
        self.start_key[span] = first
        self.next_key = first + t + 1
        return rows, evicted_steps, int(np.count_nonzero(stored))

    def live(self, k64: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Which keys still name a stored step (not evicted, not a bootstrap row, issued)."""
        return (k64 >= 0) & (self.row_key[rows] == k64) & (self.end_key[rows] != k64)

    def live_rows_from(self, key: int, limit: int) -> np.ndarray:
        """The rows of the oldest ``limit`` stored steps whose keys are ``>= key``, in key order."""
        low = max(key, self.next_key - self.capacity)
        # Bootstrap rows are at most one in two rows, so 2 * limit candidates hold limit steps.
        candidates = np.arange(low, min(self.next_key, low + 2 * limit), dtype=np.int64)
        rows = candidates % self.capacity
        return rows[self.live(candidates, rows)][:limit]

    def uniform_rows(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` rows drawn uniformly among stored step rows (rejecting bootstrap rows; at most
        half of the stored rows are bootstrap rows, so a few vectorised rounds suffice)."""
        low = max(0, self.next_key - self.capacity)
        picked = np.empty(0, dtype=np.int64)
        while picked.shape[0] < n:
            keys = rng.integers(low, self.next_key, size=2 * n)
            rows = keys % self.capacity
            picked = np.concatenate([picked, rows[self.end_key[rows] != keys]])
        return picked[:n]

    def gather(self, rows: np.ndarray, probabilities: np.ndarray, size: int) -> Batch:
        """The windows whose sampled steps are in ``rows``."""
        keys = self.row_key[rows]
        ends = self.end_key[rows][:, None]
        pos = (keys - self.burn_in)[:, None] + np.arange(self.window + 1, dtype=np.int64)
        if not self.burn_in:
            read = np.minimum(pos, ends) % self.capacity  # [B, L+1]; clamped to the bootstrap row
            step = read[:, :-1]  # bootstrap rows hold zeros, so masked steps come out zero/False
            return Batch(
                keys=keys.astype(np.uint64),
                probabilities=probabilities,
                table_size=int(size),
                obs=[store[read] for store in self.obs],
                mask=pos[:, :-1] < ends,
                rnn_state=None if self.rnn is None else self.rnn[rows],
                **{name: store[step] for name, store in self.steps.items()},
            )
        # Look-back: rows before the chunk's first live row (evicted ones included) read as zeros.
        starts = np.maximum(self.start_key[rows], self.next_key - self.capacity)[:, None]
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
            obs=[zero_before(store[read], before) for store in self.obs],
            mask=mask,
            rnn_state=None if self.rnn is None else self.rnn[read[:, 0]],
            **{name: zero_before(store[step], before[:, :-1]) for name, store in self.steps.items()},
        )

    # -- snapshots: the arrays are saved under these names (files written before the split load)

    def arrays(self) -> dict[str, np.ndarray]:
        """The ring's arrays by their names in a replay file (not copies)."""
        arrays = {f"obs_{i}": store for i, store in enumerate(self.obs)}
        arrays.update(self.steps)
        arrays.update(row_key=self.row_key, end_key=self.end_key, start_key=self.start_key)
        if self.rnn is not None:
            arrays["rnn_state"] = self.rnn
        return arrays

    def checked_step_rows(self, data: dict[str, np.ndarray], next_key: int) -> np.ndarray:
        """Check that a file's row keys form a ring of consecutive chunks ending before ``next_key``;
        returns which rows are step rows. Raises ``ValueError``."""
        cap = self.capacity
        row_key, end_key, start_key = data["row_key"], data["end_key"], data["start_key"]
        stored = row_key != EMPTY
        rk, ek = row_key[stored], end_key[stored]
        if not (
            (rk % cap == np.flatnonzero(stored)).all()
            and (rk >= next_key - cap).all()
            and (ek >= rk).all()
            and (ek < next_key).all()
            and (row_key[ek % cap] == ek).all()
            and (end_key[~stored] == EMPTY).all()
            and (start_key[stored] <= rk).all()
            and (start_key[~stored] == EMPTY).all()
        ):
            raise ValueError("row keys are not a ring of consecutive chunks")
        return stored & (row_key != end_key)

    def install(self, data: dict[str, np.ndarray], next_key: int) -> None:
        """Take a checked file's arrays (:meth:`checked_step_rows`) as the ring's."""
        self.obs = [data[f"obs_{i}"] for i in range(len(self.obs))]
        self.steps = {name: data[name] for name in self.steps}
        self.rnn = data.get("rnn_state")
        self.row_key, self.end_key, self.start_key = data["row_key"], data["end_key"], data["start_key"]
        self.next_key = next_key
