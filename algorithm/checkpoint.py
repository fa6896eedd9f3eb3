"""Atomic checkpoints in ``<run>/model/<step>.pt``, keeping the last K.

A checkpoint is a plain dict of tensors, numbers, strings and containers (loaded with
``torch.load(weights_only=True)``, so a file from elsewhere cannot run code). It is written to a
temp file in the same folder, fsynced and renamed, so a crash mid-write leaves the previous
checkpoint intact and never a half-written ``<step>.pt``. What such a crash leaves is a temp file
(``.<step>.pt.*.tmp``): never taken for a checkpoint, and deleted by the next save.
"""

from __future__ import annotations

import random
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from algorithm.files import atomic_write

FORMAT_VERSION = 1
_NAME = re.compile(r"^(\d+)\.pt$")
_TEMP = re.compile(r"^\.\d+\.pt\..*\.tmp$")  # algorithm/files.py's temp names for <step>.pt


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable, or not one of ours; the message names the file."""


def list_checkpoints(model_dir: Path) -> list[int]:
    """Steps of the checkpoints in ``model_dir``, ascending."""
    if not model_dir.is_dir():
        return []
    return sorted(int(m.group(1)) for p in model_dir.iterdir() if (m := _NAME.match(p.name)))


def save_checkpoint(model_dir: Path, step: int, state: dict[str, Any], keep: int) -> Path:
    """Write ``model_dir/<step>.pt`` atomically, then delete all but the last ``keep`` checkpoints and
    the temp files of saves that were killed mid-write (one process writes a run's checkpoints)."""
    path = model_dir / f"{step}.pt"
    atomic_write(path, lambda f: torch.save({"format_version": FORMAT_VERSION, **state}, f))
    for old in list_checkpoints(model_dir)[:-keep]:
        (model_dir / f"{old}.pt").unlink(missing_ok=True)
    for leftover in (p for p in model_dir.iterdir() if _TEMP.match(p.name)):
        leftover.unlink(missing_ok=True)
    return path


def checkpoint_path(model_dir: Path, step: int | None = None) -> Path:
    """The checkpoint for ``step``, or the latest; raises :class:`CheckpointError` if there is none."""
    steps = list_checkpoints(model_dir)
    if step is None:
        if not steps:
            raise CheckpointError(f"no checkpoint in {model_dir}")
        step = steps[-1]
    elif step not in steps:
        raise CheckpointError(f"no checkpoint for step {step} in {model_dir}; available: {steps or 'none'}")
    return model_dir / f"{step}.pt"


def load_checkpoint(path: Path) -> dict[str, Any]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {path} does not exist") from None
    except Exception as e:  # torch raises several types for corrupt or foreign files
        raise CheckpointError(f"checkpoint {path} is unreadable or not an ASAC checkpoint: {e}") from None
    if not isinstance(state, dict) or state.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(
            f"checkpoint {path} is not an ASAC checkpoint of format {FORMAT_VERSION} "
            f"(found {state.get('format_version') if isinstance(state, dict) else type(state).__name__})"
        )
    return state


def capture_rng() -> dict[str, Any]:
    """Global RNG states (python, numpy legacy, torch) for exact resumption."""
    np_state: Any = np.random.get_state()  # noqa: NPY002 - the legacy global state is what we capture
    return {
        "python": random.getstate(),
        "numpy": [np_state[0], torch.from_numpy(np_state[1].astype(np.int64)), *np_state[2:]],
        "torch": torch.get_rng_state(),
    }


def restore_rng(state: dict[str, Any]) -> None:
    random.setstate(state["python"])
    name, keys, *rest = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), *rest))  # noqa: NPY002
    torch.set_rng_state(state["torch"])
