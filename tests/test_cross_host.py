"""A run across hosts: replay, learner and actor each in its own Linux network namespace, with its own
address on a private subnet (veth pairs to a bridge), its own run folder, and no loopback path to the
others. Creating namespaces needs root (CAP_SYS_ADMIN and CAP_NET_ADMIN); without it the test skips
and says so."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from tests.network import Host, hosts, namespaces_available, start_role

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1", "MUJOCO_GL": "egl"}
BUDGET = 1_500


def role(host: Host, name: str, model_root: Path, log: Path, *args: str) -> subprocess.Popen[bytes]:
    """``main_ds.py gym/pendulum <name>`` inside ``host``, listening on its address only."""
    common = ["-n", "xhost", "--no_progress", "--override", "sac.seed=0", "--override", f"base.max_step={BUDGET}",
              "--override", "eval.eval_per_step=500", "--override", "eval.eval_episodes=2"]  # fmt: skip
    return start_role(host, model_root, name, "gym/pendulum", [*common, *args], ENV, log)


@pytest.mark.slow
@pytest.mark.grpc
def test_roles_in_separate_network_namespaces_train_together(tmp_path: Path) -> None:
    """ISSUE 4: each role sees only its own address and the others' over the bridge (its loopback
    holds nobody else); started in reverse order, they find each other and finish the budget."""
    reason = namespaces_available()
    if reason:
        pytest.skip(reason)
    with hosts(["replay", "learner", "actor"]) as net:
        replay_addr, learner_addr = net["replay"].address, net["learner"].address
        peers = ["--replay_host", replay_addr, "--learner_host", learner_addr]
        logs = {name: tmp_path / f"{name}.log" for name in net}
        # Reverse start order: the actor and the learner must wait for the replay and say so; it is
        # started once both have (a replay starts in ~1.5 s, before they would ask for it otherwise).
        procs = {"actor": role(net["actor"], "actor", tmp_path / "actor_host", logs["actor"], *peers)}
        procs["learner"] = role(net["learner"], "learner", tmp_path / "learner_host", logs["learner"], *peers)
        try:
            deadline = time.monotonic() + 120
            for name in ("actor", "learner"):
                while f"waiting for replay at {replay_addr}" not in logs[name].read_text():
                    assert procs[name].poll() is None, logs[name].read_text()[-3000:]
                    assert time.monotonic() < deadline, f"the {name} never said it waits for the replay"
                    time.sleep(0.2)
            procs["replay"] = role(net["replay"], "replay", tmp_path / "replay_host", logs["replay"])
            for name in ("actor", "learner"):
                assert procs[name].wait(timeout=420) == 0, logs[name].read_text()[-3000:]
        finally:
            for proc in procs.values():
                if proc.poll() is None:
                    proc.send_signal(signal.SIGINT)
            for proc in procs.values():
                proc.wait(timeout=60)
        text = {name: log.read_text() for name, log in logs.items()}
        assert f"waiting for replay at {replay_addr}" in text["actor"]
        assert f"waiting for replay at {replay_addr}" in text["learner"]
        evaluations = tmp_path / "learner_host/gym/pendulum/xhost/evaluations.csv"
        rows = list(csv.DictReader(evaluations.open()))
        assert rows and int(rows[-1]["env_steps"]) >= BUDGET
        # Each "host" kept its own folder: the actor's and replay's hold only their own logs.
        assert not (tmp_path / "actor_host/gym/pendulum/xhost/model").exists()
        assert (tmp_path / "learner_host/gym/pendulum/xhost/model").is_dir()
