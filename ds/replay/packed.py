"""Sampled batches in one buffer: the layout of a SampleReply's ``data`` (protos/replay.proto).

A learner receives hundreds of batches a second; decoding each of a batch's dozen tensors from its
own proto field (a bytes object, a copy, a dtype and shape check, a finiteness pass) cost more CPU
than the sampling itself. Here both ends compute every field's offset from what they already agree
on (the replay's specs, ``B`` and ``L``), so the receiver copies the buffer once, into memory of its
choosing (pinned on CUDA: the copy to the device then does not block), and takes each field as a
view of it. The checks stay, over regions rather than fields: the length exactly, the bools (0 or
1) in one pass and the float32 fields (observations, actions, rewards, behaviour log-probabilities,
recurrent state) in one finiteness pass.

    layout = BatchLayout.of(specs, batch_size=256, window=1)
    data = pack_batches(layout, batches)                          # server: bytes for SampleReply.data
    batches = unpack_batches(layout, data, table_sizes, allocate=pinned)  # client; allocate: optional
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from algorithm.spaces import SensorSpec
from algorithm.types import Batch
from ds.net.wire import WireError

ALIGN = 8  # every field and every batch starts at a multiple of this many bytes
# Memory for a reply's batches: a writable uint8 array of the given number of bytes.
Allocate = Callable[[int], np.ndarray]
_F32, _F64, _U64, _BOOL = np.dtype(np.float32), np.dtype(np.float64), np.dtype(np.uint64), np.dtype(bool)


@dataclass(frozen=True)
class Field:
    """One array of a batch: its place in :attr:`Batch` (``obs`` fields by sensor index), dtype,
    shape and byte offset from the batch's start."""

    name: str
    sensor: int | None
    dtype: np.dtype
    shape: tuple[int, ...]
    offset: int

    @property
    def little(self) -> np.dtype:
        """The dtype as the buffer holds it (little-endian: the native order on x86 and ARM)."""
        return self.dtype.newbyteorder("<")

    @property
    def nbytes(self) -> int:
        return math.prod(self.shape) * self.dtype.itemsize


@dataclass(frozen=True)
class BatchLayout:
    """Where each field of a ``batch_size`` x ``window`` batch lies (see the module docstring).

    ``fields`` are in buffer order; ``float32_span`` and ``bool_span`` are the ``(start, end)`` byte
    ranges checked in one pass each; ``batch_bytes`` is one batch's size, padding included."""

    batch_size: int
    window: int
    fields: tuple[Field, ...]
    float32_span: tuple[int, int]
    bool_span: tuple[int, int]
    batch_bytes: int

    @classmethod
    def of(
        cls, sensors: Sequence[SensorSpec], action_size: int, batch_size: int, window: int, rnn_state_size: int = 0
    ) -> BatchLayout:
        b, length, a = int(batch_size), int(window), int(action_size)
        float32_obs = [i for i, s in enumerate(sensors) if np.dtype(s.dtype) == _F32]
        other_obs = [i for i, s in enumerate(sensors) if np.dtype(s.dtype) != _F32]
        plan: list[tuple[str, int | None, np.dtype, tuple[int, ...]]] = [
            ("keys", None, _U64, (b,)),
            ("probabilities", None, _F64, (b,)),
            *(("obs", i, _F32, (b, length + 1, *sensors[i].shape)) for i in float32_obs),
            ("actions", None, _F32, (b, length, a)),
            ("prev_actions", None, _F32, (b, length, a)),
            ("rewards", None, _F32, (b, length)),
            ("behaviour_logp", None, _F32, (b, length)),
            *([("rnn_state", None, _F32, (b, int(rnn_state_size)))] if rnn_state_size else []),
            *(("obs", i, np.dtype(sensors[i].dtype), (b, length + 1, *sensors[i].shape)) for i in other_obs),
            ("terminated", None, _BOOL, (b, length)),
            ("truncated", None, _BOOL, (b, length)),
            ("mask", None, _BOOL, (b, length)),
        ]
        fields, offset = [], 0
        for name, sensor, dtype, shape in plan:
            offset = _aligned(offset)
            fields.append(Field(name, sensor, dtype, tuple(shape), offset))
            offset += fields[-1].nbytes
        f32 = [f for f in fields if f.dtype == _F32]
        bools = [f for f in fields if f.dtype == _BOOL]
        return cls(
            batch_size=b,
            window=length,
            fields=tuple(fields),
            float32_span=(f32[0].offset, f32[-1].offset + f32[-1].nbytes),
            bool_span=(bools[0].offset, bools[-1].offset + bools[-1].nbytes),
            batch_bytes=_aligned(offset),
        )


