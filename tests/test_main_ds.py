"""The distributed CLI as a user runs it: real subprocesses on loopback, stopped like a terminal does."""

from __future__ import annotations

import csv
import re
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest

from ds.launch.local import free_port
from ds.net.security import ROLES
from tests.pki import Pki
from tests.role_runs import ENV, TINY, TINY_OVERRIDES, RoleRun, event_files, flags, main_ds_command

ROOT = Path(__file__).resolve().parents[1]


command = main_ds_command


def run_ds(*args: str, cwd: Path, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    return subprocess.run(command(*args), cwd=cwd, env=ENV, text=True, capture_output=True, timeout=timeout)


def start_ds(*args: str, cwd: Path, log: Path) -> subprocess.Popen[bytes]:
    with log.open("wb") as out:
        return subprocess.Popen(command(*args), cwd=cwd, env=ENV, stdout=out, stderr=subprocess.STDOUT)


# ---------------------------------------------------------------------- usage errors


@pytest.mark.parametrize(
    "args, message",
    [
        (["gym/pendulum", "learnr"], "invalid choice: 'learnr'"),
        (["gym/pendulum", "actor", "--replay_port", "70000"], "'70000' is not a port number"),
        (["gym/pendulum", "actor", "--noise", "-1"], "'-1' is not a noise level"),
        (["gym/pendlum", "replay"], "unknown task 'gym/pendlum'"),
        (["gym/pendulum", "learner", "--actors", "3"], "--actors is for the local role"),
        (["gym/pendulum", "replay", "--override", "net.replay_prot=5"], "did you mean 'replay_port'"),
        (["gym/pendulum", "learner", "--override", "net.token_file=absent.key"], "net_config.token_file: cannot read"),
        (
            ["gym/pendulum", "replay", "--tls_cert", "absent.crt", "--tls_key", "absent.key"],
            "net_config.tls_cert: cannot read 'absent.crt'",
        ),
        (["gym/pendulum", "evolver", "--tls_cert", "absent.crt"], "net_config.tls_cert needs net_config.tls_key"),
    ],
)
def test_bad_input_is_a_one_line_error_with_exit_2(args: list[str], message: str, tmp_path: Path) -> None:
    done = run_ds(*args, cwd=tmp_path, timeout=120)
    assert done.returncode == 2, done.stderr
    errors = [line for line in done.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and message in done.stderr, done.stderr  # config errors list each key below
    assert "Traceback" not in done.stderr
    assert not (tmp_path / "models").exists() or not any((tmp_path / "models").rglob("*.pt"))


def test_a_taken_port_is_a_clear_error(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = run_ds("gym/pendulum", "replay", "-n", "port", "--replay_port", str(port), cwd=tmp_path, timeout=120)
    assert done.returncode == 1, done.stderr
    assert f"replay cannot listen on 127.0.0.1:{port}" in done.stderr and "--replay_port" in done.stderr
    assert "Traceback" not in done.stderr


@pytest.mark.grpc
def test_a_port_another_replay_serves_is_a_clear_error(tmp_path: Path) -> None:
    """A replay started on the port of one that still runs (a forgotten earlier run's, say) must not
    share it: with gRPC's default SO_REUSEPORT both bound, and the kernel spread a run's learner and
    actors over two replays that each waited for the other's clients."""
    port = free_port()
    log = tmp_path / "first.log"
    first = start_ds("gym/pendulum", "replay", "-n", "first", "--replay_port", str(port), cwd=tmp_path, log=log)
    try:
        deadline = time.monotonic() + 60
        while f"replay serving on 127.0.0.1:{port}" not in log.read_text():
            assert first.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
        second = run_ds("gym/pendulum", "replay", "-n", "second", "--replay_port", str(port), cwd=tmp_path, timeout=60)
        assert second.returncode == 1, second.stderr
        assert f"replay cannot listen on 127.0.0.1:{port}" in second.stderr and "--replay_port" in second.stderr
        assert first.poll() is None  # the first one serves on
    finally:
        first.send_signal(signal.SIGINT)
        first.wait(timeout=60)


@pytest.mark.grpc
def test_in_k8s_pairs_learner_k_with_replay_k_by_pod_name(tmp_path: Path) -> None:
    """--in_k8s: the learner in pod asac-learner-2 looks for replay 2 through its headless Service,
    and says so while it waits; an explicit --replay_host still wins."""
    log = tmp_path / "learner.log"
    env = {**ENV, "ASAC_POD_NAME": "asac-learner-2"}
    for extra, expected in (([], "waiting for replay at asac-replay-2.asac-replay:61002"),
                            (["--replay_host", "10.9.9.9"], "waiting for replay at 10.9.9.9:61002")):  # fmt: skip
        with log.open("wb") as out:
            learner = command("gym/pendulum", "learner", "-n", "k8s", "--in_k8s", "--no_progress", *extra)
            proc = subprocess.Popen(learner, cwd=tmp_path, env=env, stdout=out, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 120
            while expected not in log.read_text() and time.monotonic() < deadline and proc.poll() is None:
                time.sleep(0.2)
            assert expected in log.read_text(), log.read_text()[-2000:]
        finally:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=60)


# ---------------------------------------------------------------------- local runs


# ---------------------------------------------------------------------- learning

THRESHOLD = -250.0
BUDGET = 5_000  # env steps over both actors; measured: -150 at ~1,500 steps (seed 0)


@pytest.mark.slow
@pytest.mark.learning
@pytest.mark.grpc
def test_replay_learner_and_two_actors_learn_pendulum(tmp_path: Path) -> None:
    """ISSUE 4: replay + learner + 2 actors as subprocesses reach a mean deterministic return of
    -250 on Pendulum-v1 (10 episodes) within the env-step budget, with the task's default config."""
    log = tmp_path / "local.log"
    proc = start_ds("gym/pendulum", "local", "--actors", "2", "-n", "learn", "--no_progress", "--override",
                    "sac.seed=0", "--override", f"base.max_step={BUDGET}", "--override", "eval.eval_per_step=500",
                    cwd=tmp_path, log=log)  # fmt: skip
    evaluations = tmp_path / "models/gym/pendulum/learn/evaluations.csv"
    rows: list[dict[str, str]] = []
    started = time.monotonic()
    try:
        while proc.poll() is None and time.monotonic() - started < 420:
            rows = list(csv.DictReader(evaluations.open())) if evaluations.exists() else []
            if any(float(r["return_mean"]) >= THRESHOLD for r in rows):
                break
            time.sleep(1.0)
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=90)
    rows = list(csv.DictReader(evaluations.open())) if evaluations.exists() else []
    best = max(rows, key=lambda r: float(r["return_mean"]), default=None)
    assert best is not None, log.read_text()[-4000:]
    assert float(best["return_mean"]) >= THRESHOLD, f"best {best} of {len(rows)} evaluations"
    assert int(best["env_steps"]) <= BUDGET + 100  # the learner may read the counter a chunk late
    print(f"reached {float(best['return_mean']):.1f} at {best['env_steps']} env steps in "
          f"{time.monotonic() - started:.0f} s wall")  # fmt: skip


@pytest.mark.grpc
def test_roles_started_by_hand_stop_at_the_budget_and_the_replay_says_the_run_is_finished(tmp_path: Path) -> None:
    """The journey of README's "one role per terminal": replay, learner and an actor started one by one
    finish a 600-step budget; the learner and the actor exit 0 on their own, and the replay, which
    nothing tells that no learner will come back, says once that the run looks finished and how to stop
    it, then stops and saves on Ctrl-C (exit 130)."""
    run = RoleRun(tmp_path, "by_hand", flags(*TINY_OVERRIDES, "base.max_step=600", "net.lease_s=3"))
    for label in ("replay", "learner", "actor"):
        run.start(label, label)
    try:
        assert run.procs["learner"].wait(timeout=240) == 0, run.logs()
        assert run.procs["actor"].wait(timeout=60) == 0, run.logs()
        run.ended.update({"learner", "actor"})  # their exits were expected
        assert run.procs["replay"].poll() is None  # it serves on: a resumed learner may come
        notice = run.wait_for_line("replay", r"the run looks finished.*Ctrl-C stops it \(and saves it\)", 30)
        time.sleep(4)  # another quiet spell: the line is not repeated
        assert len(re.findall("the run looks finished", run.text("replay"))) == 1, notice
    finally:
        codes = run.stop_all()
    assert codes["replay"] == 130, run.logs()
    assert (run.run / "replay" / "replay.npz").is_file()  # saved at the stop, as save_replay_on_stop says


def test_roles_started_by_hand_without_a_name_share_one_run_and_the_same_commands_resume_it(tmp_path: Path) -> None:
    """The original's README starts each role with no run name (``main_ds.py TASK learner --replay_host=...
    --logger_in_file``): the roles agree on one run folder (``ds``), and after Ctrl-C the same commands
    resume it (the replay restores its steps, the learner its checkpoint)."""
    run = RoleRun(tmp_path, None, flags(*TINY_OVERRIDES, "base.max_step=100000", "net.lease_s=3"))
    for label in ("replay", "learner", "actor"):
        run.start(label, label, "--logger_in_file")
    try:
        run.wait_for_line("learner", r"eval at \d+ env steps", 180)  # it has trained (eval_per_step=300)
    finally:
        first = run.stop_all()
    assert first["learner"] == 130 and first["replay"] == 130, run.logs()
    assert sorted(p.name for p in (tmp_path / "models" / "gym" / "pendulum").iterdir()) == ["ds"]
    for role in ("replay", "learner", "actor"):
        assert (run.run / f"log_{role}.txt").is_file(), role  # --logger_in_file: each role's log in the one folder
    saved = run.wait_for_line("replay", r"replay saved to \S+: (\d+) env steps", 5)
    stopped_at = len(run.text("learner"))
    for label in ("replay", "learner", "actor"):
        run.start(label, label, "--logger_in_file")
    try:
        restored = run.wait_for_line("replay", r"replay restored from \S+: (\d+) steps", 120, len(saved.string))
        resumed = run.wait_for_line("learner", r"resumed from \S+ at (\d+) env steps", 120, stopped_at)
    finally:
        run.stop_all()
    assert int(restored.group(1)) == int(saved.group(1)) >= 300 and int(resumed.group(1)) >= 300, run.logs()


# ---------------------------------------------------------------------- security


@pytest.mark.slow
@pytest.mark.grpc
def test_local_run_with_a_token_and_mutual_tls_trains(tmp_path: Path) -> None:
    """Every role of a local run with the token and mutual TLS (one certificate naming every role, as
    docs/security.md section 3 says for local runs): the learner trains to the budget; each server says it
    requires both; nothing warns of an open server. A server role given a CA but no certificate of
    its own stops before it starts; an actor (a client only) may run so."""
    pki = Pki(tmp_path / "pki")
    local = pki.issue("local", *sorted(ROLES))
    (tmp_path / "token").write_text("s3cret-for-this-run\n")
    tls = ["--tls_cert", str(local.cert), "--tls_key", str(local.key), "--tls_ca", str(pki.ca)]
    token = ["--override", f"net.token_file={tmp_path / 'token'}"]
    done = run_ds("gym/pendulum", "local", "--actors", "1", "-n", "secure", *TINY, *token, *tls,
                  "--override", "base.max_step=1200", cwd=tmp_path)  # fmt: skip
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-4000:]
    for role in ("replay", "learner"):
        assert re.search(rf"\[{role}\].* {role} on 127.0.0.1:\d+: mutual TLS .*token required", output), role
    assert "open to anyone" not in output, output[-4000:]
    assert "not reachable: " not in output, output[-4000:]  # the reason a TLS handshake failed (ds/net/rpc.py)
    run = tmp_path / "models/gym/pendulum/secure"
    assert max(int(p.stem) for p in run.glob("model/*.pt")) >= 1200  # the learner trained to the budget
    for role in ("learner", "actor_0", "replay"):
        assert event_files(run, role), f"no TensorBoard events for {role}"
    refused = run_ds("gym/pendulum", "replay", "--tls_ca", str(pki.ca), cwd=tmp_path, timeout=120)
    assert refused.returncode == 2 and "the replay serves gRPC and needs its own certificate" in refused.stderr
