"""Channels to ASAC's gRPC servers: how a client finds a peer that is not there (yet or any more),
the run's token on every call, TLS that names the role it expects, and credentials rotated while it
runs (ds/net/credentials.py). ds/net/security.py has the servers' side.

Usage::

    channel = open_channel("replay-0:61002", "replay", creds, options)   # TLS, the token on every call
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import grpc

from ds.net.credentials import Credentials, Keyring

CLIENT_LINK_OPTIONS = [
    ("grpc.initial_reconnect_backoff_ms", 200),
    ("grpc.max_reconnect_backoff_ms", 2000),
    ("grpc.keepalive_time_ms", 10_000),
    ("grpc.keepalive_timeout_ms", 5_000),
    ("grpc.keepalive_permit_without_calls", 1),
    ("grpc.http2.max_pings_without_data", 0),
    ("grpc.dns_min_time_between_resolutions_ms", 2000),
]
"""How a channel finds a peer that is not there and comes back to it. Reconnects: gRPC's defaults (1 s,
growing by 1.6x to 120 s) leave a role that started before its peer connecting 5-10 s after the peer
is serving (measured), and calls fail fast while the channel waits out that backoff; a connect attempt
every 2 s at most costs nothing and matches the 2 s cap of :func:`ds.net.rpc.wait_until_serving`. A
connect attempt itself may take gRPC's default 20 s ("min reconnect backoff"): set to 2 s it let a
partitioned link come back 4-6 s after the heal instead of ~10 s, but a TLS channel to a learner
that had just started then never completed its handshake (a local run with mutual TLS stalled), so
it is left as it is. Keepalive: across a partition (packets dropped, no reset) a connection looks
alive to both ends and, once the link heals, resumes only at TCP's next retransmission, tens of
seconds later; a ping every 10 s, unanswered for 5 s, closes it, and the channel reconnects. Servers accept
these pings (ds/net/security.py ``SERVER_KEEPALIVE_OPTIONS``). A name is looked up again at most every 2 s (30 s by
default) when its address stops answering: a peer rescheduled behind a Kubernetes Service name is
found at its new address within seconds of serving there."""


def open_channel(address: str, role: str, credentials: Credentials, options: Sequence[tuple[str, Any]]) -> grpc.Channel:
    """A channel to the ``role`` server at ``address``: TLS when ``credentials`` have a CA or a
    certificate (accepting only a server certificate that names ``role``; presenting this process's
    certificate when the server asks), carrying one bearer key per token of the run's token file on
    every call when there is one. A peer that is down is retried every 2 s at most
    (:data:`CLIENT_LINK_OPTIONS`). Rotated credentials are taken up without a new channel: the tokens
    at each call, new TLS files by opening new connections (:class:`_RenewingChannel`)."""
    options = [*CLIENT_LINK_OPTIONS, *options]

    def connect() -> grpc.Channel:
        if credentials.tls:
            cert, key, ca = credentials.tls_now()
            tls = grpc.ssl_channel_credentials(ca, key, cert)
            channel = grpc.secure_channel(address, tls, options=[*options, ("grpc.ssl_target_name_override", role)])
        else:
            channel = grpc.insecure_channel(address, options=list(options))
        if credentials.token is None:
            return channel
        return grpc.intercept_channel(channel, _BearerInterceptor(credentials.token))

    if credentials.tls_files is None:
        return connect()
    return _RenewingChannel(connect, credentials.tls_generation)


RETIRED_CLOSE_AFTER_S = 300.0
"""How long a channel replaced by one with new TLS files stays open for the calls still on it."""


class _RenewingChannel(grpc.Channel):
    """A channel that, once this process's TLS files were taken up again (``generation`` grew), opens
    a new one (``connect``) for every later call, so that new connections present the new certificate
    and trust the new CA. Stubs built on it keep working: each method resolves to the newest channel
    at call time. The replaced channel is closed :data:`RETIRED_CLOSE_AFTER_S` after, when the next
    one is replaced, or with this one."""

    def __init__(self, connect: Callable[[], grpc.Channel], generation: Callable[[], int]) -> None:
        self._connect, self._generation = connect, generation
        self._lock = threading.Lock()
        self._serving = (generation(), connect())
        self._retired: list[tuple[float, grpc.Channel]] = []

    def current(self) -> tuple[int, grpc.Channel]:
        """(generation, channel) to call through now."""
        generation = self._generation()
        if generation != self._serving[0]:
            with self._lock:
                if generation != self._serving[0]:
                    now = time.monotonic()
                    old = [c for t, c in self._retired if now - t > RETIRED_CLOSE_AFTER_S]
                    self._retired = [(t, c) for t, c in self._retired if now - t <= RETIRED_CLOSE_AFTER_S]
                    self._retired.append((now, self._serving[1]))
                    self._serving = (generation, self._connect())
                    for channel in old:
                        channel.close()
        return self._serving

    def _method(self, kind: str, method: str, **kwargs: Any) -> _NewestMethod:
        return _NewestMethod(self, kind, method, kwargs)

    def unary_unary(self, method: str, *args: Any, **kwargs: Any) -> Any:
        return self._method("unary_unary", method, **_named(args, kwargs))

    def unary_stream(self, method: str, *args: Any, **kwargs: Any) -> Any:
        return self._method("unary_stream", method, **_named(args, kwargs))

    def stream_unary(self, method: str, *args: Any, **kwargs: Any) -> Any:
        return self._method("stream_unary", method, **_named(args, kwargs))

    def stream_stream(self, method: str, *args: Any, **kwargs: Any) -> Any:
        return self._method("stream_stream", method, **_named(args, kwargs))

    def subscribe(self, callback: Callable[[grpc.ChannelConnectivity], None], try_to_connect: bool = False) -> None:
        self.current()[1].subscribe(callback, try_to_connect)

    def unsubscribe(self, callback: Callable[[grpc.ChannelConnectivity], None]) -> None:
        self.current()[1].unsubscribe(callback)

    def close(self) -> None:
        with self._lock:
            for _, channel in self._retired:
                channel.close()
            self._retired = []
            self._serving[1].close()

    def __enter__(self) -> _RenewingChannel:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _named(args: tuple[Any, ...], kwargs: dict[str, Any]) -> dict[str, Any]:
    names = ("request_serializer", "response_deserializer", "_registered_method")
    return {**dict(zip(names, args, strict=False)), **kwargs}


class _NewestMethod:
    """One rpc of a :class:`_RenewingChannel`: calls (``__call__``, ``future``, ``with_call``) go to
    the channel current at call time."""

    def __init__(self, channel: _RenewingChannel, kind: str, method: str, kwargs: dict[str, Any]) -> None:
        self._channel, self._kind, self._rpc, self._kwargs = channel, kind, method, kwargs
        self._made: tuple[int, Any] = (-1, None)

    def _target(self) -> Any:
        generation, channel = self._channel.current()
        if self._made[0] != generation:
            self._made = (generation, getattr(channel, self._kind)(self._rpc, **self._kwargs))
        return self._made[1]

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._target()(*args, **kwargs)

    def __getattr__(self, name: str) -> Any:  # future, with_call
        return getattr(self._target(), name)


class _CallDetails(
    collections.namedtuple(
        "_CallDetails", ["method", "timeout", "metadata", "credentials", "wait_for_ready", "compression"]
    ),
    grpc.ClientCallDetails,
):
    """A call's details with our metadata added (grpc.ClientCallDetails is abstract)."""


