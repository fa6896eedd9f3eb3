"""Replay messages <-> algorithm types (Chunk, Batch, info dicts), checked against the replay's specs.

The server decodes what actors and learners send with :meth:`ReplaySpecs.chunk_from_proto` and
:meth:`ReplaySpecs.priorities_from_proto`; the client decodes the batches the server returns with
:meth:`ReplaySpecs.batches_from_reply` (packed in one buffer: ds/replay/packed.py). Both check
every tensor (dtype, shape, leading dimensions consistent within the message, finiteness) before
the data goes anywhere, and name the offending field in the :class:`~ds.net.wire.WireError`.
:func:`message_limit_bytes` sizes gRPC's message limits from the largest message the configuration
produces.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from algorithm.replay.base import NormalizerStats, ReplayInfo
from algorithm.spaces import SensorSpec
from algorithm.types import Batch, Chunk
from ds.net.rpc import GRPC_DEFAULT_MESSAGE_BYTES
from ds.net.wire import TensorSpec, WireError, from_tensor, to_tensor
from ds.replay.packed import Allocate, BatchLayout, pack_batches, unpack_batches
from protos import replay_pb2

# protobuf cannot serialise a message of 2 GiB or more.
PROTOBUF_MAX_MESSAGE_BYTES = 2**31 - 1
# Framing of one Tensor inside a message (tags, length prefixes, dtype name, up to ~6 shape varints), or
# of a SampleReply around its data.
TENSOR_FRAMING_BYTES = 128

# Specs are built per received tensor with the same arguments over and over (field names carry the
# chunk index): cache them, as building one costs several microseconds on the servers' hot path.
_spec = functools.lru_cache(maxsize=4096)(TensorSpec)
_layout = functools.lru_cache(maxsize=64)(BatchLayout.of)
_F32, _F64, _BOOL, _U64 = np.dtype(np.float32), np.dtype(np.float64), np.dtype(bool), np.dtype(np.uint64)
# Per-step fields shared by Chunk and Batch, with their dtypes; actions also have a trailing A.
_STEP_FIELDS = (
    ("actions", _F32),
    ("prev_actions", _F32),
    ("rewards", _F32),
    ("terminated", _BOOL),
    ("truncated", _BOOL),
    ("behaviour_logp", _F32),
)


@dataclass(frozen=True)
class ReplaySpecs:
    """What a replay table stores, hence what its server accepts and its client expects back."""

    sensors: tuple[SensorSpec, ...]
    action_size: int
    rnn_state_size: int = 0

    # ------------------------------------------------------------------ chunks (actor -> server)

    def chunk_from_proto(self, msg: replay_pb2.Chunk, where: str) -> tuple[Chunk, np.ndarray | None]:
        """Decode and check one chunk; returns it and its raw priorities (None: not given).

        ``where`` prefixes field names (``"chunks[3]"``). The table itself still checks what
        is not about the wire (flags only on the last step, length against capacity).
        """
        dims: dict[str, int] = {}
        rewards = _required(msg, "rewards", self._step_spec(where, "rewards"), dims)
        if dims["T"] < 1:
            raise WireError(f"{where}.rewards", "is float32 of shape [0], expected float32 of shape [T] with T >= 1")
        if len(msg.obs) != len(self.sensors):
            raise WireError(
                f"{where}.obs", f"has {len(msg.obs)} observation sensors, the table expects {len(self.sensors)}"
            )
        obs = [from_tensor(t, self._obs_spec(where, i, "T+1"), dims) for i, t in enumerate(msg.obs)]
        steps = {name: _required(msg, name, self._step_spec(where, name), dims) for name, _ in _STEP_FIELDS}
        steps["rewards"] = rewards
        rnn_state = None
        if self.rnn_state_size:
            rnn_spec = _spec(f"{where}.rnn_state", _F32, (self.rnn_state_size,), finite=True, leading=("T",))
            rnn_state = _required(msg, "rnn_state", rnn_spec, dims)
        elif msg.HasField("rnn_state"):
            raise WireError(f"{where}.rnn_state", "is set but the table stores no recurrent state (rnn_state_size=0)")
        priorities = None
        if msg.HasField("priorities"):
            spec = _spec(f"{where}.priorities", _F64, finite=True, nonnegative=True, leading=("T",))
            priorities = from_tensor(msg.priorities, spec, dims)
        return Chunk(obs=obs, rnn_state=rnn_state, **steps), priorities

    # ------------------------------------------------------------------ priorities (learner -> server)

    def priorities_from_proto(self, msg: replay_pb2.UpdatePrioritiesRequest) -> tuple[np.ndarray, np.ndarray]:
        """Decode and check ``(keys uint64 [N], raw priorities float64 [N], finite, >= 0)``."""
        dims: dict[str, int] = {}
        keys = _required(msg, "keys", _spec("keys", _U64, leading=("N",)), dims)
        spec = _spec("priorities", _F64, finite=True, nonnegative=True, leading=("N",))
        return keys, _required(msg, "priorities", spec, dims)

    def rnn_states_from_proto(self, msg: replay_pb2.UpdateRnnStatesRequest) -> tuple[np.ndarray, np.ndarray]:
        """Decode and check ``(keys uint64 [N], states float32 [N, H], finite)``."""
        if not self.rnn_state_size:
            raise WireError("states", "cannot be stored: this replay keeps no recurrent state (rnn_state_size=0)")
        dims: dict[str, int] = {}
        keys = _required(msg, "keys", _spec("keys", _U64, leading=("N",)), dims)
        spec = _spec("states", _F32, (self.rnn_state_size,), finite=True, leading=("N",))
        return keys, _required(msg, "states", spec, dims)

    # ------------------------------------------------------------------ batches (server -> learner)

    def layout(self, batch_size: int, window: int) -> BatchLayout:
        """Where each field of a sampled batch lies in a SampleReply's data (ds/replay/packed.py)."""
        return _layout(self.sensors, self.action_size, int(batch_size), int(window), self.rnn_state_size)

    def batches_from_reply(
        self,
        msg: replay_pb2.SampleReply,
        batch_size: int,
        window: int | None = None,
        allocate: Allocate | None = None,
        data: bytes | memoryview | None = None,
    ) -> list[Batch]:
        """The checked batches of a SampleReply of ``batch_size`` windows (``window`` steps each;
        None: as the reply says), in memory from ``allocate`` (see :func:`~ds.replay.packed.unpack_batches`).
        ``data``: the reply's data where it was kept apart (:func:`split_sample_reply`)."""
        if msg.batch_size != batch_size:
            raise WireError("batch_size", f"is {msg.batch_size}, expected {batch_size}")
        if msg.window < 1 or (window is not None and msg.window != window):
            raise WireError("window", f"is {msg.window}, expected {window if window is not None else '>= 1'}")
        payload = msg.data if data is None else data
        return unpack_batches(self.layout(batch_size, msg.window), payload, msg.table_size, allocate)

    # ------------------------------------------------------------------ info (server -> anyone)

    def info_from_proto(self, msg: replay_pb2.InfoReply) -> ReplayInfo:
        """The table's ``info()`` dict back: counters as ``int``, values as ``float``, and
        ``"normalizer"``: ``{sensor: {"count": int, "mean": float64 array, "var": float64 array}}``."""
        out: dict[str, Any] = {key: int(v) for key, v in msg.counters.items()}
        out.update((key, float(v)) for key, v in msg.values.items())
        out["normalizer"] = self.normalizer_from_proto(msg)
        return cast(ReplayInfo, out)

    def normalizer_from_proto(self, msg: replay_pb2.InfoReply) -> dict[str, NormalizerStats]:
        """``{sensor: {"count", "mean", "var"}}`` of an InfoReply; every sensor must be known."""
        shapes = {s.name: s.shape for s in self.sensors}
        out: dict[str, NormalizerStats] = {}
        for name, stats in msg.normalizer.items():
            if name not in shapes:
                raise WireError(f"normalizer[{name!r}]", f"names no sensor of this replay ({sorted(shapes)})")
            where = f"normalizer[{name!r}]"
            mean = _required(stats, "mean", _spec(f"{where}.mean", _F64, shapes[name], finite=True), {})
            var = _required(stats, "var", _spec(f"{where}.var", _F64, shapes[name], finite=True), {})
            out[name] = {"count": int(stats.count), "mean": mean, "var": var}
        return out

    # ------------------------------------------------------------------ specs

    def _obs_spec(self, where: str, i: int, *leading: str) -> TensorSpec:
        s = self.sensors[i]
        name = f"{where}.obs[{i}] ({s.name})" if where else f"obs[{i}] ({s.name})"
        return _spec(name, s.dtype, s.shape, finite=np.dtype(s.dtype).kind == "f", leading=leading)

    def _step_spec(self, where: str, name: str) -> TensorSpec:
        dtype = dict(_STEP_FIELDS)[name]
        suffix = (self.action_size,) if name in ("actions", "prev_actions") else ()
        return _spec(f"{where}.{name}", dtype, suffix, finite=dtype.kind == "f", leading=("T",))


