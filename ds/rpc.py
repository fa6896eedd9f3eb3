"""What every gRPC client and server of ours shares: message limits, retries of UNAVAILABLE with
exponential backoff, the health service, and waiting for a peer to come up.

Usage::

    channel = security.open_channel(address, "replay", credentials, channel_options(limit))   # ds/security.py
    reply = call_with_retry(stub.Info, request, deadline_s=30.0, retry=RetryPolicy())   # or grpc.RpcError
    if not wait_until_serving(channel, "asac.ReplayService", "replay", address, stop):   # logs while waiting
        return  # stop was set

A call always has a deadline (ARCHITECTURE.md 6); only a peer that went away is retried: UNAVAILABLE
(down, restarting, or not listening yet) and CANCELLED (a server shutting down cancels the calls it
is still running; we never cancel our own calls). Every other status surfaces at once.
"""

from __future__ import annotations

import logging
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

_T = TypeVar("_T")
log = logging.getLogger("asac.rpc")


def channel_options(max_message_bytes: int) -> list[tuple[str, int]]:
    """Send and receive limits for a channel or server (both ends must raise them)."""
    return [
        ("grpc.max_send_message_length", int(max_message_bytes)),
        ("grpc.max_receive_message_length", int(max_message_bytes)),
    ]


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


def wait_until_serving(
    channel: grpc.Channel,
    service: str,
    what: str,
    address: str,
    stop: threading.Event,
    log_every_s: float = 10.0,
    max_backoff_s: float = 2.0,
) -> bool:
    """Block until ``service`` on ``channel`` reports SERVING (True) or ``stop`` is set (False),
    logging what it waits for right away and then every ``log_every_s`` seconds."""
    stub = health_pb2_grpc.HealthStub(channel)
    backoff, last_log, started = 0.05, -float("inf"), time.monotonic()
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
        stop.wait(backoff)
        backoff = min(2 * backoff, max_backoff_s)
    return False
