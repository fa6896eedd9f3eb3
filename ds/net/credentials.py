"""What a role proves and trusts, read from its files and read again when they change: the run's
token(s) (``net_config.token_file``) and its TLS certificate, key and CA (``tls_cert``, ``tls_key``,
``tls_ca``). ds/net/security.py builds servers and channels from them.

Usage::

    creds = load_credentials(config.net_config)   # ConfigError naming the key and the file
    creds.token.tokens      # the token file's tokens now (each non-empty line is one)
    creds.tls_now()         # (cert, key, ca) PEM bytes now
    creds.tls_generation()  # grows each time changed TLS files were taken up

**Rotation without a restart.** A role looks at its files again at most every
:data:`CHECK_EVERY_S` seconds while it uses them (each rpc, each handshake, each signed parameter
message); when a file changed (size, modification time or inode: a Kubernetes Secret's atomic swap
counts), it reads and checks all of them again as at start. What fails a check (a half-written
certificate, a key that is not the certificate's, an empty token file) is logged once, naming the
file and the problem, and the role keeps what it read before until the files change again, so a
rotation in progress never stops a run.

A token file may hold several tokens, one per line: a role proves itself with each (one bearer
key per token on every rpc, one MAC per token on every parameter message) and accepts any. So a
token is rotated by adding the new one as a second line on every role, then removing the old one:
at every moment of either step any two roles share a token (docs/security.md section 8). TLS:
servers present the certificate and trust the CA of the files now at each new handshake; clients
open new connections with them (ds/net/channels.py). A CA rollover is the same two steps with the CA
file: both CAs (one PEM file holding both certificates), then the new one alone.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import logging
import os
import secrets
import ssl
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Generic, NamedTuple, TypeVar

from algorithm.config.load import ConfigError
from algorithm.config.schema import NetConfig

log = logging.getLogger("asac.security")

CHECK_EVERY_S = 2.0
"""How often a role looks at its credential files again (at most; only while it uses them)."""

_BEARER_LABEL = b"asac grpc bearer"
_T = TypeVar("_T")


def bearer(token: bytes) -> str:
    """The value rpcs carry for ``token``: derived from it, so that the token itself never travels."""
    return hmac.new(token, _BEARER_LABEL, hashlib.sha256).hexdigest()


class _Watched(Generic[_T]):
    """A value read from ``paths`` by ``read`` (which raises ConfigError for what it must not take),
    read again when a file has changed since, at most every :data:`CHECK_EVERY_S`; thread-safe."""

    def __init__(self, what: str, paths: tuple[str, ...], read: Callable[[], _T], taken: Callable[[_T], str]) -> None:
        self._what, self._paths, self._read, self._taken = what, paths, read, taken
        self._lock = threading.Lock()
        self._seen = _signature(paths)
        self._value = read()
        self._checked = time.monotonic()
        self.generation = 0

    def now(self) -> _T:
        if time.monotonic() - self._checked < CHECK_EVERY_S:
            return self._value
        with self._lock:
            if time.monotonic() - self._checked >= CHECK_EVERY_S:
                self._look()
            return self._value

    def _look(self) -> None:
        self._checked = time.monotonic()
        seen = _signature(self._paths)
        if seen == self._seen:
            return
        self._seen = seen  # whatever comes of it: the next attempt is at the next change
        try:
            value = self._read()
        except ConfigError as e:
            log.error("%s changed but cannot be taken up: %s; keeping the %s read before until it changes again",
                      self._what, e, self._what)  # fmt: skip
            return
        self._value, self.generation = value, self.generation + 1
        log.warning("%s changed: taken up (%s)", self._what, self._taken(value))


def _signature(paths: tuple[str, ...]) -> tuple[tuple[int, int, int] | None, ...]:
    def one(path: str) -> tuple[int, int, int] | None:
        try:
            st = os.stat(path)  # follows links: a Secret volume swaps the link's target
        except OSError:
            return None
        return st.st_mtime_ns, st.st_size, st.st_ino

    return tuple(one(p) for p in paths)


class Keyring:
    """The run's token(s): each non-empty line of ``net_config.token_file`` (whitespace around a line
    ignored), read again when the file changes (module docstring). :attr:`tokens` is what proves
    and what is accepted now; a fixed keyring (:meth:`of`) never changes."""

    def __init__(self, tokens: tuple[bytes, ...] = (), watched: _Watched[tuple[bytes, ...]] | None = None) -> None:
        if watched is None and (not tokens or not all(isinstance(t, bytes) and t for t in tokens)):
            raise ValueError("a keyring needs at least one token, each non-empty bytes")
        self._fixed, self._watched = tokens, watched

    @classmethod
    def of(cls, *tokens: bytes) -> Keyring:
        return cls(tuple(tokens))

    @classmethod
    def read(cls, path: str) -> Keyring:
        """The keyring of ``path``, read again when it changes; ConfigError if it cannot be read or is empty."""
        taken = "{} token(s), each proved and each accepted".format
        return cls(watched=_Watched(f"net_config.token_file {path!r}", (path,), lambda: _read_tokens(path),
                                    lambda tokens: taken(len(tokens))))  # fmt: skip

    @property
    def tokens(self) -> tuple[bytes, ...]:
        return self._fixed if self._watched is None else self._watched.now()

    def bearers(self) -> tuple[str, ...]:
        """:func:`bearer` of each token now."""
        return _bearers(self.tokens)

    def __repr__(self) -> str:  # the tokens stay out of logs and tracebacks
        return f"Keyring({len(self.tokens)} token(s){', read again when its file changes' if self._watched else ''})"


@functools.lru_cache(maxsize=8)
def _bearers(tokens: tuple[bytes, ...]) -> tuple[str, ...]:
    return tuple(bearer(t) for t in tokens)


def _read_tokens(path: str) -> tuple[bytes, ...]:
    tokens = tuple(line.strip() for line in (_read("token_file", path) or b"").splitlines() if line.strip())
    if not tokens:
        raise ConfigError(f"net_config.token_file: {path!r} is empty; put the run's shared secret in it")
    return tokens


class TlsFiles(NamedTuple):
    """PEM bytes of this process's certificate and key and of the CA(s) it trusts (None: not set)."""

    cert: bytes | None
    key: bytes | None
    ca: bytes | None


