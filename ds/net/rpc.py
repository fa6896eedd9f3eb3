"""What every gRPC client and server of ours shares: message limits, strict request parsing, retries
of UNAVAILABLE with exponential backoff, the health service, and waiting for a peer to come up.

Usage::

    server = security.new_server("replay", SERVICE_NAME, CALLERS, credentials, max_workers, options)  # security.py
    add_servicer(server, servicer, replay_pb2.DESCRIPTOR.services_by_name["ReplayService"])   # strict parsing
    channel = security.open_channel(address, "replay", credentials, channel_options(limit))
    reply = call_with_retry(stub.Info, request, deadline_s=30.0, retry=RetryPolicy())   # or grpc.RpcError
    if not wait_until_serving(channel, "asac.ReplayService", "replay", address, stop):   # logs while waiting
        return  # stop was set

A call always has a deadline (docs/architecture.md section 8); only a peer that went away is retried: UNAVAILABLE
(down, restarting, or not listening yet) and CANCELLED (a server shutting down cancels the calls it
is still running; we never cancel our own calls). Every other status surfaces at once.

Servers registered with :func:`add_servicer` answer a request that does not parse, or that carries
a field the server's .proto does not define (at any depth), with INVALID_ARGUMENT naming it, before
the servicer sees it. gRPC's own deserialisation would answer INTERNAL for the first and silently
drop the second; every role of a run is built from the same protos, so an unknown field means a peer
of another version whose data would otherwise vanish without a word. Their refusals' details are
shortened to what a status can carry (:func:`status_details`), whatever the servicer aborts with.
"""

from __future__ import annotations

import functools
import logging
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar, cast

import grpc
from google.protobuf import message_factory, unknown_fields
from google.protobuf.descriptor import ServiceDescriptor
from google.protobuf.message import Message
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

_T = TypeVar("_T")
log = logging.getLogger("asac.rpc")
LOCAL_HOST = "127.0.0.1"  # where a client connects when no host is named (and every role of `local`)


# gRPC sends a status's details as a header; headers past its soft limit (8 KiB) drop the answer for
# RESOURCE_EXHAUSTED "received metadata size exceeds soft limit", so the caller would not see the
# status or the message. A zip error on a damaged snapshot can quote 11 KB of the file's bytes.
MAX_STATUS_DETAILS = 2000


def status_details(message: str, limit: int = MAX_STATUS_DETAILS) -> str:
    """``message`` within ``limit`` characters for a status's details: its start and its end, with
    how much was left out between them."""
    if len(message) <= limit:
        return message
    cut = len(message) - limit + 40
    head = (limit - 40) * 2 // 3
    return f"{message[:head]} ...[{cut} characters]... {message[head + cut :]}"


# gRPC's own default receive limit: every client's and server's default, and the least any limit is set to.
GRPC_DEFAULT_MESSAGE_BYTES = 4 * 1024 * 1024


def channel_options(max_message_bytes: int) -> list[tuple[str, int]]:
    """Send and receive limits for a channel or server (both ends must raise them)."""
    return [
        ("grpc.max_send_message_length", int(max_message_bytes)),
        ("grpc.max_receive_message_length", int(max_message_bytes)),
    ]


@dataclass(frozen=True)
class MalformedRequest:
    """What :func:`add_servicer`'s parser hands on instead of a request it refuses: the handler answers
    INVALID_ARGUMENT with ``reason`` and the servicer never runs."""

    reason: str


def add_servicer(server: grpc.Server, servicer: object, service: ServiceDescriptor) -> None:
    """Register ``servicer``'s methods for the unary-unary rpcs of ``service`` (a generated module's
    ``DESCRIPTOR.services_by_name[...]``), as the generated ``add_*_to_server`` does, but with
    :func:`strict_parser` requests: an undecodable request or one with unknown fields is answered
    INVALID_ARGUMENT naming the problem, never passed on (see the module docstring)."""
    handlers = {}
    for method in service.methods:
        if method.client_streaming or method.server_streaming:
            raise ValueError(f"{method.full_name}: add_servicer serves unary-unary rpcs only")
        reply = message_factory.GetMessageClass(method.output_type)
        handlers[method.name] = grpc.unary_unary_rpc_method_handler(
            _refusing_malformed(getattr(servicer, method.name)),
            request_deserializer=strict_parser(message_factory.GetMessageClass(method.input_type)),
            response_serializer=reply.SerializeToString,
        )
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(service.full_name, handlers),))
    server.add_registered_method_handlers(service.full_name, handlers)


