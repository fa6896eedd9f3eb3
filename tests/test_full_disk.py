"""Full disks on real processes: the run folder on a small tmpfs that a filler file fills mid-run
(root only: without it these skip, saying why). ``main.py`` trains on and the replay role serves on;
each kind of file that cannot be written is said once on one line, never with a traceback; the
files before stay as they were; once the filler is gone they are written again, and the process
ends with its usual status. tests/algorithm/test_files_full_disk.py and
tests/ds/evolver/test_state_full_disk.py check each writer on its own."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from algorithm.run.evaluation import read_evaluations
from envs.make import make_vector_env
from tests.algorithm.replay.chunks import make_chunk
from tests.role_runs import ENV, RoleRun, flags, scalars
from tests.small_disk import small_disk

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[1]
NO_SPACE = "No space left on device"


def no_space_lines(text: str) -> dict[str, int]:
    """How many lines say "no space", by what could not be written ("checkpoint", "log file", ...)."""
    kinds: dict[str, int] = {}
    for line in text.splitlines():
        if NO_SPACE in line:
            match = re.search(r"could not write the (.+?) /", line)
            kind = match.group(1) if match else f"other: {line}"
            kinds[kind] = kinds.get(kind, 0) + 1
    return kinds


def wait_until(
    what: str, ready: Callable[[], bool], proc: subprocess.Popen[bytes], log: Path, timeout_s: float
) -> None:
    deadline = time.monotonic() + timeout_s
    while not ready():
        assert proc.poll() is None, f"exited {proc.returncode} while waiting for {what}\n{log.read_text()[-4000:]}"
        assert time.monotonic() < deadline, f"no {what} within {timeout_s:.0f} s\n{log.read_text()[-4000:]}"
        time.sleep(0.1)


def checkpoints(model: Path) -> list[int]:
    return sorted(int(p.stem) for p in model.glob("*.pt")) if model.is_dir() else []


# The disk fills after the checkpoint at 400 env steps and is freed ~600 steps later (two evaluations
# after the failures); the budget leaves room for the checkpoints after that under a loaded machine.
MAIN_BUDGET = 2400


def test_main_trains_on_through_a_full_disk_and_saves_again_once_space_is_back(tmp_path: Path) -> None:
    overrides = [
        "sac.seed=3", "nn.hidden_units=[16,16]", "replay.batch_size=16", "replay.samples_per_insert=null",
        "replay.min_size_to_sample=64", "replay.capacity=20000", "replay.save_replay=true",
        f"base.max_step={MAIN_BUDGET}", "sac.save_model_per_step=200", "eval.eval_per_step=200",
        "eval.eval_episodes=1", "eval.eval_envs=1", "sac.write_summary_per_step=10",
    ]  # fmt: skip
    with small_disk(tmp_path / "disk", "32m") as disk:
        run = disk.path / "models/gym/pendulum/full"
        log = tmp_path / "stderr.txt"  # off the small disk: what the test reads
        command = [sys.executable, str(ROOT / "main.py"), "gym/pendulum", "-n", "full", "--model_root",
                   str(disk.path / "models"), "--logger_in_file", *flags(*overrides)]  # fmt: skip
        with log.open("wb") as err:
            proc = subprocess.Popen(command, cwd=tmp_path, env=ENV, stdout=subprocess.DEVNULL, stderr=err)
        try:
            wait_until("a checkpoint at 400 steps", lambda: checkpoints(run / "model")[-1:] >= [400], proc, log, 240)
            with disk.kept_full():
                full_at = checkpoints(run / "model")[-1]
                kept = {p: p.read_bytes() for p in (run / "model").glob("*.pt")}

                def failed_and_went_on() -> bool:
                    text = log.read_text()
                    said = all(f"could not write the {kind} " in text for kind in
                               ("checkpoint", "replay snapshot", "evaluations", "TensorBoard summaries"))  # fmt: skip
                    evals = [int(s) for s in re.findall(r"eval at (\d+) env steps", text)]
                    return said and len([s for s in evals if s > full_at + 200]) >= 2

                wait_until("the failures and two evaluations after them", failed_and_went_on, proc, log, 240)
                assert {p: p.read_bytes() for p in (run / "model").glob("*.pt")} == kept  # as they were
                # A failed write leaves no temp file. One seen now may be a save still under way (seen
                # in a loaded run: .1000.pt.<random>.tmp): it must be gone by the next evaluation.
                temps = set(run.rglob(".*.tmp"))
                if temps:
                    evals = log.read_text().count("eval at ")
                    wait_until("the next evaluation", lambda: log.read_text().count("eval at ") > evals, proc, log, 240)
                    assert not temps & set(run.rglob(".*.tmp")), temps
                full_until = max(int(s) for s in re.findall(r"eval at (\d+) env steps", log.read_text()))
            disk.free()
            wait_until("a checkpoint written after the disk was full",
                       lambda: checkpoints(run / "model")[-1] > full_until, proc, log, 240)  # fmt: skip
            assert proc.wait(timeout=240) == 0, log.read_text()[-4000:]
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        text = log.read_text()
        assert "Traceback" not in text and "Logging error" not in text, text[-4000:]
        assert not list(run.rglob(".*.tmp"))  # no write, failed or not, left its temp file behind
        counts = no_space_lines(text)
        # log.txt fails only once its last page is full (the page it had is still its own on tmpfs):
        # a few lines in this run, whether it fails is luck; tests/algorithm/test_files_full_disk.py fills it.
        log_file_failed = counts.pop("log file", 0)
        assert log_file_failed <= 1, text[-4000:]
        assert counts == {"checkpoint": 1, "replay snapshot": 1, "evaluations": 1, "TensorBoard summaries": 1}, counts
        for kind in ("checkpoint", "replay snapshot", "evaluations", "TensorBoard summaries"):
            assert f"writing the {kind} works again" in text, kind
        assert checkpoints(run / "model")[-1] == MAIN_BUDGET
        rows = [int(r["env_steps"]) for r in read_evaluations(run / "evaluations.csv")]
        assert rows == list(range(200, MAIN_BUDGET + 1, 200)), (
            rows
        )  # the rows held while the disk was full too, in order
        updates = [step for _, step, _ in scalars(run / "log", "learner/updates")]
        assert updates == sorted(updates) and updates[-1] > full_until  # readable after the full disk too
        assert any(full_at < s <= full_until for s in updates)  # and what was held while it was full
        in_file = (run / "log.txt").read_text()
        noted = re.search(r"\(\d+ log records before this one could not be written here; see stderr\)", in_file)
        assert bool(noted) == bool(log_file_failed)
        assert f"finished at {MAIN_BUDGET} env steps" in in_file and in_file.endswith("\n")


def snapshot_inserted(path: Path) -> int:
    with np.load(path, allow_pickle=False) as f:
        return int(json.loads(str(f["meta"]))["rate_limiter"]["inserted"])


def test_the_replay_role_serves_on_through_a_full_disk_and_snapshots_again_once_space_is_back(tmp_path: Path) -> None:
    spec = make_vector_env("Pendulum-v1", 1, seed=0).spec
    common = flags("sac.seed=0", "replay.save_replay=true", "replay.save_replay_per_minute=0.01",
                   "replay.samples_per_insert=null", "replay.capacity=20000")  # fmt: skip
    with small_disk(tmp_path / "disk", "16m") as disk:
        run = RoleRun(tmp_path, "full", [*common, "--model_root", str(disk.path / "models"), "--logger_in_file"])
        snapshot = disk.path / "models/gym/pendulum/full/replay/replay.npz"
        proc = run.start("replay", "replay")
        key = 0
        try:
            run.wait_for_line("replay", r"replay serving on", 120)
            with run.replay_client(spec.sensors, spec.action.size) as replay:

                def insert(n: int) -> None:
                    nonlocal key
                    for _ in range(n):
                        replay.insert(make_chunk(16, key, spec.sensors, spec.action.size), timeout=10.0)
                        key += 17

                insert(10)  # (with no learner sampling, the rate limiter lets ~1000 steps in)
                run.wait_for("a snapshot of 160 steps",
                             lambda: snapshot.exists() and snapshot_inserted(snapshot) == 160, 60)  # fmt: skip
                with disk.kept_full():
                    insert(10)  # into a replay whose next snapshot fails
                    failed = run.wait_for_line("replay", r"could not write the replay snapshot", 60)
                    kept = snapshot.read_bytes()
                    insert(10)
                    time.sleep(3.0)  # ~5 more tries (every 0.6 s)
                    assert replay.info()["inserted_steps"] == 480  # served on
                    assert snapshot.read_bytes() == kept and not list(snapshot.parent.glob(".*.tmp"))
                    assert snapshot_inserted(snapshot) in (160, 320)
                disk.free()
                run.wait_for_line("replay", r"writing the replay snapshot works again", 60, failed.end())
                run.wait_for("a snapshot of all 480 steps", lambda: snapshot_inserted(snapshot) == 480, 60)

                with disk.kept_full():  # full again, and then stopped: the final save fails
                    insert(3)
                    run.wait_for_line("replay", r"could not write the replay snapshot", 60, failed.end())
                    last = snapshot.read_bytes()
                    run.signal("replay", signal.SIGINT)
                    assert proc.wait(timeout=60) == 130  # a stopped role's status, not a crash
                    assert snapshot.read_bytes() == last
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        text = run.text("replay")
        assert "Traceback" not in text and "Logging error" not in text, text[-4000:]
        final = [line for line in text.splitlines() if "could not write the final replay snapshot" in line]
        assert len(final) == 1 and NO_SPACE in final[0] and f"{snapshot} keeps the previous snapshot" in final[0]
        counts = no_space_lines(text)
        assert counts["replay snapshot"] == 2, counts  # once each time the disk was full
        assert counts.get("log file", 0) <= 2 and counts.get("TensorBoard summaries", 0) <= 2, counts
        assert set(counts) <= {"replay snapshot", "final replay snapshot", "log file", "TensorBoard summaries"}, counts
