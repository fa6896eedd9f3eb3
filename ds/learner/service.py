"""The learner's gRPC service (protos/learner.proto): actor registration with leases, the latest
parameters for late joiners, actions for actors that hold no weights, and the full model weights
for the evolver.

Usage, the learner's side (ds/learner/learner.py feeds the store and the acting copy)::

    registry, store = ActorRegistry(lease_s=15.0), ParamsStore()
    acting = PublishedPolicy(Policy(...)) if not update_policy_mode else None
    servicer = LearnerServicer(spec, registry, store, params_port=publisher_port, acting=acting,
                               weights=latest_full_weights,  # with an evolver: () -> (version, frames) | None
                               stream=publisher.stream)      # the key actors check the parameters with
    server, port, health = serve_learner(servicer, "127.0.0.1:61001", max_message_bytes=limit, credentials=creds)
    store.put(version, publisher.frames); acting.load(version, sac.acting_state_dict())
    rpc.set_serving(health, SERVICE_NAME, True)                # after the first publication

and an actor's (the client is ds/learner/client.py, which imports no torch)::

    learner = LearnerClient("learner:61001", spec, rnn_state_size, max_message_bytes=limit, credentials=creds)
    me = learner.register("actor on host-3")                   # id, index, params port and key, lease
    learner.heartbeat(me.actor_id, env_steps)                  # every few seconds; LeaseExpired: register again
    version, frames = learner.get_params()                     # decode with ds.net.params.decode_params
    actions, logp, next_state = learner.act(obs, noise=0.05)   # update_policy_mode: false

and the evolver's (ds/evolver/evolver.py), which needs no EnvSpec::

    version, frames = LearnerClient("learner:61001", credentials=creds).get_weights()   # decode_params

(``creds``: ds.net.security.load_credentials; under mutual TLS each rpc is open only to the roles
:data:`CALLERS` names: GetWeights to the evolver, the rest to actors.)
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TypeAlias

import grpc
import numpy as np
import torch
from grpc_health.v1 import health, health_pb2_grpc

from algorithm.config.schema import MAX_EXPLORATION_NOISE
from algorithm.sac.policy import Policy
from algorithm.spaces import EnvSpec
from ds.net import rpc, security
from ds.net.rpc import GRPC_DEFAULT_MESSAGE_BYTES
from ds.net.security import ACTOR, EVOLVER, NO_CREDENTIALS, Credentials
from ds.net.stream_key import StreamKey
from ds.net.wire import TensorSpec, WireError, from_tensor, to_tensor
from protos import learner_pb2, learner_pb2_grpc

SERVICE_NAME = "asac.LearnerService"
log = logging.getLogger("asac.learner")
# Who calls what (under mutual TLS, no other role may): actors, except GetWeights, which feeds the
# evolver's CEM round and is open to the evolver alone.
CALLERS: security.Callers = {
    "RegisterActor": frozenset({ACTOR}),
    "Heartbeat": frozenset({ACTOR}),
    "GetParams": frozenset({ACTOR}),
    "GetAction": frozenset({ACTOR}),
    "GetWeights": frozenset({EVOLVER}),
}
_F32 = np.dtype(np.float32)
# Framing of the frames and tensors of a message beyond their raw bytes (tags, lengths, JSON header).
_FRAMING_BYTES = 64 * 1024

WeightsSource: TypeAlias = Callable[[], tuple[int, list[bytes]] | None]
"""What serves GetWeights: ``() -> (version, frames)`` of the learner's full model weights, encoded with
:func:`ds.net.params.encode_params` (signed with the run's token), or None while there is no snapshot yet."""


def learner_message_limit(sac: Policy, max_actors_envs: int = 1024) -> int:
    """The gRPC message limit for a learner and its clients: ``max(4 MiB, 2 * P + 1 MiB)`` where P is
    the largest of the acting parameters (GetParams), the full models (GetWeights) and a GetAction of
    ``max_actors_envs`` envs."""
    param_bytes = max(_nbytes(sac.acting_state_dict()), _nbytes(sac.models.state_dict()))
    spec = sac.spec
    obs_bytes = sum(int(np.prod(s.shape)) * s.dtype.itemsize for s in spec.sensors)
    action_bytes = max_actors_envs * (obs_bytes + 4 * (2 * spec.action.size + 1 + 2 * sac.rnn_state_size))
    return max(GRPC_DEFAULT_MESSAGE_BYTES, 2 * max(param_bytes, action_bytes) + _FRAMING_BYTES + 1024 * 1024)


def _nbytes(state: dict[str, torch.Tensor]) -> int:
    return sum(t.numel() * t.element_size() for t in state.values())


# ---------------------------------------------------------------------- the learner's state


@dataclass
class ActorLease:
    actor_id: str
    index: int
    name: str
    expires: float
    env_steps: int = 0


class ActorRegistry:
    """Actors known to this learner, each with an index and a lease renewed by heartbeat.

    An actor gets the lowest index no live actor holds (its ``preferred_index`` if that one is
    free), so a restarted actor, or every actor after a learner restart, gets its old index back
    and with it the same seeds and exploration noise. A lease not renewed within ``lease_s``
    seconds expires and frees the index. Registrations and expiries are logged and counted
    (``registered``, ``expired``). Thread-safe.

    ``run_done`` is set by the learner once the run's budget is spent: every heartbeat answers it
    (the actors stop), an actor that has sent its last inserts says it is leaving (:meth:`leave`:
    its index is free at once), and :meth:`alive` empty tells the learner that nothing more is on
    its way. Leases running out after ``run_done`` are logged as normal, not as warnings."""

    def __init__(self, lease_s: float = 15.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.lease_s = float(lease_s)
        self._clock = clock
        self._lock = threading.Lock()
        self._actors: dict[str, ActorLease] = {}
        self.registered = 0
        self.expired = 0
        self.left = 0
        self.run_done = threading.Event()
        self.updates: Callable[[], int] = lambda: 0  # the learner's update count (the Learner sets it)

    def register(self, name: str, preferred_index: int | None = None) -> ActorLease:
        with self._lock:
            self._expire()
            taken = {a.index for a in self._actors.values()}
            if preferred_index is not None and preferred_index not in taken:
                index = preferred_index
            else:
                index = next(i for i in range(len(taken) + 1) if i not in taken)
            lease = ActorLease(f"actor-{index}-{uuid.uuid4().hex[:8]}", index, name, self._clock() + self.lease_s)
            self._actors[lease.actor_id] = lease
            self.registered += 1
            log.info("%s registered as %s (index %d); %d live", name, lease.actor_id, index, len(self._actors))
            return lease

    def renew(self, actor_id: str, env_steps: int) -> bool:
        """Extend ``actor_id``'s lease; False if it is unknown or already expired."""
        with self._lock:
            self._expire()
            lease = self._actors.get(actor_id)
            if lease is None:
                return False
            lease.expires = self._clock() + self.lease_s
            lease.env_steps = int(env_steps)
            return True

    def leave(self, actor_id: str, env_steps: int) -> bool:
        """Forget ``actor_id`` now: it has sent everything it will insert and stops. False if it was
        not live."""
        with self._lock:
            self._expire()
            lease = self._actors.pop(actor_id, None)
            if lease is None:
                return False
            self.left += 1
            log.info("%s (%s, index %d) left after %d env steps; %d live", actor_id, lease.name, lease.index,
                     env_steps, len(self._actors))  # fmt: skip
            return True

    def alive(self) -> list[ActorLease]:
        with self._lock:
            self._expire()
            return sorted(self._actors.values(), key=lambda a: a.index)

    def _expire(self) -> None:
        now = self._clock()
        for actor_id in [a.actor_id for a in self._actors.values() if a.expires < now]:
            lease = self._actors.pop(actor_id)
            self.expired += 1
            level = logging.INFO if self.run_done.is_set() else logging.WARNING  # leaving at the end is normal
            log.log(level, "%s (%s, index %d) dropped: no heartbeat for %.1f s (lease %.1f s); %d live", actor_id,
                    lease.name, lease.index, now - lease.expires + self.lease_s, self.lease_s,
                    len(self._actors))  # fmt: skip


class ParamsStore:
    """The latest published version and its frames (one serialisation, shared with ZeroMQ)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._latest: tuple[int, list[bytes]] | None = None

    def put(self, version: int, frames: list[bytes]) -> None:
        with self._lock:
            self._latest = (int(version), list(frames))

    def get(self) -> tuple[int, list[bytes]] | None:
        with self._lock:
            return self._latest

    @property
    def version(self) -> int:
        latest = self.get()
        return -1 if latest is None else latest[0]


class PublishedPolicy:
    """A copy of the learner's acting weights as of the last publication, for ``GetAction``.

    The learner trains its own SAC and loads each published version here, so served actions
    always come from a published version (never from weights halfway through an optimizer step).
    One lock serialises acting and loading."""

    def __init__(self, policy: Policy) -> None:
        self.sac = policy
        self.version = -1
        self._lock = threading.Lock()

    def load(self, version: int, state: dict[str, torch.Tensor]) -> None:
        with self._lock:
            self.sac.load_acting_state_dict(state)
            self.version = int(version)

    def act(
        self,
        obs: list[np.ndarray],
        prev_actions: np.ndarray | None,
        rnn_state: np.ndarray | None,
        noise: float,
        deterministic: bool,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, int]:
        with self._lock:
            self.sac.exploration_noise = noise
            if self.sac.rnn_state_size:
                assert prev_actions is not None and rnn_state is not None
                actions, logp, state = self.sac.act_recurrent(obs, prev_actions, rnn_state, deterministic)
                return actions, logp, state, self.version
            actions, logp = self.sac.act(obs, deterministic)
            return actions, logp, None, self.version


# ---------------------------------------------------------------------- server


class LearnerServicer(learner_pb2_grpc.LearnerServiceServicer):
    """Serves one learner's registry, parameter store and (optionally) acting copy and full weights.

    ``weights`` serves GetWeights (the evolver's CEM round); it runs on an RPC thread while the
    learner trains, so it must return a consistent snapshot (frames built between updates, say),
    never weights halfway through an optimizer step. Without it GetWeights is UNIMPLEMENTED. ``stream``:
    the publisher's :class:`~ds.net.stream_key.StreamKey` (its id is the learner's; its secret goes to each
    actor); without it a fresh one (a learner whose parameters no actor subscribes to)."""

    def __init__(
        self,
        spec: EnvSpec,
        registry: ActorRegistry,
        store: ParamsStore,
        params_port: int,
        acting: PublishedPolicy | None = None,
        rnn_state_size: int = 0,
        weights: WeightsSource | None = None,
        stream: StreamKey | None = None,
    ) -> None:
        self.spec = spec
        self.weights = weights
        self.registry = registry
        self.store = store
        self.params_port = int(params_port)
        self.acting = acting
        self.rnn_state_size = int(rnn_state_size)
        self.stream = stream or StreamKey.fresh()
        self.learner_id = self.stream.learner_id
        self.actions_served = 0

    def RegisterActor(
        self, request: learner_pb2.RegisterActorRequest, context: grpc.ServicerContext
    ) -> learner_pb2.RegisterActorReply:
        preferred = request.preferred_index if request.HasField("preferred_index") else None
        if preferred is not None and preferred < 0:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"preferred_index must be >= 0, got {preferred}")
        lease = self.registry.register(request.name, preferred)
        return learner_pb2.RegisterActorReply(
            actor_id=lease.actor_id,
            index=lease.index,
            learner_id=self.learner_id,
            params_port=self.params_port,
            lease_s=self.registry.lease_s,
            params_key=self.stream.secret,
            live_actors=len(self.registry.alive()),
        )

    def Heartbeat(
        self, request: learner_pb2.HeartbeatRequest, context: grpc.ServicerContext
    ) -> learner_pb2.HeartbeatReply:
        if request.env_steps < 0:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"env_steps must be >= 0, got {request.env_steps}")
        if request.leaving:
            self.registry.leave(request.actor_id, request.env_steps)  # an unknown id has gone already: fine
        elif not self.registry.renew(request.actor_id, request.env_steps):
            context.abort(grpc.StatusCode.NOT_FOUND, f"no live actor {request.actor_id!r} (lease expired?): register")
        return learner_pb2.HeartbeatReply(
            learner_id=self.learner_id,
            params_version=self.store.version,
            run_done=self.registry.run_done.is_set(),
            live_actors=len(self.registry.alive()),
            updates=self.registry.updates(),
        )

    def GetParams(
        self, request: learner_pb2.GetParamsRequest, context: grpc.ServicerContext
    ) -> learner_pb2.GetParamsReply:
        latest = self.store.get()
        if latest is None:
            context.abort(grpc.StatusCode.UNAVAILABLE, "no parameters published yet")
        version, frames = latest  # type: ignore[misc]  # abort raises
        return learner_pb2.GetParamsReply(version=version, frames=frames)

    def GetWeights(
        self, request: learner_pb2.GetWeightsRequest, context: grpc.ServicerContext
    ) -> learner_pb2.GetParamsReply:
        if self.weights is None:
            context.abort(
                grpc.StatusCode.UNIMPLEMENTED, "this learner runs without an evolver and does not serve its weights"
            )
        assert self.weights is not None
        snapshot = self.weights()
        if snapshot is None:
            context.abort(grpc.StatusCode.UNAVAILABLE, "no snapshot of the weights yet")
        version, frames = snapshot  # type: ignore[misc]  # abort raises
        return learner_pb2.GetParamsReply(version=version, frames=frames)

    def GetAction(
        self, request: learner_pb2.GetActionRequest, context: grpc.ServicerContext
    ) -> learner_pb2.GetActionReply:
        if self.acting is None:
            context.abort(
                grpc.StatusCode.FAILED_PRECONDITION,
                "this learner keeps no acting copy (actor_config.update_policy_mode: true): "
                "subscribe to its parameters instead",
            )
        assert self.acting is not None
        if self.acting.version < 0:
            context.abort(grpc.StatusCode.UNAVAILABLE, "no parameters published yet")
        with _invalid_argument(context):
            obs, prev_actions, rnn_state, noise = self._decode(request)
        actions, logp, state, version = self.acting.act(obs, prev_actions, rnn_state, noise, request.deterministic)
        self.actions_served += len(actions)
        reply = learner_pb2.GetActionReply(
            actions=to_tensor(actions.astype(np.float32)),
            behaviour_logp=to_tensor(logp.astype(np.float32)),
            params_version=version,
        )
        if state is not None:
            reply.rnn_state.CopyFrom(to_tensor(state.astype(np.float32)))
        return reply

    def _decode(
        self, request: learner_pb2.GetActionRequest
    ) -> tuple[list[np.ndarray], np.ndarray | None, np.ndarray | None, float]:
        sensors, dims = self.spec.sensors, dict[str, int]()
        if len(request.obs) != len(sensors):
            raise WireError("obs", f"has {len(request.obs)} sensors, the learner expects {len(sensors)}")
        obs = [
            from_tensor(t, TensorSpec(f"obs[{i}] ({s.name})", s.dtype, s.shape, finite=True, leading=("N",)), dims)
            for i, (t, s) in enumerate(zip(request.obs, sensors, strict=True))
        ]
        prev_actions = rnn_state = None
        recurrent = {"prev_actions": self.spec.action.size, "rnn_state": self.rnn_state_size}
        for name in recurrent:
            if self.rnn_state_size and not request.HasField(name):
                raise WireError(name, "is required: this learner's policy is recurrent")
            if not self.rnn_state_size and request.HasField(name):
                raise WireError(name, "is set but this learner's policy is not recurrent")
        if self.rnn_state_size:
            specs = {name: TensorSpec(name, _F32, (width,), True, ("N",)) for name, width in recurrent.items()}
            prev_actions = from_tensor(request.prev_actions, specs["prev_actions"], dims)
            rnn_state = from_tensor(request.rnn_state, specs["rnn_state"], dims)
        if not 0 <= request.noise <= MAX_EXPLORATION_NOISE:  # also NaN
            raise WireError("noise", f"must be in [0, {MAX_EXPLORATION_NOISE:.0f}], got {request.noise}")
        return obs, prev_actions, rnn_state, float(request.noise)


@contextmanager
def _invalid_argument(context: grpc.ServicerContext) -> Iterator[None]:
    try:
        yield
    except ValueError as e:
        context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))


def serve_learner(
    servicer: LearnerServicer,
    address: str = "127.0.0.1:0",
    *,
    max_message_bytes: int = GRPC_DEFAULT_MESSAGE_BYTES,
    max_workers: int = 16,
    credentials: Credentials = NO_CREDENTIALS,
    health_port: int | None = None,
) -> tuple[grpc.Server, int, health.HealthServicer]:
    """Start the learner's gRPC server on ``address`` (port 0: any free port); returns the server,
    its port and its health servicer, which reports NOT_SERVING until the caller flips it with
    ``ds.net.rpc.set_serving(health, SERVICE_NAME, True)`` (after the first publication).
    ``credentials`` and ``health_port``: see :func:`ds.net.security.listen`."""
    options = rpc.channel_options(max_message_bytes)
    server = security.new_server("learner", SERVICE_NAME, CALLERS, credentials, max_workers, options)
    rpc.add_servicer(server, servicer, learner_pb2.DESCRIPTOR.services_by_name["LearnerService"])
    health_servicer = health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    rpc.set_serving(health_servicer, SERVICE_NAME, False)
    port = security.listen(server, address, credentials, "learner", health_port)
    server.start()
    return server, port, health_servicer


__all__ = [
    "CALLERS",
    "SERVICE_NAME",
    "PublishedPolicy",
    "ActorRegistry",
    "LearnerServicer",
    "ParamsStore",
    "WeightsSource",
    "learner_message_limit",
    "serve_learner",
]
