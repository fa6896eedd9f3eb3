"""Security of the three gRPC services on loopback (ds/net/security.py): the token on every rpc, TLS and
mutual TLS with certificates made at test time (tests/pki.py), which role may call which rpc, clients
that accept only a server holding the role's certificate (a learner loads CEM samples from the
evolver only), the plaintext health-only port, the checks of the credential files, and the warning
for a server open beyond loopback."""

from __future__ import annotations

import ipaddress
import logging
import tempfile
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from types import ModuleType
from typing import Any

import grpc
import numpy as np
import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from grpc_health.v1 import health_pb2, health_pb2_grpc

from algorithm.config import ConfigError
from algorithm.config_schema import Config, NetConfig
from algorithm.replay import PrioritizedTable
from algorithm.spaces import ActionSpec, EnvSpec
from ds.evolver import service as evolver_service
from ds.evolver.evolver import Evolver
from ds.evolver.service import EvolverClient, serve_evolver
from ds.launch.local import free_port
from ds.learner import service as learner_service
from ds.learner.client import LearnerClient
from ds.learner.service import ActorRegistry, LearnerServicer, ParamsStore, serve_learner
from ds.net import security
from ds.net.params import encode_params, params_spec
from ds.net.rpc import RetryPolicy, set_serving, wait_until_serving
from ds.net.security import ROLES, Credentials, load_credentials
from ds.replay import service as replay_service
from ds.replay.client import ReplayClient, ReplayRpcError
from ds.replay.service import serve_replay
from protos import evolver_pb2, evolver_pb2_grpc, learner_pb2, replay_pb2
from tests.algorithm.replay.chunks import VECTOR, make_chunk
from tests.pki import Pki

pytestmark = pytest.mark.grpc

TOKEN = b"the run's secret"
SPEC = EnvSpec((VECTOR,), ActionSpec(continuous_dim=2, low=(-1.0, -1.0), high=(1.0, 1.0)))
WEIGHTS: dict[str, np.ndarray] = {"q.weight": np.full((3, 4), 0.5, np.float32), "policy.bias": np.zeros(2, np.float64)}
ONCE = RetryPolicy(attempts=1)
SERVICES = ("replay", "learner", "evolver")
MODULES: dict[str, tuple[ModuleType, str, Any]] = {  # role -> (pb2 module, service, callers)
    "replay": (replay_pb2, "ReplayService", replay_service.CALLERS),
    "learner": (learner_pb2, "LearnerService", learner_service.CALLERS),
    "evolver": (evolver_pb2, "EvolverService", evolver_service.CALLERS),
}
# What the guard answers; any other code means the call reached the servicer.
GUARD_CODES = {grpc.StatusCode.UNAUTHENTICATED, grpc.StatusCode.PERMISSION_DENIED, grpc.StatusCode.UNAVAILABLE}


# ---------------------------------------------------------------------- certificates and credentials


@dataclass
class Material:
    """A CA, a wrong CA, one certificate per role, one naming every role, and the token file."""

    pki: Pki
    token_file: Path

    def creds(
        self, cert: str | None = "all", token: bytes | None = TOKEN, ca: str | None = "ca", cert_ca: str = "ca"
    ) -> Credentials:
        """Credentials loaded the way main_ds.py loads them; ``cert``: a role, "all", or None (no certificate)."""
        token_file = None
        if token is not None:
            token_file = self.pki.folder / f"token-{token.hex()}"
            token_file.write_bytes(token + b"\n")
        issued = None
        if cert is not None:
            roles = tuple(sorted(ROLES)) if cert == "all" else (cert,)
            issued = self.pki.issue(cert if cert_ca == "ca" else f"{cert}-stranger", *roles, ca=cert_ca)
        trusted = {"ca": self.pki.ca, "wrong": self.pki.wrong_ca, None: None}[ca]
        net = NetConfig(
            token_file=None if token_file is None else str(token_file),
            tls_cert=None if issued is None else str(issued.cert),
            tls_key=None if issued is None else str(issued.key),
            tls_ca=None if trusted is None else str(trusted),
        )
        return load_credentials(net)


