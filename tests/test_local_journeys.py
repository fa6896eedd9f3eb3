"""``main_ds.py TASK local`` from start to end as a user lives it: how it stops (learners first, then
actors, then replays, the evolver last; no kill in a normal finish), the summary it ends with (and
that its play command works), and labels that agree with the ids the roles use (ds/launch/local.py).

The journeys run the real roles on gym/pendulum with tiny budgets; the stop order over stand-in roles,
checked in seconds and exactly, is tests/test_local_stop_order.py's.
"""

from __future__ import annotations

import contextlib
import os
import pty
import re
import select
import shlex
import signal
import subprocess
import time
from pathlib import Path

import pytest
import torch
import yaml

from algorithm.run.evaluation import read_evaluations
from ds.launch.local import learner_threads
from tests.role_runs import (
    ENV,
    TINY,
    as_a_shell_starts_it,
    child_pids,
    event_files,
    main_ds_command,
    no_process_mentions,
    running,
)

ROOT = Path(__file__).resolve().parents[1]
SUMMARY_HEAD = re.compile(r"^== local run (.+) ==$", re.M)
# A hang guard, not a timing: a local run of 1,000-1,600 env steps takes 40-120 s on the 2-core machine.
HANG_S = 300

# ---------------------------------------------------------------------- journeys on real processes


command = main_ds_command


def summary_of(output: str) -> tuple[str, list[str]]:
    """The summary's outcome words and its lines, checked to be the last lines of ``output``."""
    heads = list(SUMMARY_HEAD.finditer(output))
    assert len(heads) == 1, f"one summary expected:\n{output[-4000:]}"
    lines = output[heads[0].start() :].strip().splitlines()
    assert all(not line.startswith("[") and " INFO " not in line for line in lines), lines  # nothing after it
    return heads[0].group(1), lines


def play_command(lines: list[str]) -> list[str]:
    plays = [line.split("play it: ", 1)[1] for line in lines if "play it: " in line]
    assert plays, lines
    return shlex.split(plays[0])


def first(pattern: str, output: str) -> int:
    """Where the first match of ``pattern`` starts in ``output`` (fails naming it)."""
    match = re.search(pattern, output, re.M)
    assert match, f"no {pattern!r} in:\n{output[-4000:]}"
    return match.start()


def check_nothing_collected_was_lost(output: str) -> None:
    """At a Ctrl-C the learner stops first and draws no more, so the rate limiter holds the actors'
    last inserts back; they are stored anyway: every env step the actors say they collected is in the
    replay they saved, and no actor says it could not insert some."""
    assert "were not inserted" not in output, output[-4000:]
    collected = re.findall(r"^\[actor-\d\] .*actor \d (?:finished|stopped) after (\d+) env steps", output, re.M)
    saved = re.findall(r"^\[replay\] .*replay saved to .*: (\d+) env steps inserted over the run", output, re.M)
    assert len(collected) == 2 and len(saved) == 1, output[-4000:]
    assert sum(map(int, collected)) == int(saved[0]), output[-4000:]


def check_actor_labels(output: str) -> None:
    """Every line where an actor says its index is prefixed by the launcher with that index."""
    said = re.findall(r"^\[actor-(\d+)\] .*(?:: index (\d+),| actor (\d+) (?:finished|stopped) after)", output, re.M)
    assert said, output[-4000:]
    for label, *index in said:
        assert label == next(i for i in index if i), f"[actor-{label}] says index {index}:\n{output[-4000:]}"


