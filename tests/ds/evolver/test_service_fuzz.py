"""Every rpc of the evolver's server fed hostile payloads (hypothesis): bad ports and addresses, NaN,
infinite and negative numbers, unknown ids, unknown fields, bytes that are no message at all, and
oversize messages.

Each must be refused with INVALID_ARGUMENT naming the field (or the code its .proto documents instead:
RESOURCE_EXHAUSTED for size, NOT_FOUND for an id the server does not know, naming the id); the server
then still answers a valid request, and what it stores is exactly what it stored before: its Info and
its state file.

Requests are raw protos sent with the generated stubs, or raw bytes, past every check our clients
make. One real server, on loopback, serves the whole module. The learner's rpcs:
tests/ds/learner/test_service_fuzz.py; the payload strategies: tests/ds/fuzz.py.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import grpc
import pytest
from google.protobuf.message import Message
from hypothesis import given
from hypothesis import strategies as st

from algorithm.config.schema import Config
from ds.evolver.evolver import Evolver
from ds.evolver.service import serve_evolver
from protos import evolver_pb2, evolver_pb2_grpc
from tests.ds.fuzz import (
    BIG_SEND,
    FUZZ,
    INVALID,
    LIMIT,
    raw_call,
    refused,
    text,
    unknown_field,
    with_unknown_field,
)

pytestmark = pytest.mark.grpc


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
