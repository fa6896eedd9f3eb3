"""Every rpc of the learner's server fed hostile payloads (hypothesis): wrong dtypes, shapes and byte
counts, NaN, infinite and negative numbers, missing and unknown fields, wrong counts, bytes that are no
message at all, and oversize messages.

Each must be refused with INVALID_ARGUMENT naming the field (or the code its .proto documents instead:
RESOURCE_EXHAUSTED for size, NOT_FOUND for an id the server does not know, naming the id); the server
then still answers a valid request, and what it stores is exactly what it stored before: its registry,
parameter versions and served actions.

Requests are raw protos sent with the generated stubs, or raw bytes, past every check our clients
make. One real server, on loopback, serves the whole module. The evolver's rpcs:
tests/ds/evolver/test_service_fuzz.py; the replay's: tests/ds/replay/test_service_fuzz.py; the payload
strategies: tests/ds/fuzz.py.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import grpc
import numpy as np
import pytest
from google.protobuf.message import Message
from hypothesis import given
from hypothesis import strategies as st

from algorithm.config.schema import Config
from algorithm.sac.learner import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from ds.learner.service import ActorRegistry, LearnerServicer, ParamsStore, PublishedPolicy, serve_learner
from ds.net.wire import to_tensor
from protos import learner_pb2, learner_pb2_grpc
from tests.ds.fuzz import (
    BIG_SEND,
    FUZZ,
    LIMIT,
    broken,
    raw_call,
    refused,
    text,
    unknown_field,
    with_unknown_field,
)

pytestmark = pytest.mark.grpc


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
