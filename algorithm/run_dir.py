"""A run's folder, ``models/<task>/<name>/``, and what lives in it (README, "The run directory")."""

from __future__ import annotations

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
