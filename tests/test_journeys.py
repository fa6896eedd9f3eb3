"""A new user's journeys through ``main.py``, on real processes: train, interrupt (Ctrl-C or SIGTERM)
at several points, run the same command again, finish, re-run the finished run, play it.

What must hold (README, "Train, resume, play"): every interruption saves and exits 130 (SIGINT) or 143
(SIGTERM); the same command resumes and never hangs, whether or not the replay was saved; updates
owed before the interruption are never demanded from data that is not there, and over the resumed
part the update-to-data ratio is the config's; a resumed run ends within the return band of the same
run uninterrupted; a finished run, started again, says where it is, what it reached and how to play it.
"""

from __future__ import annotations

import os
import pty
import re
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch

from algorithm.run.evaluation import read_evaluations
from tests.role_runs import as_a_shell_starts_it, scalars

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.fault

# gym/pendulum's own config (64x64, 4 updates per env step, min_size_to_sample 1000), 3,000 steps:
# seeds 0-2 are at -109 to -134 by then (at 2,000 steps one of them was still at -266: too early to
# compare runs); a random policy scores about -1,200.
MAX_STEP = 3000
COMMON = ["gym/pendulum", "--no_progress", "--override", "sac.seed=0", "--override", f"base.max_step={MAX_STEP}"]
# How far a resumed run's final evaluation may be from the uninterrupted run's: Pendulum's mean over
# 10 evaluation episodes spreads by about +-60 between runs that differ only in their training
# episodes (a resume cuts the episodes in progress), so 200 is a band that flags a run that lost what it
# had learned. Evaluations are scored on the same starts as the uninterrupted run's (the eval envs'
# RNGs are in the checkpoint): before that, the evaluation after each resume reused the first
# evaluation's ten starts, and this test's run ended at -245 to -260 in four repeats and -328 once in
# CI (uninterrupted: -112); with them -113 and -126 (tests/algorithm/run/test_trainer.py pins it).
RETURN_BAND = 200.0


def main_env() -> dict[str, str]:
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1"}
    env.pop("DISPLAY", None)
    return env


# Hang guards, not timings: a 3,000-step run takes 30-120 s on the 2-core machine, alone or beside a
# benchmark; CI on a loaded machine hit 120 s (the resume without a replay) and 240 s before.
HANG_S = 600


def run_main(cwd: Path, *args: str, timeout: float = HANG_S) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(ROOT / "main.py"), *args], cwd=cwd, env=main_env(), text=True,
                          capture_output=True, timeout=timeout)  # fmt: skip


