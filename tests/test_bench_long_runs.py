"""bench/long_runs.py, the runs that outlast a working session: SIGTERM to the driver saves the run in
progress, the same command resumes it to its budget and copies its evaluations, a finished run is
skipped, and the report reads what was copied (real main.py processes on Pendulum, tiny networks)."""

from __future__ import annotations

import csv
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import bench.long_runs as long_runs

ROOT = Path(__file__).resolve().parents[1]
TINY = ["nn.hidden_units=[16,16]", "replay.batch_size=16", "replay.samples_per_insert=null",
        "replay.min_size_to_sample=100", "eval.eval_episodes=1",
        "eval.eval_envs=1", "sac.save_model_per_step=200"]  # fmt: skip


def driver(runs: Path, *extra: str) -> list[str]:
    args = [sys.executable, "-m", "bench.long_runs", "gym/pendulum", "--sections", "default", "--seeds", "0",
            "--steps", "1200", "--every", "200", "--runs", str(runs), *extra]  # fmt: skip
    return [*args, *(x for o in TINY for x in ("--override", o))]


@pytest.mark.slow
def test_sigterm_saves_the_run_the_same_command_resumes_it_and_a_finished_run_is_skipped(tmp_path: Path) -> None:
    results = tmp_path / "results"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "ASAC_LONG_RUNS_RESULTS": str(results)}
    runs = tmp_path / "runs"
    run = runs / "gym/pendulum" / long_runs.run_name("default", 0, 1200)
    log = tmp_path / "first.txt"
    with log.open("w") as out:
        first = subprocess.Popen(driver(runs), cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 120
    while not re.search(r"eval at [2-9]\d\d env steps", log.read_text()):
        assert first.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
        time.sleep(0.2)
    first.send_signal(signal.SIGTERM)
    assert first.wait(timeout=60) == 130, log.read_text()[-3000:]
    text = log.read_text()
    assert "interrupted after" in text and "the same command resumes it" in text, text[-3000:]
    stopped = max(int(p.stem) for p in (run / "model").glob("*.pt"))
    assert stopped < 1200

    again = subprocess.run(driver(runs), cwd=ROOT, env=env, text=True, capture_output=True, timeout=300)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert f"resumed at {stopped} env steps" in again.stderr, again.stderr[-3000:]
    copied = results / f"gym_pendulum_{long_runs.run_name('default', 0, 1200)}.csv"
    with copied.open(newline="") as f:
        steps = [int(r["env_steps"]) for r in csv.DictReader(f)]
    assert steps == list(range(200, 1201, 200)), steps  # the interrupted part's rows and the resumed part's

    third = subprocess.run(driver(runs), cwd=ROOT, env=env, text=True, capture_output=True, timeout=120)
    assert third.returncode == 0 and "already finished at 1200 env steps" in third.stdout + third.stderr

    report = subprocess.run(driver(runs, "--report"), cwd=ROOT, env=env, text=True, capture_output=True, timeout=60)
    last = float(re.search(r"seed 0: (-?[\d.]+) \(", report.stdout).group(1))  # type: ignore[union-attr]
    with copied.open(newline="") as f:
        assert last == pytest.approx(float(list(csv.DictReader(f))[-1]["return_mean"]), abs=0.05)
    assert "mean" in report.stdout and "over 1" in report.stdout, report.stdout
