"""The images (Dockerfile, Dockerfile.cuda) and the lock files that they and the Makefile install from
(requirements/), read as files: every install from a lock with hashes, the dependencies before the
code, no test tooling in the runtime image, the CUDA base of the locked torch's CUDA, locks that
satisfy pyproject.toml and agree with each other, and an environment under which the image runs
as any user. ``make image-test`` (tests/image_smoke.sh) builds and runs the image itself."""

from __future__ import annotations

import ast
import importlib.metadata
import json
import re
import shlex
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml
from packaging.requirements import Requirement
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
LOCKS = ROOT / "requirements"
TORCH = "2.13.0"
TEST_TOOLING = {"pytest", "hypothesis", "ruff", "mypy", "kubernetes-validate", "cryptography"}
# Where the images keep what they write: caches under /tmp, run folders on the /data volume.
WRITABLE = {"HOME", "XDG_CACHE_HOME", "TORCH_HOME", "TORCHINDUCTOR_CACHE_DIR", "TRITON_CACHE_DIR", "NUMBA_CACHE_DIR",
            "MPLCONFIGDIR"}  # fmt: skip


# ---------------------------------------------------------------------- reading Dockerfiles


def dockerfiles() -> list[Path]:
    return sorted(ROOT.glob("Dockerfile*"))