@dataclass(frozen=True)
class Credentials:
    """What this process proves and trusts: the run's ``token`` (a :class:`Keyring`; bytes are taken as
    a keyring of one), and PEM bytes of its own certificate ``cert`` and ``key`` and of the ``ca`` it
    trusts, as read at start; with ``tls_files`` (:func:`load_credentials`) the TLS files are read again
    when they change (:meth:`tls_now`). All None: plaintext, no token. Secrets stay out of ``repr``."""

    token: Keyring | None = None
    cert: bytes | None = None
    key: bytes | None = field(default=None, repr=False)
    ca: bytes | None = None
    tls_files: _Watched[TlsFiles] | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if isinstance(self.token, bytes):
            object.__setattr__(self, "token", Keyring.of(self.token))

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

    def tls_now(self) -> TlsFiles:
        """The certificate, key and CA to use for a new connection now: the fields until the files
        changed, then what was read from them."""
        if self.tls_generation() == 0:
            return TlsFiles(self.cert, self.key, self.ca)
        assert self.tls_files is not None
        return self.tls_files.now()

    def tls_generation(self) -> int:
        """Grows by one each time changed TLS files were taken up (0: as at start)."""
        if self.tls_files is None:
            return 0
        self.tls_files.now()
        return self.tls_files.generation


NO_CREDENTIALS = Credentials()


def load_credentials(net: NetConfig) -> Credentials:
    """Read and check ``net.token_file``, ``net.tls_cert``, ``net.tls_key`` and ``net.tls_ca``:
    a file that cannot be read, an empty token file, a file that is not PEM, a key that is not the
    certificate's (or is encrypted), a certificate without its key: :class:`ConfigError` naming the
    key and the path, before anything starts. The same checks run when a file changes later (module
    docstring)."""
    token = None if net.token_file is None else Keyring.read(net.token_file)
    if (net.tls_cert is None) != (net.tls_key is None):
        given, missing = ("tls_cert", "tls_key") if net.tls_key is None else ("tls_key", "tls_cert")
        raise ConfigError(f"net_config.{given} needs net_config.{missing} (--{missing}): a certificate and its key")
    paths = tuple(p for p in (net.tls_cert, net.tls_key, net.tls_ca) if p is not None)
    if not paths:
        return Credentials(token)
    watched = _Watched("TLS files " + ", ".join(repr(p) for p in paths), paths, lambda: _read_tls(net),
                       lambda _: "new connections use the certificate, key and CA read now")  # fmt: skip
    cert, key, ca = watched.now()
    return Credentials(token, cert, key, ca, watched)


def _read_tls(net: NetConfig) -> TlsFiles:
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
    return TlsFiles(cert, key, ca)


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


def token_keys(token: bytes | Keyring | None) -> tuple[bytes, ...]:
    """The tokens now of ``token`` (a keyring, one token, or none: ``()``)."""
    if token is None:
        return ()
    if isinstance(token, Keyring):
        return token.tokens
    if not isinstance(token, bytes) or not token:
        raise ValueError("token must be non-empty bytes, a Keyring, or None for no signing")
    return (token,)


__all__ = [
    "CHECK_EVERY_S",
    "NO_CREDENTIALS",
    "Credentials",
    "Keyring",
    "TlsFiles",
    "bearer",
    "check_server_credentials",
    "load_credentials",
    "token_keys",
    "write_token_file",
]
