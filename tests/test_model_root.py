"""A model root the process cannot write (issue 17, item 5): ``main.py`` and every ``main_ds.py`` role
end with one line ``error: ...`` naming the path and what to do, exit code 2, before anything starts,
rather than a PermissionError traceback (the image's root-owned /opt/asac, a volume mounted for
another user, a read-only mount, a file in the way). Real processes, as a user runs them."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1"}
ENV.pop("ASAC_MODEL_ROOT", None)


def run(script: str, *args: str, cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(ROOT / script), *args], cwd=cwd, env=env or ENV,
                          capture_output=True, text=True, timeout=120)  # fmt: skip


def assert_one_line_error(done: subprocess.CompletedProcess[str], model_root: Path, culprit: Path) -> None:
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2, done.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith("error: "), done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    assert f"under {model_root}: {culprit} " in lines[0], lines[0]  # the root given, and the path in the way
    assert "--model_root" in lines[0] and "writable" in lines[0], lines[0]  # what to do


COMMANDS = {
    "main.py": ("main.py", "gym/pendulum"),
    "replay": ("main_ds.py", "gym/pendulum", "replay"),
    "learner": ("main_ds.py", "gym/pendulum", "learner"),
    "actor": ("main_ds.py", "gym/pendulum", "actor"),
    "evolver": ("main_ds.py", "gym/pendulum", "evolver"),
    "local": ("main_ds.py", "gym/pendulum", "local", "--actors", "1"),
}


@pytest.mark.parametrize("command", COMMANDS, ids=str)
def test_a_file_in_the_way_is_a_one_line_error(command: str, tmp_path: Path) -> None:
    """Works for root too (a regular file cannot hold folders, whatever the permissions)."""
    blocker = tmp_path / "data"
    blocker.write_text("not a folder")
    root = blocker / "models"
    done = run(*COMMANDS[command], "--model_root", str(root), "--no_progress", cwd=tmp_path)
    assert_one_line_error(done, root, blocker)
    assert blocker.read_text() == "not a folder"


def test_the_default_from_asac_model_root_is_checked_too(tmp_path: Path) -> None:
    """The images set ASAC_MODEL_ROOT (/data/models) rather than passing --model_root."""
    blocker = tmp_path / "data"
    blocker.write_text("")
    done = run("main_ds.py", "gym/pendulum", "replay", cwd=tmp_path, env={**ENV, "ASAC_MODEL_ROOT": str(blocker)})
    assert_one_line_error(done, blocker, blocker)


@pytest.fixture
def read_only_folder(tmp_path: Path) -> Iterator[Path]:
    """A folder this process cannot write: a read-only bind mount as root (root writes through any
    mode bits), mode 0555 otherwise."""
    folder = tmp_path / "volume"
    folder.mkdir()
    if os.geteuid() != 0:
        folder.chmod(0o555)
        yield folder
        folder.chmod(0o755)
        return
    bind = ["mount", "--bind", str(folder), str(folder)]
    if subprocess.run(bind, capture_output=True).returncode != 0:
        pytest.skip("running as root without the right to bind-mount: no way to make a folder root cannot write")
    try:
        remount = subprocess.run(["mount", "-o", "remount,bind,ro", str(folder)], capture_output=True, text=True)
        assert remount.returncode == 0, remount.stderr
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


@pytest.mark.parametrize("command", ["main.py", "replay", "local"], ids=str)
def test_a_read_only_model_root_is_a_one_line_error(command: str, read_only_folder: Path, tmp_path: Path) -> None:
    root = read_only_folder / "models"
    done = run(*COMMANDS[command], "--model_root", str(root), "--no_progress", cwd=tmp_path)
    assert_one_line_error(done, root, read_only_folder)
    assert not root.exists()
