"""The learners', actors' and replays' end of the evolver's gRPC service (the server: ds/evolver/service.py).

A learner's usage::

    evolver = EvolverClient("evolver:61000", token=token, credentials=creds)  # creds: ds.net.security
    me = evolver.register_learner("learner-0", host="", learner_port=61001, params_port=61003,
                                  previous_id=saved_id)                # host "": the address the call came from
    orders = evolver.heartbeat(me.learner_id, env_steps, loaded_round=loaded)   # every few seconds
    if orders.instruction is Instruction.LOAD_WEIGHTS:
        sample = evolver.get_sample(me.learner_id, expected=params_spec(full_weights))
    evolver.post_reward(me.learner_id, mean_return, env_steps, weights_round=loaded)

an actor's or replay's::

    job = evolver.assign_actor("actor-3")            # NoWorkYet: no learner has room yet; retry later
    job = evolver.assign_replay("replay-0", "10.0.0.7:61002")
    job = evolver.renew_assignment(job.assignment_id)  # every few seconds; UnknownAssignment: assign again

Status codes map to the exceptions of ds/evolver/state.py: NOT_FOUND is :class:`UnknownLearner` (or
:class:`UnknownAssignment` for assignments), FAILED_PRECONDITION :class:`LearnerRetired`, UNAVAILABLE
from Assign :class:`NoWorkYet`, INVALID_ARGUMENT :class:`EvolverRequestRejected` (a ``ValueError``).
Every call has a deadline; UNAVAILABLE (evolver down or restarting) is retried with backoff and then
raised as ``grpc.RpcError``. An :class:`EvolverClient` accepts only a server whose certificate names the
evolver: a learner loads CEM samples from nobody else (ds/net/security.py).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import grpc
import numpy as np

from ds.evolver.evolver import EVOLVER_MESSAGE_BYTES
from ds.evolver.state import (
    Assignment,
    EvolverInfo,
    Instruction,
    LearnerInfo,
    LearnerOrders,
    LearnerRegistration,
    LearnerRetired,
    NoWorkYet,
    Role,
    UnknownAssignment,
    UnknownLearner,
)
from ds.net import rpc, security
from ds.net.client import RpcClient
from ds.net.params import ParamsError, ParamsSpec, Token, decode_params
from ds.net.security import NO_CREDENTIALS, Credentials
from protos import evolver_pb2, evolver_pb2_grpc

# How both ends put a role and a learner's instruction on the wire (the server imports these).
ROLE_TO_PROTO = {Role.ACTOR: evolver_pb2.ACTOR, Role.REPLAY: evolver_pb2.REPLAY}
ROLE_FROM_PROTO = {v: k for k, v in ROLE_TO_PROTO.items()}
INSTRUCTION_TO_PROTO = {
    Instruction.CONTINUE: evolver_pb2.CONTINUE,
    Instruction.LOAD_WEIGHTS: evolver_pb2.LOAD_WEIGHTS,
    Instruction.RETIRE: evolver_pb2.RETIRE,
}
_INSTRUCTION_FROM_PROTO = {v: k for k, v in INSTRUCTION_TO_PROTO.items()}


class EvolverRequestRejected(ValueError):
    """The evolver answered INVALID_ARGUMENT; the message names the field."""


@dataclass(frozen=True)
class Sample:
    """The weights a CEM round drew for a learner: load them, then hard-copy the target networks."""

    round: int
    weights: dict[str, np.ndarray]


class EvolverClient(RpcClient):
    """The learners', actors' and replays' end of :class:`EvolverServicer`. Every call has a deadline
    of ``rpc_timeout_s``; UNAVAILABLE is retried per ``retry``. ``token`` verifies samples (the
    evolver signs them with the run's token); ``credentials``: TLS and the token on every call
    (:func:`ds.net.security.open_channel`; the server must hold the evolver's certificate). Thread-safe."""

    def __init__(
        self,
        address: str,
        *,
        token: Token = None,
        max_message_bytes: int = EVOLVER_MESSAGE_BYTES,
        rpc_timeout_s: float = 10.0,
        retry: rpc.RetryPolicy | None = None,
        credentials: Credentials = NO_CREDENTIALS,
    ) -> None:
        super().__init__(
            address,
            security.EVOLVER,
            evolver_pb2_grpc.EvolverServiceStub,
            max_message_bytes=max_message_bytes,
            rpc_timeout_s=rpc_timeout_s,
            retry=retry,
            credentials=credentials,
        )
        self.token = token

    def register_learner(
        self,
        name: str,
        host: str,
        learner_port: int,
        params_port: int = 0,
        replay_address: str = "",
        previous_id: int | None = None,
    ) -> LearnerRegistration:
        """An id, the experiment and this learner's config; ``host=""`` lets the evolver use the
        address the call came from. :class:`UnknownLearner` / :class:`LearnerRetired` for a
        ``previous_id`` it does not know / retired."""
        request = evolver_pb2.RegisterLearnerRequest(
            name=name, host=host, learner_port=learner_port, params_port=params_port, replay_address=replay_address
        )
        if previous_id is not None:
            request.previous_id = int(previous_id)
        r = self._call(self._stub.RegisterLearner, request)
        params = json.loads(r.params_json) if r.params_json else {}
        return LearnerRegistration(
            r.learner_id, r.experiment, r.config_yaml, params, r.lease_s, r.replay_address, r.rounds
        )

    def heartbeat(self, learner_id: int, env_steps: int, loaded_round: int | None = None) -> LearnerOrders:
        """Renew the lease and learn what to do; send the last loaded sample round every time.
        :class:`UnknownLearner`: register again with ``previous_id``."""
        request = evolver_pb2.LearnerHeartbeatRequest(learner_id=learner_id, env_steps=env_steps)
        if loaded_round is not None:
            request.loaded_round = int(loaded_round)
        r = self._call(self._stub.LearnerHeartbeat, request)
        instruction = _INSTRUCTION_FROM_PROTO[r.instruction]
        return LearnerOrders(instruction, r.sample_round, r.replay_address, r.lease_s, r.rounds)

    def post_reward(self, learner_id: int, mean_return: float, env_steps: int, weights_round: int = 0) -> bool:
        """Post one evaluation's mean return; False when it was dropped as stale."""
        request = evolver_pb2.PostRewardRequest(
            learner_id=learner_id, mean_return=mean_return, env_steps=env_steps, weights_round=weights_round
        )
        return bool(self._call(self._stub.PostReward, request).accepted)

    def get_sample(self, learner_id: int, expected: ParamsSpec | None = None) -> Sample | None:
        """The sample waiting for this learner, checked by :func:`ds.net.params.decode_params` against
        ``expected`` (the learner's own full weights: names, dtypes, shapes; finite values) and the
        token; None when none waits. :class:`ds.net.params.ParamsError` for a sample that fails a check."""
        r = self._call(self._stub.GetSample, evolver_pb2.GetSampleRequest(learner_id=learner_id))
        if r.round == 0:
            return None
        version, weights = decode_params(list(r.frames), expected, self.token)
        if version != r.round:
            raise ParamsError(f"sample frames are of round {version}, the reply says {r.round}")
        return Sample(r.round, weights)

    def assign_actor(self, name: str, previous: str = "") -> Assignment:
        """The learner (and its replay) this actor works for; :class:`NoWorkYet` when none has room
        (or the evolver is unreachable): retry later."""
        return self._assign(
            evolver_pb2.AssignRequest(role=evolver_pb2.ACTOR, name=name, previous_assignment_id=previous)
        )

    def assign_replay(self, name: str, address: str, previous: str = "") -> Assignment:
        """The learner this replay (serving at ``address``) works for; :class:`NoWorkYet` as for actors."""
        request = evolver_pb2.AssignRequest(
            role=evolver_pb2.REPLAY, name=name, address=address, previous_assignment_id=previous
        )
        return self._assign(request)

    def _assign(self, request: evolver_pb2.AssignRequest) -> Assignment:
        try:
            return _assignment_from_proto(self._call(self._stub.Assign, request, UnknownAssignment))
        except grpc.RpcError as e:
            if e.code() == grpc.StatusCode.UNAVAILABLE:
                raise NoWorkYet(e.details()) from None
            raise

    def renew_assignment(self, assignment_id: str) -> Assignment:
        """Renew the lease; the assignment comes back with its learner's current address and replay.
        :class:`UnknownAssignment`: assign again."""
        request = evolver_pb2.AssignmentHeartbeatRequest(assignment_id=assignment_id)
        return _assignment_from_proto(self._call(self._stub.AssignmentHeartbeat, request, UnknownAssignment))

    def info(self) -> EvolverInfo:
        r = self._call(self._stub.Info, evolver_pb2.EvolverInfoRequest())
        return EvolverInfo(
            r.experiment,
            r.rounds,
            list(r.last_elites),
            [_learner_from_proto(m) for m in r.learners],
            [_assignment_from_proto(m) for m in r.assignments],
        )

    def _call(self, method: Callable[..., Any], request: Any, not_found: type[LookupError] = UnknownLearner) -> Any:
        try:
            return self._unary(method, request)
        except grpc.RpcError as e:
            code, details = e.code(), e.details()
            if code == grpc.StatusCode.NOT_FOUND:
                raise not_found(details) from None
            if code == grpc.StatusCode.FAILED_PRECONDITION:
                raise LearnerRetired(details) from None
            if code == grpc.StatusCode.INVALID_ARGUMENT:
                raise EvolverRequestRejected(details) from None
            raise


def _assignment_from_proto(m: evolver_pb2.Assignment) -> Assignment:
    return Assignment(
        m.assignment_id,
        ROLE_FROM_PROTO[m.role],
        m.learner_id,
        m.learner_host,
        m.learner_port,
        m.params_port,
        m.replay_address,
        m.config_yaml,
        m.experiment,
        m.lease_s,
        m.learner_live,
    )


def _learner_from_proto(m: evolver_pb2.LearnerInfo) -> LearnerInfo:
    return LearnerInfo(
        m.learner_id,
        m.name,
        m.host,
        m.learner_port,
        m.params_port,
        m.replay_address,
        m.mean_return if m.HasField("mean_return") else None,
        m.returns,
        m.rounds,
        m.times_elite,
        m.retired,
        m.live,
        json.loads(m.params_json) if m.params_json else {},
        m.actors,
        m.env_steps,
        m.pending_round,
    )


__all__ = [
    "INSTRUCTION_TO_PROTO",
    "ROLE_FROM_PROTO",
    "ROLE_TO_PROTO",
    "EvolverClient",
    "EvolverRequestRejected",
    "Sample",
]
