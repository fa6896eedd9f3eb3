"""The deployment: the learner/replay pairing by pod ordinal (ds/launch/k8s.py), the k8s/ manifests as
``kubectl kustomize`` renders them (valid against the Kubernetes schemas; commands that main_ds.py's
parser accepts; ports, probes and mounts that agree with each role's resolved config, and with the
image: its user, working directory and model root, tests/test_image.py)."""

from __future__ import annotations

import argparse
import functools
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from algorithm.config.load import ConfigError, load_config
from algorithm.config.schema import Config
from cli import UsageError, cli_overrides, task_dir
from ds.evolver import service as evolver_service
from ds.launch.k8s import PodName, paired_hosts, parse_pod_name, stable_host
from ds.learner import service as learner_service
from ds.replay import service as replay_service
from main_ds import ROLES, build_parser
from tests.test_image import image_env, image_uid, image_workdir

ROOT = Path(__file__).resolve().parents[1]
K8S = ROOT / "k8s"
# The oldest Kubernetes minor the manifests are checked against (native gRPC probes are GA from 1.27).
CLUSTER_VERSION = "1.30"
HEALTH_SERVICE = {
    "replay": replay_service.SERVICE_NAME,
    "learner": learner_service.SERVICE_NAME,
    "evolver": evolver_service.SERVICE_NAME,
}
SERVERS = tuple(HEALTH_SERVICE)  # roles that listen; actors only connect
GRACE_FOR_SAVING = {"learner": 60, "replay": 60}  # they checkpoint / snapshot on SIGTERM


# ---------------------------------------------------------------------- pairing by ordinal (pure)


def test_learner_k_is_paired_with_replay_k() -> None:
    assert paired_hosts("asac-learner-2", "learner") == {
        "learner_host": "asac-learner-2.asac-learner",
        "replay_host": "asac-replay-2.asac-replay",
    }
    assert paired_hosts("asac-replay-2", "replay") == {"replay_host": "asac-replay-2.asac-replay"}
    assert parse_pod_name("asac-learner-2") == PodName("asac", "learner", 2)


def test_pairing_reads_the_first_label_and_keeps_any_app_prefix() -> None:
    assert paired_hosts("asac-learner-0.asac-learner.ns.svc.cluster.local", "learner")["replay_host"] == (
        "asac-replay-0.asac-replay"
    )
    assert paired_hosts("hc-replay-learner-11", "learner")["replay_host"] == "hc-replay-replay-11.hc-replay-replay"


@pytest.mark.parametrize(
    ("hostname", "role"),
    [
        ("asac-actor-7d9f8c6b5-x2kq4", "actor"),  # a Deployment's pod: the evolver places actors
        ("asac-evolver-5c8d7-abcde", "evolver"),
        ("asac-replay-1", "learner"),  # another role's pod derives nothing for this role
        ("asac-learner-1", "replay"),
        ("asac-learner-01", "learner"),  # StatefulSet ordinals have no leading zeros
        ("asac-learner-", "learner"),
        ("learner-3", "learner"),  # no app name
        ("ASAC-learner-3", "learner"),  # not a Kubernetes name
        ("laptop", "learner"),
    ],
)
def test_other_pods_derive_nothing(hostname: str, role: str) -> None:
    assert paired_hosts(hostname, role) == {}


@given(
    app=st.from_regex(r"[a-z0-9]([-a-z0-9]{0,20}[a-z0-9])?", fullmatch=True),
    ordinal=st.integers(0, 10_000),
)
def test_learner_is_given_the_address_its_replay_announces(app: str, ordinal: int) -> None:
    learner = paired_hosts(f"{app}-learner-{ordinal}", "learner")
    replay = paired_hosts(f"{app}-replay-{ordinal}", "replay")
    assert learner["replay_host"] == replay["replay_host"] == stable_host(app, "replay", ordinal)
    assert learner["learner_host"] == stable_host(app, "learner", ordinal)
    assert parse_pod_name(f"{app}-replay-{ordinal}") == PodName(app, "replay", ordinal)


# ---------------------------------------------------------------------- rendering


