"""The evolver's state on a real full disk (a small tmpfs filled to the last byte; root only): a save
that fails keeps the saved state and the sample files it names as they were, is logged once with
the path and the cause, never reaches the rpc that caused it, and is made again once space is back."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from ds.evolver.evolver import Evolver
from ds.evolver.state import SAMPLES_DIR, STATE_FILE, PendingSample, Role
from tests.ds.evolver.evolver_setup import evolver_config, weights_of
from tests.small_disk import small_disk


def test_a_full_disk_keeps_the_saved_state_and_the_evolver_saves_again_once_space_is_back(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with small_disk(tmp_path / "disk", "2m") as disk, caplog.at_level(logging.INFO, "asac.evolver"):
        folder = disk.path / "evolver"
        evolver = Evolver(evolver_config(), folder, "exp", lease_s=600.0)
        first = evolver.register_learner("l0", "h", 61001, 0, "replay-0:1").learner_id
        evolver.registry.pending[first] = PendingSample(first, 1, weights_of(0.5))
        assert evolver.save()
        before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
        assert folder / STATE_FILE in before and folder / SAMPLES_DIR / "learner_0.round_1.npz" in before

        disk.fill()
        second = evolver.register_learner("l1", "h", 61002, 0, "replay-1:1").learner_id  # saves: fails, not raised
        evolver.assign(Role.ACTOR, "a0")
        evolver.registry.pending[second] = PendingSample(second, 1, weights_of(1.5))
        evolver.registry.dirty = True
        assert not evolver.save()
        assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} == before  # no temp file either
        assert evolver.registry.dirty  # to be saved again
        (line,) = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
        assert line.startswith(f"could not write the evolver state {folder / STATE_FILE}: No space left on device")
        assert f"{folder / STATE_FILE} keeps its previous contents" in line

        disk.free()
        assert evolver.save()
        assert any(r.getMessage().startswith("writing the evolver state works again") for r in caplog.records)
        evolver.stop()
        revived = Evolver(evolver_config(), folder, "exp", lease_s=600.0)
        assert [x.learner_id for x in revived.info().learners] == [first, second]
        assert (folder / SAMPLES_DIR / f"learner_{second}.round_1.npz").is_file()


def test_a_final_save_that_fails_at_stop_is_logged_and_the_evolver_stops(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with small_disk(tmp_path / "disk", "2m") as disk, caplog.at_level(logging.INFO, "asac.evolver"):
        folder = disk.path / "evolver"
        evolver = Evolver(evolver_config(), folder, "exp", lease_s=600.0)
        evolver.start()
        evolver.register_learner("l0", "h", 61001, 0, "replay-0:1")
        state = (folder / STATE_FILE).read_bytes()
        disk.fill()
        evolver.register_learner("l1", "h", 61002, 0, "replay-1:1")
        evolver.stop()  # no exception: the last try is logged
        finals = [r.getMessage() for r in caplog.records if "could not write the final evolver state" in r.getMessage()]
        assert len(finals) == 1 and "No space left on device" in finals[0], finals
        assert (folder / STATE_FILE).read_bytes() == state
