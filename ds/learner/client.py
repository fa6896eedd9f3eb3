"""The actor's and the evolver's end of the learner's gRPC service (ds/learner/service.py, which
holds the server and its usage): registration, heartbeats, parameters, actions for actors that hold
no weights, and the full weights for the evolver. Nothing here imports torch: the evolver uses it."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import grpc
import numpy as np

from algorithm.spaces import EnvSpec
from algorithm.types import ActingProgress
from ds.net import rpc, security
from ds.net.client import RpcClient
from ds.net.rpc import GRPC_DEFAULT_MESSAGE_BYTES
from ds.net.security import NO_CREDENTIALS, Credentials
from ds.net.wire import TensorSpec, from_tensor, to_tensor
from protos import learner_pb2, learner_pb2_grpc

LEAVE_TIMEOUT_S = 2.0  # an actor's goodbye (LearnerClient.leave) is one try: the run is ending
_F32 = np.dtype(np.float32)


class LeaseExpired(RuntimeError):
    """The learner does not know this actor id (lease expired, or the learner restarted): register again."""


class Beat(NamedTuple):
    """A heartbeat's answer (learner.proto HeartbeatReply)."""

    learner_id: str
    params_version: int
    run_done: bool
    live_actors: int = 0  # actors holding a lease (0: a learner that does not say)
    updates: int = 0  # the learner's updates so far


@dataclass(frozen=True)
class Registration:
    actor_id: str
    index: int
    learner_id: str
    params_port: int
    lease_s: float
    params_key: bytes = field(default=b"", repr=False)  # the learner's StreamKey secret (ds/net/stream_key.py)
    live_actors: int = 0  # actors holding a lease, this one included (0: a learner that does not say)


