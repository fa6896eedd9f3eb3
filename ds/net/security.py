"""Who may talk to our gRPC servers: TLS / mutual TLS with role identities, the run's token on
every rpc, and the warning for a server that listens beyond loopback without either.

Usage (every server and client of ds/ goes through these; none opens a port or channel itself)::

    creds = load_credentials(config.net_config)          # ConfigError naming the key and the file
    server = new_server("replay", SERVICE_NAME, CALLERS, creds, max_workers, options)
    port = listen(server, "0.0.0.0:61002", creds, health_port=None)    # TLS when creds have a certificate
    channel = open_channel("replay-0:61002", REPLAY, creds, options)   # TLS, the token on every call

What is checked, on the server, for every rpc but the standard health service (which Kubernetes
probes call with neither TLS nor metadata; it says SERVING or NOT_SERVING and nothing else):

1. **Token** (``net_config.token_file``): the call must carry ``authorization: Bearer <key>``,
   where the key is derived from the token (HMAC-SHA256(token, "asac grpc bearer")), so the secret
   that signs parameters (ds/net/params.py) never travels itself. Missing or wrong: UNAUTHENTICATED.
2. **TLS** (``tls_cert`` + ``tls_key``): the server speaks only TLS on its port; a call that came
   in over the plaintext health port (``health_port``) is PERMISSION_DENIED.
3. **Mutual TLS and roles** (``tls_ca`` too): the handshake fails for a client without a
   certificate signed by that CA (the client sees UNAVAILABLE), and each rpc is open only to
   the roles its service's ``CALLERS`` table names (e.g. a learner's GetWeights only to the
   evolver): a client's roles are the DNS subject alternative names of its certificate among
   :data:`ROLES` (:func:`client_roles`; URI, email and IP SANs and the subject CN never count).
   Otherwise PERMISSION_DENIED.

Clients verify servers the same way: a channel to a role accepts only a server certificate
signed by ``tls_ca`` that names that role (``grpc.ssl_target_name_override``; certificates name
roles, not hosts, which move). So a learner loads CEM samples only from a process holding the
evolver's credentials, and the evolver reads weights only from learners. One certificate may name
several roles (``main_ds.py local`` runs every role with the same flags). The client's check is
gRPC's own hostname check, which, for a certificate with no DNS SAN at all, accepts a subject CN
equal to the role instead: the run's CA should sign no such certificate (the commands in
docs/security.md section 3 give each a DNS SAN).
"""

from __future__ import annotations

import collections
import functools
import hashlib
import hmac
import ipaddress
import logging
import os
import secrets
import ssl
from collections.abc import Callable, Mapping, Sequence
from concurrent import futures
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc

from algorithm.config.load import ConfigError
from algorithm.config.schema import NetConfig

log = logging.getLogger("asac.security")

ACTOR, LEARNER, REPLAY, EVOLVER = "actor", "learner", "replay", "evolver"
ROLES = frozenset({ACTOR, LEARNER, REPLAY, EVOLVER})
Callers = Mapping[str, frozenset[str]]
"""Per service: rpc name -> the roles whose certificates may call it (under mutual TLS)."""

HEALTH_PREFIX = "/grpc.health.v1.Health/"
_BEARER_LABEL = b"asac grpc bearer"
_TOKEN_HINT = "every role of a run must name the same secret in net_config.token_file"
_REMEDY = "net_config.token_file and/or TLS (--tls_cert, --tls_key, --tls_ca)"
_SET_TOKEN = ("set --override net.token_file=FILE on every role of the run (FILE: a secret only they can read, "
              "e.g. `openssl rand -hex 32 > FILE; chmod 600 FILE`; docs/security.md section 2)")  # fmt: skip