def instructions(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, rest) per Dockerfile instruction, line continuations joined, comments dropped."""
    text = re.sub(r"\\\n", " ", "\n".join(line for line in path.read_text().splitlines() if not line.startswith("#")))
    return [(m[1].upper(), m[2].strip()) for m in re.finditer(r"^\s*(\w+)\s+(.*)$", text, re.M)]


@dataclass
class Stage:
    name: str
    base: str  # an image, or the stage it builds on
    ops: list[tuple[str, str]] = field(default_factory=list)


def stages(path: Path) -> dict[str, Stage]:
    found: dict[str, Stage] = {}
    for op, rest in instructions(path):
        if op == "FROM":
            words = rest.split()
            name = words[2] if len(words) == 3 and words[1].upper() == "AS" else str(len(found))
            found[name] = Stage(name, words[0])
        else:
            list(found.values())[-1].ops.append((op, rest))
    return found


def chain(path: Path, target: str | None = None) -> list[tuple[str, str]]:
    """The instructions that build ``target`` (default: the last stage, what ``docker build`` builds)."""
    all_stages = stages(path)
    stage = all_stages[target or list(all_stages)[-1]]
    ops = list(stage.ops)
    while stage.base in all_stages:
        stage = all_stages[stage.base]
        ops = stage.ops + ops
    return ops


def env(path: Path, target: str | None = None) -> dict[str, str]:
    """The ENV of the built image (``KEY=VALUE`` pairs; ``$PATH``-style references left as written)."""
    found: dict[str, str] = {}
    for op, rest in chain(path, target):
        if op == "ENV":
            found.update(word.split("=", 1) for word in shlex.split(rest))
    return found


def pip_installs(commands: list[str]) -> list[str]:
    """Each ``pip install`` among ``commands``, as its arguments after ``install`` (``--quiet`` dropped)."""
    found = []
    for command in commands:
        for part in command.split("&&"):
            words = shlex.split(part)
            if "pip" in words and "install" in words[words.index("pip") :]:
                args = words[words.index("install", words.index("pip")) + 1 :]
                found.append(" ".join(a for a in args if a not in ("--quiet", "-q")))
    return found


def image_installs(path: Path, target: str | None = None) -> list[str]:
    return pip_installs([rest for op, rest in chain(path, target) if op == "RUN"])


def makefile_installs() -> list[str]:
    """The pip installs of the recipe that ``make install`` (hence ``make test`` and ``make train``) runs."""
    text = (ROOT / "Makefile").read_text().replace("$(VENV)", ".venv")
    (target,) = re.findall(r"^install:\s*(\S+)", text, re.M)
    recipe = text.split(f"\n{target}:", 1)[1].split("\n\n", 1)[0]
    return pip_installs([line.strip() for line in recipe.splitlines() if line.startswith("\t")])


def image_uid() -> int:
    users = {rest for path in dockerfiles() for op, rest in instructions(path) if op == "USER"}
    assert len(users) == 1, f"the Dockerfiles run as different users: {users}"
    return int(users.pop().split(":")[0])


def image_workdir() -> str:
    (workdir,) = {rest for path in dockerfiles() for op, rest in instructions(path) if op == "WORKDIR"}
    return workdir


def image_env() -> dict[str, str]:
    """The environment every image sets for running (k8s/ relies on it)."""
    envs = [{k: v for k, v in env(path).items() if k in WRITABLE | {"ASAC_MODEL_ROOT"}} for path in dockerfiles()]
    assert all(e == envs[0] for e in envs), f"the images set different environments: {envs}"
    return envs[0]


# ---------------------------------------------------------------------- reading lock files


@dataclass(frozen=True)
class Pin:
    version: str
    hashes: tuple[str, ...]


def lock(name: str) -> dict[str, Pin]:
    """``name==version`` entries of requirements/<name>.txt with their ``--hash`` options."""
    text = (LOCKS / f"{name}.txt").read_text()
    pins = {}
    for m in re.finditer(r"^([A-Za-z0-9_.-]+)==(\S+)((?:\s*\\\n\s+--hash=sha256:[0-9a-f]{64})*)", text, re.M):
        pins[canonical(m[1])] = Pin(m[2], tuple(re.findall(r"sha256:([0-9a-f]{64})", m[3])))
    return pins


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def pyproject() -> dict[str, list[Requirement]]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extras = {k: [Requirement(r) for r in v] for k, v in project["optional-dependencies"].items()}
    return {"runtime": [Requirement(r) for r in project["dependencies"]], **extras}


# ---------------------------------------------------------------------- images


def test_there_is_a_cpu_and_a_cuda_image() -> None:
    assert [p.name for p in dockerfiles()] == ["Dockerfile", "Dockerfile.cuda"]
    cpu = stages(ROOT / "Dockerfile")
    assert list(cpu)[-1] == "runtime" and "test" in cpu, "docker build builds the runtime; --target test the tests"
    assert next(iter(stages(ROOT / "Dockerfile.cuda").values())).base.startswith("nvidia/cuda:")
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert {".git", ".venv", "models"} <= set(ignored)


def test_the_cuda_base_is_the_cuda_of_the_locked_torch() -> None:
    """torch's default wheel names its CUDA with cuda-toolkit==X.Y.*; the base image is NVIDIA's of that
    X.Y (its NVIDIA_REQUIRE_CUDA makes a node whose driver is too old refuse the container), and its
    smallest flavour, since the wheel brings every CUDA library itself."""
    toolkit = Version(lock("cuda")["cuda-toolkit"].version)
    base = next(iter(stages(ROOT / "Dockerfile.cuda").values())).base
    tag = base.split(":", 1)[1]
    assert Version(tag.split("-")[0]).release[:2] == toolkit.release[:2], f"{base}: torch needs CUDA {toolkit}"
    assert "-base-" in tag, f"{base}: the runtime/cudnn flavours carry CUDA libraries the wheel brings again"


@pytest.mark.parametrize(("path", "target"), [("Dockerfile", "runtime"), ("Dockerfile", "test"),
                                              ("Dockerfile.cuda", None)])  # fmt: skip
def test_every_install_is_from_a_lock_file_before_the_code_is_copied(path: str, target: str | None) -> None:
    """Dependencies only from requirements/ with --require-hashes, in layers that only the lock files
    feed (a code change reuses them); then the package itself, with nothing resolved."""
    ops = chain(ROOT / path, target)
    runs = [i for i, (op, _) in enumerate(ops) if op == "RUN" and pip_installs([ops[i][1]])]
    *deps, package = runs
    assert pip_installs([ops[package][1]]) == ["--no-deps --no-build-isolation -e ."]
    for i in deps:
        (args,) = pip_installs([ops[i][1]])
        assert re.fullmatch(r"--require-hashes (--no-deps )?-r requirements/[\w-]+\.txt", args), f"{path}: {args}"
        copies = [rest for op, rest in ops[:i] if op in ("COPY", "ADD")]
        assert all(all(w.startswith("requirements/") for w in c.split()[:-1]) for c in copies), (
            f"{path}: {copies} before the dependencies: any code change would install them again"
        )
    code = [rest for op, rest in ops[deps[-1] : package] if op == "COPY"]
    assert code and not all(w.startswith("requirements/") for c in code for w in c.split()[:-1]), path


def test_make_install_installs_what_the_test_image_installs_in_its_order() -> None:
    assert makefile_installs() == image_installs(ROOT / "Dockerfile", "test")
    assert image_installs(ROOT / "Dockerfile", "runtime") == [
        "--require-hashes --no-deps -r requirements/torch-cpu.txt",
        "--require-hashes -r requirements/runtime.txt",
        "--no-deps --no-build-isolation -e .",
    ]
    assert image_installs(ROOT / "Dockerfile.cuda") == [
        "--require-hashes -r requirements/cuda.txt",
        "--no-deps --no-build-isolation -e .",
    ]


def test_the_runtime_images_carry_no_test_tooling() -> None:
    for name in ("runtime", "cuda", "torch-cpu"):
        assert not TEST_TOOLING & lock(name).keys(), f"requirements/{name}.txt: {TEST_TOOLING & lock(name).keys()}"
    assert lock("test").keys() >= TEST_TOOLING
    for path, target in (("Dockerfile", "runtime"), ("Dockerfile.cuda", None)):
        copies = [rest for op, rest in chain(ROOT / path, target) if op == "COPY"]
        assert not [c for c in copies if c.split()[0] in (".", "tests")], f"{path}: copies the tests: {copies}"


@pytest.mark.parametrize("path", dockerfiles(), ids=lambda p: p.name)
def test_image_runs_main_ds_as_a_non_root_user(path: Path) -> None:
    ops = dict(chain(path))  # the last of each
    assert json.loads(ops["ENTRYPOINT"]) == ["python", "main_ds.py"], "exec form: python gets SIGTERM itself"
    assert json.loads(ops["CMD"]) == ["--help"]
    assert image_uid() > 0 and ops["USER"].split(":")[0].isdigit(), "numeric, so runAsNonRoot can check it"
    assert ops["WORKDIR"] == image_workdir()


@pytest.mark.parametrize("path", dockerfiles(), ids=lambda p: p.name)
def test_image_runs_without_extra_environment(path: Path) -> None:
    """As any user, on a read-only root file system with /tmp writable: home and caches under /tmp
    (numba cannot load the sum tree without a writable cache), run folders on the declared /data
    volume, which the image's user owns."""
    values = env(path)
    assert values.keys() >= WRITABLE, f"{path.name}: sets no {WRITABLE - values.keys()}"
    assert all(Path(values[k]).is_relative_to("/tmp") for k in WRITABLE), values
    volumes = [json.loads(rest) if rest.startswith("[") else rest.split() for op, rest in chain(path) if op == "VOLUME"]
    assert [v for vs in volumes for v in vs] == ["/data"], f"{path.name}: declares {volumes}"
    assert Path(values["ASAC_MODEL_ROOT"]).is_relative_to("/data")
    runs = " ".join(rest for op, rest in chain(path) if op == "RUN")
    assert f"chown -R {image_uid()}:{image_uid()} /data" in runs, f"{path.name}: /data must be the user's"


