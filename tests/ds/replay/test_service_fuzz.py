"""Every rpc of the replay server fed hostile payloads (hypothesis): wrong dtypes, shapes and byte
counts, NaN, infinite and negative numbers, missing and unknown fields, wrong counts, bytes that are
no message at all, oversize messages, bad snapshot paths and corrupt snapshots.

Each must be refused with INVALID_ARGUMENT naming the field (or the code its .proto documents instead:
RESOURCE_EXHAUSTED for size); the server then still answers a valid request, and what it stores is
exactly what it stored before: the whole table (saved with its Save rpc) and its counters.

Requests are raw protos sent with the generated stubs, or raw bytes, past every check our clients
make. One real server, on loopback, serves the whole module. The learner's and evolver's rpcs:
tests/ds/learner/test_service_fuzz.py and tests/ds/evolver/test_service_fuzz.py; the payload
strategies: tests/ds/fuzz.py.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest
from google.protobuf.message import Message
from hypothesis import example, given
from hypothesis import strategies as st

from algorithm.replay import PrioritizedTable
from ds.net.wire import to_tensor
from ds.replay.codec import chunk_to_proto
from ds.replay.service import serve_replay
from protos import replay_pb2, replay_pb2_grpc
from tests.algorithm.replay.chunks import IMAGE, VECTOR, make_chunk
from tests.ds.fuzz import (
    BIG_SEND,
    FUZZ,
    INVALID,
    LIMIT,
    broken,
    raw_call,
    refused,
    unknown_field,
    with_unknown_field,
)

pytestmark = pytest.mark.grpc


# ---------------------------------------------------------------------- the replay


SENSORS = (VECTOR, IMAGE)
RNN = 2
T = 4


@dataclass
class Replay:
    table: PrioritizedTable
    stub: replay_pb2_grpc.ReplayServiceStub
    channel: grpc.Channel
    folder: Path  # the server's snapshot folder: Save and Load name files in it
    baseline: dict[str, Any]

    def state(self) -> dict[str, Any]:
        """Everything the table stores, through its own Save rpc, and its counters."""
        self.stub.Save(replay_pb2.SaveRequest(path="state.npz"), timeout=10)
        with np.load(self.folder / "state.npz") as f:
            arrays = {name: f[name] for name in f.files}
        state: dict[str, Any] = {"meta": json.loads(str(arrays.pop("meta")))}
        state |= {name: (a.dtype.str, a.shape, a.tobytes()) for name, a in arrays.items()}
        state["counters"] = dict(self.stub.Info(replay_pb2.InfoRequest(), timeout=10).counters)
        return state

    def assert_unchanged(self) -> None:
        assert self.state() == self.baseline  # and Save and Info, valid requests, were answered

    def insert_request(self, chunks: int = 1) -> replay_pb2.InsertRequest:
        """A valid insert of ``chunks`` chunks of T steps, each with its priorities."""
        protos = [chunk_to_proto(make_chunk(T, 0, SENSORS, rnn_state_size=RNN), np.full(T, 0.5)) for _ in range(chunks)]
        return replay_pb2.InsertRequest(chunks=protos)


@pytest.fixture(scope="module")
def replay(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Replay]:
    table = PrioritizedTable(200, SENSORS, 2, window=3, alpha=0.6, rnn_state_size=RNN, seed=0)
    for t in (5, 9, 3):
        table.insert(make_chunk(t, table.info()["next_key"], SENSORS, rnn_state_size=RNN))
    folder = tmp_path_factory.mktemp("replay")
    server, port = serve_replay(table, max_message_bytes=LIMIT, snapshot_dir=folder)
    channel = grpc.insecure_channel(f"127.0.0.1:{port}", options=BIG_SEND)
    r = Replay(table, replay_pb2_grpc.ReplayServiceStub(channel), channel, folder, {})
    r.baseline = r.state()
    yield r
    channel.close()
    server.stop(None)


CHUNK_TENSORS = ["obs[0]", "obs[1]", "actions", "prev_actions", "rewards", "terminated", "truncated",
                 "behaviour_logp", "rnn_state", "priorities"]  # fmt: skip


@FUZZ
@given(data=st.data())
def test_insert_with_one_broken_tensor_is_refused_naming_it(replay: Replay, data: st.DataObject) -> None:
    at = data.draw(st.sampled_from([0, 1]), "chunk")  # chunks[1]: the valid chunks[0] is not stored either
    name = data.draw(st.sampled_from(CHUNK_TENSORS), "field")
    request = replay.insert_request(at + 1)
    chunk = request.chunks[at]
    field = f"chunks[{at}].{name}"
    if name.startswith("obs["):
        i = int(name[4])
        if data.draw(st.booleans(), "drop it"):
            del chunk.obs[i]
            field, kind = f"chunks[{at}].obs", "count"
        else:
            bad, kind = data.draw(broken(chunk.obs[i]))
            chunk.obs[i].CopyFrom(bad)
    elif name != "priorities" and data.draw(st.booleans(), "clear it"):
        chunk.ClearField(name)
        kind = "missing"
    else:
        bad, kind = data.draw(broken(getattr(chunk, name), nonnegative=name == "priorities"))
        getattr(chunk, name).CopyFrom(bad)
    details = refused(replay.stub.Insert, request)
    if name == "rewards" and kind == "shape":
        field = f"chunks[{at}]."  # rewards bind T: fields that then disagree with the new T are named
    assert field in details, details
    replay.assert_unchanged()


@pytest.mark.parametrize(
    "case, field",
    [("no chunks", "chunks is empty"), ("an extra sensor", "chunks[0].obs has 3 observation sensors"),
     ("a flag before the last step", "chunk.terminated: only the last step"),
     ("longer than the table", "chunks[0]: chunk of 200 steps needs 201 rows")],
)  # fmt: skip
def test_insert_breaking_the_chunk_rules_is_refused(replay: Replay, case: str, field: str) -> None:
    request = replay.insert_request()
    if case == "no chunks":
        del request.chunks[:]
    elif case == "an extra sensor":
        request.chunks[0].obs.append(request.chunks[0].obs[0])
    elif case == "a flag before the last step":
        request.chunks[0].terminated.CopyFrom(to_tensor(np.array([False, True, False, False])))
    else:
        request = replay_pb2.InsertRequest(chunks=[chunk_to_proto(make_chunk(200, 0, SENSORS, rnn_state_size=RNN))])
    assert field in refused(replay.stub.Insert, request)
    replay.assert_unchanged()


@FUZZ
@given(
    n=st.integers(0, 6),
    keys=st.lists(st.integers(0, 2**64 - 1), min_size=6, max_size=6),
    what=st.sampled_from(["keys", "priorities", "missing keys", "missing priorities"]),
    data=st.data(),
)
def test_priority_updates_with_a_broken_tensor_are_refused(
    replay: Replay, n: int, keys: list[int], what: str, data: st.DataObject
) -> None:
    """Never-issued keys are fine (ignored); every request here breaks something else as well."""
    request = replay_pb2.UpdatePrioritiesRequest(
        keys=to_tensor(np.array(keys[:n], np.uint64)), priorities=to_tensor(np.full(n, 0.5))
    )
    field = what.removeprefix("missing ")
    if what.startswith("missing"):
        request.ClearField(field)
    else:
        bad, kind = data.draw(broken(getattr(request, field), nonnegative=True))
        getattr(request, field).CopyFrom(bad)
        if field == "keys" and kind == "shape":
            field = ""  # new N from the keys: priorities may be what disagrees
    assert field in refused(replay.stub.UpdatePriorities, request)
    replay.assert_unchanged()


@FUZZ
@given(n=st.integers(1, 5), what=st.sampled_from(["keys", "states", "missing keys", "missing states"]), data=st.data())
def test_rnn_state_updates_with_a_broken_tensor_are_refused(
    replay: Replay, n: int, what: str, data: st.DataObject
) -> None:
    request = replay_pb2.UpdateRnnStatesRequest(
        keys=to_tensor(np.arange(n, dtype=np.uint64)), states=to_tensor(np.ones((n, RNN), np.float32))
    )
    field = what.removeprefix("missing ")
    if what.startswith("missing"):
        request.ClearField(field)
    else:
        bad, kind = data.draw(broken(getattr(request, field)))
        getattr(request, field).CopyFrom(bad)
        if field == "keys" and kind == "shape":
            field = ""  # new N from the keys: states may be what disagrees
    assert field in refused(replay.stub.UpdateRnnStates, request)
    replay.assert_unchanged()


@FUZZ
@given(
    batch=st.integers(-(2**31), 0) | st.integers(100_000, 2**31 - 1) | st.just(4),
    timeout=st.none() | st.floats(max_value=-1e-9) | st.just(math.nan) | st.just(1.0),
)
def test_sample_with_a_bad_size_or_timeout_is_refused(replay: Replay, batch: int, timeout: float | None) -> None:
    if batch == 4 and (timeout is None or timeout == 1.0):
        timeout = -1.0  # a valid request would draw: break its timeout
    request = replay_pb2.SampleRequest(batch_size=batch)
    if timeout is not None:
        request.timeout_s = timeout
    if batch >= 100_000:  # the reply would be over the limit: refused before drawing
        assert f"a batch of {batch} windows" in refused(replay.stub.Sample, request, grpc.StatusCode.RESOURCE_EXHAUSTED)
    else:  # the wait is read first, so a bad one is named even with a bad size
        bad_wait = timeout is not None and not timeout >= 0
        assert ("timeout_s" if bad_wait else "batch_size") in refused(replay.stub.Sample, request)
    replay.assert_unchanged()


@FUZZ
@given(timeout=st.floats(max_value=-1e-9) | st.just(math.nan))
def test_insert_with_a_bad_timeout_is_refused(replay: Replay, timeout: float) -> None:
    request = replay.insert_request()
    request.timeout_s = timeout
    assert "timeout_s must be >= 0" in refused(replay.stub.Insert, request)
    replay.assert_unchanged()


@FUZZ
@given(target=st.sampled_from(["", "chunks[0]", "chunks[0].rewards", "chunks[0].obs[1]"]), field=unknown_field())
def test_an_unknown_field_at_any_depth_is_refused_naming_where(
    replay: Replay, target: str, field: tuple[int, bytes]
) -> None:
    number, encoded = field
    request = replay.insert_request()
    part = {"": request, "chunks[0]": request.chunks[0], "chunks[0].rewards": request.chunks[0].rewards,
            "chunks[0].obs[1]": request.chunks[0].obs[1]}[target]  # fmt: skip
    with_unknown_field(part, encoded)
    details = refused(replay.stub.Insert, request)
    assert details.startswith(f"{target or 'InsertRequest'} ") and f"unknown field number {number}" in details
    replay.assert_unchanged()


@FUZZ
@given(
    method=st.sampled_from(["Sample", "UpdatePriorities", "UpdateRnnStates", "Windows", "Info", "Save", "Load"]),
    field=unknown_field(),
)
def test_an_unknown_field_in_any_other_replay_request_is_refused(
    replay: Replay, method: str, field: tuple[int, bytes]
) -> None:
    """Each request is valid but for the unknown field (a Sample would draw, a Save would write)."""
    keys = to_tensor(np.arange(2, dtype=np.uint64))
    request: Message = {
        "Sample": replay_pb2.SampleRequest(batch_size=2, timeout_s=0.0),
        "UpdatePriorities": replay_pb2.UpdatePrioritiesRequest(keys=keys, priorities=to_tensor(np.ones(2))),
        "UpdateRnnStates": replay_pb2.UpdateRnnStatesRequest(
            keys=keys, states=to_tensor(np.ones((2, RNN), np.float32))
        ),
        "Windows": replay_pb2.WindowsRequest(from_key=0, max_windows=2),
        "Info": replay_pb2.InfoRequest(),
        "Save": replay_pb2.SaveRequest(path="unknown.npz"),
        "Load": replay_pb2.LoadRequest(path="good.npz"),
    }[method]
    with_unknown_field(request, field[1])
    assert f"unknown field number {field[0]}" in refused(getattr(replay.stub, method), request)
    assert not (replay.folder / "unknown.npz").exists()
    replay.assert_unchanged()


@FUZZ
@given(cut=st.integers(0, 10**6))
def test_a_truncated_request_is_refused(replay: Replay, cut: int) -> None:
    """One chunk is one top-level field: every cut is inside it (or leaves no chunk at all)."""
    data = replay.insert_request().SerializeToString()
    details = refused(raw_call(replay.channel, "/asac.ReplayService/Insert"), data[: cut % len(data)])
    assert "InsertRequest" in details or "chunks is empty" in details, details
    replay.assert_unchanged()


@FUZZ
@given(method=st.sampled_from(["Insert", "UpdatePriorities", "UpdateRnnStates"]), data=st.binary(min_size=1))
@example(method="Insert", data=replay_pb2.InsertRequest(producer=0x5EED, acked_below=3).SerializeToString())
def test_random_bytes_are_refused(replay: Replay, method: str, data: bytes) -> None:
    """Refused, or (bytes that decode as an acknowledge-only Insert of a producer the table never
    stored anything of: a valid request) answered; the table is unchanged either way."""
    call = raw_call(replay.channel, f"/asac.ReplayService/{method}")
    try:
        call(data, timeout=10)
    except grpc.RpcError as e:
        assert e.code() == INVALID, (e.code(), e.details())
    else:
        request = replay_pb2.InsertRequest.FromString(data) if method == "Insert" else None
        assert request is not None and request.producer and not request.chunks, (method, data)
    replay.assert_unchanged()


def test_an_oversize_insert_is_resource_exhausted(replay: Replay) -> None:
    request = replay.insert_request()
    request.chunks[0].rewards.data = b"\x00" * (LIMIT + 1)
    refused(replay.stub.Insert, request, grpc.StatusCode.RESOURCE_EXHAUSTED)
    replay.assert_unchanged()


@pytest.mark.parametrize("path", ["with\0nul", "/tmp/replay.npz", "../replay.npz", "."])
def test_save_to_a_nul_or_outside_path_is_refused(replay: Replay, path: str) -> None:
    assert refused(replay.stub.Save, replay_pb2.SaveRequest(path=path)).startswith("path ")
    replay.assert_unchanged()


@FUZZ
@given(
    how=st.sampled_from(["truncate", "flip"]),
    at=st.integers(0, 10**7),
    flips=st.lists(st.integers(1, 255), min_size=1, max_size=3),
)
# A flip in the zip directory's first file name: zipfile's error quoted 11 KB of the file, more than a
# status can carry (RESOURCE_EXHAUSTED "metadata size exceeds soft limit" instead of INVALID_ARGUMENT).
@example(how="flip", at=27, flips=[12])
def test_loading_a_corrupt_snapshot_is_refused_and_changes_nothing(
    replay: Replay, how: str, at: int, flips: list[int]
) -> None:
    """A snapshot of this very table, damaged: refused naming the file, or (a flip in bytes nobody
    reads, such as a zip timestamp) loaded as the same table. Never anything in between."""
    good = replay.folder / "good.npz"
    replay.stub.Save(replay_pb2.SaveRequest(path=good.name), timeout=10)
    data = bytearray(good.read_bytes())
    if how == "truncate":
        data = data[: at % len(data)]
    else:
        for k, xor in enumerate(flips):
            data[(at + 977 * k) % len(data)] ^= xor
    bad = replay.folder / "bad.npz"
    bad.write_bytes(bytes(data))
    try:
        replay.stub.Load(replay_pb2.LoadRequest(path=bad.name), timeout=10)
    except grpc.RpcError as e:
        assert e.code() == INVALID and str(bad) in str(e.details()), e.details()
    replay.assert_unchanged()


def test_loading_a_missing_foreign_or_empty_path_is_refused(replay: Replay) -> None:
    other = PrioritizedTable(200, (VECTOR,), 2, window=3, alpha=0.6, rnn_state_size=RNN)  # another task's table
    foreign = replay.folder / "foreign.npz"
    other.save(foreign)
    (replay.folder / "sub").mkdir(exist_ok=True)
    for name, message in [
        ("foreign.npz", "saved sensors"),
        ("missing.npz", "not a readable replay file"),
        ("sub", "is a folder"),
        (".", "names the snapshot folder itself"),
        ("", "not a readable replay file"),
    ]:  # fmt: skip  (empty: the default replay.npz)
        details = refused(replay.stub.Load, replay_pb2.LoadRequest(path=name))
        assert message in details and (name or "replay.npz") in details, details
    replay.assert_unchanged()