class _BearerInterceptor(
    grpc.UnaryUnaryClientInterceptor,
    grpc.UnaryStreamClientInterceptor,
    grpc.StreamUnaryClientInterceptor,
    grpc.StreamStreamClientInterceptor,
):
    """Adds ``authorization: Bearer <key>``, one per token now, to every call (blocking, ``.future()``,
    streaming)."""

    def __init__(self, token: Keyring) -> None:
        self._token = token

    def _with_bearer(self, details: grpc.ClientCallDetails) -> grpc.ClientCallDetails:
        metadata = [*(details.metadata or ()), *(("authorization", f"Bearer {key}") for key in self._token.bearers())]
        return _CallDetails(
            details.method,
            details.timeout,
            metadata,
            details.credentials,
            getattr(details, "wait_for_ready", None),
            getattr(details, "compression", None),
        )

    def intercept_unary_unary(self, continuation: Any, client_call_details: Any, request: Any) -> Any:
        return continuation(self._with_bearer(client_call_details), request)

    def intercept_unary_stream(self, continuation: Any, client_call_details: Any, request: Any) -> Any:
        return continuation(self._with_bearer(client_call_details), request)

    def intercept_stream_unary(self, continuation: Any, client_call_details: Any, request_iterator: Any) -> Any:
        return continuation(self._with_bearer(client_call_details), request_iterator)

    def intercept_stream_stream(self, continuation: Any, client_call_details: Any, request_iterator: Any) -> Any:
        return continuation(self._with_bearer(client_call_details), request_iterator)


__all__ = ["CLIENT_LINK_OPTIONS", "RETIRED_CLOSE_AFTER_S", "open_channel"]
