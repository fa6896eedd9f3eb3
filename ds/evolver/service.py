"""The evolver over gRPC (protos/evolver.proto): a servicer around :class:`ds.evolver.evolver.Evolver`, the
server with its health service, and the client learners, actors and replays use.

Usage, the evolver's process::

    evolver = Evolver(config, run_dir / "evolver", name, metrics=MetricsWriter(run_dir / "log" / "evolver"))
    evolver.start()
    server, port, health = serve_evolver(evolver, "0.0.0.0:61000", credentials=creds)  # SERVING at once
    ...
    server.stop(grace=5.0); evolver.stop()

a learner's::

    evolver = EvolverClient("evolver:61000", token=token, credentials=creds)  # creds: ds.net.security
    me = evolver.register_learner("learner-0", host="", learner_port=61001, params_port=61003,
                                  previous_id=saved_id)                # host "": the address the call came from
    orders = evolver.heartbeat(me.learner_id, env_steps, loaded_round=loaded)   # every few seconds
    if orders.instruction is Instruction.LOAD_WEIGHTS:
        sample = evolver.get_sample(me.learner_id, expected=params_spec(full_weights))
    evolver.post_reward(me.learner_id, mean_return, env_steps, weights_round=loaded)

and an actor's or replay's::

    job = evolver.assign_actor("actor-3")            # NoWorkYet: no learner has room yet; retry later
    job = evolver.assign_replay("replay-0", "10.0.0.7:61002")
    job = evolver.renew_assignment(job.assignment_id)  # every few seconds; UnknownAssignment: assign again

Status codes map to the exceptions of ds/evolver/state.py on both ends: NOT_FOUND is
:class:`UnknownLearner` (or :class:`UnknownAssignment` for assignments), FAILED_PRECONDITION
:class:`LearnerRetired`, UNAVAILABLE from Assign :class:`NoWorkYet`, INVALID_ARGUMENT
:class:`EvolverRequestRejected` (a ``ValueError``). Every call has a deadline; UNAVAILABLE (evolver
down or restarting) is retried with backoff and then raised as ``grpc.RpcError``. Under mutual TLS
each rpc is open only to the roles :data:`CALLERS` names, and an :class:`EvolverClient` accepts only
a server whose certificate names the evolver: a learner loads CEM samples from nobody else
(ds/net/security.py).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import grpc
import numpy as np
from grpc_health.v1 import health, health_pb2_grpc

from ds.evolver.evolver import EVOLVER_MESSAGE_BYTES, Evolver
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
from ds.net.params import ParamsError, ParamsSpec, decode_params
from ds.net.security import ACTOR, LEARNER, NO_CREDENTIALS, REPLAY, ROLES, Credentials
from protos import evolver_pb2, evolver_pb2_grpc

SERVICE_NAME = "asac.EvolverService"
# Who calls what (under mutual TLS, no other role may): learners join, report and fetch their CEM
# samples; actors and replays ask where to work; Info (the local launcher, operators) is open to any role.
CALLERS: security.Callers = {
    "RegisterLearner": frozenset({LEARNER}),
    "LearnerHeartbeat": frozenset({LEARNER}),
    "PostReward": frozenset({LEARNER}),
    "GetSample": frozenset({LEARNER}),
    "Assign": frozenset({ACTOR, REPLAY}),
    "AssignmentHeartbeat": frozenset({ACTOR, REPLAY}),
    "Info": ROLES,
}
_ROLE_TO_PROTO = {Role.ACTOR: evolver_pb2.ACTOR, Role.REPLAY: evolver_pb2.REPLAY}
_ROLE_FROM_PROTO = {v: k for k, v in _ROLE_TO_PROTO.items()}
_INSTRUCTION_TO_PROTO = {
    Instruction.CONTINUE: evolver_pb2.CONTINUE,
    Instruction.LOAD_WEIGHTS: evolver_pb2.LOAD_WEIGHTS,
    Instruction.RETIRE: evolver_pb2.RETIRE,
}
_INSTRUCTION_FROM_PROTO = {v: k for k, v in _INSTRUCTION_TO_PROTO.items()}
_FRAMING_BYTES = 64 * 1024  # tags and lengths of a GetSample reply beyond its frames


# ---------------------------------------------------------------------- server


class EvolverServicer(evolver_pb2_grpc.EvolverServiceServicer):
    """Serves one :class:`Evolver`. Every handler answers at once (rounds run on the evolver's thread)."""

    def __init__(self, evolver: Evolver, max_message_bytes: int = EVOLVER_MESSAGE_BYTES) -> None:
        self.evolver = evolver
        self.max_message_bytes = int(max_message_bytes)

    def RegisterLearner(
        self, request: evolver_pb2.RegisterLearnerRequest, context: grpc.ServicerContext
    ) -> evolver_pb2.RegisterLearnerReply:
        previous = request.previous_id if request.HasField("previous_id") else None
        with _status_codes(context):
            host = request.host or _peer_host(context.peer())
            ports = (request.learner_port, request.params_port, request.replay_address)
            r = self.evolver.register_learner(request.name, host, *ports, previous_id=previous)
        return evolver_pb2.RegisterLearnerReply(
            learner_id=r.learner_id,
            experiment=r.experiment,
            config_yaml=r.config_yaml,
            params_json=json.dumps(r.params, sort_keys=True),
            lease_s=r.lease_s,
            replay_address=r.replay_address,
            rounds=r.rounds,
        )

    def LearnerHeartbeat(
        self, request: evolver_pb2.LearnerHeartbeatRequest, context: grpc.ServicerContext
    ) -> evolver_pb2.LearnerHeartbeatReply:
        loaded = request.loaded_round if request.HasField("loaded_round") else None
        with _status_codes(context):
            orders = self.evolver.learner_heartbeat(request.learner_id, request.env_steps, loaded)
        return evolver_pb2.LearnerHeartbeatReply(
            instruction=_INSTRUCTION_TO_PROTO[orders.instruction],
            sample_round=orders.sample_round,
            replay_address=orders.replay_address,
            lease_s=orders.lease_s,
            rounds=orders.rounds,
        )

    def PostReward(
        self, request: evolver_pb2.PostRewardRequest, context: grpc.ServicerContext
    ) -> evolver_pb2.PostRewardReply:
        with _status_codes(context):
            accepted = self.evolver.post_reward(
                request.learner_id, request.mean_return, request.env_steps, request.weights_round
            )
        return evolver_pb2.PostRewardReply(accepted=accepted)

    def GetSample(
        self, request: evolver_pb2.GetSampleRequest, context: grpc.ServicerContext
    ) -> evolver_pb2.GetSampleReply:
        with _status_codes(context):
            got = self.evolver.sample(request.learner_id)
        if got is None:
            return evolver_pb2.GetSampleReply(round=0)
        round_, frames = got
        size = sum(len(f) for f in frames) + _FRAMING_BYTES
        if size > self.max_message_bytes:
            context.abort(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"the sample of round {round_} is about {size} bytes, over this evolver's message limit of "
                f"{self.max_message_bytes} bytes: start the evolver and its learners with a larger max_message_bytes",
            )
        return evolver_pb2.GetSampleReply(round=round_, frames=frames)

    def Assign(self, request: evolver_pb2.AssignRequest, context: grpc.ServicerContext) -> evolver_pb2.Assignment:
        with _status_codes(context):
            role = _ROLE_FROM_PROTO.get(request.role)
            if role is None:
                raise ValueError(f"role: must be ACTOR or REPLAY, got {_role_name(request.role)}")
            job = self.evolver.assign(role, request.name, request.address, request.previous_assignment_id)
        return _assignment_to_proto(job)

    def AssignmentHeartbeat(
        self, request: evolver_pb2.AssignmentHeartbeatRequest, context: grpc.ServicerContext
    ) -> evolver_pb2.Assignment:
        with _status_codes(context):
            return _assignment_to_proto(self.evolver.renew_assignment(request.assignment_id))

    def Info(
        self, request: evolver_pb2.EvolverInfoRequest, context: grpc.ServicerContext
    ) -> evolver_pb2.EvolverInfoReply:
        info = self.evolver.info()
        return evolver_pb2.EvolverInfoReply(
            experiment=info.experiment,
            rounds=info.rounds,
            last_elites=info.last_elites,
            learners=[_learner_to_proto(learner) for learner in info.learners],
            assignments=[_assignment_to_proto(a) for a in info.assignments],
        )


@contextmanager
def _status_codes(context: grpc.ServicerContext) -> Iterator[None]:
    try:
        yield
    except (UnknownLearner, UnknownAssignment) as e:
        context.abort(grpc.StatusCode.NOT_FOUND, str(e))
    except LearnerRetired as e:
        context.abort(grpc.StatusCode.FAILED_PRECONDITION, str(e))
    except NoWorkYet as e:
        context.abort(grpc.StatusCode.UNAVAILABLE, str(e))
    except ValueError as e:
        context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))


