"""Checkpoint writes killed part-way (ISSUE 7): a real process saving with ``save_checkpoint`` is
sent SIGKILL while it writes. The previous checkpoint is intact and loads, nothing half-written is
taken for a checkpoint, and the next save deletes what the killed one left."""

from __future__ import annotations

import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from algorithm.run import checkpoint as ck

pytestmark = pytest.mark.fault
ROOT = Path(__file__).resolve().parents[3]
SIZE = 4_000_000  # float32 values: a 16 MB checkpoint, about as big as a 1024x1024 SAC's

# The child saves checkpoint 100, says so, then saves 200; PAUSE stops it at one point of that save
# so that the kill lands there every time: "mid-write" after half of the bytes are on disk (inside
# torch.save), "before-rename" after the temp file is complete and fsynced but before os.replace.
# "loop" pauses nowhere: it saves 200, 300, ... until it is killed at a random moment.
CHILD = f"""
import io, os, sys, time
from pathlib import Path
import torch
from algorithm import files
from algorithm.run import checkpoint as ck

model, pause = Path(sys.argv[1]), sys.argv[2]

def state(step):
    return {{"w": torch.full(({SIZE},), float(step)), "step": step}}

ck.save_checkpoint(model, 100, state(100), keep=2)
print("saved 100", flush=True)
if pause == "mid-write":
    real_save = torch.save
    def half_then_hang(obj, f):
        buffer = io.BytesIO()
        real_save(obj, buffer)
        data = buffer.getvalue()
        f.write(data[: len(data) // 2])
        f.flush()
        os.fsync(f.fileno())
        print("paused", flush=True)
        time.sleep(600)
    ck.torch.save = half_then_hang
elif pause == "before-rename":
    real_fsync = os.fsync
    def fsync_then_hang(fd):
        real_fsync(fd)
        print("paused", flush=True)
        time.sleep(600)
    files.os.fsync = fsync_then_hang
step = 200
while True:
    ck.save_checkpoint(model, step, state(step), keep=2)
    step += 100
"""


def start(model: Path, pause: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-c", CHILD, str(model), pause], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)  # fmt: skip


def read_line(proc: subprocess.Popen[str], expected: str) -> None:
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line.strip() == expected, line + proc.stdout.read()


def temp_files(model: Path) -> list[Path]:
    return sorted(model.glob(".*.tmp"))


def assert_latest_loads(model: Path) -> int:
    """Every file named like a checkpoint loads and holds its own step; returns the latest step."""
    steps = ck.list_checkpoints(model)
    assert steps, f"no checkpoint left in {sorted(p.name for p in model.iterdir())}"
    for step in steps:
        state = ck.load_checkpoint(model / f"{step}.pt")
        assert state["step"] == step and bool((state["w"] == float(step)).all())
    assert ck.checkpoint_path(model) == model / f"{steps[-1]}.pt"
    return steps[-1]


def assert_next_save_cleans_up(model: Path, step: int) -> None:
    ck.save_checkpoint(model, step, {"w": torch.full((SIZE,), float(step)), "step": step}, keep=2)
    assert temp_files(model) == []
    assert assert_latest_loads(model) == step


@pytest.mark.parametrize("pause", ["mid-write", "before-rename"])
def test_a_save_killed_at_a_set_point_leaves_the_previous_checkpoint(tmp_path: Path, pause: str) -> None:
    model = tmp_path / "model"
    proc = start(model, pause)
    try:
        read_line(proc, "saved 100")
        before = (model / "100.pt").read_bytes()
        read_line(proc, "paused")
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        proc.kill()
    (leftover,) = temp_files(model)  # what the killed save wrote: not a checkpoint
    assert leftover.name.startswith(".200.pt.") and leftover.stat().st_size > 0
    assert ck.list_checkpoints(model) == [100]
    assert (model / "100.pt").read_bytes() == before
    assert assert_latest_loads(model) == 100
    if pause == "mid-write":
        with pytest.raises(ck.CheckpointError, match="unreadable"):
            ck.load_checkpoint(leftover)
    assert_next_save_cleans_up(model, 300)


@pytest.mark.slow
def test_saves_killed_at_random_moments_always_leave_a_loadable_latest_checkpoint(tmp_path: Path) -> None:
    """No pause: a process saves 16 MB checkpoints back to back (keep 2) and is killed at a random
    moment, again and again until two kills have landed inside a save (a temp file left behind)."""
    rng = random.Random(0)
    model, inside, kills = tmp_path / "model", 0, 0
    while inside < 2:
        # Most kills land inside a save, but not all (one CI run: 1 of 8, when serialising the state,
        # before any temp file exists, took most of the time): 24 tries keep that from failing the run.
        assert kills < 24, f"only {inside} of {kills} kills landed inside a save"
        proc = start(model, "loop")
        try:
            read_line(proc, "saved 100")
            time.sleep(rng.uniform(0.0, 1.0))
            proc.send_signal(signal.SIGKILL)
            assert proc.wait(timeout=30) == -signal.SIGKILL
        finally:
            proc.kill()
        kills += 1
        inside += bool(temp_files(model))
        latest = assert_latest_loads(model)
        assert_next_save_cleans_up(model, latest + 1_000_000)  # the next run's saves go on from here
        for step in ck.list_checkpoints(model):
            (model / f"{step}.pt").unlink()
