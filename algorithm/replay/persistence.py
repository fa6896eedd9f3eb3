"""Replay files: one ``.npz`` archive of plain arrays plus a JSON ``meta`` entry; never pickles.

:func:`write_atomic` writes to a temp file beside the target, fsyncs it, renames it over the target
and fsyncs the directory, so a crash leaves either the old file or the new one. :func:`read_checked`
reads everything and checks the format, the layout the reader expects and every array's name,
shape and dtype before returning; any problem is a ``ValueError`` that names the file and the field.
It opens only a regular file, never blocking (:func:`algorithm.files.open_regular`): a FIFO, device
or socket in its place is refused at once. :func:`restored_state` then checks that what a table file
holds is consistent with itself (priorities against the rows, counters against each other).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from algorithm.errors import CheckpointError
from algorithm.files import atomic_write, open_regular
from algorithm.normalizer import RunningMeanStd
from algorithm.spaces import SensorSpec

FORMAT = "asac-replay-v1"


def write_atomic(
    path: Path,
    arrays: dict[str, np.ndarray],
    meta: dict[str, Any],
    before_replace: Callable[[], object] | None = None,
) -> None:
    """Write ``arrays`` and JSON ``meta`` to ``path`` atomically (temp file, fsync, rename);
    ``before_replace``: see :func:`algorithm.files.atomic_write` (raise to keep the old file)."""
    contents: dict[str, Any] = {**arrays, "meta": np.array(json.dumps({"format": FORMAT, **meta}))}
    atomic_write(path, lambda f: np.savez(f, **contents), before_replace)


def snapshot_kept(path: Path) -> str:
    """What a failed save of the snapshot ``path`` leaves, for its log line."""
    if path.exists():
        return f"{path} keeps the previous snapshot"
    return "there is no earlier snapshot: what the replay holds now is in memory only"


class _Loadable(Protocol):  # a PrioritizedTable (snapshot.py, its mixin, imports this module)
    def load(self, path: Path) -> None: ...


def load_replay_snapshot(table: _Loadable, path: Path) -> None:
    """``table.load(path)``, with a file that cannot be loaded (damaged, truncated, another task's)
    as a :class:`CheckpointError`: the table and the file stay as they are."""
    try:
        table.load(path)
    except ValueError as e:
        raise CheckpointError(
            f"replay snapshot {e}; nothing was overwritten: repair it, or move it away to start with an empty replay"
        ) from None


def read_checked(
    path: Path,
    layout: dict[str, Any],
    expected: dict[str, tuple[tuple[int, ...], np.dtype]],
    follow_symlinks: bool = True,
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a file written by :func:`write_atomic`; returns ``(arrays, meta)``.

    ``meta`` must hold every ``layout`` entry with the same value, and the arrays must be exactly
    ``expected`` (name -> shape, dtype). ``follow_symlinks=False``: a symlink at ``path`` is refused.
    """
    try:
        with open_regular(path, follow_symlinks=follow_symlinks) as raw, np.load(raw, allow_pickle=False) as f:
            arrays = {name: f[name] for name in f.files}
        meta = json.loads(str(arrays.pop("meta")))
    except Exception as e:  # numpy and zipfile raise many types for a damaged file (NotImplementedError too)
        why = str(e) if len(str(e)) <= 300 else f"{str(e)[:300]}..."  # zipfile may quote kilobytes of the file
        raise ValueError(f"{path}: not a readable replay file ({type(e).__name__}: {why})") from e
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ValueError(f"{path}: not a replay file of format {FORMAT}")
    for name, want in layout.items():
        if meta.get(name) != want:
            raise ValueError(f"{path}: saved {name} is {meta.get(name)!r}, this table has {want!r}")
    if set(arrays) != set(expected):
        raise ValueError(f"{path}: arrays {sorted(arrays)} do not match the expected {sorted(expected)}")
    for name, (shape, dtype) in expected.items():
        got = arrays[name]
        if got.shape != shape or got.dtype != dtype:
            raise ValueError(f"{path}: array {name!r} is {got.dtype} {got.shape}, expected {dtype} {shape}")
    return arrays, meta


def normalizer_arrays(normalized: dict[int, RunningMeanStd]) -> dict[str, np.ndarray]:
    """The arrays a table file holds for its running normalizers (sensor index -> normalizer); their
    counts go in ``meta["normalizer_counts"]``. :func:`restored_state` reads them back."""
    arrays = {}
    for i, rms in normalized.items():
        state = rms.state_dict()
        arrays[f"norm_mean_{i}"], arrays[f"norm_var_{i}"] = state["mean"], state["var"]
    return arrays


@dataclass
class RestoredState:
    """A table file's state besides the ring's arrays and the chunk ledger, checked."""

    priorities: np.ndarray
    limiter: dict[str, int]  # the rate limiter's inserted / evicted / sampled
    counters: dict[str, int]
    max_priority: float
    rng: np.random.Generator
    normalizers: dict[str, RunningMeanStd]


def restored_state(
    data: dict[str, np.ndarray],
    meta: dict[str, Any],
    is_step: np.ndarray,
    counter_names: tuple[str, ...],
    normalized: dict[int, SensorSpec],
) -> RestoredState:
    """The state of a table file that :func:`read_checked` returned, checked against the file's own step
    rows ``is_step``: priorities finite, >= 0 and 0 off step rows; the rate limiter's counters agreeing
    with the rows stored. ``normalized``: sensor index -> spec of the sensors with a running normalizer.
    A counter added after the file was written (rnn_state_updates) starts at 0. Raises ``ValueError``."""
    leaves = data["priorities"]
    if not np.isfinite(leaves).all() or (leaves < 0).any() or (leaves[~is_step] != 0).any():
        raise ValueError("priorities must be finite, >= 0, and 0 on bootstrap and empty rows")
    limiter = {k: int(meta["rate_limiter"][k]) for k in ("inserted", "evicted", "sampled")}
    if min(limiter.values()) < 0 or limiter["inserted"] - limiter["evicted"] != int(np.count_nonzero(is_step)):
        raise ValueError(f"rate limiter counters {limiter} disagree with the stored rows")
    max_priority = float(meta["max_priority"])
    if not 0.0 <= max_priority < np.inf:
        raise ValueError(f"max_priority must be finite and >= 0, got {max_priority}")
    rng = np.random.default_rng()
    rng.bit_generator.state = meta["rng"]
    normalizers = {}
    for i, sensor in normalized.items():
        rms = RunningMeanStd(sensor.shape)
        count = meta["normalizer_counts"][sensor.name]
        rms.load_state_dict({"count": count, "mean": data[f"norm_mean_{i}"], "var": data[f"norm_var_{i}"]})
        normalizers[sensor.name] = rms
    counters = {name: int(meta["counters"].get(name, 0)) for name in counter_names}
    return RestoredState(leaves, limiter, counters, max_priority, rng, normalizers)
