"""Checkpoint files: atomic writes, keep-last-K, clear errors on bad files, RNG round trip."""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import pytest
import torch

from algorithm import checkpoint as ck
from algorithm.files import atomic_write


def test_keep_last_k_and_latest(tmp_path: Path) -> None:
    for step in (10, 20, 30, 40):
        ck.save_checkpoint(tmp_path, step, {"w": torch.full((2,), float(step))}, keep=2)
    assert ck.list_checkpoints(tmp_path) == [30, 40]
    assert ck.checkpoint_path(tmp_path) == tmp_path / "40.pt"
    assert float(ck.load_checkpoint(ck.checkpoint_path(tmp_path, 30))["w"][0]) == 30.0
    assert not list(tmp_path.glob(".*.tmp"))


def test_failed_write_keeps_previous_checkpoint(tmp_path: Path) -> None:
    ck.save_checkpoint(tmp_path, 5, {"w": torch.ones(3)}, keep=3)
    before = (tmp_path / "5.pt").read_bytes()

    def explode(_f: object) -> None:
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(tmp_path / "5.pt", explode)
    assert (tmp_path / "5.pt").read_bytes() == before
    assert not list(tmp_path.glob(".*.tmp"))


def test_missing_step_lists_available(tmp_path: Path) -> None:
    ck.save_checkpoint(tmp_path, 7, {}, keep=3)
    with pytest.raises(ck.CheckpointError, match=r"no checkpoint for step 8 .*available: \[7\]"):
        ck.checkpoint_path(tmp_path, 8)
    with pytest.raises(ck.CheckpointError, match="no checkpoint in"):
        ck.checkpoint_path(tmp_path / "empty")


@pytest.mark.parametrize("content", [b"", b"not a checkpoint at all", b"PK\x03\x04garbage"])
def test_corrupt_files_are_named(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "3.pt"
    path.write_bytes(content)
    with pytest.raises(ck.CheckpointError, match=str(path)):
        ck.load_checkpoint(path)


def test_foreign_torch_file_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "1.pt"
    torch.save({"weights": torch.zeros(1)}, path)
    with pytest.raises(ck.CheckpointError, match="not an ASAC checkpoint"):
        ck.load_checkpoint(path)


def test_pickled_code_is_not_executed(tmp_path: Path) -> None:
    class Boom:
        def __reduce__(self) -> tuple:
            return (Path.touch, (tmp_path / "pwned",))

    path = tmp_path / "2.pt"
    torch.save({"format_version": ck.FORMAT_VERSION, "x": Boom()}, path)
    with pytest.raises(ck.CheckpointError):
        ck.load_checkpoint(path)
    assert not (tmp_path / "pwned").exists()


def test_rng_round_trip_through_a_checkpoint(tmp_path: Path) -> None:
    ck.save_checkpoint(tmp_path, 1, {"rng": ck.capture_rng()}, keep=1)
    expected = (random.random(), np.random.rand(), torch.rand(1).item())  # noqa: NPY002
    ck.restore_rng(ck.load_checkpoint(tmp_path / "1.pt")["rng"])
    assert (random.random(), np.random.rand(), torch.rand(1).item()) == expected  # noqa: NPY002