@dataclass(frozen=True)
class Credentials:
    """What this process proves and trusts: the run's shared ``token``, and PEM bytes of its own
    certificate ``cert`` and ``key`` and of the ``ca`` it trusts. All None: plaintext, no token.
    The secrets stay out of ``repr`` (logs, tracebacks)."""

    token: bytes | None = field(default=None, repr=False)
    cert: bytes | None = None
    key: bytes | None = field(default=None, repr=False)
    ca: bytes | None = None

    @property
    def tls(self) -> bool:
        """Whether channels and (with a certificate) servers speak TLS."""
        return self.cert is not None or self.ca is not None

    @property
    def mutual(self) -> bool:
        """Whether this process's servers require client certificates (and check roles)."""
        return self.cert is not None and self.ca is not None

    @property
    def secured(self) -> bool:
        """Whether a server with these credentials refuses strangers (token or TLS)."""
        return self.token is not None or self.tls


NO_CREDENTIALS = Credentials()


def bearer(token: bytes) -> str:
    """The value rpcs carry for ``token``: derived from it, so that the token itself never travels."""
    return hmac.new(token, _BEARER_LABEL, hashlib.sha256).hexdigest()


# ---------------------------------------------------------------------- loading


def load_credentials(net: NetConfig) -> Credentials:
    """Read and check ``net.token_file``, ``net.tls_cert``, ``net.tls_key`` and ``net.tls_ca``:
    a file that cannot be read, an empty token, a file that is not PEM, a key that is not the
    certificate's (or is encrypted), a certificate without its key: :class:`ConfigError` naming the
    key and the path, before anything starts."""
    token = _read("token_file", net.token_file)
    if token is not None:
        token = token.strip()
        if not token:
            raise ConfigError(f"net_config.token_file: {net.token_file!r} is empty; put the run's shared secret in it")
    if (net.tls_cert is None) != (net.tls_key is None):
        given, missing = ("tls_cert", "tls_key") if net.tls_key is None else ("tls_key", "tls_cert")
        raise ConfigError(f"net_config.{given} needs net_config.{missing} (--{missing}): a certificate and its key")
    cert, key, ca = _read("tls_cert", net.tls_cert), _read("tls_key", net.tls_key), _read("tls_ca", net.tls_ca)
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    if net.tls_ca is not None:
        _pem("tls_ca", net.tls_ca, ca, b"CERTIFICATE")
        try:
            context.load_verify_locations(cadata=(ca or b"").decode("ascii", "replace"))
        except ssl.SSLError as e:
            raise ConfigError(f"net_config.tls_ca: {net.tls_ca!r} holds no usable CA certificate ({e})") from None
    if net.tls_cert is not None and net.tls_key is not None:
        _pem("tls_cert", net.tls_cert, cert, b"CERTIFICATE")
        _pem("tls_key", net.tls_key, key, b"PRIVATE KEY")

        def encrypted() -> bytes:
            raise ConfigError(f"net_config.tls_key: {net.tls_key!r} is encrypted; gRPC needs the key unencrypted")

        try:
            context.load_cert_chain(net.tls_cert, net.tls_key, password=encrypted)
        except ssl.SSLError as e:
            raise ConfigError(
                f"net_config.tls_key: {net.tls_key!r} is not the key of net_config.tls_cert {net.tls_cert!r} ({e})"
            ) from None
    return Credentials(token, cert, key, ca)


