"""What the replay table checks of its callers' data before it takes the lock: chunks against the
table's specs, raw priorities, and keys. Every problem is a ``ValueError`` that names the field."""

from __future__ import annotations

from typing import Any

import numpy as np

from algorithm.spaces import SensorSpec
from algorithm.types import Chunk


def check_table_args(
    capacity: int,
    sensors: tuple[SensorSpec, ...],
    action_size: int,
    window: int,
    burn_in: int,
    rnn_state_size: int,
    alpha: float,
    td_error_min: float,
    td_error_max: float,
) -> None:
    """The arguments of a :class:`~algorithm.replay.table.PrioritizedTable`."""
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


def check_chunk(
    chunk: Chunk, sensors: tuple[SensorSpec, ...], action_size: int, rnn_state_size: int, capacity: int
) -> int:
    """Validate ``chunk`` against a table's specs; returns its number of steps ``T``."""
    rewards = np.asarray(chunk.rewards)
    if rewards.ndim != 1 or rewards.shape[0] < 1:
        raise ValueError(f"chunk.rewards must have shape [T] with T >= 1, got {rewards.shape}")
    t = rewards.shape[0]
    if t + 1 > capacity:
        raise ValueError(f"chunk of {t} steps needs {t + 1} rows but replay capacity is {capacity}")
    if len(chunk.obs) != len(sensors):
        raise ValueError(f"chunk has {len(chunk.obs)} observation sensors, the table expects {len(sensors)}")
    a = action_size
    fields: list[tuple[str, Any, tuple[int, ...], np.dtype]] = [
        (f"obs[{i}] ({s.name})", chunk.obs[i], (t + 1, *s.shape), np.dtype(s.dtype)) for i, s in enumerate(sensors)
    ]
    fields += [
        ("actions", chunk.actions, (t, a), np.dtype(np.float32)),
        ("prev_actions", chunk.prev_actions, (t, a), np.dtype(np.float32)),
        ("rewards", chunk.rewards, (t,), np.dtype(np.float32)),
        ("terminated", chunk.terminated, (t,), np.dtype(bool)),
        ("truncated", chunk.truncated, (t,), np.dtype(bool)),
        ("behaviour_logp", chunk.behaviour_logp, (t,), np.dtype(np.float32)),
    ]
    if rnn_state_size:
        fields.append(("rnn_state", chunk.rnn_state, (t, rnn_state_size), np.dtype(np.float32)))
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


def check_priorities(priorities: np.ndarray, n: int, where: str) -> np.ndarray:
    """``n`` raw priorities as float64, finite and >= 0."""
    p = np.asarray(priorities, dtype=np.float64)
    if p.shape != (n,):
        raise ValueError(f"{where}: priorities must have shape ({n},), got {p.shape}")
    if not np.isfinite(p).all() or (p < 0).any():
        raise ValueError(f"{where}: priorities must be finite and >= 0")
    return p


def keys_int64(keys: np.ndarray, what: str) -> np.ndarray:
    """``keys`` (a 1-D integer array) as int64; uint64 keys >= 2**63 wrap to negatives, which were
    never issued and so are ignored like evicted ones."""
    k = np.asarray(keys)
    if k.ndim != 1 or (k.size and k.dtype.kind not in "ui"):
        raise ValueError(f"{what}: keys must be a 1-D integer array, got {k.dtype} {k.shape}")
    return k.astype(np.int64)