class LearnerClient(RpcClient):
    """The actor's (and the evolver's) end of :class:`LearnerServicer`. Every call has a deadline of
    ``rpc_timeout_s``; UNAVAILABLE is retried per ``retry`` and then raised as ``grpc.RpcError``, as
    is every other status except the ones named per method. ``spec`` is needed by :meth:`act` only.
    ``credentials``: TLS and the token (:func:`ds.net.security.open_channel`; the server must be a learner).
    Thread-safe."""

    def __init__(
        self,
        address: str,
        spec: EnvSpec | None = None,
        rnn_state_size: int = 0,
        *,
        max_message_bytes: int = GRPC_DEFAULT_MESSAGE_BYTES,
        rpc_timeout_s: float = 10.0,
        retry: rpc.RetryPolicy | None = None,
        credentials: Credentials = NO_CREDENTIALS,
    ) -> None:
        super().__init__(
            address,
            security.LEARNER,
            learner_pb2_grpc.LearnerServiceStub,
            max_message_bytes=max_message_bytes,
            rpc_timeout_s=rpc_timeout_s,
            retry=retry,
            credentials=credentials,
        )
        self.spec = spec
        self.rnn_state_size = int(rnn_state_size)

    def register(self, name: str, preferred_index: int | None = None) -> Registration:
        request = learner_pb2.RegisterActorRequest(name=name)
        if preferred_index is not None:
            request.preferred_index = int(preferred_index)
        reply = self._call(self._stub.RegisterActor, request)
        return Registration(reply.actor_id, reply.index, reply.learner_id, reply.params_port, reply.lease_s,
                            reply.params_key, reply.live_actors)  # fmt: skip

    def leave(self, actor_id: str, env_steps: int) -> bool:
        """Tell the learner this actor has sent its last inserts and stops (its lease ends now).
        One try with a short deadline, never raises: a learner that has gone needs no goodbye.
        Returns whether the learner heard it."""
        request = learner_pb2.HeartbeatRequest(actor_id=actor_id, env_steps=env_steps, leaving=True)
        try:
            self._stub.Heartbeat(request, timeout=min(self.rpc_timeout_s, LEAVE_TIMEOUT_S))
        except grpc.RpcError:
            return False
        return True

    def heartbeat(self, actor_id: str, env_steps: int) -> Beat:
        """Renew the lease; returns the learner's id, its latest params version and updates, and whether
        the run's budget is spent; :class:`LeaseExpired` when the learner no longer knows ``actor_id``."""
        try:
            request = learner_pb2.HeartbeatRequest(actor_id=actor_id, env_steps=env_steps)
            reply = self._call(self._stub.Heartbeat, request)
        except grpc.RpcError as e:
            if e.code() == grpc.StatusCode.NOT_FOUND:
                raise LeaseExpired(e.details()) from None
            raise
        return Beat(reply.learner_id, reply.params_version, reply.run_done, reply.live_actors, reply.updates)

    def get_params(self) -> tuple[int, list[bytes]]:
        """The latest published ``(version, frames)``; decode with :func:`ds.net.params.decode_params`."""
        reply = self._call(self._stub.GetParams, learner_pb2.GetParamsRequest())
        return reply.version, list(reply.frames)

    def get_weights(self) -> tuple[int, list[bytes]]:
        """The learner's full model weights as ``(version, frames)`` (the evolver's CEM round);
        decode with :func:`ds.net.params.decode_params`. UNIMPLEMENTED when it runs without an evolver."""
        reply = self._call(self._stub.GetWeights, learner_pb2.GetWeightsRequest())
        return reply.version, list(reply.frames)

    def act(
        self,
        obs: list[np.ndarray],
        noise: float = 0.0,
        deterministic: bool = False,
        prev_actions: np.ndarray | None = None,
        rnn_state: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Actions ``[N, A]``, behaviour log-probs ``[N]`` and (recurrent) next states from the learner."""
        if self.spec is None:
            raise ValueError("LearnerClient.act needs the EnvSpec: pass spec when creating the client")
        request = learner_pb2.GetActionRequest(
            obs=[to_tensor(o, f"obs[{i}]") for i, o in enumerate(obs)], noise=noise, deterministic=deterministic
        )
        if prev_actions is not None:
            request.prev_actions.CopyFrom(to_tensor(prev_actions.astype(np.float32)))
        if rnn_state is not None:
            request.rnn_state.CopyFrom(to_tensor(rnn_state.astype(np.float32)))
        reply = self._call(self._stub.GetAction, request)
        dims = {"N": len(obs[0])}
        a = self.spec.action.size
        actions = from_tensor(reply.actions, TensorSpec("actions", _F32, (a,), True, ("N",)), dims)
        logp = from_tensor(reply.behaviour_logp, TensorSpec("behaviour_logp", _F32, (), True, ("N",)), dims)
        state = None
        if self.rnn_state_size:
            spec = TensorSpec("rnn_state", _F32, (self.rnn_state_size,), True, ("N",))
            state = from_tensor(reply.rnn_state, spec, dims)
        return actions, logp, state

    def _call(self, method: Callable[..., Any], request: Any) -> Any:
        return self._unary(method, request)


class RemotePolicy:
    """The :class:`~algorithm.run.actor.ActionSource` of an actor with ``update_policy_mode: false``: every
    action comes from the learner (``GetAction``), with this actor's exploration noise."""

    def __init__(self, learner: LearnerClient, noise: float = 0.0) -> None:
        self.learner = learner
        self.noise = float(noise)
        self.rnn_state_size = learner.rnn_state_size
        self.progress = ActingProgress()  # the loop's; the learner acts with its own policy's schedule

    def act(self, obs: list[np.ndarray], deterministic: bool = False) -> tuple[np.ndarray, np.ndarray]:
        actions, logp, _ = self.learner.act(obs, self.noise, deterministic)
        return actions, logp

    def act_recurrent(
        self, obs: list[np.ndarray], prev_actions: np.ndarray, rnn_state: np.ndarray, deterministic: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        actions, logp, state = self.learner.act(obs, self.noise, deterministic, prev_actions, rnn_state)
        assert state is not None
        return actions, logp, state


__all__ = ["Beat", "LearnerClient", "LeaseExpired", "Registration", "RemotePolicy"]
