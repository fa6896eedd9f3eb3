"""Each writer of the learner on a real full disk (a small tmpfs filled to the last byte; root only):
checkpoints, the in-process replay snapshot, evaluations.csv, TensorBoard summaries and the log
file. Each keeps its previous file as it was, logs once with the path and the cause, goes on, and
writes again at its next try once space is back (tests/test_full_disk.py: the same on processes)."""

from __future__ import annotations

import errno
import logging
import struct
from pathlib import Path

import pytest
import torch

from algorithm.files import WriteFailures, atomic_write
from algorithm.run.checkpoint import load_checkpoint
from algorithm.run.evaluation import read_evaluations
from algorithm.run.logging import LogFileHandler, MetricsWriter
from tests.algorithm.run.test_trainer import make_trainer, small_config
from tests.small_disk import small_disk

NO_SPACE = "No space left on device [ENOSPC]"


def errors(caplog: pytest.LogCaptureFixture, what: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR and what in r.getMessage()]


def files_of(folder: Path) -> dict[Path, bytes]:
    """Every file under ``folder`` but the append-only logs (TensorBoard's, checked on their own)."""
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file() and "tfevents" not in p.name}


def test_write_failures_log_once_per_cause_and_once_when_writing_works_again(caplog: pytest.LogCaptureFixture) -> None:
    failures = WriteFailures("widget", logging.getLogger("test.widget"), retry="trying again later")
    path = Path("/nowhere/widget.bin")

    def fail(code: int) -> None:
        raise OSError(code, "simulated")

    with caplog.at_level(logging.DEBUG, "test.widget"):
        for _ in range(3):
            assert not failures.attempt(path, lambda: fail(errno.ENOSPC))
        assert not failures.attempt(path, lambda: fail(errno.EIO))  # another cause: said once too
        assert not failures.attempt(path, lambda: fail(errno.ENOSPC))
        assert failures.failing and failures.failures == 5
        assert failures.attempt(path, lambda: None) and not failures.failing
        assert not failures.attempt(path, lambda: fail(errno.ENOSPC))  # failing again after a success: said again
    said = [(r.levelname, r.getMessage()) for r in caplog.records if r.levelno >= logging.INFO]
    assert said == [
        ("ERROR", "could not write the widget /nowhere/widget.bin: simulated [ENOSPC]; /nowhere/widget.bin was not "
                  "created; trying again later (logged once until it works again)"),
        ("ERROR", "could not write the widget /nowhere/widget.bin: simulated [EIO]; /nowhere/widget.bin was not "
                  "created; trying again later (logged once until it works again)"),
        ("INFO", "writing the widget works again (/nowhere/widget.bin), after 5 failed attempts"),
        ("ERROR", "could not write the widget /nowhere/widget.bin: simulated [ENOSPC]; /nowhere/widget.bin was not "
                  "created; trying again later (logged once until it works again)"),
    ]  # fmt: skip
    with pytest.raises(ValueError):  # not an I/O error: a bug, raised as it is
        failures.attempt(path, lambda: int("x"))


@pytest.mark.parametrize("left", [0, 65536])
def test_torch_save_on_a_full_disk_fails_as_the_os_error_and_keeps_the_previous_file(tmp_path: Path, left: int) -> None:
    """A disk that fills up during torch.save (64 kB left of the 400 kB it writes) makes its zip
    writer raise a RuntimeError ("unexpected pos ..."), the cause lost; atomic_write raises the
    OSError it saw instead, so that a full disk is told from a bug."""
    with small_disk(tmp_path / "disk", "1m") as disk:
        path = disk.path / "state.pt"
        atomic_write(path, lambda f: torch.save({"w": torch.zeros(10)}, f))
        before = path.read_bytes()
        disk.fill(leave=left)
        with pytest.raises(OSError) as raised:
            atomic_write(path, lambda f: torch.save({"w": torch.zeros(100_000)}, f))
        assert raised.value.errno == errno.ENOSPC
        assert path.read_bytes() == before
        assert sorted(p.name for p in disk.path.iterdir()) == ["filler", "state.pt"]  # no temp file left


