"""Every rpc of the replay, learner and evolver servers fed hostile payloads (hypothesis): wrong dtypes,
shapes and byte counts, NaN, infinite and negative numbers, missing and unknown fields, wrong counts,
bytes that are no message at all, and oversize messages.

Each must be refused with INVALID_ARGUMENT naming the field (or the code its .proto documents instead:
RESOURCE_EXHAUSTED for size, NOT_FOUND for an id the server does not know, naming the id); the server
then still answers a valid request, and what it stores is exactly what it stored before: the replay's
whole table (saved with its Save rpc) and counters, the learner's registry, parameter versions and
served actions, the evolver's Info and its state file.

Requests are raw protos sent with the generated stubs, or raw bytes, past every check our clients
make. One real server of each kind, on loopback, serves the whole module.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import grpc
import numpy as np
import pytest
from google.protobuf.message import Message
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from algorithm.config_schema import Config
from algorithm.replay import PrioritizedTable
from algorithm.sac import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from ds.evolver.evolver import Evolver
from ds.evolver.service import serve_evolver
from ds.learner.service import ActorRegistry, LearnerServicer, ParamsStore, PublishedPolicy, serve_learner
from ds.net.wire import WIRE_DTYPES, to_tensor
from ds.replay.codec import chunk_to_proto
from ds.replay.service import serve_replay
from protos import evolver_pb2, evolver_pb2_grpc, learner_pb2, learner_pb2_grpc, replay_pb2, replay_pb2_grpc
from tests.algorithm.replay.chunks import IMAGE, VECTOR, make_chunk

pytestmark = pytest.mark.grpc

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


# ---------------------------------------------------------------------- the learner


TWO_SENSORS = (SensorSpec("state", (3,)), SensorSpec("goal", (2,)))
ACTIONS = ActionSpec(continuous_dim=2, low=(-1.0, -1.0), high=(1.0, 1.0))


@dataclass
class Learner:
    servicer: LearnerServicer
    stub: learner_pb2_grpc.LearnerServiceStub
    channel: grpc.Channel
    rnn_state_size: int
    baseline: tuple[Any, ...] = ()

    def state(self) -> tuple[Any, ...]:
        s = self.servicer
        self.stub.GetParams(learner_pb2.GetParamsRequest(), timeout=10)  # a valid request is answered
        actors = [(a.actor_id, a.index, a.env_steps) for a in s.registry.alive()]
        assert s.acting is not None
        return s.registry.registered, actors, s.store.version, s.acting.version, s.actions_served

    def action_request(self, n: int = 2) -> learner_pb2.GetActionRequest:
        rng = np.random.default_rng(n)
        obs = [to_tensor(rng.normal(size=(n, *s.shape)).astype(np.float32)) for s in TWO_SENSORS]
        request = learner_pb2.GetActionRequest(obs=obs, noise=0.1)
        if self.rnn_state_size:
            request.prev_actions.CopyFrom(to_tensor(np.zeros((n, ACTIONS.size), np.float32)))
            request.rnn_state.CopyFrom(to_tensor(np.zeros((n, self.rnn_state_size), np.float32)))
        return request


def learner_server(recurrent: bool) -> tuple[Learner, grpc.Server]:
    sac_config = {"seed": 0, "use_rnn": recurrent}
    cfg = Config.model_validate({"sac_config": sac_config, "nn_config": {"hidden_units": [8], "rnn_units": 4}})
    spec = EnvSpec(TWO_SENSORS, ACTIONS)
    sac = SAC(spec, cfg.sac_config, cfg.nn_config, cfg.replay_config)
    acting = PublishedPolicy(SAC(spec, cfg.sac_config, cfg.nn_config, cfg.replay_config))
    acting.load(3, sac.acting_state_dict())
    store = ParamsStore()
    store.put(3, [b"frames as published"])
    registry = ActorRegistry(lease_s=600)
    servicer = LearnerServicer(spec, registry, store, 1234, acting, sac.rnn_state_size)
    registry.register("a known actor")
    server, port, _ = serve_learner(servicer, max_message_bytes=LIMIT)
    channel = grpc.insecure_channel(f"127.0.0.1:{port}", options=BIG_SEND)
    learner = Learner(servicer, learner_pb2_grpc.LearnerServiceStub(channel), channel, sac.rnn_state_size)
    learner.baseline = learner.state()
    return learner, server


@pytest.fixture(scope="module", params=[False, True], ids=["feedforward", "recurrent"])
def learner(request: pytest.FixtureRequest) -> Iterator[Learner]:
    served, server = learner_server(request.param)
    yield served
    served.channel.close()
    server.stop(None)


@FUZZ
@given(data=st.data())
def test_get_action_with_a_broken_field_is_refused_naming_it(learner: Learner, data: st.DataObject) -> None:
    request = learner.action_request(data.draw(st.integers(1, 3), "N"))
    recurrent = bool(learner.rnn_state_size)
    names = ["obs[0]", "obs[1]", "obs count", "noise"] + (["prev_actions", "rnn_state"] if recurrent else [])
    name = data.draw(st.sampled_from(names), "field")
    field = name
    if name == "obs count":
        if data.draw(st.booleans(), "drop one"):
            del request.obs[-1]
        else:
            request.obs.append(request.obs[0])
        field = "obs has"
    elif name.startswith("obs["):
        bad, kind = data.draw(broken(request.obs[int(name[4])]))
        request.obs[int(name[4])].CopyFrom(bad)
        field = "obs[" if kind == "shape" else name  # obs[0] binds N: obs[1] may be what disagrees
    elif name == "noise":
        request.noise = data.draw(st.floats(max_value=-1e-300) | st.floats(min_value=1.0001e6) | st.just(math.nan))
    elif data.draw(st.booleans(), "clear it"):
        request.ClearField(name)
    else:
        bad, _ = data.draw(broken(getattr(request, name)))
        getattr(request, name).CopyFrom(bad)
    assert field in refused(learner.stub.GetAction, request)
    assert learner.state() == learner.baseline


def test_get_action_with_recurrent_fields_that_do_not_match_the_policy_is_refused(learner: Learner) -> None:
    request = learner.action_request()
    if learner.rnn_state_size:
        request.ClearField("rnn_state")
        message = "rnn_state is required: this learner's policy is recurrent"
    else:
        request.rnn_state.CopyFrom(to_tensor(np.zeros((2, 4), np.float32)))
        message = "rnn_state is set but this learner's policy is not recurrent"
    assert message in refused(learner.stub.GetAction, request)
    assert learner.state() == learner.baseline


@FUZZ
@given(
    what=st.sampled_from(["preferred_index", "env_steps", "actor_id"]),
    number=st.integers(-(2**31), -1),
    actor_id=text(),
)
def test_registration_and_heartbeats_with_bad_fields_are_refused(
    learner: Learner, what: str, number: int, actor_id: str
) -> None:
    known = learner.servicer.registry.alive()[0]
    if what == "preferred_index":
        assert "preferred_index" in refused(learner.stub.RegisterActor, learner_pb2.RegisterActorRequest(
            name="x", preferred_index=number))  # fmt: skip
    elif what == "env_steps":
        request = learner_pb2.HeartbeatRequest(actor_id=known.actor_id, env_steps=number)
        assert "env_steps" in refused(learner.stub.Heartbeat, request)
    elif actor_id != known.actor_id:  # an id nobody holds: NOT_FOUND, register again (learner.proto)
        request = learner_pb2.HeartbeatRequest(actor_id=actor_id, env_steps=known.env_steps)
        assert repr(actor_id) in refused(learner.stub.Heartbeat, request, grpc.StatusCode.NOT_FOUND)
    assert learner.state() == learner.baseline


@FUZZ
@given(
    method=st.sampled_from(["RegisterActor", "Heartbeat", "GetParams", "GetWeights", "GetAction"]),
    field=unknown_field(),
    garbage=st.binary(min_size=1, max_size=64),
)
def test_unknown_fields_and_random_bytes_are_refused_by_the_learner(
    learner: Learner, method: str, field: tuple[int, bytes], garbage: bytes
) -> None:
    request: Message = {
        "RegisterActor": learner_pb2.RegisterActorRequest(name="x"),
        "Heartbeat": learner_pb2.HeartbeatRequest(actor_id="x"),
        "GetParams": learner_pb2.GetParamsRequest(),
        "GetWeights": learner_pb2.GetWeightsRequest(),
        "GetAction": learner.action_request(),
    }[method]
    with_unknown_field(request, field[1])
    assert f"unknown field number {field[0]}" in refused(getattr(learner.stub, method), request)
    if method == "GetAction":  # random bytes are never a valid GetAction (it needs float32 observations)
        refused(raw_call(learner.channel, "/asac.LearnerService/GetAction"), garbage)
    assert learner.state() == learner.baseline


def test_an_oversize_get_action_is_resource_exhausted(learner: Learner) -> None:
    request = learner.action_request()
    request.obs[0].data = b"\x00" * (LIMIT + 1)
    refused(learner.stub.GetAction, request, grpc.StatusCode.RESOURCE_EXHAUSTED)
    assert learner.state() == learner.baseline


# ---------------------------------------------------------------------- the evolver


@dataclass
class EvolverServer:
    evolver: Evolver
    stub: evolver_pb2_grpc.EvolverServiceStub
    channel: grpc.Channel
    state_file: Path
    learner_id: int
    baseline: tuple[Any, ...] = ()

    def state(self) -> tuple[Any, ...]:
        info = self.stub.Info(evolver_pb2.EvolverInfoRequest(), timeout=10)
        return info.SerializeToString(deterministic=True), self.state_file.read_bytes()


@pytest.fixture(scope="module")
def evolver(tmp_path_factory: pytest.TempPathFactory) -> Iterator[EvolverServer]:
    config = Config.model_validate(
        {"sac_config": {"seed": 0}, "random_params": {"sac_config": {"n_step": {"in": [1, 3]}}}}
    )
    folder = tmp_path_factory.mktemp("evolver")
    evolver = Evolver(config, folder, "fuzz", lease_s=600.0)  # no round thread: only rpcs change it
    server, port, _ = serve_evolver(evolver, max_message_bytes=LIMIT)
    channel = grpc.insecure_channel(f"127.0.0.1:{port}", options=BIG_SEND)
    stub = evolver_pb2_grpc.EvolverServiceStub(channel)
    me = stub.RegisterLearner(evolver_pb2.RegisterLearnerRequest(
        name="l0", host="127.0.0.1", learner_port=61001, replay_address="10.0.0.6:61002"), timeout=10)  # fmt: skip
    stub.Assign(evolver_pb2.AssignRequest(role=evolver_pb2.ACTOR, name="a0"), timeout=10)
    served = EvolverServer(evolver, stub, channel, folder / "state.json", me.learner_id)
    served.baseline = served.state()
    yield served
    channel.close()
    server.stop(None)


BAD_ADDRESSES = (
    text(min_size=1, max_size=12, without=":")  # no port at all
    | st.builds(lambda h, p: f"{h}:{p}", st.just("replay"), st.integers(65536, 2**40) | st.just(0))
    | st.builds(lambda p: f"replay:{p}", st.text(alphabet="-+x. ", min_size=1, max_size=4))  # not a number
    | st.builds(lambda h: f"{h}:61002", st.sampled_from(["", "re play", "tab\there", "new\nline"]))
)


@st.composite
def bad_evolver_call(draw: st.DrawFn, me: int) -> tuple[str, Message, grpc.StatusCode, str]:
    """(rpc, request, expected code, what the details must name) with one thing wrong."""
    negative = st.integers(-(2**63), -1)
    unknown_id = st.integers(-(2**63), 2**63 - 1).filter(lambda i: i != me)
    case = draw(st.sampled_from(["learner_port", "params_port", "replay_address", "host", "previous_id",
                                 "heartbeat", "unknown heartbeat", "post", "unknown post", "sample", "role",
                                 "replay address", "assignment"]))  # fmt: skip
    register = {"name": "l", "host": "10.0.0.1", "learner_port": 61001, "params_port": 0, "replay_address": ""}
    if case == "learner_port":
        port = draw(st.integers(-(2**31), 0) | st.integers(65536, 2**31 - 1))
        return "RegisterLearner", evolver_pb2.RegisterLearnerRequest(**register | {case: port}), INVALID, case
    if case == "params_port":
        port = draw(st.integers(-(2**31), -1) | st.integers(65536, 2**31 - 1))
        return "RegisterLearner", evolver_pb2.RegisterLearnerRequest(**register | {case: port}), INVALID, case
    if case in ("replay_address", "host"):
        value = draw(BAD_ADDRESSES if case == "replay_address" else st.sampled_from([" ", "a b", "h\x00", "\t"]))
        return "RegisterLearner", evolver_pb2.RegisterLearnerRequest(**register | {case: value}), INVALID, case
    if case == "previous_id":
        i = draw(unknown_id)
        request = evolver_pb2.RegisterLearnerRequest(**register, previous_id=i)
        return "RegisterLearner", request, grpc.StatusCode.NOT_FOUND, f"learner {i} "
    if case == "heartbeat":
        name = draw(st.sampled_from(["env_steps", "loaded_round"]))
        request = evolver_pb2.LearnerHeartbeatRequest(learner_id=me, **{name: draw(negative)})
        return "LearnerHeartbeat", request, INVALID, name
    if case in ("unknown heartbeat", "unknown post", "sample"):
        i = draw(unknown_id)
        method, request_type = {"unknown heartbeat": ("LearnerHeartbeat", evolver_pb2.LearnerHeartbeatRequest),
                                "unknown post": ("PostReward", evolver_pb2.PostRewardRequest),
                                "sample": ("GetSample", evolver_pb2.GetSampleRequest)}[case]  # fmt: skip
        return method, request_type(learner_id=i), grpc.StatusCode.NOT_FOUND, f"learner {i} "
    if case == "post":
        name = draw(st.sampled_from(["mean_return", "env_steps", "weights_round"]))
        value = draw(st.sampled_from([math.nan, math.inf, -math.inf]) if name == "mean_return" else negative)
        request = evolver_pb2.PostRewardRequest(learner_id=me, **{"mean_return": 1.0} | {name: value})
        return "PostReward", request, INVALID, name
    if case == "role":
        role = draw(st.integers(-(2**31), 2**31 - 1).filter(lambda r: r not in (1, 2)))
        return "Assign", evolver_pb2.AssignRequest(role=cast(Any, role), name="x"), INVALID, "role"
    if case == "replay address":
        request = evolver_pb2.AssignRequest(role=evolver_pb2.REPLAY, name="r", address=draw(BAD_ADDRESSES))
        return "Assign", request, INVALID, "address"
    assignment = draw(text())
    request = evolver_pb2.AssignmentHeartbeatRequest(assignment_id=assignment)
    return "AssignmentHeartbeat", request, grpc.StatusCode.NOT_FOUND, repr(assignment)


@FUZZ
@given(data=st.data())
def test_evolver_calls_with_a_bad_field_or_unknown_id_are_refused(evolver: EvolverServer, data: st.DataObject) -> None:
    method, request, code, named = data.draw(bad_evolver_call(evolver.learner_id))
    assert named in refused(getattr(evolver.stub, method), request, code)
    assert evolver.state() == evolver.baseline


@FUZZ
@given(
    method=st.sampled_from(
        ["RegisterLearner", "LearnerHeartbeat", "PostReward", "GetSample", "Assign", "AssignmentHeartbeat", "Info"]
    ),
    field=unknown_field(),
)
def test_unknown_fields_are_refused_by_the_evolver(
    evolver: EvolverServer, method: str, field: tuple[int, bytes]
) -> None:
    request: Message = {
        "RegisterLearner": evolver_pb2.RegisterLearnerRequest(name="l", host="h", learner_port=1),
        "LearnerHeartbeat": evolver_pb2.LearnerHeartbeatRequest(learner_id=evolver.learner_id),
        "PostReward": evolver_pb2.PostRewardRequest(learner_id=evolver.learner_id, mean_return=1.0),
        "GetSample": evolver_pb2.GetSampleRequest(learner_id=evolver.learner_id),
        "Assign": evolver_pb2.AssignRequest(role=evolver_pb2.ACTOR, name="a"),
        "AssignmentHeartbeat": evolver_pb2.AssignmentHeartbeatRequest(assignment_id="actor-0"),
        "Info": evolver_pb2.EvolverInfoRequest(),
    }[method]
    with_unknown_field(request, field[1])
    assert f"unknown field number {field[0]}" in refused(getattr(evolver.stub, method), request)
    assert evolver.state() == evolver.baseline


@pytest.mark.parametrize(
    "payload",
    [b"\x0a\x02\xff\xfe", b"\x0a\x05ab", b"\x18\xff\xff\xff"],
    ids=["name is not UTF-8", "name shorter than its length", "port varint cut short"],
)
def test_undecodable_registrations_are_refused(evolver: EvolverServer, payload: bytes) -> None:
    details = refused(raw_call(evolver.channel, "/asac.EvolverService/RegisterLearner"), payload)
    assert "request is not a valid RegisterLearnerRequest" in details
    assert evolver.state() == evolver.baseline


def test_an_oversize_registration_is_resource_exhausted(evolver: EvolverServer) -> None:
    request = evolver_pb2.RegisterLearnerRequest(name="x" * (LIMIT + 1), host="h", learner_port=1)
    refused(evolver.stub.RegisterLearner, request, grpc.StatusCode.RESOURCE_EXHAUSTED)
    assert evolver.state() == evolver.baseline