def kustomizations() -> list[str]:
    """Every kustomization we ship, relative to k8s/: the base and each overlay."""
    return ["base"] + sorted(f"overlays/{p.parent.name}" for p in (K8S / "overlays").glob("*/kustomization.yaml"))


def components() -> list[str]:
    return sorted(p.parent.name for p in (K8S / "components").glob("*/kustomization.yaml"))


RENDERS = kustomizations() + [f"smoke+{c}" for c in components()]


def kubectl() -> str:
    path = shutil.which("kubectl")
    if path is None:
        pytest.skip("kubectl is not on PATH: it renders k8s/ (kubectl kustomize); install kubectl >= 1.27 to run these")
    return path


@functools.cache
def _render(name: str, tmp_root: str) -> tuple[dict[str, Any], ...]:
    binary = kubectl()
    if "+" in name:  # an optional component on top of the smoke overlay, in a copy of k8s/
        overlay, component = name.split("+")
        tree = Path(tmp_root) / name / "k8s"
        shutil.copytree(K8S, tree)
        folder = tree / "overlays" / "with-component"
        folder.mkdir()
        folder.joinpath("kustomization.yaml").write_text(
            yaml.safe_dump(
                {
                    "apiVersion": "kustomize.config.k8s.io/v1beta1",
                    "kind": "Kustomization",
                    "resources": [f"../{overlay}"],
                    "components": [f"../../components/{component}"],
                }
            )
        )
    else:
        folder = K8S / name
    done = subprocess.run([binary, "kustomize", str(folder)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, f"kubectl kustomize k8s/{name} failed:\n{done.stderr}"
    return tuple(doc for doc in yaml.safe_load_all(done.stdout) if doc)


@pytest.fixture(scope="module")
def render(tmp_path_factory: pytest.TempPathFactory) -> Any:
    root = str(tmp_path_factory.mktemp("k8s"))
    return lambda name: _render(name, root)


@dataclass
class Container:
    """A rendered ASAC container with its role's resolved config (what main_ds.py would run with)."""

    workload: dict[str, Any]
    spec: dict[str, Any]
    argv: list[str]
    args: argparse.Namespace
    config: Config

    @property
    def role(self) -> str:
        return ROLES[self.args.role]

    @property
    def task(self) -> str:
        return str(self.args.env)

    @property
    def pod(self) -> dict[str, Any]:
        return self.workload["spec"]["template"]["spec"]

    @property
    def where(self) -> str:
        return f"{self.workload['kind']}/{self.workload['metadata']['name']}"

    def role_port(self) -> int:
        return int(getattr(self.config.net_config, f"{self.role}_port"))


def workloads(docs: tuple[dict[str, Any], ...]) -> list[dict[str, Any]]:
    return [d for d in docs if d["kind"] in ("Deployment", "StatefulSet")]


def resolve(workload: dict[str, Any], spec: dict[str, Any]) -> Container:
    """Parse the container's arguments with main_ds.py's parser and resolve its config the way
    main_ds.py does (the four layers, then the address flags); exits of the parser fail the test."""
    where = f"{workload['kind']}/{workload['metadata']['name']}"
    assert "command" not in spec, f"{where}: overrides the image's entrypoint (python main_ds.py)"
    argv = [str(a) for a in spec.get("args", [])]
    try:
        args = build_parser().parse_args(argv)
    except SystemExit:
        pytest.fail(f"{where}: main_ds.py rejects its arguments {argv}")
    try:
        config = load_config(task_dir(args.env), args.config, cli_overrides(args)).config
    except (ConfigError, UsageError) as e:
        pytest.fail(f"{where}: {e}")
    flags = ("evolver_host", "evolver_port", "learner_host", "learner_port", "replay_host", "replay_port", "tls_cert",
             "tls_key", "tls_ca")  # fmt: skip
    for flag in flags:
        if (value := getattr(args, flag)) is not None:
            setattr(config.net_config, flag, value)
    return Container(workload, spec, argv, args, config)


def asac_containers(docs: tuple[dict[str, Any], ...]) -> list[Container]:
    found = []
    for workload in workloads(docs):
        for spec in workload["spec"]["template"]["spec"]["containers"]:
            found.append(resolve(workload, spec))
    return found


def by_role(docs: tuple[dict[str, Any], ...]) -> dict[str, Container]:
    containers = asac_containers(docs)
    roles = {c.role: c for c in containers}
    assert len(roles) == len(containers), "one workload per role"
    return roles


def config_map(docs: tuple[dict[str, Any], ...], name: str) -> dict[str, Any]:
    (found,) = [d for d in docs if d["kind"] == "ConfigMap" and d["metadata"]["name"] == name]
    return found


@pytest.mark.parametrize("name", RENDERS)
def test_renders_and_validates_against_the_kubernetes_schemas(render: Any, name: str) -> None:
    validator = pytest.importorskip("kubernetes_validate", reason="pip install kubernetes-validate (test extra)")
    docs = render(name)
    assert {"Service", "StatefulSet", "Deployment", "ConfigMap"} <= {d["kind"] for d in docs}
    for doc in docs:
        try:
            validator.validate(doc, CLUSTER_VERSION, strict=True)
        except validator.ValidationError as e:
            path = ".".join(str(p) for p in e.path)
            pytest.fail(f"k8s/{name}: {doc['kind']}/{doc['metadata']['name']}: {path}: {e.message}")


@pytest.mark.parametrize("name", RENDERS)
def test_every_role_runs_a_command_main_ds_accepts(render: Any, name: str) -> None:
    roles = by_role(render(name))
    assert set(roles) == {"evolver", "learner", "replay", "actor"}
    tasks = {c.task for c in roles.values()}
    assert len(tasks) == 1, f"k8s/{name}: roles run different tasks {tasks}"
    names = {c.args.name for c in roles.values()}
    for c in roles.values():
        assert "--in_k8s" in c.argv, f"{c.where}: needs --in_k8s (listen on all interfaces, pairing)"
        assert "-n" in c.argv, f"{c.where}: every role of a run must name it (the default has {{time}})"
    assert len(names) == 1 and "{time}" not in str(names.pop()), f"k8s/{name}: one fixed run name for every role"
    for role in ("learner", "replay", "actor"):
        assert roles[role].config.net_config.evolver_host == "asac-evolver", f"{role} must find the evolver"


@pytest.mark.parametrize("name", RENDERS)
def test_service_ports_are_the_roles_configured_ports(render: Any, name: str) -> None:
    docs = render(name)
    containers = asac_containers(docs)
    for c in containers:  # every port a container declares is one its role serves
        for port in c.spec.get("ports", []):
            key = {"grpc": f"{c.role}_port", "params": "params_port", "health": "health_port"}.get(port["name"])
            assert key is not None and c.role in SERVERS, f"{c.where}: unexpected port {port}"
            assert port["containerPort"] == getattr(c.config.net_config, key), f"{c.where}: {port} != net.{key}"
    services = [d for d in docs if d["kind"] == "Service"]
    assert len(services) == len(SERVERS)
    for service in services:
        selector = service["spec"]["selector"]
        (c,) = [
            c for c in containers if selector.items() <= c.workload["spec"]["template"]["metadata"]["labels"].items()
        ]
        declared = {p["name"]: p["containerPort"] for p in c.spec.get("ports", [])}
        for port in service["spec"]["ports"]:
            target = port.get("targetPort", port["port"])
            number = declared[target] if isinstance(target, str) else target
            assert port["port"] == number, f"Service/{service['metadata']['name']}: port {port} is not the container's"
            assert port["name"] in declared, f"Service/{service['metadata']['name']}: {port['name']} not served"


@pytest.mark.parametrize("name", RENDERS)
def test_probes_ask_the_roles_health_service_on_a_port_that_serves_it(render: Any, name: str) -> None:
    """The role's gRPC port; under TLS, which Kubernetes gRPC probes cannot speak, the plaintext
    health-only port (net_config.health_port, ds/net/security.py)."""
    for c in asac_containers(render(name)):
        probes = [c.spec[k] for k in ("startupProbe", "readinessProbe", "livenessProbe") if k in c.spec]
        if c.role not in SERVERS:
            assert not probes, f"{c.where}: an {c.role} serves no health service"
            continue
        assert len(probes) == 3, f"{c.where}: needs startup, readiness and liveness probes"
        net = c.config.net_config
        if net.tls_cert is not None:
            assert net.health_port is not None, f"{c.where}: TLS on its gRPC port, so probes need net.health_port"
        port = c.role_port() if net.health_port is None else net.health_port
        expected = {"port": port, "service": HEALTH_SERVICE[c.role]}
        for probe in probes:
            assert probe.get("grpc") == expected, f"{c.where}: probe {probe} should ask {expected}"


@pytest.mark.parametrize("name", RENDERS)
def test_pods_run_as_non_root_with_writes_on_volumes(render: Any, name: str) -> None:
    docs = render(name)
    for c in asac_containers(docs):
        (source,) = c.spec["envFrom"]
        env = config_map(docs, source["configMapRef"]["name"])["data"]
        security = c.spec["securityContext"]
        assert c.pod["securityContext"]["runAsNonRoot"] is True, c.where
        assert c.pod["securityContext"]["runAsUser"] == image_uid(), f"{c.where}: not the image's user"
        assert security["readOnlyRootFilesystem"] is True and security["allowPrivilegeEscalation"] is False
        writable = [m["mountPath"] for m in c.spec["volumeMounts"] if not m.get("readOnly")]
        model_root = c.argv[c.argv.index("--model_root") + 1]
        assert model_root == image_env()["ASAC_MODEL_ROOT"], f"{c.where}: not the image's model root (its volume)"
        for path in [model_root, "/tmp", *env.values()]:  # asac-env holds the cache folders
            assert any(Path(path).is_relative_to(m) for m in writable), f"{c.where}: {path} is on the read-only root"
        threads = next((e["value"] for e in c.spec.get("env", []) if e["name"] == "OMP_NUM_THREADS"), None)
        assert threads is not None and int(threads) == cpus(c.spec["resources"]["limits"]["cpu"]), (
            f"{c.where}: OMP_NUM_THREADS {threads} should be its CPU limit"
        )
        if c.role in GRACE_FOR_SAVING:
            assert c.pod["terminationGracePeriodSeconds"] >= GRACE_FOR_SAVING[c.role], f"{c.where}: saves on SIGTERM"


@pytest.mark.parametrize("name", RENDERS)
def test_the_task_config_map_is_the_tasks_config(render: Any, name: str) -> None:
    docs = render(name)
    for c in asac_containers(docs):
        (mount,) = [m for m in c.spec["volumeMounts"] if m["name"] == "task-config"]
        assert mount["mountPath"] == f"{image_workdir()}/envs/{c.task}/config.yaml", c.where
        (volume,) = [v for v in c.pod["volumes"] if v["name"] == mount["name"]]
        shipped = config_map(docs, volume["configMap"]["name"])["data"][mount["subPath"]]
        assert shipped == (ROOT / "envs" / c.task / "config.yaml").read_text(), (
            f"k8s/{name}: the ConfigMap's config.yaml is not envs/{c.task}/config.yaml; copy it over"
        )


@pytest.mark.parametrize("name", RENDERS)
def test_learner_k_finds_replay_k(render: Any, name: str) -> None:
    docs = render(name)
    sets = {w["metadata"]["name"]: w for w in workloads(docs) if w["kind"] == "StatefulSet"}
    roles = by_role(docs)
    learner, replay = roles["learner"].workload, roles["replay"].workload
    assert learner["kind"] == replay["kind"] == "StatefulSet" and len(sets) == 2
    assert learner["spec"]["replicas"] == replay["spec"]["replicas"], f"k8s/{name}: one replay per learner"
    headless = {d["metadata"]["name"] for d in docs if d["kind"] == "Service" and d["spec"].get("clusterIP") == "None"}
    for workload in (learner, replay):
        assert workload["spec"]["serviceName"] == workload["metadata"]["name"] in headless
    replay_name, service = replay["metadata"]["name"], replay["spec"]["serviceName"]
    for k in range(learner["spec"]["replicas"]):
        given = paired_hosts(f"{learner['metadata']['name']}-{k}", "learner")["replay_host"]
        assert given == f"{replay_name}-{k}.{service}"  # replay pod k through its headless Service
        assert paired_hosts(f"{replay_name}-{k}", "replay") == {"replay_host": given}  # what replay k announces
    for c in (roles["learner"], roles["replay"]):
        assert c.args.replay_host is None, f"{c.where}: a fixed --replay_host overrides the pairing by ordinal"


@pytest.mark.parametrize("name", RENDERS)
def test_cuda_goes_with_a_gpu_and_the_cuda_image(render: Any, name: str) -> None:
    for c in asac_containers(render(name)):
        gpu = "nvidia.com/gpu" in c.spec["resources"].get("limits", {})
        cuda_image = c.spec["image"].split(":")[0].endswith("asac-cuda")
        assert (c.args.device == "cuda") == gpu == cuda_image, f"{c.where}: --device {c.args.device}, gpu {gpu}"


def test_overlays_have_the_sizes_they_promise(render: Any) -> None:
    def sizes(name: str) -> dict[str, int]:
        return {c.role: c.workload["spec"]["replicas"] for c in asac_containers(render(name))}

    assert sizes("overlays/smoke") == {"evolver": 1, "learner": 1, "replay": 1, "actor": 2}
    for name in ("overlays/half-cheetah", "overlays/half-cheetah-gpu"):
        assert sizes(name) == {"evolver": 1, "learner": 3, "replay": 3, "actor": 12}
        assert {c.task for c in asac_containers(render(name))} == {"mujoco/half_cheetah"}
    assert {c.task for c in asac_containers(render("overlays/smoke"))} == {"gym/pendulum"}


def test_token_component_names_the_mounted_secret(render: Any) -> None:
    """The Secret is mounted as a folder, without subPath (a subPath mount never sees the Secret's
    updates, and the token rotates without a restart: ds/net/credentials.py)."""
    for c in asac_containers(render("smoke+token")):
        assert c.config.net_config.token_file == "/var/run/asac/secret/token"
        (mount,) = [m for m in c.spec["volumeMounts"] if m["mountPath"] == "/var/run/asac/secret"]
        (volume,) = [v for v in c.pod["volumes"] if v["name"] == mount["name"]]
        assert volume["secret"]["secretName"] == "asac-token" and "subPath" not in mount


def test_tls_component_gives_each_role_its_own_secret_through_the_tls_flags(render: Any) -> None:
    """k8s/components/tls: --tls_cert/--tls_key/--tls_ca name files of a read-only mount of the Secret
    asac-tls-<role> (one per role: an actor pod never holds another role's key); servers open the
    plaintext health-only port for the probes and declare it."""
    roles = by_role(render("smoke+tls"))
    assert set(roles) == {"evolver", "learner", "replay", "actor"}
    for c in roles.values():
        net = c.config.net_config
        files = {"tls_cert": net.tls_cert, "tls_key": net.tls_key, "tls_ca": net.tls_ca}
        assert None not in files.values(), f"{c.where}: {files}"
        (mount,) = [m for m in c.spec["volumeMounts"] if Path(str(net.tls_cert)).parent == Path(m["mountPath"])]
        assert mount.get("readOnly") is True and "subPath" not in mount, f"{c.where}: {mount}"
        assert all(Path(str(f)).parent == Path(mount["mountPath"]) for f in files.values())
        assert {Path(str(f)).name for f in files.values()} == {"tls.crt", "tls.key", "ca.crt"}  # cert-manager's keys
        (volume,) = [v for v in c.pod["volumes"] if v["name"] == mount["name"]]
        assert volume["secret"]["secretName"] == f"asac-tls-{c.role}", c.where
        declared = {p["name"]: p["containerPort"] for p in c.spec.get("ports", [])}
        if c.role in SERVERS:
            assert net.health_port is not None and declared.get("health") == net.health_port, c.where
            assert net.health_port not in (c.role_port(), net.params_port), c.where
        else:
            assert "health" not in declared, c.where
    secrets = {v["secret"]["secretName"] for c in roles.values() for v in c.pod["volumes"] if "secret" in v}
    assert len(secrets) == 4, secrets


def cpus(quantity: str | int) -> int:
    text = str(quantity)
    return max(1, int(text[:-1]) // 1000) if text.endswith("m") else int(float(text))
