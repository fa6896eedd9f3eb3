"""What the security tests (tests/ds/net/test_security.py, test_security_files.py) share: the run's token and
certificates made at test time (tests/pki.py), real servers of each role on loopback holding given
credentials, and raw calls of every rpc of a service, reporting the status code each got. The
``material`` and ``servers`` fixtures are in tests/ds/net/conftest.py."""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import grpc
import numpy as np
from grpc_health.v1 import health_pb2, health_pb2_grpc

from algorithm.config.schema import Config, NetConfig
from algorithm.replay import PrioritizedTable
from algorithm.spaces import ActionSpec, EnvSpec
from ds.evolver import service as evolver_service
from ds.evolver.evolver import Evolver
from ds.evolver.service import serve_evolver
from ds.learner import service as learner_service
from ds.learner.service import ActorRegistry, LearnerServicer, ParamsStore, serve_learner
from ds.net import security
from ds.net.params import encode_params
from ds.net.rpc import RetryPolicy, set_serving
from ds.net.security import ROLES, Credentials, load_credentials
from ds.replay import service as replay_service
from ds.replay.service import serve_replay
from protos import evolver_pb2, learner_pb2, replay_pb2
from tests.algorithm.replay.chunks import VECTOR
from tests.pki import Pki

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


def serve(role: str, credentials: Credentials, tmp_path: Path, health_port: int | None = None, port: int = 0) -> Served:
    """A real server of ``role`` on loopback with ``credentials`` (its own certificate decides who it is);
    ``port`` (0: a free one) for the replay only."""
    if role == "replay":
        table = PrioritizedTable(100, (VECTOR,), 2, window=2, alpha=0.6, seed=0)
        server, port = serve_replay(table, f"127.0.0.1:{port}", credentials=credentials, health_port=health_port)
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