def strict_parser(request_class: type[Message]) -> Callable[[bytes], Message | MalformedRequest]:
    """``parse(data)``: the request, or a :class:`MalformedRequest` when ``data`` is not a valid
    ``request_class`` or holds a field it does not define. Unknown fields are found by size: the
    request's serialised size drops when they are discarded (C code, ~2 us per KB-sized message);
    only then is it walked in Python to name the first one."""
    name = request_class.DESCRIPTOR.name

    def parse(data: bytes) -> Message | MalformedRequest:
        try:
            request = request_class.FromString(data)
        except Exception as e:  # DecodeError, for bytes that are no such message (invalid UTF-8 included)
            return MalformedRequest(f"request is not a valid {name} ({e})")
        size = request.ByteSize()
        request.DiscardUnknownFields()
        if request.ByteSize() == size:
            return request
        where, number = _first_unknown_field(request_class.FromString(data), "")
        return MalformedRequest(
            f"{where or name} has an unknown field number {number} (or a known one with another wire type): "
            "is the peer built from other protos?"
        )

    return parse


def _first_unknown_field(message: Message, path: str) -> tuple[str, int]:
    """``(where, field number)`` of the first unknown field in ``message`` or below, where is the
    field path and message type (``chunks[0].rewards (a Tensor)``); ``(path, -1)`` when there is none."""
    unknown = unknown_fields.UnknownFieldSet(message)
    if len(unknown):
        return f"{path} (a {message.DESCRIPTOR.name})" if path else "", unknown[0].field_number
    for field, value in message.ListFields():
        if field.message_type is None:
            continue
        where = f"{path}.{field.name}" if path else field.name
        if field.message_type.GetOptions().map_entry:
            values = value.items() if field.message_type.fields_by_name["value"].message_type else []
            children = [(f"{where}[{key!r}]", item) for key, item in values]
        elif field.is_repeated:
            children = [(f"{where}[{i}]", item) for i, item in enumerate(value)]
        else:
            children = [(where, value)]
        for child_path, child in children:
            found = _first_unknown_field(child, child_path)
            if found[1] >= 0:
                return found
    return path, -1


class _BoundedDetails:
    """A servicer's context whose ``abort`` and ``set_details`` shorten the details with
    :func:`status_details`; everything else is the context's own."""

    def __init__(self, context: grpc.ServicerContext) -> None:
        self._context = context

    def abort(self, code: grpc.StatusCode, details: str) -> None:
        self._context.abort(code, status_details(details))

    def set_details(self, details: str) -> None:
        self._context.set_details(status_details(details))

    def __getattr__(self, name: str) -> Any:
        return getattr(self._context, name)


def _refusing_malformed(behaviour: Callable[[Any, grpc.ServicerContext], Any]) -> Callable[..., Any]:
    @functools.wraps(behaviour)
    def handle(request: Any, context: grpc.ServicerContext) -> Any:
        bounded = cast(grpc.ServicerContext, _BoundedDetails(context))
        if isinstance(request, MalformedRequest):
            bounded.abort(grpc.StatusCode.INVALID_ARGUMENT, request.reason)
        return behaviour(request, bounded)

    return handle


@dataclass(frozen=True)
class RetryPolicy:
    """Exponential backoff for UNAVAILABLE (server down or restarting): ``attempts`` tries in all,
    sleeping ``initial_backoff_s * multiplier**k`` (at most ``max_backoff_s``, jittered down by up
    to half so that many actors do not retry in step) between them."""

    attempts: int = 6
    initial_backoff_s: float = 0.1
    max_backoff_s: float = 5.0
    multiplier: float = 2.0

    def delays(self) -> list[float]:
        """The sleeps between the attempts, before jitter."""
        return [min(self.initial_backoff_s * self.multiplier**k, self.max_backoff_s) for k in range(self.attempts - 1)]


PEER_GONE = (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.CANCELLED)


def peer_gone(code: grpc.StatusCode) -> bool:
    """Whether a call failed because the server went away (retry later) rather than refused it."""
    return code in PEER_GONE