def _peer_host(peer: str) -> str:
    """The host part of a gRPC peer (``ipv4:10.0.0.5:4711``, ``ipv6:[::1]:4711``); "" for others (unix)."""
    kind, _, rest = peer.partition(":")
    return rest.rsplit(":", 1)[0] if kind in ("ipv4", "ipv6") else ""


def _role_name(value: int) -> str:
    try:
        return str(evolver_pb2.Role.Name(value))
    except ValueError:
        return str(value)


def serve_evolver(
    evolver: Evolver,
    address: str = "127.0.0.1:0",
    *,
    max_message_bytes: int = EVOLVER_MESSAGE_BYTES,
    max_workers: int = 16,
    ready: bool = True,
    credentials: Credentials = NO_CREDENTIALS,
    health_port: int | None = None,
) -> tuple[grpc.Server, int, health.HealthServicer]:
    """Start the evolver's gRPC server on ``address`` (port 0: any free port); returns the server, its
    port and its health servicer. The evolver's state is loaded when it is constructed, so the health
    service reports SERVING once the server runs (``ready=False``: the caller flips it with
    ``ds.net.rpc.set_serving(health, SERVICE_NAME, True)``). ``credentials`` and ``health_port``: see
    :func:`ds.net.security.listen`. Stop it with ``server.stop(grace)``."""
    options = rpc.channel_options(max_message_bytes)
    server = security.new_server("evolver", SERVICE_NAME, CALLERS, credentials, max_workers, options)
    servicer = EvolverServicer(evolver, max_message_bytes)
    rpc.add_servicer(server, servicer, evolver_pb2.DESCRIPTOR.services_by_name["EvolverService"])
    health_servicer = health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    rpc.set_serving(health_servicer, SERVICE_NAME, False)
    port = security.listen(server, address, credentials, "evolver", health_port)
    server.start()
    if ready:
        rpc.set_serving(health_servicer, SERVICE_NAME, True)
    return server, port, health_servicer


