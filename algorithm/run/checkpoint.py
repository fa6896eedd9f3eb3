"""Atomic checkpoints in ``<run>/model/<step>.pt``, keeping the last K.

A checkpoint is a plain dict of tensors, numbers, strings and containers (loaded with
``torch.load(weights_only=True)``, so a file from elsewhere cannot run code). It is written to a
temp file in the same folder, fsynced and renamed, so a crash mid-write leaves the previous
checkpoint intact and never a half-written ``<step>.pt``. What such a crash leaves is a temp file
(``.<step>.pt.*.tmp``): never taken for a checkpoint, and deleted by the next save.

Each checkpoint carries a SHA-256 digest of its contents, checked on load: ``torch.load`` checks no
CRCs, and of the single-byte flips of a small checkpoint about 70% loaded without an error, most of
them with other weights (measured flipping every byte of one). A damaged file is a
:class:`CheckpointError` naming it; nothing falls back to an older checkpoint silently.

Usage::

    save_checkpoint(run / "model", env_steps, {"sac": sac.state_dict(), ...}, keep=3)
    path = checkpoint_path(run / "model")          # the latest, or CheckpointError
    state = load_checkpoint(path)                  # verified, or CheckpointError naming the file
    with restoring(path):                          # contents that do not fit: CheckpointError too
        sac.load_state_dict(state["sac"])
"""

from __future__ import annotations

import hashlib
import random
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch

# CheckpointError is defined in algorithm/errors.py (importable without torch), raised here and
# importable from here as before.
from algorithm.errors import CheckpointError as CheckpointError
from algorithm.files import atomic_write

# 2: with a digest of the contents. Checkpoints of format 1 (no digest) still load.
FORMAT_VERSION = 2
_READABLE_VERSIONS = (1, 2)
_DIGEST = "digest"
_NAME = re.compile(r"^(\d+)\.pt$")
_TEMP = re.compile(r"^\.\d+\.pt\..*\.tmp$")  # algorithm/files.py's temp names for <step>.pt


def list_checkpoints(model_dir: Path) -> list[int]:
    """Steps of the checkpoints in ``model_dir``, ascending."""
    if not model_dir.is_dir():
        return []
    return sorted(int(m.group(1)) for p in model_dir.iterdir() if (m := _NAME.match(p.name)))


def save_checkpoint(model_dir: Path, step: int, state: dict[str, Any], keep: int) -> Path:
    """Write ``state`` (with its digest) as ``<model_dir>/<step>.pt`` atomically, then delete all but
    the last ``keep`` checkpoints and the temp files of saves that were killed mid-write (one process
    writes a run's checkpoints)."""
    path = model_dir / f"{step}.pt"
    contents = {"format_version": FORMAT_VERSION, **state}
    contents[_DIGEST] = content_digest(contents)
    atomic_write(path, lambda f: torch.save(contents, f))
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
    """The contents :func:`save_checkpoint` wrote (without the digest), verified against the digest.
    :class:`CheckpointError` names the file when it is missing, unreadable, damaged or not ours."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {path} does not exist") from None
    except Exception as e:  # torch raises several types for corrupt or foreign files
        raise CheckpointError(f"checkpoint {path} is unreadable or not an ASAC checkpoint: {e}") from None
    if not isinstance(state, dict) or state.get("format_version") not in _READABLE_VERSIONS:
        raise CheckpointError(
            f"checkpoint {path} is not an ASAC checkpoint of format {FORMAT_VERSION} "
            f"(found {state.get('format_version') if isinstance(state, dict) else type(state).__name__})"
        )
    digest = state.pop(_DIGEST, None)
    if digest is None and state["format_version"] != 1:
        raise CheckpointError(f"checkpoint {path} is damaged: its digest is missing")
    try:
        actual = content_digest(state)
    except TypeError as e:
        raise CheckpointError(f"checkpoint {path} is damaged: {e}") from None
    if digest is not None and digest != actual:
        raise CheckpointError(f"checkpoint {path} is damaged: its contents do not match the digest written with them")
    return state


def load_for_resume(model_dir: Path, step: int | None = None) -> tuple[Path, dict[str, Any]]:
    """The path and contents of checkpoint ``step`` (None: the latest) to resume from or play. When
    the latest is damaged the error says so and names the older ones to pass as ``--ckpt``: a run
    never falls back to an older checkpoint by itself, which would silently throw the newer work away."""
    path = checkpoint_path(model_dir, step)
    try:
        return path, load_checkpoint(path)
    except CheckpointError as e:
        older = [s for s in list_checkpoints(model_dir) if s < int(path.stem)]
        if step is not None or not older:
            raise
        raise CheckpointError(
            f"{e}; nothing was overwritten: to use an older checkpoint, pass --ckpt {older[-1]} (older ones: {older})"
        ) from None


@contextmanager
def restoring(path: Path) -> Iterator[None]:
    """Around code that installs a loaded checkpoint: contents that do not fit (a missing key, a
    tensor of another shape, a value of another type: a file of another task or model) become a
    :class:`CheckpointError` naming ``path``, on one line."""
    try:
        yield
    except (KeyError, IndexError, TypeError, ValueError, RuntimeError) as e:
        reason = " ".join(f"{type(e).__name__}: {e}".split())
        raise CheckpointError(f"checkpoint {path} does not fit this run's models and state ({reason})") from None


def content_digest(state: dict[str, Any]) -> str:
    """SHA-256 over the contents of a checkpoint dict (tensors by dtype, shape and bytes; containers,
    numbers and strings by type and value), in dict order, which a save/load round trip keeps."""
    h = hashlib.sha256()
    _feed(h, state)
    return h.hexdigest()


def _feed(h: Any, value: Any) -> None:
    if isinstance(value, torch.Tensor):
        flat = value.detach().to("cpu").contiguous().reshape(-1)
        h.update(f"T{flat.dtype}{list(value.shape)};".encode())
        h.update(flat.view(torch.uint8).numpy())
    elif isinstance(value, dict):
        h.update(f"D{len(value)};".encode())
        for key, item in value.items():
            _feed(h, key)
            _feed(h, item)
    elif isinstance(value, list | tuple):
        h.update(f"{type(value).__name__}{len(value)};".encode())
        for item in value:
            _feed(h, item)
    elif isinstance(value, str | bytes):
        raw = value.encode() if isinstance(value, str) else value
        h.update(f"{type(value).__name__}{len(raw)};".encode() + raw)
    elif value is None or isinstance(value, bool | int | float | np.generic):
        h.update(f"{type(value).__name__}:{value!r};".encode())
    else:
        raise TypeError(f"a checkpoint cannot hold a {type(value).__name__}")


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
