"""Security of the three gRPC services on loopback (ds/net/security.py): the token on every rpc, TLS and
mutual TLS with certificates made at test time (tests/pki.py), which role may call which rpc, and clients
that accept only a server holding the role's certificate (a learner loads CEM samples from the evolver
only). The health-only port, the credential files and loopback: tests/ds/net/test_security_files.py."""

from __future__ import annotations

import ipaddress
import logging
import threading
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest
from cryptography import x509
from grpc_health.v1 import health_pb2

from ds.evolver import service as evolver_service
from ds.evolver.client import EvolverClient
from ds.learner import service as learner_service
from ds.learner.client import LearnerClient
from ds.net import security
from ds.net.params import encode_params, params_spec
from ds.net.rpc import wait_until_serving
from ds.net.security import ROLES, Credentials
from ds.replay import service as replay_service
from ds.replay.client import ReplayClient, ReplayRpcError
from protos import evolver_pb2, evolver_pb2_grpc
from tests.algorithm.replay.chunks import VECTOR, make_chunk
from tests.ds.net.security_setup import (
    GUARD_CODES,
    MODULES,
    ONCE,
    SERVICES,
    TOKEN,
    WEIGHTS,
    Material,
    Served,
    allowed_roles,
    codes,
    health_status,
    rpc_names,
)

pytestmark = pytest.mark.grpc


# ---------------------------------------------------------------------- the callers tables


@pytest.mark.parametrize("role", SERVICES)
def test_every_rpc_of_every_service_names_the_roles_that_may_call_it(role: str) -> None:
    callers = MODULES[role][2]
    assert sorted(callers) == sorted(rpc_names(role)), "a new rpc needs its callers in CALLERS"
    assert all(roles and roles <= ROLES for roles in callers.values())
    assert learner_service.CALLERS["GetWeights"] == {"evolver"}  # weights leave a learner for the evolver only
    assert evolver_service.CALLERS["GetSample"] == {"learner"}


# ---------------------------------------------------------------------- the token


@pytest.mark.parametrize("tls", [False, True], ids=["plaintext", "mtls"])
@pytest.mark.parametrize("role", SERVICES)
def test_a_client_without_the_token_or_with_a_wrong_one_is_refused_on_every_rpc(
    role: str, tls: bool, material: Material, servers: Callable[..., Served], tmp_path: Path
) -> None:
    cert, ca = ("all", "ca") if tls else (None, None)
    served = servers(role, material.creds(role if tls else None, ca=ca))
    unauthenticated = dict.fromkeys(rpc_names(role), grpc.StatusCode.UNAUTHENTICATED)
    assert codes(served, material.creds(cert, token=None, ca=ca), tmp_path) == unauthenticated
    assert codes(served, material.creds(cert, token=b"a guess", ca=ca), tmp_path) == unauthenticated
    # The server kept serving; with the token every rpc reaches the servicer (whatever it makes of an
    # empty request), and the health service answers without the token.
    right = codes(served, material.creds(cert, ca=ca), tmp_path)
    assert not set(right.values()) & GUARD_CODES, right
    serving = health_pb2.HealthCheckResponse.SERVING
    assert health_status(served.address, role, material.creds(cert, token=None, ca=ca)) == serving


# ---------------------------------------------------------------------- TLS


CLIENTS_WITHOUT_THE_RUNS_CERTIFICATES: dict[str, dict[str, Any]] = {
    "trusts the wrong CA": {"ca": "wrong"},
    "its certificate is from the wrong CA": {"cert_ca": "wrong"},
    "no client certificate": {"cert": None},
    "plaintext": {"cert": None, "ca": None},
}


@pytest.mark.parametrize("case", sorted(CLIENTS_WITHOUT_THE_RUNS_CERTIFICATES))
@pytest.mark.parametrize("role", SERVICES)
def test_mutual_tls_refuses_a_client_without_the_runs_certificates_on_every_rpc(
    role: str, case: str, material: Material, servers: Callable[..., Served], tmp_path: Path
) -> None:
    served = servers(role, material.creds(role))
    stranger = material.creds(**CLIENTS_WITHOUT_THE_RUNS_CERTIFICATES[case])  # the right token, though
    # The handshake fails: the client sees UNAVAILABLE (nothing reached a handler), even for health.
    assert codes(served, stranger, tmp_path) == dict.fromkeys(rpc_names(role), grpc.StatusCode.UNAVAILABLE)
    with pytest.raises(grpc.RpcError) as refused:
        health_status(served.address, role, stranger)
    assert refused.value.code() == grpc.StatusCode.UNAVAILABLE
    assert health_status(served.address, role, material.creds()) == health_pb2.HealthCheckResponse.SERVING