# ---------------------------------------------------------------------- client


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
        token: bytes | None = None,
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


# ---------------------------------------------------------------------- conversions


def _assignment_to_proto(a: Assignment) -> evolver_pb2.Assignment:
    return evolver_pb2.Assignment(
        assignment_id=a.assignment_id,
        role=_ROLE_TO_PROTO[a.role],
        learner_id=a.learner_id,
        learner_host=a.learner_host,
        learner_port=a.learner_port,
        params_port=a.params_port,
        replay_address=a.replay_address,
        config_yaml=a.config_yaml,
        experiment=a.experiment,
        lease_s=a.lease_s,
        learner_live=a.learner_live,
    )


def _assignment_from_proto(m: evolver_pb2.Assignment) -> Assignment:
    return Assignment(
        m.assignment_id,
        _ROLE_FROM_PROTO[m.role],
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


def _learner_to_proto(x: LearnerInfo) -> evolver_pb2.LearnerInfo:
    message = evolver_pb2.LearnerInfo(
        learner_id=x.learner_id,
        name=x.name,
        host=x.host,
        learner_port=x.learner_port,
        params_port=x.params_port,
        replay_address=x.replay_address,
        returns=x.returns,
        rounds=x.rounds,
        times_elite=x.times_elite,
        retired=x.retired,
        live=x.live,
        params_json=json.dumps(x.params, sort_keys=True),
        actors=x.actors,
        env_steps=x.env_steps,
        pending_round=x.pending_round,
    )
    if x.mean_return is not None:
        message.mean_return = x.mean_return
    return message


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
    "CALLERS",
    "SERVICE_NAME",
    "EvolverClient",
    "EvolverRequestRejected",
    "EvolverServicer",
    "Sample",
    "serve_evolver",
]