def peer_unresponsive(code: grpc.StatusCode) -> bool:
    """Whether a call failed because the server went away (:func:`peer_gone`) or did not answer
    within its deadline (DEADLINE_EXCEEDED: a stopped or stalled process keeps its connections open,
    so only the deadline tells). A caller whose call can be repeated waits and tries again."""
    return peer_gone(code) or code == grpc.StatusCode.DEADLINE_EXCEEDED


def call_with_retry(rpc: Callable[..., _T], request: Any, deadline_s: float, retry: RetryPolicy) -> _T:
    """One unary call with a deadline of ``deadline_s`` seconds, retried per ``retry`` while it
    fails because the server went away (:data:`PEER_GONE`). Raises the last ``grpc.RpcError`` (any
    other status: the first one). A retried call may have taken effect before its server went
    away: callers whose calls are not idempotent must tolerate a repeat."""
    delays = retry.delays()
    for attempt in range(retry.attempts):
        try:
            return rpc(request, timeout=deadline_s)
        except grpc.RpcError as e:
            if not peer_gone(e.code()) or attempt == len(delays):
                raise
        time.sleep(delays[attempt] * random.uniform(0.5, 1.0))
    raise AssertionError("unreachable: the last attempt returns or raises")


def set_serving(health_servicer: health.HealthServicer, service: str, serving: bool) -> None:
    """Report SERVING or NOT_SERVING for the server as a whole ("") and for ``service``."""
    status = health_pb2.HealthCheckResponse.SERVING if serving else health_pb2.HealthCheckResponse.NOT_SERVING
    for name in ("", service):
        health_servicer.set(name, status)


def _unreachable(e: grpc.RpcError) -> str:
    """Why a health check failed, in a few words; a failed TLS handshake (wrong CA, a certificate that
    does not name the role) reads UNAVAILABLE like a peer that is down, so its reason is kept."""
    details = e.details() or ""
    if e.code() != grpc.StatusCode.UNAVAILABLE:
        return f"{e.code().name}: {details}"
    tls = any(word in details.lower() for word in ("handshake", "certificate", "verification", "ssl", "tls"))
    return f"not reachable: {details}" if tls else "not reachable"


PEER_WARN_AFTER_S = 60.0
"""How long a role waits for a peer before it warns, once, that the peer may never come: longer than
any start here takes (a role's imports and a replay restoring a snapshot take seconds)."""


def silent_peer(what: str, address: str, waited_s: float, reason: str) -> str:
    """What a role that has waited ``waited_s`` for its ``what`` (replay, learner, evolver) says to do."""
    return (
        f"no {what} has answered at {address} for {waited_s:.0f} s ({reason}); still waiting. Start the {what} "
        f"(main_ds.py TASK {what}, with this role's -n), or give this role its address with "
        f"--{what}_host/--{what}_port (net_config.{what}_host/{what}_port in the task's config)"
    )


def wait_until_serving(
    channel: grpc.Channel,
    service: str,
    what: str,
    address: str,
    stop: threading.Event,
    log_every_s: float = 10.0,
    max_backoff_s: float = 2.0,
    warn_after_s: float = PEER_WARN_AFTER_S,
) -> bool:
    """Block until ``service`` on ``channel`` reports SERVING (True) or ``stop`` is set (False),
    logging what it waits for right away and then every ``log_every_s`` seconds. A peer silent for
    ``warn_after_s`` gets one WARNING saying what to check: a role waits as long as it takes (peers
    start in any order, and a rescheduled pod comes back), but never without saying why."""
    stub = health_pb2_grpc.HealthStub(channel)
    backoff, last_log, started, warned = 0.05, -float("inf"), time.monotonic(), False
    while not stop.is_set():
        try:
            reply = stub.Check(health_pb2.HealthCheckRequest(service=service), timeout=2.0)
            if reply.status == health_pb2.HealthCheckResponse.SERVING:
                if last_log > -float("inf"):
                    log.info("%s at %s is up after %.1f s", what, address, time.monotonic() - started)
                return True
            reason = "up but not serving yet"
        except grpc.RpcError as e:
            reason = _unreachable(e)
        if time.monotonic() - last_log >= log_every_s:
            log.info("waiting for %s at %s (%s)", what, address, reason)
            last_log = time.monotonic()
        if not warned and time.monotonic() - started >= warn_after_s:
            log.warning("%s", silent_peer(what, address, time.monotonic() - started, reason))
            warned = True
        stop.wait(backoff)
        backoff = min(2 * backoff, max_backoff_s)
    return False