@pytest.mark.slow
@pytest.mark.grpc
def test_a_local_run_finishes_in_order_and_its_summary_plays_it(tmp_path: Path) -> None:
    """``local --actors 2`` to its budget: exit 0, every child gone before its grace ran out; the learner's
    checkpoint before the replay is told to stop; no traceback, no kill; nothing collected thrown
    away (each actor leaves after its last inserts, the run's count is the sum of theirs, at most a
    chunk per actor past max_step); every role logs under its prefix and is gone at the
    end; one evaluation row per evaluation and a final checkpoint; the last lines are the summary,
    whose play command works; ``[actor-k]`` is index k."""
    done = subprocess.run(command("gym/pendulum", "local", "--actors", "2", "-n", "journey", *TINY,
                                  "--override", "base.max_step=1000", "--override", "eval.eval_per_step=250"),
                          cwd=tmp_path, env=ENV, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          timeout=HANG_S)  # fmt: skip
    out = done.stdout
    assert done.returncode == 0, out[-4000:]
    assert "still running after" not in out, out[-4000:]  # the old stop waited out the grace for a child
    assert first(r"^\[learner\] .*checkpoint ", out) < first(r"^\[replay\] .*SIGINT: stopping", out)
    for bad in ("Traceback", "SIGTERM", "SIGKILL"):
        assert bad not in out, f"{bad!r} in:\n{out[-4000:]}"
    assert "were not inserted" not in out, out[-4000:]  # the learner trains until the actors have left
    assert len(re.findall(r"^\[learner\] .*index \d\) left after \d+ env steps", out, re.M)) == 2, out[-4000:]
    collected = sum(int(n) for n in re.findall(r"^\[actor-\d\] .*actor \d finished after (\d+) env steps", out, re.M))
    ended = int(re.findall(r"^\[learner\] .*learner finished after (\d+) env steps", out, re.M)[0])
    assert ended == collected, out[-4000:]  # every step an actor collected is in the run's count
    # past max_step by at most a chunk per actor: each stops stepping once the replay's count plus what
    # it holds reaches max_step, so only the other's holding (an insert on its way, an open chunk) is
    # past it (before: what both held, up to 2 chunks each)
    assert 1000 <= ended <= 1000 + 2 * 64, out[-4000:]
    replay_told = first(r"^\[replay\] .*SIGINT: stopping", out)
    for k in (0, 1):  # done by themselves (the budget is spent), or told to stop before the replay is
        assert first(rf"^\[actor-{k}\] .*actor {k} (?:finished|stopped) after", out) < replay_told, out[-4000:]
    check_actor_labels(out)
    for role in ("[replay]", "[learner]", "[actor-0]", "[actor-1]"):
        assert re.search(rf"^{re.escape(role)} ", out, re.M), f"no log lines prefixed {role}"
    pids = child_pids(out)
    assert set(pids) == {"replay", "learner", "actor-0", "actor-1"} and not any(map(running, pids.values()))
    # on the replay's host the learner's batches come through a file in /dev/shm, gone once it ends
    shared = re.findall(r"^\[learner\] .*come through (/dev/shm/asac-batches-\S+)", out, re.M)
    assert len(shared) == 1 and not Path(shared[0]).exists(), out[-4000:]
    assert "batches come over gRPC" not in out, out[-4000:]
    run = tmp_path / "models/gym/pendulum/journey"
    steps = [int(r["env_steps"]) for r in read_evaluations(run / "evaluations.csv")]
    assert steps and steps == sorted(set(steps)), steps  # one row per evaluation, in order
    # one evaluation at the end, after the updates on the last data (an evaluation due at 1,000 was a
    # second row a few steps before it)
    assert [s for s in steps if s >= 1000] == [ended], steps
    assert max(int(p.stem) for p in run.glob("model/*.pt")) >= 1000  # the final checkpoint
    outcome, lines = summary_of(out)
    assert outcome == "finished"
    assert "run folder: models/gym/pendulum/journey" in lines
    assert any(line.startswith("final evaluation return ") for line in lines), lines
    play = play_command(lines)
    assert play[-4:] == ["gym/pendulum", "-n", "journey", "--run"] and play[1].endswith("main.py"), play
    played = subprocess.run(play, cwd=tmp_path, env=ENV, text=True, capture_output=True, timeout=120)
    assert played.returncode == 0, played.stdout + played.stderr
    assert "models/gym/pendulum/journey checkpoint" in played.stdout


