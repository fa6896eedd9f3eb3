"""Security beyond the rpcs themselves (ds/net/security.py): the plaintext health-only port Kubernetes
probes, the checks of the credential files (each error names its key and file), secrets kept out of
reprs, and the warning for a server open beyond loopback. The token, TLS and the roles' rpcs:
tests/ds/net/test_security.py."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from pathlib import Path

import grpc
import pytest
from cryptography.hazmat.primitives import serialization
from grpc_health.v1 import health_pb2

from algorithm.config.load import ConfigError
from algorithm.config.schema import NetConfig
from algorithm.replay import PrioritizedTable
from ds.launch.local import free_port
from ds.net import security
from ds.net.rpc import wait_until_serving
from ds.net.security import Credentials, load_credentials
from ds.replay.service import serve_replay
from tests.algorithm.replay.chunks import VECTOR
from tests.ds.net.security_setup import MODULES, SERVICES, TOKEN, Material, Served, codes, health_status, rpc_names

pytestmark = pytest.mark.grpc


# ---------------------------------------------------------------------- health


@pytest.mark.parametrize("client_certificates", [True, False], ids=["mtls", "tls"])
@pytest.mark.parametrize("role", SERVICES)
def test_the_plaintext_health_port_answers_health_and_refuses_everything_else(
    role: str, client_certificates: bool, material: Material, servers: Callable[..., Served], tmp_path: Path
) -> None:
    """What Kubernetes gRPC probes (no TLS, no metadata) get under TLS: health, and nothing else."""
    credentials = material.creds(role, ca="ca" if client_certificates else None)
    served = servers(role, credentials, health_port=free_port())
    assert served.health_port is not None
    probe = f"127.0.0.1:{served.health_port}"
    assert health_status(probe, role, Credentials()) == health_pb2.HealthCheckResponse.SERVING
    with security.open_channel(probe, role, Credentials(), []) as channel:
        module, service, _ = MODULES[role]
        name = module.DESCRIPTOR.services_by_name[service].full_name
        assert wait_until_serving(channel, name, role, probe, threading.Event())
    # Even with the token, plaintext on the health port reaches no rpc.
    on_health_port = codes(served, Credentials(token=TOKEN), tmp_path, port=served.health_port)
    assert on_health_port == dict.fromkeys(rpc_names(role), grpc.StatusCode.PERMISSION_DENIED)


# ---------------------------------------------------------------------- the credential files


def write(path: Path, data: bytes) -> str:
    path.write_bytes(data)
    return str(path)


def test_credential_files_that_cannot_be_used_are_config_errors_naming_key_and_file(
    material: Material, tmp_path: Path
) -> None:
    pki = material.pki
    good, other = pki.issue("learner-files", "learner"), pki.issue("replay-files", "replay")
    cert, key = str(good.cert), str(good.key)
    encrypted = serialization.load_pem_private_key(good.key.read_bytes(), None).private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.BestAvailableEncryption(b"passphrase"),
    )
    # (the files, the key the error must name (with its file), what it must say)
    cases: list[tuple[dict[str, str], str, str]] = [
        ({"tls_cert": str(tmp_path / "absent.crt"), "tls_key": key}, "tls_cert", "cannot read"),
        ({"tls_cert": cert, "tls_key": key, "tls_ca": str(tmp_path / "absent-ca.crt")}, "tls_ca", "cannot read"),
        ({"tls_cert": cert}, "tls_cert", "needs net_config.tls_key"),
        ({"tls_key": key}, "tls_key", "needs net_config.tls_cert"),
        ({"tls_cert": cert, "tls_key": str(other.key)}, "tls_key", f"is not the key of net_config.tls_cert {cert!r}"),
        ({"tls_cert": key, "tls_key": key}, "tls_cert", "is not a PEM file with a certificate"),
        ({"tls_cert": cert, "tls_key": cert}, "tls_key", "is not a PEM file with a private key"),
        ({"tls_ca": write(tmp_path / "junk.crt", b"not a certificate")}, "tls_ca", "is not a PEM file"),
        ({"tls_cert": cert, "tls_key": write(tmp_path / "enc.key", encrypted)}, "tls_key", "is encrypted"),
        ({"token_file": write(tmp_path / "empty", b" \n")}, "token_file", "is empty"),
        ({"token_file": str(tmp_path / "absent-token")}, "token_file", "cannot read"),
    ]
    for keys, key_name, message in cases:
        with pytest.raises(ConfigError) as error:
            load_credentials(NetConfig.model_validate(keys))
        text = str(error.value)
        assert text.startswith(f"net_config.{key_name}") and message in text, (keys, text)
        if "needs" not in message:
            assert repr(keys[key_name]) in text, (keys, text)
    with pytest.raises(ConfigError, match="the replay serves gRPC and needs its own certificate"):
        security.check_server_credentials(material.creds(None), "replay")  # a CA, but no certificate


def test_secrets_stay_out_of_repr(material: Material) -> None:
    creds = material.creds("learner")
    assert creds.token is not None and creds.key is not None
    assert TOKEN.decode() not in repr(creds) and "PRIVATE KEY" not in repr(creds)
    assert security.bearer(TOKEN) not in repr(creds) and TOKEN.hex() not in security.bearer(TOKEN)


# ---------------------------------------------------------------------- loopback by default


@pytest.mark.parametrize(
    ("host", "loopback"),
    [("127.0.0.1", True), ("127.0.0.2", True), ("localhost", True), ("::1", True), ("[::1]", True),
     ("0.0.0.0", False), ("::", False), ("10.0.0.7", False), ("asac-replay-0.asac-replay", False)],
)  # fmt: skip
def test_loopback_hosts(host: str, loopback: bool) -> None:
    assert security.is_loopback(host) is loopback


def test_a_server_open_beyond_loopback_without_credentials_warns(
    material: Material, servers: Callable[..., Served], caplog: pytest.LogCaptureFixture, tmp_path: Path
) -> None:
    table = PrioritizedTable(10, (VECTOR,), 2, window=2, alpha=0.6, seed=0)
    for address, credentials, warns in (
        ("0.0.0.0:0", Credentials(), True),
        ("127.0.0.1:0", Credentials(), False),
        ("0.0.0.0:0", Credentials(token=TOKEN), False),
        ("0.0.0.0:0", material.creds("replay", token=None), False),
    ):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="asac.security"):
            server, _ = serve_replay(table, address, credentials=credentials)
            server.stop(None)
        warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert bool(warnings) is warns, (address, credentials, warnings)
        if warns:
            assert "open to anyone" in warnings[0] and "net_config.token_file" in warnings[0]