@pytest.fixture(scope="module")
def material(tmp_path_factory: pytest.TempPathFactory) -> Material:
    folder = tmp_path_factory.mktemp("pki")
    return Material(Pki(folder), folder / "token")


# ---------------------------------------------------------------------- servers


@dataclass
class Served:
    role: str
    port: int
    health_port: int | None
    stop: Callable[[], None]

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"


def serve(role: str, credentials: Credentials, tmp_path: Path, health_port: int | None = None) -> Served:
    """A real server of ``role`` on loopback with ``credentials`` (its own certificate decides who it is)."""
    if role == "replay":
        table = PrioritizedTable(100, (VECTOR,), 2, window=2, alpha=0.6, seed=0)
        server, port = serve_replay(table, "127.0.0.1:0", credentials=credentials, health_port=health_port)
        return Served(role, port, health_port, lambda: server.stop(None))
    if role == "learner":
        store = ParamsStore()
        store.put(3, encode_params(3, WEIGHTS, TOKEN))  # GetParams answers (UNAVAILABLE before a publication)
        servicer = LearnerServicer(SPEC, ActorRegistry(), store, params_port=0, weights=store.get)
        server, port, health = serve_learner(servicer, credentials=credentials, health_port=health_port)
        set_serving(health, learner_service.SERVICE_NAME, True)
        return Served(role, port, health_port, lambda: server.stop(None))
    config = Config.model_validate({"sac_config": {"seed": 0}})
    evolver = Evolver(config, Path(tempfile.mkdtemp(dir=tmp_path)), "exp", token=TOKEN)
    server, port, _ = serve_evolver(evolver, credentials=credentials, health_port=health_port)

    def stop() -> None:
        server.stop(None)
        evolver.stop()

    return Served(role, port, health_port, stop)


@pytest.fixture
def servers(tmp_path: Path) -> Iterator[Callable[..., Served]]:
    started: list[Served] = []

    def start(role: str, credentials: Credentials, health_port: int | None = None) -> Served:
        started.append(serve(role, credentials, tmp_path, health_port))
        return started[-1]

    yield start
    for served in started:
        served.stop()


def rpc_names(role: str) -> list[str]:
    module, service, _ = MODULES[role]
    return [m.name for m in module.DESCRIPTOR.services_by_name[service].methods]


def call(channel: grpc.Channel, role: str, name: str, tmp_path: Path) -> grpc.StatusCode:
    """One raw call of rpc ``name`` of ``role``'s service with a harmless request; its status code."""
    module, service, _ = MODULES[role]
    method = module.DESCRIPTOR.services_by_name[service].methods_by_name[name]
    request_type, reply_type = getattr(module, method.input_type.name), getattr(module, method.output_type.name)
    request = request_type()
    if name in ("Save", "Load"):  # somewhere harmless on the replay's filesystem
        request.path = str(tmp_path / "absent" / "replay.npz")
    stub = channel.unary_unary(
        f"/{module.DESCRIPTOR.services_by_name[service].full_name}/{name}",
        request_serializer=request_type.SerializeToString,
        response_deserializer=reply_type.FromString,
    )
    try:
        stub(request, timeout=10)
    except grpc.RpcError as e:
        return e.code()
    return grpc.StatusCode.OK


def codes(served: Served, client: Credentials, tmp_path: Path, port: int | None = None) -> dict[str, grpc.StatusCode]:
    """Every rpc of ``served``'s service called by a client holding ``client``: {rpc: status code}."""
    address = served.address if port is None else f"127.0.0.1:{port}"
    with security.open_channel(address, served.role, client, []) as channel:
        return {name: call(channel, served.role, name, tmp_path) for name in rpc_names(served.role)}


def health_status(address: str, role: str, credentials: Credentials) -> int:
    module, service, _ = MODULES[role]
    name = module.DESCRIPTOR.services_by_name[service].full_name
    with security.open_channel(address, role, credentials, []) as channel:
        request = health_pb2.HealthCheckRequest(service=name)
        return int(health_pb2_grpc.HealthStub(channel).Check(request, timeout=10).status)


def allowed_roles(role: str, name: str) -> frozenset[str]:
    return frozenset(MODULES[role][2][name])


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