def test_k8s_sets_the_images_environment() -> None:
    """k8s/base's asac-env ConfigMap repeats the image's cache settings (kept so a pod spec shows them);
    they must not drift apart."""
    kustomization = yaml.safe_load((ROOT / "k8s" / "base" / "kustomization.yaml").read_text())
    (generator,) = [g for g in kustomization["configMapGenerator"] if g["name"] == "asac-env"]
    literals = dict(line.split("=", 1) for line in generator["literals"])
    assert literals == {k: v for k, v in image_env().items() if k in WRITABLE}


# ---------------------------------------------------------------------- lock files


def test_every_locked_package_has_an_exact_version_and_hashes() -> None:
    for name in ("runtime", "test", "cuda", "torch-cpu"):
        pins = lock(name)
        assert pins, name
        text = (LOCKS / f"{name}.txt").read_text()
        entries = re.findall(r"^[A-Za-z0-9][A-Za-z0-9_.-]*[=<>~!@ ]", text, re.M)
        assert len(entries) == len(pins), f"requirements/{name}.txt: an entry without '==' and hashes"
        assert all(p.hashes for p in pins.values()), f"requirements/{name}.txt: entries without a hash"


@pytest.mark.parametrize(("name", "groups"), [("runtime", ["runtime"]), ("test", ["runtime", "test"]),
                                              ("cuda", ["runtime"])])  # fmt: skip
