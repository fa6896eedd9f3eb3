"""The evolver's gRPC server (protos/evolver.proto): a servicer around :class:`ds.evolver.evolver.Evolver`
and the server with its health service. Learners, actors and replays call it through
:class:`ds.evolver.client.EvolverClient` (ds/evolver/client.py, with their usage).

Usage, the evolver's process::

    evolver = Evolver(config, run_dir / "evolver", name, metrics=MetricsWriter(RunDir(run_dir).role_log("evolver")))
    evolver.start()
    server, port, health = serve_evolver(evolver, "0.0.0.0:61000", credentials=creds)  # SERVING at once
    ...
    server.stop(grace=5.0); evolver.stop()

The exceptions of ds/evolver/state.py become status codes: :class:`UnknownLearner` and
:class:`UnknownAssignment` NOT_FOUND, :class:`LearnerRetired` FAILED_PRECONDITION, :class:`NoWorkYet`
UNAVAILABLE, a ``ValueError`` INVALID_ARGUMENT (the client raises them again). Under mutual TLS each rpc
is open only to the roles :data:`CALLERS` names (ds/net/security.py).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager

import grpc
from grpc_health.v1 import health, health_pb2_grpc

from ds.evolver.client import INSTRUCTION_TO_PROTO, ROLE_FROM_PROTO, ROLE_TO_PROTO
from ds.evolver.evolver import EVOLVER_MESSAGE_BYTES, Evolver
from ds.evolver.state import Assignment, LearnerInfo, LearnerRetired, NoWorkYet, UnknownAssignment, UnknownLearner
from ds.net import rpc, security
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
            instruction=INSTRUCTION_TO_PROTO[orders.instruction],
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
            role = ROLE_FROM_PROTO.get(request.role)
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


# ---------------------------------------------------------------------- conversions


def _assignment_to_proto(a: Assignment) -> evolver_pb2.Assignment:
    return evolver_pb2.Assignment(
        assignment_id=a.assignment_id,
        role=ROLE_TO_PROTO[a.role],
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


__all__ = ["CALLERS", "SERVICE_NAME", "EvolverServicer", "serve_evolver"]