@pytest.mark.parametrize("role", SERVICES)
def test_each_rpc_is_open_only_to_the_roles_that_call_it(
    role: str, material: Material, servers: Callable[..., Served], tmp_path: Path
) -> None:
    served = servers(role, material.creds(role))
    for caller in sorted(ROLES):
        got = codes(served, material.creds(caller), tmp_path)
        for name, code in got.items():
            if caller in allowed_roles(role, name):
                assert code not in GUARD_CODES, f"{caller} calling {role}.{name}: {code}"
            else:
                assert code == grpc.StatusCode.PERMISSION_DENIED, f"{caller} calling {role}.{name}: {code}"


@pytest.mark.parametrize("role", SERVICES)
def test_clients_refuse_a_server_whose_certificate_does_not_name_their_role(
    role: str, material: Material, servers: Callable[..., Served], tmp_path: Path
) -> None:
    """A process with the run's CA, token and a certificate of another role cannot pose as ``role``."""
    impostor = servers(role, material.creds(next(r for r in sorted(ROLES) if r != role)))
    assert codes(impostor, material.creds(), tmp_path) == dict.fromkeys(rpc_names(role), grpc.StatusCode.UNAVAILABLE)
    genuine = servers(role, material.creds(role))
    assert not set(codes(genuine, material.creds(), tmp_path).values()) & GUARD_CODES


class SampleServer(evolver_pb2_grpc.EvolverServiceServicer):
    """Serves a CEM sample signed with the run's token to whoever asks: all an impostor needs."""

    def GetSample(self, request: evolver_pb2.GetSampleRequest, context: grpc.ServicerContext) -> Any:
        return evolver_pb2.GetSampleReply(round=7, frames=encode_params(7, WEIGHTS, TOKEN))


def serve_samples(credentials: Credentials) -> tuple[grpc.Server, int]:
    server = security.new_server("sample", evolver_service.SERVICE_NAME, evolver_service.CALLERS, credentials, 2, [])
    evolver_pb2_grpc.add_EvolverServiceServicer_to_server(SampleServer(), server)
    port = security.listen(server, "127.0.0.1:0", credentials)
    server.start()
    return server, port


@pytest.mark.parametrize("impostor", ["replay", "learner", "actor", "stranger"])
def test_a_learner_loads_weight_samples_from_the_evolvers_credentials_only(material: Material, impostor: str) -> None:
    """Weight updates (evolver -> learner): the learner's EvolverClient takes a sample only from a server
    holding the evolver's certificate, even when the sample is otherwise valid (signed with the token)."""
    learner = material.creds("learner")
    credentials = material.creds(impostor, cert_ca="wrong") if impostor == "stranger" else material.creds(impostor)
    expected = params_spec(WEIGHTS)
    for holder, loads in ((credentials, False), (material.creds("evolver"), True)):
        server, port = serve_samples(holder)
        try:
            with EvolverClient(f"127.0.0.1:{port}", token=TOKEN, credentials=learner, retry=ONCE) as client:
                if loads:
                    sample = client.get_sample(1, expected)
                    assert sample is not None and sample.round == 7
                    np.testing.assert_array_equal(sample.weights["q.weight"], WEIGHTS["q.weight"])
                else:
                    with pytest.raises(grpc.RpcError) as refused:
                        client.get_sample(1, expected)
                    assert refused.value.code() == grpc.StatusCode.UNAVAILABLE
        finally:
            server.stop(None)


def test_the_evolver_reads_weights_from_learners_only(material: Material, servers: Callable[..., Served]) -> None:
    evolver = material.creds("evolver")
    impostor, genuine = servers("learner", material.creds("actor")), servers("learner", material.creds("learner"))
    with LearnerClient(impostor.address, credentials=evolver, retry=ONCE) as client:
        with pytest.raises(grpc.RpcError) as refused:
            client.get_weights()
        assert refused.value.code() == grpc.StatusCode.UNAVAILABLE
    with LearnerClient(genuine.address, credentials=evolver, retry=ONCE) as client:
        assert client.get_weights()[0] == 3
    with LearnerClient(genuine.address, credentials=material.creds("actor"), retry=ONCE) as client:
        with pytest.raises(grpc.RpcError) as denied:  # an actor may not read the full weights
            client.get_weights()
        assert denied.value.code() == grpc.StatusCode.PERMISSION_DENIED
        assert "GetWeights is for evolver" in (denied.value.details() or "")