def _required(msg: Any, name: str, spec: TensorSpec, dims: dict[str, int]) -> np.ndarray:
    """Decode the Tensor field ``name`` of ``msg``, which must be present."""
    if not msg.HasField(name):
        raise WireError(spec.name, "is missing")
    return from_tensor(getattr(msg, name), spec, dims)


# ---------------------------------------------------------------------- encoders (no checks beyond to_tensor)


def chunk_to_proto(chunk: Chunk, priorities: np.ndarray | None = None, where: str = "chunks[0]") -> replay_pb2.Chunk:
    """Encode a chunk (and optional raw priorities, sent as float64) for an InsertRequest."""
    msg = replay_pb2.Chunk(obs=[to_tensor(o, f"{where}.obs[{i}]") for i, o in enumerate(chunk.obs)])
    for name, _ in _STEP_FIELDS:
        getattr(msg, name).CopyFrom(to_tensor(getattr(chunk, name), f"{where}.{name}"))
    if chunk.rnn_state is not None:
        msg.rnn_state.CopyFrom(to_tensor(chunk.rnn_state, f"{where}.rnn_state"))
    if priorities is not None:
        msg.priorities.CopyFrom(to_tensor(np.asarray(priorities, dtype=np.float64), f"{where}.priorities"))
    return msg


