"""The import direction of docs/architecture.md section 2: algorithm imports nothing of ours but
itself, envs only algorithm.spaces, nothing imports main*.py, only they import cli.py (the command-line
code they share), and they import torch only once a command is checked; and every docs/*.md
section the tree cites exists."""

from __future__ import annotations

import ast
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.role_runs import torch_is_loaded

ROOT = Path(__file__).resolve().parents[1]
OURS = ("algorithm", "envs", "ds", "protos", "cli", "main", "main_ds")


def imported_packages(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return {n for n in names if n.split(".")[0] in OURS}


def test_algorithm_imports_only_itself() -> None:
    for path in (ROOT / "algorithm").rglob("*.py"):
        bad = {n for n in imported_packages(path) if not n.startswith("algorithm")}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_envs_import_only_spaces_from_algorithm() -> None:
    for path in (ROOT / "envs").rglob("*.py"):
        if (path.parent / "config.yaml").exists():
            continue  # a task's model file (algorithm/nn/user.py): user code built on algorithm's models
        bad = {n for n in imported_packages(path) if not (n.startswith("envs") or n == "algorithm.spaces")}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_nothing_imports_the_launchers() -> None:
    for folder in ("algorithm", "envs", "ds", "tests"):
        for path in (ROOT / folder).rglob("*.py"):
            if path.name in ("test_main.py", "test_k8s.py", "test_bad_input.py"):  # they test the launchers
                continue
            bad = {n for n in imported_packages(path) if n.split(".")[0] in ("main", "main_ds", "cli")}
            assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_the_launchers_share_cli_and_not_each_other() -> None:
    """Issue 16: main_ds.py imported 14 names from main.py, a script used as a library."""
    for launcher in ("main.py", "main_ds.py"):
        imported = {n.split(".")[0] for n in imported_packages(ROOT / launcher)}
        assert "cli" in imported and not imported & {"main", "main_ds"} - {launcher[:-3]}, (launcher, imported)
    assert not {n.split(".")[0] for n in imported_packages(ROOT / "cli.py")} & {"main", "main_ds"}


# Runs a launcher as `python LAUNCHER ARGS` would, then says its exit code and whether torch was imported.
PROBE = """
import runpy, sys
sys.argv = {argv!r}
try:
    runpy.run_path({path!r}, run_name="__main__")
except SystemExit as e:
    print("exit", e.code, "torch" in sys.modules)
"""


def test_a_mistyped_command_is_answered_before_torch_is_imported() -> None:
    """main.py, main_ds.py and cli.py import torch (~3 s of CPU on a laptop core, most of a bad
    command's wait) only once the flags, the task and the config are known to be good."""
    commands = (
        ["main.py", "gym/pendlum"],
        ["main.py", "gym/pendulum", "--override", "sac.gama=0.5"],
        ["main.py", "gym/pendulum", "--device", "banana"],
        ["main_ds.py", "gym/pendulum", "replay", "--override", "sac.gama=0.5"],
        ["main_ds.py", "gym/pendulum", "actor", "--noise", "-1"],
        ["main_ds.py", "gym/pendulum", "learner", "--actors", "2"],
        ["main_ds.py", "gym/pendulum", "local", "--replay_host", "10.0.0.9"],  # local places its roles itself
        ["main.py", "gym/pendulum", "-p", "5006"],  # a flag of the original's command line
    )
    for argv in commands:
        code = PROBE.format(argv=argv, path=str(ROOT / argv[0]))
        done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert "error:" in done.stderr, (argv, done.stderr)
        assert done.stdout.split() == ["exit", "2", "False"], (argv, done.stdout, done.stderr)


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="reads /proc/PID/maps (Linux)")
@pytest.mark.parametrize("role", ["replay", "evolver"])
def test_the_replay_and_the_evolver_serve_without_importing_torch(role: str, tmp_path: Path) -> None:
    """A replay needs the table's layout (the spec, a recurrent state width) and an evolver relays
    weights as arrays: neither builds a model, so neither loads torch (a replay of Pendulum started
    in ~1.5 s of CPU and held ~140 MB instead of ~6.7 s and ~410 MB with it, docs/architecture.md
    section 2)."""
    command = [sys.executable, str(ROOT / "main_ds.py"), "gym/pendulum", role, "-n", "light", "--no_progress",
               f"--{role}_port", "0"]  # fmt: skip
    log = tmp_path / "role.log"
    with log.open("w") as out:
        proc = subprocess.Popen(command, cwd=tmp_path, stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while "serving on" not in log.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.1)
        assert not torch_is_loaded(proc.pid), f"the {role} role loaded torch"
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 130, log.read_text()