def interrupt_at(cwd: Path, args: list[str], line: str, signum: int, timeout: float = HANG_S) -> tuple[int, str]:
    """Start ``main.py args``, send ``signum`` once a log line matches ``line``; (exit code, stderr)."""
    proc = subprocess.Popen([sys.executable, str(ROOT / "main.py"), *args], cwd=cwd, env=main_env(), text=True,
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL)  # fmt: skip
    assert proc.stderr is not None
    seen: list[str] = []
    sent = threading.Event()

    def read() -> None:
        assert proc.stderr is not None
        for text in proc.stderr:
            seen.append(text)
            if not sent.is_set() and re.search(line, text):
                sent.set()
                proc.send_signal(signum)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        code = proc.wait(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
    reader.join(5)
    assert sent.is_set(), f"never saw {line!r}:\n{''.join(seen)}"
    return code, "".join(seen)


def counters(run: Path) -> dict:
    latest = max((run / "model").glob("*.pt"), key=lambda p: int(p.stem))
    return torch.load(latest, weights_only=True)["counters"]


def final_return(run: Path) -> float:
    rows = read_evaluations(run / "evaluations.csv")
    assert rows[-1]["env_steps"] == MAX_STEP, rows
    return rows[-1]["return_mean"]


@pytest.fixture(scope="module")
def whole(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The working directory of a run trained to MAX_STEP without interruption (``-n whole``)."""
    cwd = tmp_path_factory.mktemp("whole")
    done = run_main(cwd, *COMMON, "-n", "whole")
    assert done.returncode == 0, done.stderr
    return cwd


@pytest.fixture(scope="module")
def uninterrupted(whole: Path) -> float:
    return final_return(whole / "models/gym/pendulum/whole")


# Interruption points, in this order in one run: during the warm-up (before min_size_to_sample), while
# updates run, and late. Each is resumed by the same command; the run then finishes.
POINTS = (
    ("sigint_in_warmup", r"eval at 500 env steps", signal.SIGINT, 130),
    ("sigint_while_training", r"eval at 1500 env steps", signal.SIGINT, 130),
    ("sigterm_late", r"eval at 2500 env steps", signal.SIGTERM, 143),
)


def test_interrupted_at_three_points_the_same_command_resumes_each_time_and_ends_in_the_band(
    uninterrupted: float, tmp_path: Path
) -> None:
    # One run interrupted three times, rather than three runs interrupted once each: the same
    # points are covered, each resume starts from a run that was itself resumed, and CI trains two
    # Pendulum runs fewer (~300 s of its 2 cores).
    args = [*COMMON, "-n", "myrun"]
    run = tmp_path / "models/gym/pendulum/myrun"
    stopped_at = 0
    for point, line, signum, expected_code in POINTS:
        code, log = interrupt_at(tmp_path, args, line, signum)
        assert code == expected_code, f"{point}:\n{log}"
        assert "saved; the same command resumes" in log and "Traceback" not in log, f"{point}:\n{log}"
        if stopped_at:
            assert f"resumed at {stopped_at} env steps" in log, f"{point}:\n{log}"
        previous, stopped_at = stopped_at, counters(run)["env_steps"]
        assert previous < stopped_at < MAX_STEP, (point, previous, stopped_at)
        assert (run / "replay/replay.npz").is_file()  # replay_config.save_replay_on_stop (the default)

    resumed = run_main(tmp_path, *args)
    assert resumed.returncode == 0, resumed.stderr
    assert f"resumed at {stopped_at} env steps" in resumed.stderr
    assert re.search(r"replay restored from \S+replay\.npz: \d+ steps", resumed.stderr), resumed.stderr  # says so
    got = final_return(run)
    curve = [(int(r["env_steps"]), round(r["return_mean"], 1)) for r in read_evaluations(run / "evaluations.csv")]
    # pytest -rP shows it (bench/results/modes/README.md, "Evaluations after a resume")
    print(f"evaluations {curve}, uninterrupted at the end {uninterrupted:.1f}")
    assert abs(got - uninterrupted) <= RETURN_BAND, f"resumed run ended at {got:.1f}, uninterrupted {uninterrupted:.1f}"
    # Started again once finished, it reports and leaves: the snapshot written at the last interruption
    # is neither loaded nor talked about (it was: "not loading replay.npz: checkpoint ... saved without it").
    again = run_main(tmp_path, *args)
    assert again.returncode == 0 and f"already finished at {MAX_STEP} env steps" in again.stderr, again.stderr
    assert "replay" not in again.stderr, again.stderr


def test_resume_without_the_replay_does_not_hang_and_keeps_the_ratio(tmp_path: Path) -> None:
    # The replay is not saved: the resumed run starts from an empty one, refills it to
    # min_size_to_sample (500 here) and from then on every env step earns samples_per_insert /
    # batch_size = 4 updates, as the config asks. Chunks are 64 steps, so the refilled replay first
    # holds >= 500 steps after 500 to 563 new steps. 2,000 steps in all: the ratio, not a return, is
    # what this test reads, and 1,000 resumed steps hold ~2,000 updates.
    args = [*COMMON, "-n", "noreplay", "--override", "replay.save_replay_on_stop=false",
            "--override", "replay.min_size_to_sample=500", "--override", "base.max_step=2000"]  # fmt: skip
    code, log = interrupt_at(tmp_path, args, r"eval at 1000 env steps", signal.SIGINT)
    assert code == 130, log
    run = tmp_path / "models/gym/pendulum/noreplay"
    before = counters(run)
    assert not (run / "replay").exists()
    resumed = run_main(tmp_path, *args)
    assert resumed.returncode == 0, resumed.stderr
    after = counters(run)
    new_steps, new_updates = after["env_steps"] - before["env_steps"], after["updates"] - before["updates"]
    assert 4 * (new_steps - 564) <= new_updates <= 4 * (new_steps - 500), (before, after)


def test_a_finished_run_started_again_reports_its_result_and_how_to_play_it(whole: Path) -> None:
    # the uninterrupted run above, started again by the same command (it changes nothing there)
    rows = read_evaluations(whole / "models/gym/pendulum/whole/evaluations.csv")
    again = run_main(whole, *COMMON, "-n", "whole", timeout=180)
    assert again.returncode == 0, again.stderr
    assert f"already finished at {MAX_STEP} env steps; last eval return {rows[-1]['return_mean']:.1f}" in again.stderr
    # as the user would type it here: this interpreter (python when that is it on PATH) and main.py's path
    command = re.search(r"play it with: (\S+) (\S*main\.py) (.*--run)$", again.stderr, re.M)
    assert command is not None and "models/gym/pendulum/whole" in again.stderr, again.stderr
    assert Path(command.group(2)) == ROOT / "main.py" and command.group(1) in ("python", sys.executable), command[0]
    played = run_main(whole, *command.group(3).split(), "--episodes", "2")
    assert played.returncode == 0 and f"checkpoint {MAX_STEP}: return" in played.stdout, played.stderr


def test_a_second_process_on_a_run_in_training_stops_and_a_killed_run_resumes(tmp_path: Path) -> None:
    # The same command in a second terminal while the first still trains: it must not write a second
    # run's rows into evaluations.csv nor its checkpoints over the first's (it did, interleaved).
    args = [*COMMON, "-n", "shared", "--override", "eval.eval_per_step=250"]
    run = tmp_path / "models/gym/pendulum/shared"
    first = subprocess.Popen([sys.executable, str(ROOT / "main.py"), *args], cwd=tmp_path, env=main_env(), text=True,
                             stderr=subprocess.PIPE, stdout=subprocess.DEVNULL)  # fmt: skip
    assert first.stderr is not None
    try:
        for text in first.stderr:  # training: past its first evaluation
            if "eval at 500 env steps" in text:
                break
        else:
            raise AssertionError(f"the first run ended early, exit {first.wait()}")
        second = run_main(tmp_path, *args, timeout=120)
        assert second.returncode == 2, second.stderr
        assert second.stderr.strip().splitlines() == [
            f"error: run models/gym/pendulum/shared is in use by process {first.pid}, which is training it now: wait "
            "for it to finish or stop it (Ctrl-C saves, and the same command resumes), or give this one another "
            "name with -n"
        ], second.stderr
        first.kill()  # kill -9: no save, and the lock goes with the process
        first.wait(30)
    finally:
        if first.poll() is None:
            first.kill()
    steps = [int(r["env_steps"]) for r in read_evaluations(run / "evaluations.csv")]
    assert steps == list(range(250, steps[-1] + 1, 250)), steps  # one run's rows only
    resumed = run_main(tmp_path, *args, "--override", "base.max_step=1500")
    assert resumed.returncode == 0, resumed.stderr
    assert "finished at 1500 env steps" in resumed.stderr, resumed.stderr


def test_the_terminal_closing_under_a_run_saves_it_and_the_same_command_resumes(tmp_path: Path) -> None:
    # SIGHUP is what a run started from a terminal gets when the terminal (or the SSH session) closes.
    # It ended main.py where it stood: no save, the work since the last checkpoint lost. Here the
    # terminal is a pseudo-terminal whose far end is closed first (every write to it fails from then
    # on, the progress bar's included), then SIGHUP comes, as the shell sends it to its jobs.
    args = ["gym/pendulum", "-n", "hup", "--logger_in_file", "--override", "sac.seed=0",
            "--override", "eval.eval_per_step=500", "--override", "sac.save_model_per_step=100000"]  # fmt: skip
    terminal, far_end = pty.openpty()
    first = [*args, "--override", "base.max_step=100000"]  # still training when SIGHUP comes
    proc = subprocess.Popen(as_a_shell_starts_it([sys.executable, str(ROOT / "main.py"), *first]), cwd=tmp_path,
                            env=main_env(), stdin=far_end, stdout=far_end, stderr=far_end,
                            start_new_session=True)  # fmt: skip
    os.close(far_end)
    seen = b""
    try:
        while b"eval at 1000 env steps" not in seen:
            ready, _, _ = select.select([terminal], [], [], HANG_S)
            assert ready, seen.decode(errors="replace")[-4000:]
            seen += os.read(terminal, 65536)
    finally:
        os.close(terminal)  # the terminal is gone
    time.sleep(3)  # the progress line (every second on a terminal) and the log write into the hung-up terminal
    proc.send_signal(signal.SIGHUP)
    assert proc.wait(timeout=HANG_S) == 129
    run = tmp_path / "models/gym/pendulum/hup"
    saved = max(int(p.stem) for p in run.glob("model/*.pt"))  # none before the signal: every 100,000 steps
    assert saved >= 1000
    assert "SIGHUP: stopping after this step, saving" in (run / "log.txt").read_text()
    resumed = run_main(tmp_path, *args, "--override", f"base.max_step={saved + 500}")
    assert resumed.returncode == 0, resumed.stderr
    assert (
        f"resumed at {saved} env steps" in resumed.stderr and f"finished at {saved + 500} env steps" in resumed.stderr
    )


def scheduled_values_across_ctrl_c(cwd: Path, args: list[str], run: Path, tag: str) -> list[tuple[float, float]]:
    """Run ``main.py args``, Ctrl-C at 2,000 env steps, the same command to the end; ``(value, updates)`` of
    every ``tag`` summary in wall-time order (both runs' TensorBoard files), checked to span the resume."""
    code, log = interrupt_at(cwd, args, r"eval at 2000 env steps", signal.SIGINT)
    assert code == 130, log
    stopped_updates = counters(run)["updates"]
    resumed = run_main(cwd, *args)
    assert resumed.returncode == 0, resumed.stderr
    values = scalars(run / "log", tag)
    updates = scalars(run / "log", "learner/updates")
    assert len(values) == len(updates) and len(values) >= 10, values
    assert any(done > stopped_updates for _, _, done in updates), (stopped_updates, updates)  # after the resume
    return [(value, done) for (_, _, value), (_, _, done) in zip(values, updates, strict=True)]


def test_an_annealed_learning_rate_goes_on_where_it_was_after_ctrl_c(tmp_path: Path) -> None:
    """``sac.learning_rate_final``: the step size follows the applied-update count the checkpoint keeps,
    so the run that resumes after Ctrl-C goes on down the same line (one that restarted the schedule
    would jump back up to ``learning_rate``), read back from the run's TensorBoard files."""
    total = 7000  # ~ the updates of 3,000 Pendulum steps at 4 per step after 1,000 stored: the line's end
    args = [*COMMON, "-n", "annealed", "--override", "sac.learning_rate_final=0.00003", "--override",
            f"sac.learning_rate_anneal_updates={total}", "--override", "sac.write_summary_per_step=250"]  # fmt: skip
    rates = scheduled_values_across_ctrl_c(tmp_path, args, tmp_path / "models/gym/pendulum/annealed",
                                           "learner/learning_rate")  # fmt: skip
    start = 1e-3  # gym/pendulum's learning_rate
    for rate, done in rates:
        expected = start + (3e-5 - start) * min(1.0, (done - 1) / total)  # the update that made it the done-th
        assert rate == pytest.approx(expected, rel=1e-3), (done, rate, expected)
    assert rates[-1][0] < start / 2, rates


def test_a_scheduled_munchausen_weight_goes_on_where_it_was_after_ctrl_c(tmp_path: Path) -> None:
    """``sac.munchausen_scale_start``: the weight rides the step size's schedule (``gym/cartpole``'s default
    since 2026-12-06, rising from 0 to 0.9 while the step size anneals over the run: 2 updates per env step
    after 1,000 stored, 4,000 updates in 3,000 steps), so after Ctrl-C and the same command it goes on up the
    same line from the checkpoint's update count, read back from the run's TensorBoard files (a weight that
    restarted at 0 would fall off the line)."""
    total = 2 * (MAX_STEP - 1000)
    args = ["gym/cartpole", "--no_progress", "-n", "ramp", "--override", "sac.seed=0", "--override",
            f"base.max_step={MAX_STEP}", "--override", "sac.write_summary_per_step=250"]  # fmt: skip
    weights = scheduled_values_across_ctrl_c(tmp_path, args, tmp_path / "models/gym/cartpole/ramp",
                                             "learner/munchausen_weight")  # fmt: skip
    for weight, done in weights:
        assert weight == pytest.approx(0.9 * min(1.0, (done - 1) / total), abs=1e-6), (done, weight)
    assert weights[-1][0] > 0.8, weights
