"""Checkpoint files: atomic writes, keep-last-K, clear errors on bad or damaged files (a digest catches
flipped bytes torch.load would take), contents that do not fit, RNG round trip."""

from __future__ import annotations

import random
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from algorithm.files import atomic_write
from algorithm.run import checkpoint as ck


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


def _flip_or_cut(data: bytes, how: str, at: int, xor: int) -> bytes:
    if how == "cut":
        return data[: at % len(data)]
    damaged = bytearray(data)
    damaged[at % len(data)] ^= xor
    return bytes(damaged)


@settings(max_examples=60, deadline=None)
@given(how=st.sampled_from(["cut", "flip"]), at=st.integers(0, 10**6), xor=st.integers(1, 255))
def test_a_damaged_checkpoint_is_an_error_naming_it_or_loads_unchanged(how: str, at: int, xor: int) -> None:
    """torch.load checks no CRCs: without the digest most flips load other weights without a word."""
    with tempfile.TemporaryDirectory() as folder:
        state = {"w": torch.linspace(-1.0, 1.0, 300), "counters": {"env_steps": 40, "rate": 0.5}, "name": "x"}
        good = ck.save_checkpoint(Path(folder), 40, state, keep=1).read_bytes()
        path = Path(folder) / "50.pt"
        path.write_bytes(_flip_or_cut(good, how, at, xor))
        try:
            loaded = ck.load_checkpoint(path)
        except ck.CheckpointError as e:
            assert str(path) in str(e)
        else:
            assert loaded.keys() == {"format_version", *state} and torch.equal(loaded["w"], state["w"])
            assert (loaded["counters"], loaded["name"]) == (state["counters"], state["name"])
        assert path.read_bytes() == _flip_or_cut(good, how, at, xor)  # reading never writes


def test_a_checkpoint_of_format_1_without_digest_still_loads(tmp_path: Path) -> None:
    path = tmp_path / "1.pt"
    torch.save({"format_version": 1, "w": torch.ones(2)}, path)
    assert torch.equal(ck.load_checkpoint(path)["w"], torch.ones(2))
    torch.save({"format_version": ck.FORMAT_VERSION, "w": torch.ones(2)}, path)
    with pytest.raises(ck.CheckpointError, match="digest is missing"):
        ck.load_checkpoint(path)


def test_contents_that_do_not_fit_are_an_error_naming_the_file(tmp_path: Path) -> None:
    model = torch.nn.Linear(3, 2)
    path = ck.save_checkpoint(tmp_path, 1, {"model": torch.nn.Linear(4, 2).state_dict()}, keep=1)
    state = ck.load_checkpoint(path)
    with pytest.raises(ck.CheckpointError, match=re.escape(f"checkpoint {path} does not fit")) as e, ck.restoring(path):
        model.load_state_dict(state["model"])
    assert "size mismatch for weight" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(ck.CheckpointError, match="KeyError: 'sac'"), ck.restoring(path):
        state["sac"]
