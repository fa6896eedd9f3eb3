"""The import direction of ARCHITECTURE.md 2: algorithm imports nothing of ours but itself, envs only
algorithm.spaces, and nothing imports main*.py."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OURS = ("algorithm", "envs", "ds", "protos", "main", "main_ds")


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
            bad = {n for n in imported_packages(path) if n.split(".")[0] in ("main", "main_ds")}
            assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_protos_import_only_protos() -> None:
    for path in (ROOT / "protos").rglob("*.py"):
        bad = {n for n in imported_packages(path) if not n.startswith("protos")}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_only_roles_composes_the_network_with_the_envs() -> None:
    """ARCHITECTURE.md 2: only main*.py and ds/roles.py compose everything; the other ds/ modules are
    transports and role loops over algorithm/ interfaces (envs arrive as factories)."""
    for path in (ROOT / "ds").rglob("*.py"):
        if path.name == "roles.py":
            continue
        bad = {n for n in imported_packages(path) if n.startswith("envs") or n == "ds.roles"}
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"