def write_token_file(path: Path) -> bytes:
    """A fresh random token (64 hex digits) in a new file ``path`` that only its owner may read or
    write (mode 0600, whatever the umask; a file already there is replaced, not reused); returns it.
    What ``main_ds.py local`` does when no ``net_config.token_file`` is given."""
    token = secrets.token_hex(32).encode()
    path.unlink(missing_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    try:
        os.write(fd, token + b"\n")
    finally:
        os.close(fd)
    return token


def warn_without_token(role: str, credentials: Credentials) -> bool:
    """Log a warning when ``role``, started on its own, has no token (nor mutual TLS, which keeps
    strangers out as well): on loopback too, where every local process can reach it. Returns whether
    it warned."""
    if credentials.token is not None or credentials.mutual:
        return False
    if role == "actor":
        exposed = ("any process that can reach its learner's and replay's ports (on loopback: every local process) "
                   "may call them too, or answer in their place once they stop")  # fmt: skip
    else:
        exposed = "any process that can reach its port (on loopback: every local process) may call any of its rpcs"
    log.warning("this %s runs without a token: %s; %s", role, exposed, _SET_TOKEN)
    return True


def _read(name: str, path: str | None) -> bytes | None:
    if path is None:
        return None
    try:
        return Path(path).read_bytes()
    except OSError as e:
        raise ConfigError(f"net_config.{name}: cannot read {path!r} ({e.strerror})") from None


def _pem(name: str, path: str, data: bytes | None, kind: bytes) -> None:
    if data is None or b"-----BEGIN " not in data or kind + b"-----" not in data:
        raise ConfigError(f"net_config.{name}: {path!r} is not a PEM file with a {kind.decode().lower()}")


def check_server_credentials(credentials: Credentials, what: str) -> None:
    """A process that serves gRPC and trusts a CA needs its own certificate to speak TLS."""
    if credentials.ca is not None and credentials.cert is None:
        raise ConfigError(
            f"net_config.tls_ca is set but tls_cert/tls_key are not: the {what} serves gRPC and needs its own "
            "certificate and key (--tls_cert, --tls_key) to speak TLS"
        )


# ---------------------------------------------------------------------- servers


def new_server(
    what: str,
    service: str,
    callers: Callers,
    credentials: Credentials,
    max_workers: int,
    options: Sequence[tuple[str, Any]],
    interceptors: Sequence[grpc.ServerInterceptor] = (),
) -> grpc.Server:
    """A gRPC server (``max_workers`` threads named ``<what>-rpc``) that checks every call to
    ``service`` as the module docstring says; ``callers`` names who may call each of its rpcs.
    ``interceptors`` run after those checks (tests inject faults with them)."""
    guard = [_Guard(service, callers, credentials)] if credentials.secured else []
    executor = futures.ThreadPoolExecutor(max_workers=max_workers, thread_name_prefix=f"{what}-rpc")
    # gRPC sets SO_REUSEPORT on Linux by default, so a second server on a port already served would bind
    # as well and the kernel would spread connections over both (a new run's learner would sample from a
    # forgotten earlier run's replay while its actor inserts into the new one, and both wait forever).
    # Off, the second bind fails and the role says the port is taken.
    exclusive = [("grpc.so_reuseport", 0), *SERVER_KEEPALIVE_OPTIONS, *options]
    return grpc.server(executor, options=exclusive, interceptors=[*guard, *interceptors])


def listen(
    server: grpc.Server, address: str, credentials: Credentials, what: str = "server", health_port: int | None = None
) -> int:
    """Open ``address`` on ``server`` (TLS when ``credentials`` have a certificate, requiring client
    certificates when they also have a CA) and, with ``health_port``, a plaintext port on the same
    host on which only the health service answers. Returns the port of ``address``. Warns when the
    host is not loopback and the server has neither token nor TLS."""
    check_server_credentials(credentials, what)
    if credentials.cert is not None and credentials.key is not None:
        tls = grpc.ssl_server_credentials(
            [(credentials.key, credentials.cert)],
            root_certificates=credentials.ca,
            require_client_auth=credentials.ca is not None,
        )
        port = server.add_secure_port(address, tls)
    else:
        port = server.add_insecure_port(address)
    host = address.rsplit(":", 1)[0]
    if health_port is not None:
        server.add_insecure_port(f"{host}:{health_port}")
    if not warn_if_exposed(host, f"{what} on {address}", credentials.secured):
        log.info("%s on %s: %s", what, address, describe(credentials))
    return port


def describe(credentials: Credentials) -> str:
    """How a server with ``credentials`` admits callers, in words (for its start-up log line)."""
    if credentials.mutual:
        tls = "mutual TLS (client certificates, roles checked per rpc)"
    elif credentials.cert is not None:
        tls = "TLS (no client certificates)"
    else:
        tls = "plaintext"
    return f"{tls}, {'token required' if credentials.token is not None else 'no token'}"


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or "localhost", IPv6 in brackets or not) is this machine only."""
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def warn_if_exposed(host: str, what: str, secured: bool, remedy: str = _REMEDY) -> bool:
    """Log a warning when ``what`` listens on a non-loopback ``host`` with nothing that keeps
    strangers out (docs/security.md section 1: without credentials, loopback by default; ``bind_host``
    says otherwise). Returns whether it warned."""
    if secured or is_loopback(host):
        return False
    log.warning(
        "%s is open to anyone who can reach it: set %s, or listen on loopback (net_config.bind_host: 127.0.0.1)",
        what,
        remedy,
    )
    return True


class _Guard(grpc.ServerInterceptor):
    """The server side of the module docstring's checks 1-3 for one service."""

    def __init__(self, service: str, callers: Callers, credentials: Credentials) -> None:
        self._prefix = f"/{service}/"
        self._callers = dict(callers)
        self._bearer = None if credentials.token is None else f"Bearer {bearer(credentials.token)}".encode()
        self._tls = credentials.cert is not None
        self._mutual = credentials.mutual

    def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], grpc.RpcMethodHandler | None],
        details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler | None:
        handler = continuation(details)
        method = details.method
        if handler is None or method.startswith(HEALTH_PREFIX):
            return handler
        if self._bearer is not None and not self._bearer_matches(details.invocation_metadata):
            # Refused before its request is even parsed.
            message = f"{method}: missing or wrong token; {_TOKEN_HINT}"
            return _refusal(handler, grpc.StatusCode.UNAUTHENTICATED, message)
        allowed = self._callers.get(method[len(self._prefix) :]) if method.startswith(self._prefix) else None
        if allowed is None:
            return _refusal(handler, grpc.StatusCode.PERMISSION_DENIED, f"{method}: no role may call it")
        if not self._tls:
            return handler
        return _checked(handler, functools.partial(self._authorise, method, allowed))

    def _bearer_matches(self, metadata: Sequence[tuple[str, str | bytes]] | None) -> bool:
        assert self._bearer is not None
        for key, value in metadata or ():
            if key == "authorization":
                got = value if isinstance(value, bytes) else value.encode("utf-8", "surrogateescape")
                return hmac.compare_digest(got, self._bearer)
        return False

    def _authorise(self, method: str, allowed: frozenset[str], context: grpc.ServicerContext) -> None:
        auth = context.auth_context()
        if auth.get("transport_security_type") != [b"ssl"]:
            context.abort(
                grpc.StatusCode.PERMISSION_DENIED,
                f"{method}: this plaintext port serves only the health service; call the role's TLS port",
            )
        if self._mutual:
            roles = client_roles(auth)
            if not roles & allowed:
                context.abort(
                    grpc.StatusCode.PERMISSION_DENIED,
                    f"{method} is for {', '.join(sorted(allowed))}; the caller's certificate names "
                    f"{', '.join(sorted(roles)) or 'no role'} (roles are DNS subject alternative names; "
                    "URI, email and IP SANs and the subject CN do not count)",
                )