def test_protos_import_only_protos() -> None:
    for path in (ROOT / "protos").rglob("*.py"):
        bad = {n for n in imported_packages(path) if not n.startswith("protos")}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_only_the_role_compositions_compose_the_network_with_the_envs() -> None:
    """docs/architecture.md section 2: only main*.py and the role compositions (ds/<role>/role.py) compose
    everything; the other ds/ modules are transports and role loops over algorithm/ interfaces (envs arrive
    as factories), and no ds/ module imports a role's composition, not even another role's."""
    compositions = {f"ds.{role}.role" for role in ("replay", "learner", "actor", "evolver")}
    assert all((ROOT / f"{name.replace('.', '/')}.py").is_file() for name in compositions)
    for path in (ROOT / "ds").rglob("*.py"):
        envs_allowed = path.name == "role.py"
        bad = {n for n in imported_packages(path) if (n.startswith("envs") and not envs_allowed) or n in compositions}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def module_imports(path: Path) -> set[str]:
    """Our modules ``path`` depends on: its top-level imports, those under ``if TYPE_CHECKING:``
    included (a type is a dependency too), not the lazy ones inside functions."""
    names: set[str] = set()
    body = ast.parse(path.read_text()).body
    for node in list(body):
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            body.extend(node.body)
    for node in body:
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return {n for n in names if n.split(".")[0] in OURS}


# Test files of tests/algorithm/ named after a feature (a config switch) that spans several modules of the
# package whose folder holds them, so no one module's name fits.
ALGORITHM_FEATURE_TESTS = (
    "algorithm/sac/test_discrete.py",  # discrete and mixed actions: policy, equations, losses, learner
    "algorithm/sac/test_exploration.py",  # curiosity and RND: nn/exploration.py's models, trained by the learner
    "algorithm/sac/test_munchausen.py",  # munchausen_scale: equations, schedules, losses
    "algorithm/sac/test_recurrent.py",  # use_rnn: the sequence pass, burn-in, stored and refreshed states
    "algorithm/sac/test_tanh_log_det_epsilon.py",  # the policy's log-density as the learner's losses take it
    "algorithm/sac/test_train_every_step.py",  # returns, losses, learner and update_graph
    "algorithm/sac/test_update_order.py",  # joint or critic_first: losses, learner and update_graph
)


