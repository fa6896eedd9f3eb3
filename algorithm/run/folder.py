"""A run's folder, ``models/<task>/<name>/``, and what lives in it (README, "The run directory"); how the
commands that resume or play a run are shown to the user (both launchers print them)."""

from __future__ import annotations

import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

EVAL_SEED_OFFSET = 100_000  # eval envs never share seeds with training envs (env i gets seed + i)


@dataclass(frozen=True)
class RunDir:
    """``models/<task>/<name>/``: config, TensorBoard logs, checkpoints, replay snapshot, evaluations."""

    root: Path

    @property
    def config(self) -> Path:
        return self.root / "config.yaml"

    @property
    def log(self) -> Path:
        return self.root / "log"

    def role_log(self, role: str) -> Path:
        """A distributed role's TensorBoard folder, ``log/<role>``: ``learner``, ``replay``, ``evolver``,
        ``actor_<index>`` (``main.py`` writes to :attr:`log` itself)."""
        return self.log / role

    @property
    def model(self) -> Path:
        return self.root / "model"

    @property
    def replay(self) -> Path:
        return self.root / "replay" / "replay.npz"

    @property
    def evaluations(self) -> Path:
        return self.root / "evaluations.csv"

    @property
    def model_file(self) -> Path:
        """The run's copy of the task's model file (nn/user.py), when the task has one."""
        return self.root / "nn.py"


def python_command() -> str:
    """``python`` when that is this interpreter on PATH, else this interpreter's path (a venv's, say)."""
    found = shutil.which("python")
    if found is not None and Path(found).absolute() == Path(sys.executable).absolute():
        return "python"
    return shown_path(Path(sys.executable))


def shown_path(path: Path) -> str:
    """``path`` relative to the working directory when it lies inside it, else absolute."""
    absolute = Path(os.path.abspath(path))
    try:
        return str(absolute.relative_to(Path.cwd()))
    except ValueError:
        return str(absolute)