@pytest.mark.slow
@pytest.mark.grpc
@pytest.mark.fault
def test_ctrl_c_mid_run_stops_the_learner_before_the_replay_and_says_interrupted(tmp_path: Path) -> None:
    """SIGINT to the launcher mid-run: exit 130; the learner checkpointed and said it stopped before
    the replay was told to stop; the replay saved; the summary says interrupted and plays the run.
    Meanwhile the same command a second time is refused before it starts a role (two launchers on one
    run would mix two runs' checkpoints and evaluations)."""
    log = tmp_path / "local.log"
    args = command("gym/pendulum", "local", "--actors", "2", "-n", "ctrl_c", *TINY,
                   "--override", "base.max_step=-1", "--override", "replay.save_replay=true")  # fmt: skip
    again_log = tmp_path / "again.log"
    with log.open("w") as sink, again_log.open("w") as again_sink:
        proc = subprocess.Popen(args, cwd=tmp_path, env=ENV, stdout=sink, stderr=subprocess.STDOUT)
        again, passed = None, False
        try:
            deadline = time.monotonic() + 60
            # mid-run: training, and both actors registered (one may take 10 s to import on a loaded machine)
            while "eval at" not in log.read_text() or len(re.findall(r"registered as actor-", log.read_text())) < 2:
                assert proc.poll() is None, log.read_text()[-4000:]
                assert time.monotonic() < deadline, "the run did not get going: " + log.read_text()[-4000:]
                time.sleep(0.3)
            again = subprocess.Popen(args, cwd=tmp_path, env=ENV, stdout=again_sink, stderr=subprocess.STDOUT)
            assert again.wait(timeout=60) == 2, again_log.read_text()[-4000:]
            said = again_log.read_text()
            assert said.startswith(f"error: run models/gym/pendulum/ctrl_c is in use by process {proc.pid},"), said
            proc.send_signal(signal.SIGINT)  # what Ctrl-C in a terminal sends the launcher
            assert proc.wait(timeout=60) == 130, log.read_text()[-4000:]
            passed = True
        finally:  # after a failed assertion: no launcher or role of this test left running
            for launcher, output in ((proc, log), (again, again_log)):
                if launcher is not None and not passed:
                    for pid in (launcher.pid, *child_pids(output.read_text()).values()):
                        with contextlib.suppress(ProcessLookupError):
                            os.kill(pid, signal.SIGKILL)
    out = log.read_text()
    run = tmp_path / "models/gym/pendulum/ctrl_c"
    assert list(run.glob("model/*.pt")), "no checkpoint"
    assert (run / "replay/replay.npz").is_file(), "the replay did not save"
    assert first(r"^\[learner\] .*learner stopped after", out) < first(r"^\[replay\] .*SIGINT: stopping", out)
    assert first(r"^\[learner\] .*learner stopped after", out) < first(r"^\[actor-\d\] .*SIGINT: stopping", out)
    assert "Traceback" not in out and "SIGKILL" not in out, out[-4000:]
    for k in range(2):  # an actor told to stop does not warn that the learner, stopped before it, is gone
        after_stop = out[first(rf"^\[actor-{k}\] .*SIGINT: stopping", out) :]
        assert not re.search(rf"^\[actor-{k}\] .* WARNING ", after_stop, re.M), after_stop[-4000:]
    check_nothing_collected_was_lost(out)
    check_actor_labels(out)
    outcome, lines = summary_of(out)
    assert outcome == "interrupted (SIGINT)", lines
    assert play_command(lines)[-4:] == ["gym/pendulum", "-n", "ctrl_c", "--run"], lines


UNREACHABLE = "10.255.255.1"  # a private address nothing on the test machine answers