def test_the_trainer_keeps_its_files_on_a_full_disk_and_saves_again_once_space_is_back(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    config = small_config("replay.save_replay=true", "eval.eval_per_step=100", "base.max_step=2000")
    with small_disk(tmp_path / "disk", "8m") as disk, caplog.at_level(logging.INFO):
        run = disk.path / "run"
        trainer = make_trainer(config, run)
        trainer.run(until_step=150)  # an evaluation at 100
        assert trainer.save() == run / "model/150.pt"
        before = files_of(run)
        assert {run / "model/150.pt", run / "replay/replay.npz", run / "evaluations.csv"} <= set(before)

        disk.fill()
        caplog.clear()
        trainer.run(until_step=350)  # evaluations at 200 and 300 are not written; training goes on
        assert trainer.save() is None and trainer.save() is None
        assert trainer.env_steps == 350 and trainer.updates > 0
        assert files_of(run) == before  # nothing changed, nothing added (no temp file left behind)
        said = {}
        for what in ("checkpoint", "replay snapshot", "evaluations"):
            (said[what],) = errors(caplog, f"could not write the {what} ")
            assert NO_SPACE in said[what] and str(run) in said[what], said[what]
        assert f"the checkpoints before it are kept (the latest: {run}/model/150.pt)" in said["checkpoint"]
        assert f"{run}/replay/replay.npz keeps the previous snapshot" in said["replay snapshot"]
        assert len(errors(caplog, "TensorBoard")) <= 1

        disk.free()
        caplog.clear()
        trainer.run(until_step=400)  # the evaluation at 400 writes the rows held since 200
        assert trainer.save() == run / "model/400.pt"
        assert load_checkpoint(run / "model/400.pt")["counters"]["env_steps"] == 400
        assert [r["env_steps"] for r in read_evaluations(run / "evaluations.csv")] == [100, 200, 300, 400]
        lines = [r.getMessage() for r in caplog.records]
        for what in ("checkpoint", "replay snapshot", "evaluations"):
            assert any(m.startswith(f"writing the {what} works again") for m in lines), (what, lines)
        assert not errors(caplog, "")
        resumed = make_trainer(config, run)  # what was saved after the disk was full is whole
        assert resumed.env_steps == 400 and resumed.table.info()["inserted_steps"] == 400


def test_a_final_checkpoint_that_fails_is_logged_and_the_run_ends_as_usual(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    config = small_config("eval.eval_per_step=100", "base.max_step=300")
    with small_disk(tmp_path / "disk", "8m") as disk, caplog.at_level(logging.INFO):
        run = disk.path / "run"
        trainer = make_trainer(config, run)
        trainer.run(until_step=150)
        assert trainer.save() == run / "model/150.pt"
        before = files_of(run)
        disk.fill()
        summary = trainer.run()  # to max_step: the evaluations at 200 and 300 and the final checkpoint fail
        assert summary.env_steps == 300 and not summary.interrupted and summary.last_eval_mean is not None
        assert files_of(run) == before
        finals = [m for m in errors(caplog, "at shutdown") if "TensorBoard" not in m]
        assert finals == [
            f"could not write the final evaluations {run}/evaluations.csv at shutdown: {NO_SPACE}; "
            f"{run}/evaluations.csv keeps its rows",
            f"could not write the final checkpoint {run}/model/300.pt at shutdown: {NO_SPACE}; the checkpoints "
            f"before it are kept (the latest: {run}/model/150.pt)",
        ], finals
        assert f"2 evaluation rows are not in {run}/evaluations.csv" in " ".join(errors(caplog, "evaluation rows"))
        (summaries,) = errors(caplog, "could not write the final TensorBoard summaries")
        assert NO_SPACE in summaries and "keeps the summaries written before, readable" in summaries
        (lost,) = errors(caplog, "TensorBoard summaries held in memory")
        assert lost.endswith(" are lost")


def whole_records(data: bytes) -> int:
    """The number of TFRecords ``data`` holds, asserting it ends at a record's end (none torn)."""
    offset, count = 0, 0
    while offset < len(data):
        (length,) = struct.unpack("<Q", data[offset : offset + 8])
        offset += 8 + 4 + length + 4
        count += 1
    assert offset == len(data), "a torn record at the end of the event file"
    return count


def steps_of(folder: Path, tag: str) -> list[int]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(folder), size_guidance={"scalars": 0})
    acc.Reload()
    return [e.step for e in acc.Scalars(tag)] if tag in acc.Tags()["scalars"] else []


def test_summaries_on_a_full_disk_stay_readable_and_follow_in_order_once_space_is_back(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with small_disk(tmp_path / "disk", "1m") as disk, caplog.at_level(logging.INFO):
        writer = MetricsWriter(disk.path / "log", retry_s=0.0)
        writer.text("config", "a: 1")
        for step in range(10):
            writer.write({"x": float(step)}, step)
        written = writer.path.read_bytes()
        disk.fill()
        for step in range(10, 600):  # ~40 kB: past what the file's last page can take
            writer.write({"x": float(step), "y": -float(step)}, step)
        (line,) = errors(caplog, "could not write the TensorBoard summaries")
        assert NO_SPACE in line and str(writer.path) in line
        now = writer.path.read_bytes()
        assert now.startswith(written) and whole_records(now) >= 12  # the version, the text, 10 scalars
        readable = steps_of(disk.path / "log", "x")
        assert readable == list(range(len(readable))) and len(readable) >= 10

        disk.free()
        writer.write({"x": 600.0}, 600)
        writer.close()
        assert steps_of(disk.path / "log", "x") == list(range(601))  # the held ones too, in order
        assert steps_of(disk.path / "log", "y") == list(range(10, 600))
        assert any(r.getMessage().startswith("writing the TensorBoard summaries works again") for r in caplog.records)
        assert len(errors(caplog, "")) == 1


def test_summaries_held_past_the_bound_are_dropped_oldest_first_and_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with small_disk(tmp_path / "disk", "1m") as disk, caplog.at_level(logging.INFO):
        writer = MetricsWriter(disk.path / "log", retry_s=3600.0, max_pending_bytes=2000)
        writer.write({"x": 0.0}, 0)
        disk.fill()
        step = 1
        while not writer.dropped:  # the page's slack first, then held, then dropped
            writer.write({"x": float(step)}, step)
            step += 1
        for _ in range(50):
            writer.write({"x": float(step)}, step)
            step += 1
        disk.free()
        writer.close()  # the last try ignores retry_s
        steps = steps_of(disk.path / "log", "x")
        assert steps == sorted(steps) and steps[-1] == step - 1 and len(steps) == step - writer.dropped
        assert any(f"{writer.dropped} TensorBoard summaries were dropped" in r.getMessage() for r in caplog.records)


def test_a_log_file_on_a_full_disk_is_one_line_on_stderr_and_whole_lines_in_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with small_disk(tmp_path / "disk", "1m") as disk:
        path = disk.path / "log.txt"
        handler = LogFileHandler(path)
        logger = logging.getLogger("test.full_disk.log_file")
        logger.addHandler(handler)
        logger.propagate, logger.level = False, logging.INFO
        try:
            logger.info("before the disk is full")
            before = path.read_bytes()
            disk.fill()
            for i in range(300):  # ~30 kB
                logger.info("line %d %s", i, "x" * 100)
            err = capsys.readouterr().err
            assert err.count("could not write the log file") == 1, err
            assert f"could not write the log file {path}: {NO_SPACE}" in err
            assert "Traceback" not in err and "Logging error" not in err
            now = path.read_bytes()
            assert now.startswith(before) and now.endswith(b"\n") and handler.missed > 0
            disk.free()
            logger.info("after")
            text = path.read_text()
            assert "log records before this one could not be written here; see stderr)\nafter\n" in text
            assert text.endswith("after\n") and handler.missed == 0
        finally:
            logger.removeHandler(handler)
            handler.close()