def pack_batches(layout: BatchLayout, batches: Sequence[Batch]) -> bytes:
    """The buffer of ``batches`` (each ``layout.batch_size`` x ``layout.window``), one after another."""
    buffer = np.zeros(layout.batch_bytes * len(batches), dtype=np.uint8)
    pack_batches_into(layout, batches, buffer)
    return buffer.tobytes()


def pack_batches_into(layout: BatchLayout, batches: Sequence[Batch], buffer: np.ndarray) -> None:
    """Write ``batches`` into ``buffer`` (uint8, ``layout.batch_bytes * len(batches)`` bytes) as
    :func:`pack_batches` lays them out; the padding between fields is left as it was."""
    if buffer.shape != (layout.batch_bytes * len(batches),):
        raise ValueError(f"{len(batches)} batches take {layout.batch_bytes * len(batches)} bytes, the buffer holds "
                         f"{buffer.shape}")  # fmt: skip
    for n, batch in enumerate(batches):
        base = n * layout.batch_bytes
        for f in layout.fields:
            source = np.ascontiguousarray(_array(batch, f), dtype=f.little)
            if source.shape != f.shape:
                raise ValueError(f"{_where(f)} is of shape {list(source.shape)}, the layout expects {list(f.shape)}")
            buffer[base + f.offset : base + f.offset + f.nbytes] = source.reshape(-1).view(np.uint8)


def unpack_batches(
    layout: BatchLayout, data: bytes | memoryview, table_sizes: Sequence[int], allocate: Allocate | None = None
) -> list[Batch]:
    """The batches of ``data``: copied once into ``allocate(len(data))`` (a writable uint8 array of
    that many bytes, such as a pinned buffer's; None: new memory), checked there and returned as
    views of it. Raises :class:`WireError` naming what is wrong: a length that is not
    ``len(table_sizes)`` batches, a bool that is not 0 or 1, a non-finite float."""
    count, size = len(table_sizes), layout.batch_bytes
    if len(data) != count * size:
        raise WireError(
            "data",
            f"has {len(data)} bytes, but {count} batches of {layout.batch_size} windows of {layout.window} "
            f"steps take {count * size}",
        )
    buffer = (allocate or _new_memory)(len(data))
    buffer[:] = np.frombuffer(data, dtype=np.uint8)
    rows = buffer.reshape(count, size)  # one row per batch: each check and field is one view over all batches
    _check(layout, rows)
    arrays = {f: rows[:, f.offset : f.offset + f.nbytes].view(f.little).reshape(count, *f.shape) for f in layout.fields}
    sensors = sorted(f.sensor for f in layout.fields if f.sensor is not None)
    out = []
    for n, table_size in enumerate(table_sizes):
        named = {f.name: a[n] for f, a in arrays.items() if f.sensor is None}
        obs = {f.sensor: a[n] for f, a in arrays.items() if f.sensor is not None}
        rnn_state = named.pop("rnn_state", None)
        out.append(Batch(table_size=int(table_size), obs=[obs[i] for i in sensors], rnn_state=rnn_state, **named))
    return out


def _new_memory(nbytes: int) -> np.ndarray:
    return np.empty(nbytes, dtype=np.uint8)


def _check(layout: BatchLayout, rows: np.ndarray) -> None:
    """Bools 0 or 1 and floats finite in ``rows`` (one batch per row), each span in one pass."""
    start, end = layout.bool_span
    if rows[:, start:end].max(initial=0) > 1:
        raise WireError(
            _first_bad(layout, rows, _BOOL, lambda a: a.view(np.uint8) > 1),
            "is bool but holds bytes other than 0 and 1",
        )
    start, end = layout.float32_span
    if not np.isfinite(rows[:, start:end].view(_F32)).all():
        raise WireError(_first_bad(layout, rows, _F32, lambda a: ~np.isfinite(a)), "has non-finite values")
    for f in layout.fields:
        if f.dtype.kind == "f" and f.dtype != _F32 and not np.isfinite(_view(rows, f)).all():
            raise WireError(_where(f), "has non-finite values")


def _first_bad(layout: BatchLayout, rows: np.ndarray, dtype: np.dtype, bad: Callable[[np.ndarray], np.ndarray]) -> str:
    """The first field of ``dtype`` where ``bad`` holds somewhere (named only once a check failed)."""
    return next(
        (_where(f) for f in layout.fields if f.dtype == dtype and bad(_view(rows, f)).any()), f"a {dtype} field"
    )


def _view(rows: np.ndarray, f: Field) -> np.ndarray:
    return rows[:, f.offset : f.offset + f.nbytes].view(f.little)


def _array(batch: Batch, f: Field) -> np.ndarray:
    value = batch.obs[f.sensor] if f.sensor is not None else getattr(batch, f.name)
    return np.asarray(value)


def _where(f: Field) -> str:
    return f"obs[{f.sensor}]" if f.sensor is not None else f.name


def _aligned(offset: int) -> int:
    return -(-offset // ALIGN) * ALIGN
