"""Credentials rotated while servers serve and clients call (ds/net/credentials.py, ds/net/channels.py):
a token file that changes, a certificate renewed from the same CA, a CA rollover with both CAs
trusted for a while, an expired certificate refused, a half-done rotation that keeps the old
credentials. Real gRPC servers and channels on loopback; files replaced the way a Kubernetes Secret
volume replaces them (a new file moved over the old one)."""

from __future__ import annotations

import logging
import socket
import ssl
from collections.abc import Callable
from pathlib import Path

import grpc
import numpy as np
import pytest

from algorithm.config.schema import NetConfig
from ds.net import credentials as credentials_module
from ds.net import security
from ds.net.credentials import Keyring, load_credentials
from ds.net.params import MAC_BYTES, ParamsError, decode_params, encode_params
from ds.net.stream_key import StreamKey
from tests.ds.net.security_setup import Served, call
from tests.pki import Pki, RoleFiles, replace_file


@pytest.fixture(autouse=True)
def look_at_every_use(monkeypatch: pytest.MonkeyPatch) -> None:
    """Files are looked at on every use, not every 2 s, so that each step of a test sees the last one."""
    monkeypatch.setattr(credentials_module, "CHECK_EVERY_S", 0.0)


def info(channel: grpc.Channel, tmp_path: Path) -> grpc.StatusCode:
    return call(channel, "replay", "Info", tmp_path)


# ---------------------------------------------------------------------- the token