def sample_reply(layout: BatchLayout, batches: list[Batch]) -> replay_pb2.SampleReply:
    """Encode sampled batches (each ``layout.batch_size`` x ``layout.window``; none: an empty reply)."""
    return replay_pb2.SampleReply(
        batch_size=layout.batch_size,
        window=layout.window,
        table_size=[b.table_size for b in batches],
        data=pack_batches(layout, batches),
    )


def split_sample_reply(raw: bytes) -> tuple[replay_pb2.SampleReply, memoryview]:
    """A serialised SampleReply as its small fields (parsed) and its data (a view of ``raw``, not a
    copy): the learner reads batches straight from the received bytes, two copies of each fewer than
    parsing the message and then taking its ``data``. A field the message does not define, or bytes
    that end inside a field, are a :class:`WireError`."""
    view, pos, kept, data = memoryview(raw), 0, bytearray(), memoryview(b"")
    while pos < len(raw):
        start = pos
        tag, pos = _varint(raw, pos)
        field, wire_type = tag >> 3, tag & 7
        if wire_type == 0 and field in (1, 2, 3, 5):  # batch_size, window; table_size unpacked; shared_bytes
            _, pos = _varint(raw, pos)
        elif wire_type == 2 and field in (3, 4):  # table_size packed; data
            size, pos = _varint(raw, pos)
            if pos + size > len(raw):
                raise WireError("SampleReply", f"field {field} runs past the message's end")
            if field == 4:
                data, pos = view[pos : pos + size], pos + size
                continue
            pos += size
        else:
            raise WireError("SampleReply", f"has field {field} of wire type {wire_type}, which it does not define")
        kept += raw[start:pos]
    return replay_pb2.SampleReply.FromString(bytes(kept)), data