def client_roles(auth: Mapping[str, Sequence[bytes]]) -> frozenset[str]:
    """The roles a verified client certificate names: its DNS subject alternative names (gRPC's
    ``peer_dns`` property of the call's ``auth_context()``) that are in :data:`ROLES`.

    Only DNS SANs: gRPC's ``x509_subject_alternative_name`` lists every SAN type alike, so reading
    it would let a certificate naming ``URI:evolver`` pass as the evolver. Never the subject
    CN either (the code never read it): roles are DNS SANs (docs/security.md section 3), so a certificate
    without them names no role, whatever its CN says.
    """
    return frozenset(n.decode("utf-8", "replace") for n in auth.get("peer_dns", ())) & ROLES


_BEHAVIOURS = ("unary_unary", "unary_stream", "stream_unary", "stream_stream")


def _behaviour(handler: grpc.RpcMethodHandler) -> str:
    return next(kind for kind in _BEHAVIOURS if getattr(handler, kind) is not None)


def _refusal(handler: grpc.RpcMethodHandler, code: grpc.StatusCode, message: str) -> grpc.RpcMethodHandler:
    def refuse(request: Any, context: grpc.ServicerContext) -> Any:
        context.abort(code, message)

    # RpcMethodHandler is a namedtuple (grpc._utilities); keep its kind, drop the parsing of the request.
    return handler._replace(request_deserializer=None, **{_behaviour(handler): refuse})