def test_the_lock_files_satisfy_pyproject(name: str, groups: list[str]) -> None:
    """Run requirements/update.sh after changing pyproject.toml's dependencies."""
    pins = lock(name)
    python = "3.12" if name == "cuda" else "3.11"
    for group in groups:
        for req in pyproject()[group]:
            if req.marker is not None and not req.marker.evaluate({"python_version": python}):
                continue
            pin = pins.get(canonical(req.name))
            assert pin is not None, f"requirements/{name}.txt lacks {req.name}: run requirements/update.sh"
            assert req.specifier.contains(Version(pin.version), prereleases=True), (
                f"requirements/{name}.txt: {req.name}=={pin.version} is not {req.specifier}: run requirements/update.sh"
            )


def test_the_runtime_lock_provides_every_package_the_code_imports() -> None:
    """What algorithm/, ds/, envs/, protos/ and the launchers import is in the runtime image, not only in
    the test extra (scipy was, and the runtime image could not start)."""
    ours = {"algorithm", "ds", "envs", "protos", "main", "main_ds", "cli"}
    distributions = importlib.metadata.packages_distributions()
    runtime = lock("runtime")
    launchers = [ROOT / "main.py", ROOT / "main_ds.py", ROOT / "cli.py"]
    files = [*launchers, *(p for d in sorted(ours) for p in (ROOT / d).rglob("*.py"))]
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            else:
                continue
            for top in {name.split(".")[0] for name in names} - ours - set(sys.stdlib_module_names):
                providers = {canonical(d) for d in distributions.get(top, [])}
                assert providers & runtime.keys(), (
                    f"{path.relative_to(ROOT)} imports {top} ({providers or 'not installed'}): not in "
                    "requirements/runtime.txt; add it to pyproject.toml's dependencies"
                )


def test_torch_is_the_cpu_build_for_cpu_and_the_cuda_build_for_cuda() -> None:
    assert lock("runtime")["torch"] == lock("test")["torch"] == lock("torch-cpu")["torch"]
    assert lock("runtime")["torch"].version == f"{TORCH}+cpu"
    assert lock("cuda")["torch"].version == TORCH
    assert f'"torch=={TORCH}"' in (ROOT / "pyproject.toml").read_text()
    assert not [p for p in lock("runtime") if p.startswith(("nvidia-", "cuda-")) or p == "triton"]
    assert "--extra-index-url https://download.pytorch.org/whl/cpu" in (LOCKS / "torch-cpu.txt").read_text()


def test_the_images_and_make_install_share_every_version() -> None:
    """A run's CPU and CUDA roles, and the test venv, run the same versions; only torch's build differs."""
    runtime, test, cuda = lock("runtime"), lock("test"), lock("cuda")
    assert {k: v.version for k, v in test.items() if k in runtime} == {k: v.version for k, v in runtime.items()}
    shared = (runtime.keys() & cuda.keys()) - {"torch"}
    assert {k: cuda[k].version for k in shared} == {k: runtime[k].version for k in shared}
    assert runtime.keys() - cuda.keys() == set(), "the CUDA image lacks packages the CPU image has"


def test_readme_says_how_installs_are_locked_and_updated() -> None:
    setup = (ROOT / "README.md").read_text().split("## Set up", 1)[1].split("\n## ", 1)[0]
    assert "requirements/" in setup and "make lock" in setup
    assert f"`{TORCH}`" in setup