def test_the_tests_mirror_the_source() -> None:
    """A test folder below tests/ is the folder of the source it tests (tests/algorithm/replay/ for
    algorithm/replay/, tests/ds/learner/ for ds/learner/), with an ``__init__.py`` so that files of one
    name in two folders (tests/ds/replay/test_service.py, tests/ds/learner/test_service.py) are two
    modules. In tests/ds/, tests/protos/ and tests/algorithm/ each test file is named after the module it
    tests, ``test_<module>.py`` or ``test_<module>_<aspect>.py``, and tests/ds/ itself holds only what
    several of its packages share (conftest.py, fuzz.py). In tests/algorithm/ a file may instead be named
    after its own package (tests/algorithm/nn/test_nn.py) or, where a feature spans several modules of its
    package, be one of ``ALGORITHM_FEATURE_TESTS``. Tests across the packages stay in tests/."""
    tests = ROOT / "tests"
    problems = []
    for folder in sorted({p.parent for p in tests.rglob("*.py") if "__pycache__" not in p.parts}):
        if not (folder / "__init__.py").is_file():
            problems.append(f"{folder.relative_to(ROOT)} has no __init__.py")
        if folder != tests and not (ROOT / folder.relative_to(tests)).is_dir():
            problems.append(f"{folder.relative_to(ROOT)} names no source folder {folder.relative_to(tests)}/")
    mirrored = [*(tests / "ds").rglob("test_*.py"), *(tests / "protos").rglob("test_*.py")]
    for path in sorted([*mirrored, *(tests / "algorithm").rglob("test_*.py")]):
        source = ROOT / path.parent.relative_to(tests)
        name = str(path.relative_to(tests))
        if path.parent == tests / "ds":
            problems.append(f"{path.relative_to(ROOT)} belongs in the folder of the ds/ package it tests")
        elif name in ALGORITHM_FEATURE_TESTS or (name.startswith("algorithm/") and path.stem == f"test_{source.name}"):
            continue
        elif not any(path.stem == f"test_{m.stem}" or path.stem.startswith(f"test_{m.stem}_")
                     for m in source.glob("*.py")):  # fmt: skip
            problems.append(f"{path.relative_to(ROOT)} names no module of {source.relative_to(ROOT)}/")
    problems += [f"tests/{name} is listed in ALGORITHM_FEATURE_TESTS but does not exist"
                 for name in ALGORITHM_FEATURE_TESTS if not (tests / name).is_file()]  # fmt: skip
    assert not problems, "\n".join(problems)


def test_no_import_circles() -> None:
    """One direction between any two of our modules (a package's ``__init__`` re-exporting its own
    submodules aside): a circle makes import order matter and hides which module is the lower one."""
    modules = {}
    for folder in ("algorithm", "envs", "ds", "protos"):
        for path in (ROOT / folder).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph = {
        name: {m for m in module_imports(path) if m in modules and m != name and not m.startswith(name + ".")}
        for name, path in modules.items()
    }
    for name, deps in graph.items():  # a submodule importing its own package reaches its siblings through it
        graph[name] = {d for d in deps if not (name.startswith(d + ".") and modules[d].name == "__init__.py")}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(name: str) -> None:
        state[name] = 1
        stack.append(name)
        for dep in sorted(graph[name]):
            if state.get(dep) == 1:
                raise AssertionError("import circle: " + " -> ".join(stack[stack.index(dep) :] + [dep]))
            if dep not in state:
                visit(dep)
        stack.pop()
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name)


# The founding design notes lived outside the repository; the repository's own are docs/*.md.
# Spelled in pieces so that this file does not cite them itself.
_GONE = tuple(name + ".md" for name in ("ARCHITECTURE", "SPEC", "STYLE")) + ("../" + "shared",)
_SECTIONS = r"(?:,? sections? (\d+)(?:(?: and |-|, )(\d+))?)?"
_DOC = re.compile(r"\b(docs/[\w/.-]+?\.md)\b" + _SECTIONS)  # from the root, anywhere
_LINK = re.compile(r"\]\(([\w/.-]+?\.md)\)" + _SECTIONS)  # a Markdown link, from the linking file


def tracked_text_files() -> dict[str, str]:
    """Path -> text of every file git tracks (every file under the root but build and cache folders
    when this is not a git checkout); files that are not UTF-8 text are left out."""
    try:
        listing = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
        paths = [p for p in listing.decode().split("\0") if p]
    except (OSError, subprocess.CalledProcessError):
        skip = {".git", ".venv", "models", "__pycache__", ".mypy_cache", ".pytest_cache", ".ruff_cache", ".hypothesis"}
        paths = [
            str(p.relative_to(ROOT))
            for p in ROOT.rglob("*")
            if p.is_file() and not skip & set(p.relative_to(ROOT).parts) and ".egg-info" not in str(p)
        ]
    texts = {}
    for path in paths:
        try:
            data = (ROOT / path).read_bytes()
        except OSError:  # listed but deleted in this working tree
            continue
        if b"\0" in data:
            continue
        try:
            texts[path] = data.decode("utf-8")
        except UnicodeDecodeError:
            continue
    return texts


