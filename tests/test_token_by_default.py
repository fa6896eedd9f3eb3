"""Authenticated by default (issue 17): ``main_ds.py local`` makes its own token (``<run>/token``, mode
0600) and every child uses it, so a caller without it is refused while the run goes; a role started on
its own without a token says, in a WARNING, that any local process may call it and how to set one."""

from __future__ import annotations

import re
import signal
import stat
import subprocess
import time
from pathlib import Path

import grpc
import pytest

from ds.learner.client import LearnerClient
from ds.net.rpc import RetryPolicy
from ds.net.security import Credentials
from ds.replay.client import ReplayClient, ReplayRpcError
from tests.ds.actor.test_actor_reconnect import SPEC
from tests.role_runs import ENV, TINY, RoleRun, main_ds_command

ONCE = RetryPolicy(attempts=1)
SERVING = r"^\[{role}\] .* {role} on 127\.0\.0\.1:(\d+): plaintext, token required"
NO_TOKEN = "runs without a token"


def wait_for(pattern: str, log: Path, proc: subprocess.Popen[bytes], timeout_s: float = 90) -> re.Match[str]:
    deadline = time.monotonic() + timeout_s
    while (match := re.search(pattern, log.read_text(), re.M)) is None:
        assert proc.poll() is None, log.read_text()[-4000:]
        assert time.monotonic() < deadline, f"no {pattern!r}:\n{log.read_text()[-4000:]}"
        time.sleep(0.3)
    return match


@pytest.mark.slow
@pytest.mark.grpc
def test_a_local_run_makes_a_0600_token_and_its_roles_refuse_callers_without_it(tmp_path: Path) -> None:
    log = tmp_path / "local.log"
    with log.open("w") as sink:
        proc = subprocess.Popen(main_ds_command("gym/pendulum", "local", "--actors", "1", "-n", "tok", *TINY,
                                                "--override", "base.max_step=-1"),
                                cwd=tmp_path, env=ENV, stdout=sink, stderr=subprocess.STDOUT)  # fmt: skip
    try:
        replay_port = int(wait_for(SERVING.format(role="replay"), log, proc).group(1))
        learner_port = int(wait_for(SERVING.format(role="learner"), log, proc).group(1))
        token_file = tmp_path / "models/gym/pendulum/tok/token"
        assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
        token = Credentials(token=token_file.read_bytes().strip())
        replay = f"127.0.0.1:{replay_port}"
        with ReplayClient(replay, SPEC.sensors, SPEC.action.size, retry=ONCE) as stranger:
            with pytest.raises(ReplayRpcError) as refused:
                stranger.info()
            assert refused.value.code == grpc.StatusCode.UNAUTHENTICATED
        with LearnerClient(f"127.0.0.1:{learner_port}", retry=ONCE) as stranger:
            with pytest.raises(grpc.RpcError) as e:
                stranger.register("a stranger")
            assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
        with ReplayClient(replay, SPEC.sensors, SPEC.action.size, retry=ONCE, credentials=token) as member:
            assert member.info()["inserted_steps"] >= 0  # the children's token is the file's
    finally:
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=60)
    out = log.read_text()
    assert code == 130, out[-4000:]
    assert NO_TOKEN not in out and "Traceback" not in out, out[-4000:]


@pytest.mark.grpc
def test_a_role_started_on_its_own_without_a_token_warns_on_loopback_too(tmp_path: Path) -> None:
    run = RoleRun(tmp_path, "bare", TINY)
    run.start("replay", "replay")
    run.start("actor-0", "actor")
    try:
        said = run.wait_for_line("replay", rf"replay WARNING this replay {NO_TOKEN}: .*every local process.*", 60)
        assert "net.token_file=FILE" in said.group(0), said.group(0)
        said = run.wait_for_line("actor-0", rf"actor WARNING this actor {NO_TOKEN}: .*every local process.*", 60)
        assert "net.token_file=FILE" in said.group(0), said.group(0)
    finally:
        run.stop_all(grace_s=10)