def test_a_token_file_is_read_again_when_it_changes_and_a_bad_change_keeps_the_last(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "token"
    replace_file(path, b"first\n")
    keyring = Keyring.read(str(path))
    assert keyring.tokens == (b"first",)
    replace_file(path, b"  first \n\nsecond\n")
    assert keyring.tokens == (b"first", b"second"), "each non-empty line is a token"
    with caplog.at_level(logging.ERROR, logger="asac.security"):
        replace_file(path, b"\n")
        assert keyring.tokens == (b"first", b"second") and keyring.tokens == (b"first", b"second")
    errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 1, errors  # once, not on every use
    assert str(path) in errors[0] and "is empty" in errors[0] and "keeping" in errors[0]
    replace_file(path, b"second\n")
    assert keyring.tokens == (b"second",)
    assert "second" not in repr(keyring), "tokens stay out of repr"


def test_a_token_rotates_in_two_steps_while_one_channel_keeps_calling(
    servers: Callable[..., Served], tmp_path: Path
) -> None:
    server_file, client_file = tmp_path / "server-token", tmp_path / "client-token"
    replace_file(server_file, b"old\n")
    replace_file(client_file, b"old\n")
    served = servers("replay", load_credentials(NetConfig(token_file=str(server_file))))
    client = load_credentials(NetConfig(token_file=str(client_file)))
    with security.open_channel(served.address, "replay", client, []) as channel:
        assert info(channel, tmp_path) == grpc.StatusCode.OK
        # Step 1, in any order: every role's file holds both tokens.
        replace_file(client_file, b"old\nnew\n")
        assert info(channel, tmp_path) == grpc.StatusCode.OK
        replace_file(server_file, b"old\nnew\n")
        assert info(channel, tmp_path) == grpc.StatusCode.OK
        # Step 2, in any order: the new token alone.
        replace_file(server_file, b"new\n")
        assert info(channel, tmp_path) == grpc.StatusCode.OK, "the client still proves itself with both"
        replace_file(client_file, b"new\n")
        assert info(channel, tmp_path) == grpc.StatusCode.OK
    for stale in (b"old\n", b"other\nold\n"):
        replace_file(tmp_path / "stale", stale)
        refused = load_credentials(NetConfig(token_file=str(tmp_path / "stale")))
        with security.open_channel(served.address, "replay", refused, []) as channel:
            assert info(channel, tmp_path) == grpc.StatusCode.UNAUTHENTICATED, stale


def test_parameters_signed_with_two_tokens_are_taken_by_holders_of_either() -> None:
    weights = {"w": np.arange(6, dtype=np.float32).reshape(2, 3)}
    both = Keyring.of(b"old", b"new")
    frames = encode_params(4, weights, both)
    assert len(frames[-1]) == 2 * MAC_BYTES
    for holder in (b"old", b"new", Keyring.of(b"new", b"newer")):
        assert decode_params(frames, token=holder)[0] == 4
    with pytest.raises(ParamsError, match="MAC does not verify"):
        decode_params(frames, token=b"another")
    stream = StreamKey.fresh()
    signed = encode_params(5, weights, both, stream=stream)
    assert decode_params(signed, token=b"new", stream=stream)[0] == 5
    with pytest.raises(ParamsError, match="MAC does not verify"):
        decode_params(signed, token=b"new", stream=StreamKey.fresh())
    padded = [*frames[:-1], frames[-1] * 3]  # more MACs than any token file holds
    with pytest.raises(ParamsError, match="no MAC frame"):
        decode_params(padded, token=b"old")


# ---------------------------------------------------------------------- TLS


def tls_only(files: RoleFiles) -> NetConfig:
    """A role's TLS files without its token (these tests rotate certificates alone)."""
    return NetConfig(tls_cert=str(files.cert), tls_key=str(files.key), tls_ca=str(files.ca))


def presented_issuer(port: int, client: RoleFiles) -> str:
    """The issuer CN of the certificate the server on ``port`` presents to a new connection."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.load_verify_locations(cafile=str(client.ca))
    context.load_cert_chain(str(client.cert), str(client.key))
    context.set_alpn_protocols(["h2"])
    with socket.create_connection(("127.0.0.1", port), timeout=10) as raw, context.wrap_socket(raw) as tls:
        issuer = dict(pair for rdn in tls.getpeercert()["issuer"] for pair in rdn)
    return str(issuer["commonName"])


def test_certificates_renewed_and_a_ca_rolled_over_are_taken_up_by_serving_servers_and_open_channels(
    servers: Callable[..., Served], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    pki = Pki(tmp_path / "pki")
    old_ca, new_ca = pki.ca, pki.wrong_ca  # two independent CAs
    server = RoleFiles(tmp_path / "server", pki.issue("replay"), old_ca, b"-")
    client = RoleFiles(tmp_path / "client", pki.issue("actor"), old_ca, b"-")
    served = servers("replay", load_credentials(tls_only(server)))
    with security.open_channel(served.address, "replay", load_credentials(tls_only(client)), []) as channel:
        assert info(channel, tmp_path) == grpc.StatusCode.OK
        assert presented_issuer(served.port, client) == "ASAC test ca"
        # Renewed from the same CA: the server presents the new certificate to new connections.
        server.use(pki.issue("replay-renewed", "replay"))
        client.use(pki.issue("actor-renewed", "actor"))
        assert info(channel, tmp_path) == grpc.StatusCode.OK
        # CA rollover, step 1: both CAs trusted everywhere; step 2: certificates of the new CA.
        server.trust(old_ca, new_ca)
        client.trust(old_ca, new_ca)
        assert info(channel, tmp_path) == grpc.StatusCode.OK
        server.use(pki.issue("replay", ca="wrong"))
        assert info(channel, tmp_path) == grpc.StatusCode.OK, "the client trusts both CAs"
        client.use(pki.issue("actor", ca="wrong"))
        assert info(channel, tmp_path) == grpc.StatusCode.OK, "the server trusts both CAs"
        assert presented_issuer(served.port, client) == "ASAC test wrong-ca"
        # Step 3: the old CA no longer trusted. The open channel keeps calling, also through a new
        # connection to a server restarted on the same port (it presents the new CA's certificate).
        server.trust(new_ca)
        client.trust(new_ca)
        assert info(channel, tmp_path) == grpc.StatusCode.OK
        served.stop()
        served = servers("replay", load_credentials(tls_only(server)), port=served.port)
        assert info(channel, tmp_path) == grpc.StatusCode.OK
        # A half-done change (a certificate without its key) is refused with one error; the server
        # keeps what it had.
        with caplog.at_level(logging.ERROR, logger="asac.security"):
            replace_file(server.cert, pki.issue("replay-half", "replay", ca="wrong").cert.read_bytes())
            assert presented_issuer(served.port, client) == "ASAC test wrong-ca"
            assert info(channel, tmp_path) == grpc.StatusCode.OK
        errors = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
        assert len(errors) == 1 and "is not the key of" in errors[0] and "keeping" in errors[0], errors
    # New clients: one with a certificate of the old CA, one with an expired one, are refused.
    for name, issued in {
        "old-ca": pki.issue("actor-of-old-ca", "actor"),
        "expired": pki.issue("actor-expired", "actor", ca="wrong", expired=True),
    }.items():
        stale = RoleFiles(tmp_path / name, issued, old_ca, b"-")
        stale.trust(old_ca, new_ca)
        with security.open_channel(served.address, "replay", load_credentials(tls_only(stale)), []) as channel:
            assert info(channel, tmp_path) == grpc.StatusCode.UNAVAILABLE, name
    fresh = RoleFiles(tmp_path / "fresh", pki.issue("actor-fresh", "actor", ca="wrong"), new_ca, b"-")
    with security.open_channel(served.address, "replay", load_credentials(tls_only(fresh)), []) as channel:
        assert info(channel, tmp_path) == grpc.StatusCode.OK