def _checked(handler: grpc.RpcMethodHandler, check: Callable[[grpc.ServicerContext], None]) -> grpc.RpcMethodHandler:
    kind = _behaviour(handler)
    behaviour = getattr(handler, kind)

    def run(request: Any, context: grpc.ServicerContext) -> Any:
        check(context)
        return behaviour(request, context)

    return handler._replace(**{kind: run})


# ---------------------------------------------------------------------- clients


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
these pings (:data:`SERVER_KEEPALIVE_OPTIONS`). A name is looked up again at most every 2 s (30 s by
default) when its address stops answering: a peer rescheduled behind a Kubernetes Service name is
found at its new address within seconds of serving there."""

SERVER_KEEPALIVE_OPTIONS = [
    ("grpc.keepalive_permit_without_calls", 1),
    ("grpc.http2.min_recv_ping_interval_without_data_ms", 5_000),
    ("grpc.http2.max_ping_strikes", 0),
]
"""A server takes a client's keepalive pings (:data:`CLIENT_LINK_OPTIONS`) every 10 s, with or without calls
in flight; by default it would answer pings more often than every 5 minutes with GOAWAY."""


def open_channel(address: str, role: str, credentials: Credentials, options: Sequence[tuple[str, Any]]) -> grpc.Channel:
    """A channel to the ``role`` server at ``address``: TLS when ``credentials`` have a CA or a
    certificate (accepting only a server certificate that names ``role``; presenting this process's
    certificate when the server asks), carrying the token's bearer key on every call when there is one.
    A peer that is down is retried every 2 s at most (:data:`CLIENT_LINK_OPTIONS`)."""
    options = [*CLIENT_LINK_OPTIONS, *options]
    if credentials.tls:
        tls = grpc.ssl_channel_credentials(credentials.ca, credentials.key, credentials.cert)
        channel = grpc.secure_channel(address, tls, options=[*options, ("grpc.ssl_target_name_override", role)])
    else:
        channel = grpc.insecure_channel(address, options=list(options))
    if credentials.token is None:
        return channel
    return grpc.intercept_channel(channel, _BearerInterceptor(bearer(credentials.token)))


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
    """Adds ``authorization: Bearer <key>`` to every call (blocking, ``.future()`` and streaming)."""

    def __init__(self, key: str) -> None:
        self._metadata = ("authorization", f"Bearer {key}")

    def _with_bearer(self, details: grpc.ClientCallDetails) -> grpc.ClientCallDetails:
        metadata = [*(details.metadata or ()), self._metadata]
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


__all__ = [
    "ACTOR",
    "EVOLVER",
    "HEALTH_PREFIX",
    "LEARNER",
    "NO_CREDENTIALS",
    "REPLAY",
    "ROLES",
    "Callers",
    "Credentials",
    "bearer",
    "check_server_credentials",
    "client_roles",
    "describe",
    "is_loopback",
    "listen",
    "load_credentials",
    "new_server",
    "open_channel",
    "warn_if_exposed",
    "warn_without_token",
    "write_token_file",
]
