"""Files a run writes through ``atomic_write`` (checkpoints, evaluations, replay snapshots, configs)
get the mode the process's umask gives a plain ``open()``, not the 0600 of the temp file they are
made as: another user, or a container with another uid (TensorBoard beside a training pod), can
read them where the umask allows it."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
WRITE = (
    "import sys; from pathlib import Path; from algorithm.files import atomic_write; "
    "atomic_write(Path(sys.argv[1]), lambda f: f.write(b'rows'))"
)


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o027, 0o640), (0o077, 0o600)])
def test_a_written_file_has_the_mode_its_umask_gives(tmp_path: Path, umask: int, mode: int) -> None:
    path = tmp_path / "evaluations.csv"
    subprocess.run([sys.executable, "-c", WRITE, str(path)], cwd=ROOT, check=True, timeout=60,
                   preexec_fn=lambda: os.umask(umask))  # fmt: skip
    assert path.read_bytes() == b"rows"
    assert stat.S_IMODE(path.stat().st_mode) == mode, oct(path.stat().st_mode)
