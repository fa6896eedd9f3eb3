"""What the rpc fuzz tests (tests/ds/<role>/test_service_fuzz.py) feed the servers: hypothesis
strategies for tensors broken one way at a time and unknown fields at any depth, and the calls that
must be refused."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import grpc
import numpy as np
import pytest
from google.protobuf.message import Message
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from ds.net.wire import WIRE_DTYPES
from protos import replay_pb2

INVALID = grpc.StatusCode.INVALID_ARGUMENT
LIMIT = 1 << 20  # every server's message limit here: 1 MiB, cheap to exceed
BIG_SEND = [("grpc.max_send_message_length", 64 << 20)]  # our raw channels may send more than servers take
FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
WIRE = sorted(WIRE_DTYPES)


def text(min_size: int = 0, max_size: int = 20, without: str = "") -> st.SearchStrategy[str]:
    """Any text a proto string field can carry (UTF-8: no lone surrogates)."""
    letters = st.characters(blacklist_categories=("Cs",), blacklist_characters=without)
    return st.text(letters, min_size=min_size, max_size=max_size)


def refused(call: Callable[..., Any], request: Any, code: grpc.StatusCode = INVALID) -> str:
    """Make the call; it must fail with ``code``. Returns the details."""
    with pytest.raises(grpc.RpcError) as e:
        call(request, timeout=10)
    assert e.value.code() == code, (e.value.code(), e.value.details())
    return str(e.value.details())


def raw_call(channel: grpc.Channel, method: str) -> Callable[..., bytes]:
    """``method`` ("/asac.ReplayService/Insert") taking and returning bytes: no serialisation on our side."""
    return channel.unary_unary(method)


# ---------------------------------------------------------------------- tensors, broken one way at a time


@st.composite
def broken(draw: st.DrawFn, good: replay_pb2.Tensor, nonnegative: bool = False) -> tuple[replay_pb2.Tensor, str]:
    """``good`` with one thing wrong, and which: its dtype, shape or byte count; a non-finite (or,
    ``nonnegative``, a negative) float; a bool byte other than 0 and 1."""
    dtype, shape, data = good.dtype, list(good.shape), bytes(good.data)
    count = math.prod(shape)
    kinds = ["dtype", "shape", "bytes"]
    if count and dtype.startswith("float"):
        kinds += ["nonfinite", "negative"] if nonnegative else ["nonfinite"]
    if count and dtype == "bool":
        kinds.append("bool")
    kind = draw(st.sampled_from(kinds))
    if kind == "dtype":  # a wire dtype with matching bytes, or any other string
        new = draw((st.sampled_from(WIRE) | text(max_size=8)).filter(lambda d: d != dtype))
        size = count * (np.dtype(new).itemsize if new in WIRE_DTYPES else 1)
        return replay_pb2.Tensor(dtype=new, shape=shape, data=draw(st.binary(min_size=size, max_size=size))), kind
    if kind == "shape":  # negative, huge or merely other dimensions; bytes that fit it when they can
        dims = st.integers(-3, 9) | st.integers(-(2**63), 2**63 - 1)
        new_shape = draw(st.lists(dims, max_size=5).filter(lambda s: s != shape))
        size = math.prod(new_shape) * np.dtype(dtype).itemsize
        fits = min(new_shape, default=0) >= 0 and size <= 4096
        new_data = draw(st.binary(min_size=size, max_size=size)) if fits and draw(st.booleans()) else data
        return replay_pb2.Tensor(dtype=dtype, shape=new_shape, data=new_data), kind
    if kind == "bytes":
        new_data = draw(st.binary(max_size=2 * len(data) + 8).filter(lambda b: len(b) != len(data)))
        return replay_pb2.Tensor(dtype=dtype, shape=shape, data=new_data), kind
    values = np.frombuffer(data, dtype=np.dtype(dtype).newbyteorder("<")).copy()
    at = draw(st.integers(0, values.size - 1))
    if kind == "bool":
        raw = bytearray(data)
        raw[at] = draw(st.integers(2, 255))
        return replay_pb2.Tensor(dtype=dtype, shape=shape, data=bytes(raw)), kind
    bad = st.sampled_from([math.nan, math.inf, -math.inf])
    values[at] = draw(bad if kind == "nonfinite" else st.floats(-1e300, -1e-300))
    return replay_pb2.Tensor(dtype=dtype, shape=shape, data=values.tobytes()), kind


@st.composite
def unknown_field(draw: st.DrawFn) -> tuple[int, bytes]:
    """A field number none of our messages defines, encoded with any wire type: (number, bytes)."""
    number = draw(st.integers(64, 2**29 - 1))
    wire_type = draw(st.sampled_from([0, 1, 2, 5]))
    payload = {
        0: varint(draw(st.integers(0, 2**64 - 1))),
        1: draw(st.binary(min_size=8, max_size=8)),
        2: (lambda b: varint(len(b)) + b)(draw(st.binary(max_size=32))),
        5: draw(st.binary(min_size=4, max_size=4)),
    }[wire_type]
    return number, varint(number << 3 | wire_type) + payload


def varint(value: int) -> bytes:
    out = bytearray()
    while True:
        out.append(value & 0x7F | (0x80 if value > 0x7F else 0))
        value >>= 7
        if not value:
            return bytes(out)


def with_unknown_field(message: Message, extra: bytes) -> None:
    """Append the encoded field ``extra`` to ``message`` in place (it is kept as an unknown field)."""
    message.ParseFromString(message.SerializeToString() + extra)