# A client certificate from the run's CA whose subject CN is "evolver" (never a role: roles are DNS SANs)
# and whose subject alternative names are these: only a DNS SAN "evolver" makes it the evolver.
EVOLVER_CLAIMS: dict[str, tuple[list[x509.GeneralName], bool]] = {
    "URI:evolver": ([x509.UniformResourceIdentifier("evolver")], False),
    "email:evolver@x": ([x509.RFC822Name("evolver@x")], False),
    "URI:evolver, email:evolver@x, DNS:actor": (
        [x509.UniformResourceIdentifier("evolver"), x509.RFC822Name("evolver@x"), x509.DNSName("actor")],
        False,
    ),
    "IP:127.0.0.1": ([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))], False),
    "DNS:evolver": ([x509.DNSName("evolver")], True),
}


@pytest.mark.parametrize("claim", sorted(EVOLVER_CLAIMS))
def test_roles_are_read_from_dns_subject_alternative_names_only(
    claim: str, material: Material, servers: Callable[..., Served]
) -> None:
    """Issue 17: a certificate naming ``URI:evolver`` was accepted as the evolver on GetWeights."""
    sans, is_evolver = EVOLVER_CLAIMS[claim]
    stem = "claim-" + "".join(c if c.isalnum() else "-" for c in claim)
    issued = material.pki.issue(stem, sans=sans, common_name="evolver")
    client = replace(material.creds(None), cert=issued.cert.read_bytes(), key=issued.key.read_bytes())
    learner = servers("learner", material.creds("learner"))
    with LearnerClient(learner.address, credentials=client, retry=ONCE) as caller:
        if is_evolver:
            assert caller.get_weights()[0] == 3
            return
        with pytest.raises(grpc.RpcError) as denied:
            caller.get_weights()
    assert denied.value.code() == grpc.StatusCode.PERMISSION_DENIED
    details = denied.value.details() or ""
    assert "GetWeights is for evolver" in details and "roles are DNS subject alternative names" in details
    names = "actor" if "DNS:actor" in claim else "no role"
    assert f"the caller's certificate names {names} " in details


def test_the_clients_carry_tls_and_the_token_on_blocking_and_future_calls(
    material: Material, servers: Callable[..., Served]
) -> None:
    served = servers("replay", material.creds("replay"))
    actor, learner = material.creds("actor"), material.creds("learner")
    with ReplayClient(served.address, (VECTOR,), 2, credentials=actor, retry=ONCE) as replay:
        assert len(replay.insert(make_chunk(5, 0))) == 5
        pending = replay.insert_async([make_chunk(5, 6)])  # a .future() call: ds/actor/actor.py pipelines these
        assert [len(keys) for keys in pending.result().keys] == [5]
        assert replay.info()["inserted_steps"] == 10
        with pytest.raises(ReplayRpcError) as denied:
            replay.sample(4, timeout=1.0)  # an actor does not sample
        assert denied.value.code == grpc.StatusCode.PERMISSION_DENIED
    with ReplayClient(served.address, (VECTOR,), 2, credentials=learner, retry=ONCE) as replay:
        assert replay.sample(4, timeout=5.0).obs[0].shape[0] == 4
    with ReplayClient(served.address, (VECTOR,), 2, credentials=material.creds(token=b"a guess"), retry=ONCE) as r:
        with pytest.raises(ReplayRpcError) as refused:
            r.info()
        assert refused.value.code == grpc.StatusCode.UNAUTHENTICATED
        assert "net_config.token_file" in str(refused.value)


def test_tls_without_client_certificates(material: Material, servers: Callable[..., Served], tmp_path: Path) -> None:
    """A server with a certificate and no CA speaks TLS but asks for no client certificate; the token still counts."""
    served = servers("learner", material.creds("learner", ca=None))
    assert not set(codes(served, material.creds(None), tmp_path).values()) & GUARD_CODES  # trusts the CA only
    assert set(codes(served, material.creds(None, token=None), tmp_path).values()) == {grpc.StatusCode.UNAUTHENTICATED}
    assert set(codes(served, material.creds(None, ca="wrong"), tmp_path).values()) == {grpc.StatusCode.UNAVAILABLE}


def test_a_client_waiting_for_a_server_it_cannot_trust_logs_why(
    material: Material, servers: Callable[..., Served], caplog: pytest.LogCaptureFixture
) -> None:
    """A failed handshake reads UNAVAILABLE, like a server that is down; the wait says which it is."""
    served = servers("replay", material.creds("replay"))
    stop = threading.Event()
    timer = threading.Timer(1.0, stop.set)
    timer.start()
    with (
        caplog.at_level(logging.INFO, logger="asac.rpc"),
        security.open_channel(served.address, "replay", material.creds(ca="wrong"), []) as channel,
    ):
        assert not wait_until_serving(channel, replay_service.SERVICE_NAME, "replay", served.address, stop, 0.2)
    timer.join()
    waits = [r.getMessage() for r in caplog.records if r.getMessage().startswith("waiting for replay")]
    assert waits and all("not reachable: " in w and "handshake" in w.lower() for w in waits), waits