def _varint(raw: bytes, pos: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        if pos >= len(raw) or shift > 63:
            raise WireError("SampleReply", "ends inside a number")
        byte = raw[pos]
        value |= (byte & 0x7F) << shift
        pos, shift = pos + 1, shift + 7
        if not byte & 0x80:
            return value, pos


def info_to_proto(info: ReplayInfo) -> replay_pb2.InfoReply:
    """Encode a table's ``info()``: integers as counters, other numbers as values, plus normalizers."""
    msg = replay_pb2.InfoReply()
    for name, stats in info["normalizer"].items():
        msg.normalizer[name].CopyFrom(
            replay_pb2.NormalizerStats(
                count=int(stats["count"]),
                mean=to_tensor(np.asarray(stats["mean"], np.float64)),
                var=to_tensor(np.asarray(stats["var"], np.float64)),
            )
        )
    numbers: dict[str, Any] = {k: v for k, v in info.items() if k != "normalizer"}
    for key, value in numbers.items():
        if isinstance(value, int | np.integer):
            msg.counters[key] = int(value)
        else:
            msg.values[key] = float(value)
    return msg


# ---------------------------------------------------------------------- message sizes


def batch_payload_bytes(
    sensors: tuple[SensorSpec, ...], action_size: int, batch_size: int, window: int, rnn_state_size: int = 0
) -> int:
    """Bytes of one batch of ``batch_size`` windows of ``window`` steps in a SampleReply's data."""
    return _layout(tuple(sensors), int(action_size), int(batch_size), int(window), int(rnn_state_size)).batch_bytes


def chunk_payload_bytes(sensors: tuple[SensorSpec, ...], action_size: int, steps: int, rnn_state_size: int = 0) -> int:
    """Raw tensor bytes of one chunk of ``steps`` steps, with priorities."""
    obs = sum((steps + 1) * math.prod(s.shape) * np.dtype(s.dtype).itemsize for s in sensors)
    per_step = 2 * 4 * action_size + 4 + 1 + 1 + 4 + 8 + 4 * rnn_state_size  # ... + priority, state
    return obs + steps * per_step


def sample_reply_bytes(
    sensors: tuple[SensorSpec, ...], action_size: int, batch_size: int, window: int, rnn_state_size: int = 0
) -> int:
    """Upper estimate of a serialised SampleReply of one batch: its data plus the framing."""
    return batch_payload_bytes(sensors, action_size, batch_size, window, rnn_state_size) + TENSOR_FRAMING_BYTES


def batches_per_reply(
    sensors: tuple[SensorSpec, ...], action_size: int, batch_size: int, window: int, rnn_state_size: int,
    max_message_bytes: int,
) -> int:  # fmt: skip
    """How many batches one SampleReply carries within ``max_message_bytes`` (0: not even one): the
    first with the reply's framing, each further one its data."""
    size = sample_reply_bytes(sensors, action_size, batch_size, window, rnn_state_size)
    if size > max_message_bytes:
        return 0
    return (max_message_bytes - size) // max(size - TENSOR_FRAMING_BYTES, 1) + 1


def message_limit_bytes(
    sensors: tuple[SensorSpec, ...],
    action_size: int,
    batch_size: int,
    window: int,
    rnn_state_size: int = 0,
    max_chunk_steps: int = 0,
) -> int:
    """The gRPC send/receive limit for a replay server and its clients, from the real sizes.

    Rule: ``max(4 MiB, 2 * P + 1 MiB)`` where ``P`` is the larger of the raw tensor bytes of one
    sampled batch (``batch_size`` windows of ``window`` steps) and of one chunk of
    ``max_chunk_steps`` steps. The factor 2 leaves room for an insert of a few chunks at once or
    a learner sampling a somewhat larger batch; 1 MiB covers the framing. Never below gRPC's
    4 MiB default; a limit protobuf cannot carry (2 GiB) is a ``ValueError``.
    """
    payload = batch_payload_bytes(sensors, action_size, batch_size, window, rnn_state_size)
    if max_chunk_steps:
        payload = max(payload, chunk_payload_bytes(sensors, action_size, max_chunk_steps, rnn_state_size))
    limit = max(GRPC_DEFAULT_MESSAGE_BYTES, 2 * payload + 1024 * 1024)
    if limit > PROTOBUF_MAX_MESSAGE_BYTES:
        raise ValueError(
            f"replay messages of {payload} bytes (batch_size={batch_size}, window={window}, "
            f"max_chunk_steps={max_chunk_steps}) need a {limit}-byte limit, over protobuf's 2 GiB: "
            "sample smaller batches or cut shorter chunks"
        )
    return limit