@pytest.mark.slow
@pytest.mark.grpc
def test_a_local_run_is_placed_by_the_launcher_draws_random_params_and_says_the_config_notes_once(
    tmp_path: Path,
) -> None:
    """A task file's (here: an override's) evolver address is for roles started one by one: ``local``
    without ``--learners`` starts no evolver and says once that it does not follow it (the roles would
    otherwise wait for it forever); ``random_params`` is drawn once, as main.py draws it, and recorded
    in the run's config.yaml; what a key of the original's layout became is said once, as a WARNING,
    by the launcher alone (not once per role process)."""
    draws = "random_params.sac_config={n_step: {in: [2, 3]}, tau: {truncated: [0.001, 0.01]}}"
    done = subprocess.run(command("gym/pendulum", "local", "--actors", "1", "-n", "placed", *TINY,
                                  "--override", "base.max_step=400", "--override", f"net.evolver_host={UNREACHABLE}",
                                  "--override", draws, "--override", "base.noise_max=0.2"),
                          cwd=tmp_path, env=ENV, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          timeout=HANG_S)  # fmt: skip
    out = done.stdout
    assert done.returncode == 0, out[-4000:]
    assert len(re.findall(rf"local WARNING net_config\.evolver_host: {UNREACHABLE} ", out)) == 1, out[-4000:]
    assert "waiting for evolver" not in out, out[-4000:]
    moved = re.findall(r"^(\S+ \S+ \w+ WARNING )?.*base_config\.noise_max is actor_config\.noise_max now", out, re.M)
    assert len(moved) == 1 and moved[0], out[-4000:]  # once, tagged
    saved = yaml.safe_load((tmp_path / "models/gym/pendulum/placed/config.yaml").read_text())
    drawn = re.search(r"local INFO random_params drew (.*) \(recorded in config.yaml\)", out)
    assert drawn and saved["sac_config"]["n_step"] in (2, 3) and 0.001 <= saved["sac_config"]["tau"] <= 0.01, out
    assert f"sac_config.n_step={saved['sac_config']['n_step']}" in drawn.group(1)
    assert saved["actor_config"]["noise_max"] == 0.2
    # torch's threads left to it (0): the learner gets the cores less the actor's and the replay's
    assert saved["base_config"]["torch_threads"] == learner_threads(1, None) == max(1, (os.cpu_count() or 1) - 2)
    learner_said = re.search(r"^\[learner\] .*learner of run", out, re.M)
    assert learner_said, out[-4000:]


@pytest.mark.slow
@pytest.mark.grpc
def test_a_population_labels_each_learner_and_replay_with_the_evolver_id(tmp_path: Path) -> None:
    """``local --learners 2``: ``[learner-k]`` is the evolver's learner k, writing ``learner_k/``;
    ``[replay-k]`` serves learner k; the summary plays each learner's folder."""
    # Addresses a task file may give (for roles started one by one) are not followed: a learner sent to
    # this replay_host, or an actor to this learner_host, would wait for them forever.
    elsewhere = ["--override", f"net.replay_host={UNREACHABLE}", "--override", f"net.learner_host={UNREACHABLE}"]
    done = subprocess.run(command("gym/pendulum", "local", "--learners", "2", "--actors", "2", "-n", "pop", *TINY,
                                  "--override", "base.max_step=600", *elsewhere),
                          cwd=tmp_path, env=ENV, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          timeout=150)  # fmt: skip
    out = done.stdout
    assert done.returncode == 0, out[-4000:]
    for key in ("replay_host", "learner_host"):
        assert len(re.findall(rf"^\S+ \S+ local WARNING net_config\.{key}: {UNREACHABLE} ", out, re.M)) == 1, out[
            -4000:
        ]
    said = re.findall(r"^\[learner-(\d+)\] .*learner (\d+) of 'pop' in \S+/learner_(\d+)", out, re.M)
    assert sorted(label for label, _, _ in said) == ["0", "1"], out[-4000:]
    assert all(label == learner == folder for label, learner, folder in said), said
    served = re.findall(r"^\[replay-(\d+)\] .*serves learner (\d+)", out, re.M)
    assert sorted(served) == [("0", "0"), ("1", "1")], out[-4000:]
    for label in re.findall(r"^\[learner-(\d+)\] .*checkpoint (\S+)", out, re.M):
        assert f"/learner_{label[0]}/" in label[1], label
    check_actor_labels(out)
    _, lines = summary_of(out)
    for k in (0, 1):
        assert any(f"-n pop/learner_{k} --run" in line for line in lines), lines