def test_docs_cited_in_the_tree_exist() -> None:
    """No file cites the design notes that are not in the repository, and every ``docs/<file>.md``
    cited (and every ``.md`` a Markdown file links to), with ``section N``, ``sections N and M`` or
    ``N-M`` after it, names a file and numbered sections (``## N. Title``) that exist."""
    headings: dict[Path, set[str]] = {}
    problems = []
    for path, text in sorted(tracked_text_files().items()):
        for n, line in enumerate(text.splitlines(), 1):
            where = f"{path}:{n}"
            problems += [f"{where} cites {gone}, which is not in the repository" for gone in _GONE if gone in line]
            cited = [(ROOT / m[1], m) for m in _DOC.finditer(line)]
            if path.endswith(".md"):
                cited += [((ROOT / path).parent / m[1], m) for m in _LINK.finditer(line)]
            for doc, match in cited:
                if not doc.is_file():
                    problems.append(f"{where} cites {match[1]}, which does not exist")
                    continue
                doc = doc.resolve()
                if doc not in headings:
                    headings[doc] = set(re.findall(r"^#+ (\d+)\. ", doc.read_text(), re.M))
                missing = [s for s in (match[2], match[3]) if s and s not in headings[doc]]
                problems += [f"{where} cites {match[1]} section {s}, which it does not have" for s in missing]
    assert not problems, "\n".join(problems)


def test_the_tree_is_formatted() -> None:
    """One formatter, ``ruff format`` (make lint runs it too); its ``# fmt: skip`` markers keep the few
    hand-aligned tables and long literals as written."""
    result = subprocess.run(
        [sys.executable, "-m", "ruff", "format", "--check", "--output-format", "concise", "."],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_every_serial_group_entry_names_a_test() -> None:
    """tests/workers.py's SERIAL table (the tests `make test` runs one at a time on one worker) names
    files and test functions that exist: a renamed test would silently leave its group."""
    from tests.workers import SERIAL

    for entries in SERIAL.values():
        for entry in entries:
            path, _, name = entry.partition("::")
            assert (ROOT / path).is_file() and path.startswith("tests/"), entry
            if name:
                tests = {n.name for n in ast.parse((ROOT / path).read_text()).body if isinstance(n, ast.FunctionDef)}
                assert name in tests, entry


def test_the_two_worker_hooks_are_registered_and_group_by_the_table() -> None:
    """The root conftest.py hands xdist tests/workers.py's hooks (a lost hook once left `make test`
    ungrouped while every test still passed), and a SERIAL entry's tests share one scope."""
    import conftest
    from tests import workers

    assert conftest.pytest_xdist_make_scheduler is workers.pytest_xdist_make_scheduler
    assert conftest.pytest_runtest_protocol is workers.pytest_runtest_protocol
    assert workers.serial_group("tests/test_soak.py::test_any[x]") == "roles"
    assert workers.serial_group("tests/test_journeys.py::test_a") == workers.serial_group("tests/test_journeys.py::b")
    assert workers.serial_group("tests/algorithm/sac/test_learner.py::test_update") is None


def test_a_two_worker_run_leaves_no_lock_files_behind(tmp_path: Path) -> None:
    """`make test`'s workers take their locks through two files in the temp folder
    (tests/workers.py); the controller removes them once the last worker is down."""
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-q", "-p",
                           "no:cacheprovider", "tests/algorithm/test_files_modes.py"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert not list(tmp_path.glob("asac-tests-*")), sorted(p.name for p in tmp_path.iterdir())
