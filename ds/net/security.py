"""Who may talk to our gRPC servers: TLS / mutual TLS with role identities, the run's token on
every rpc, and the warning for a server that listens beyond loopback without either.

Usage (every server and client of ds/ goes through these; none opens a port or channel itself)::

    creds = load_credentials(config.net_config)          # ConfigError naming the key and the file
    server = new_server("replay", SERVICE_NAME, CALLERS, creds, max_workers, options)
    port = listen(server, "0.0.0.0:61002", creds, health_port=None)    # TLS when creds have a certificate
    channel = open_channel("replay-0:61002", REPLAY, creds, options)   # TLS, the token on every call

``load_credentials`` and the credentials' rotation live in ds/net/credentials.py, ``open_channel`` in
ds/net/channels.py (both re-exported here). A server checks the token(s) and presents the certificate
of its files as they are now: a rotated token file or certificate is taken up without a restart.

What is checked, on the server, for every rpc but the standard health service (which Kubernetes
probes call with neither TLS nor metadata; it says SERVING or NOT_SERVING and nothing else):

1. **Token** (``net_config.token_file``): the call must carry ``authorization: Bearer <key>``
   (one of them, when the client's file holds several tokens), where the key is derived from a token
   of this server's file (HMAC-SHA256(token, "asac grpc bearer")), so the secret
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

import functools
import hmac
import ipaddress
import logging
from collections.abc import Callable, Mapping, Sequence
from concurrent import futures
from typing import Any

import grpc

from ds.net.channels import CLIENT_LINK_OPTIONS, open_channel
from ds.net.credentials import (
    NO_CREDENTIALS,
    Credentials,
    bearer,
    check_server_credentials,
    load_credentials,
    write_token_file,
)

log = logging.getLogger("asac.security")

ACTOR, LEARNER, REPLAY, EVOLVER = "actor", "learner", "replay", "evolver"
ROLES = frozenset({ACTOR, LEARNER, REPLAY, EVOLVER})
Callers = Mapping[str, frozenset[str]]
"""Per service: rpc name -> the roles whose certificates may call it (under mutual TLS)."""

HEALTH_PREFIX = "/grpc.health.v1.Health/"
_TOKEN_HINT = "every role of a run must name the same secret in net_config.token_file"
_REMEDY = "net_config.token_file and/or TLS (--tls_cert, --tls_key, --tls_ca)"
_SET_TOKEN = ("set --override net.token_file=FILE on every role of the run (FILE: a secret only they can read, "
              "e.g. `openssl rand -hex 32 > FILE; chmod 600 FILE`; docs/security.md section 2)")  # fmt: skip


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


# ---------------------------------------------------------------------- servers

SERVER_KEEPALIVE_OPTIONS = [
    ("grpc.keepalive_permit_without_calls", 1),
    ("grpc.http2.min_recv_ping_interval_without_data_ms", 5_000),
    ("grpc.http2.max_ping_strikes", 0),
]
"""A server takes a client's keepalive pings (``CLIENT_LINK_OPTIONS``, ds/net/channels.py) every 10 s, with or
without calls in flight; by default it would answer pings more often than every 5 minutes with GOAWAY."""


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
        port = server.add_secure_port(address, _server_tls(credentials))
    else:
        port = server.add_insecure_port(address)
    host = address.rsplit(":", 1)[0]
    if health_port is not None:
        server.add_insecure_port(f"{host}:{health_port}")
    if not warn_if_exposed(host, f"{what} on {address}", credentials.secured):
        log.info("%s on %s: %s", what, address, describe(credentials))
    return port


def _server_tls(credentials: Credentials) -> grpc.ServerCredentials:
    """TLS that presents the certificate and trusts the CA of the files now at each handshake
    (ds/net/credentials.py: rotated files are taken up without a restart)."""

    def configuration(tls: Any) -> Any:
        return grpc.ssl_server_certificate_configuration([(tls.key, tls.cert)], root_certificates=tls.ca)

    served = [credentials.tls_generation()]

    def fetch() -> Any:  # gRPC asks before each handshake; None keeps the configuration it has
        generation = credentials.tls_generation()
        if generation == served[0]:
            return None
        served[0] = generation
        return configuration(credentials.tls_now())

    return grpc.dynamic_ssl_server_credentials(
        configuration(credentials.tls_now()), fetch, require_client_authentication=credentials.ca is not None
    )


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
        self._token = credentials.token
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
        if self._token is not None and not self._bearer_matches(details.invocation_metadata):
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
        """Whether any ``authorization`` entry is the bearer key of any token accepted now (a client
        sends one per token of its own file: ds/net/credentials.py, rotation)."""
        assert self._token is not None
        accepted = [f"Bearer {key}".encode() for key in self._token.bearers()]
        for key, value in metadata or ():
            if key == "authorization":
                got = value if isinstance(value, bytes) else value.encode("utf-8", "surrogateescape")
                if any(hmac.compare_digest(got, want) for want in accepted):
                    return True
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


__all__ = [
    "ACTOR",
    "CLIENT_LINK_OPTIONS",
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