@pytest.mark.slow
@pytest.mark.grpc
@pytest.mark.fault
def test_ctrl_c_then_the_command_it_prints_resumes_and_a_third_run_of_the_finished_run_changes_nothing(
    tmp_path: Path,
) -> None:
    """SIGINT mid-run of a run named by its start time (the default name): the summary prints the
    command that resumes it (the same words would start a new run), and that command does: the learner
    resumes from its checkpoint and the replay from the snapshot it saved at the stop
    (save_replay_on_stop, the default); the run ends at its budget, at most a chunk per actor past
    it, with the updates the config asks for (1 per env step once min_size_to_sample steps are
    stored: TINY's samples_per_insert is null). The SIGINT leaves no role running; every role wrote
    TensorBoard events."""
    first_args = command("gym/pendulum", "local", "--actors", "2", *TINY, "--override", "sac.seed=0",
                         "--override", "base.max_step=1600")  # fmt: skip
    log = tmp_path / "first.log"
    with log.open("w") as sink:
        proc = subprocess.Popen(first_args, cwd=tmp_path, env=ENV, stdout=sink, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 90
    while not re.search(r"eval at (6|7|8|9)\d\d env steps", log.read_text()):
        assert proc.poll() is None, log.read_text()[-4000:]
        assert time.monotonic() < deadline, "the run did not get going: " + log.read_text()[-4000:]
        time.sleep(0.3)
    pids = child_pids(log.read_text())
    assert set(pids) == {"replay", "learner", "actor-0", "actor-1"}
    proc.send_signal(signal.SIGINT)  # what Ctrl-C in a terminal sends the launcher
    assert proc.wait(timeout=60) == 130, log.read_text()[-4000:]
    outcome, lines = summary_of(log.read_text())
    assert outcome == "interrupted (SIGINT)", lines
    said = re.fullmatch(r"resume it: (.+ -n (\d{14}))", lines[-1])
    assert said, lines
    args, name = shlex.split(said.group(1)), said.group(2)
    assert args[1:] == [*first_args[1:], "-n", name], args  # the launcher's own, named by its start time
    assert not any(map(running, pids.values())) and no_process_mentions(name), log.read_text()[-4000:]
    run = tmp_path / "models/gym/pendulum" / name
    assert (run / "replay/replay.npz").is_file(), "the replay did not save at the stop"
    stopped = max(int(p.stem) for p in run.glob("model/*.pt"))
    assert stopped < 1600

    again = subprocess.run(args, cwd=tmp_path, env=ENV, text=True, stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, timeout=180)  # fmt: skip
    out = again.stdout
    assert again.returncode == 0, out[-4000:]
    assert re.search(rf"resumed from \S+/{stopped}\.pt at {stopped} env steps", out), out[-4000:]
    assert "replay restored from" in out and "Traceback" not in out, out[-4000:]
    final = max(run.glob("model/*.pt"), key=lambda p: int(p.stem))
    counters = torch.load(final, weights_only=True)["counters"]
    # past max_step by at most a chunk per actor; nothing collected is thrown away at the end, it is
    # trained on
    assert 1600 <= counters["env_steps"] <= 1600 + 2 * 64, counters
    asked = counters["env_steps"] - 200  # 1 update per step once min_size_to_sample=200 steps are stored
    assert asked - 64 <= counters["updates"] <= asked + 1, counters
    outcome, _ = summary_of(out)
    assert outcome == "finished"
    for role in ("learner", "actor_0", "actor_1", "replay"):
        assert event_files(run, role), f"no TensorBoard events for {role}"

    # A third time: the run is finished; it says so and changes nothing.
    checkpoints = sorted(p.name for p in run.glob("model/*.pt"))
    third = subprocess.run(args, cwd=tmp_path, env=ENV, text=True, stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, timeout=120)  # fmt: skip
    assert third.returncode == 0, third.stdout[-4000:]
    assert f"already finished at {counters['env_steps']} env steps" in third.stdout, third.stdout[-4000:]
    assert "started " not in third.stdout, third.stdout[-4000:]  # the launcher knew: no role was started
    assert sorted(p.name for p in run.glob("model/*.pt")) == checkpoints
    outcome, lines = summary_of(third.stdout)
    assert outcome == "finished" and f"run folder: models/gym/pendulum/{name}" in lines, lines


@pytest.mark.slow
@pytest.mark.grpc
@pytest.mark.fault
def test_a_launcher_killed_with_9_leaves_no_role_running_each_saves_and_the_same_command_resumes(
    tmp_path: Path,
) -> None:
    """``kill -9`` of the launcher (nobody stops the roles in order, nobody reads their output): every
    role stops by itself, as on SIGTERM (they ran on, unseen, holding their ports, and the learner's
    work since its last checkpoint was lost when they were killed later); the learner checkpointed and
    the replay saved; the same command then resumes the run from both (the run's lock went with the
    launcher)."""
    # --logger_in_file: each role's own log file says what it did after the launcher died
    args = command("gym/pendulum", "local", "--actors", "2", "-n", "orphans", *TINY, "--logger_in_file",
                   "--override", "sac.seed=0", "--override", "eval.eval_per_step=5000",
                   "--override", "sac.save_model_per_step=100000")  # fmt: skip
    log = tmp_path / "first.log"
    with log.open("w") as sink:
        proc = subprocess.Popen([*args, "--override", "base.max_step=-1"], cwd=tmp_path, env=ENV, stdout=sink,
                                stderr=subprocess.STDOUT)  # fmt: skip
    pids: dict[str, int] = {}
    try:
        deadline = time.monotonic() + 90
        while not re.search(r"registered as actor-.*; 2 live", log.read_text()):
            assert proc.poll() is None, log.read_text()[-4000:]
            assert time.monotonic() < deadline, "the run did not get going: " + log.read_text()[-4000:]
            time.sleep(0.3)
        time.sleep(5)  # a few hundred steps trained, none checkpointed yet (every 100,000 steps)
        pids = child_pids(log.read_text())
        assert set(pids) == {"replay", "learner", "actor-0", "actor-1"}
        run = tmp_path / "models/gym/pendulum/orphans"
        assert not list(run.glob("model/*.pt"))
        proc.kill()
        proc.wait(10)
        deadline = time.monotonic() + 60
        while any(map(running, pids.values())):
            assert time.monotonic() < deadline, f"roles still running 60 s after the launcher died: {pids}"
            time.sleep(0.5)
    finally:
        for pid in pids.values():
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    saved = max(int(p.stem) for p in run.glob("model/*.pt"))
    assert saved > 0 and (run / "replay/replay.npz").is_file()
    again = subprocess.run([*args, "--override", f"base.max_step={saved + 300}"], cwd=tmp_path, env=ENV, text=True,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=180)  # fmt: skip
    out = again.stdout
    assert again.returncode == 0, out[-4000:]
    assert re.search(rf"resumed from \S+/{saved}\.pt at {saved} env steps", out), out[-4000:]
    assert re.search(r"replay restored from \S+: \d+ steps", out), out[-4000:]
    assert summary_of(out)[0] == "finished"


@pytest.mark.slow
@pytest.mark.grpc
@pytest.mark.fault
def test_the_terminal_closing_under_local_stops_every_role_in_order(tmp_path: Path) -> None:
    """SIGHUP to the launcher after its terminal has closed (writes to it fail from then on): it stops
    the roles in order as on Ctrl-C (exit 129), though nothing it prints can be shown any more: the
    learner checkpoints, the replay saves, no role is left running."""
    args = command("gym/pendulum", "local", "--actors", "2", "-n", "hup", *TINY, "--logger_in_file",
                   "--override", "base.max_step=-1", "--override", "sac.save_model_per_step=100000")  # fmt: skip
    terminal, far_end = pty.openpty()
    proc = subprocess.Popen(as_a_shell_starts_it(args), cwd=tmp_path, env=ENV, stdin=far_end, stdout=far_end,
                            stderr=far_end, start_new_session=True)  # fmt: skip
    os.close(far_end)
    seen, passed = "", False
    try:
        try:
            while not re.search(r"eval at \d+ env steps, [1-9]\d* updates", seen):
                ready, _, _ = select.select([terminal], [], [], 300)  # a hang guard: roles start slowly when loaded
                assert ready, seen[-4000:]
                seen += os.read(terminal, 65536).decode(errors="replace")
        finally:
            os.close(terminal)  # the terminal is gone
        pids = child_pids(seen)
        assert set(pids) == {"replay", "learner", "actor-0", "actor-1"}, seen[-4000:]
        time.sleep(3)  # the roles' lines go on arriving, and the launcher fails to show them
        proc.send_signal(signal.SIGHUP)
        assert proc.wait(timeout=90) == 129
        assert not any(map(running, pids.values()))
        passed = True
    finally:  # after a failed assertion: the launcher and the roles it said it started
        for pid in () if passed else (proc.pid, *child_pids(seen).values()):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    run = tmp_path / "models/gym/pendulum/hup"
    assert list(run.glob("model/*.pt")) and (run / "replay/replay.npz").is_file()
    said = (run / "log_local.txt").read_text()
    assert "SIGHUP: stopping every role in order" in said and "SIGKILL" not in said, said[-4000:]
