"""Partitions between hosts heal by themselves: replay, learner and actor each in a network namespace of
its own (tests/network.py), and for 30 s every packet between one role and some of its peers is
dropped, as a cut link or a firewall drops them (no reset, no error). No role exits; nothing the actor
collected is lost (the replay's count is the actor's); each link is back within seconds of the heal;
each outage is logged once when it is noticed and once when it ends, not a line per retry."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from datetime import datetime
from pathlib import Path

import pytest

from tests.network import Host, hosts, nft_available, partition, start_role
from tests.role_runs import TINY

ENV = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1", "GRPC_VERBOSITY": "ERROR"}
CUT_S = 30.0
BACK_WITHIN_S = 10.0  # keepalive notices a dead link in <= 15 s while cut; after the heal a connect is tried every 2 s
ROLES = ("replay", "learner", "actor")


def wait_for(log: Path, pattern: str, timeout: float, proc: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + timeout
    while not re.search(pattern, log.read_text(), re.M):
        assert proc.poll() is None, log.read_text()[-3000:]
        assert time.monotonic() < deadline, f"no {pattern!r} within {timeout:.0f} s:\n{log.read_text()[-3000:]}"
        time.sleep(0.3)


def logged_at(line: str) -> datetime:
    return datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f")


def evaluations(learner_log: str) -> list[datetime]:
    """When the learner logged each evaluation (it trains between them)."""
    return [logged_at(line) for line in re.findall(r"^.*eval at \d+ env steps.*$", learner_log, re.M)]


def run_with_a_cut(
    tmp_path: Path, cut: str, peers: tuple[str, ...]
) -> tuple[dict[str, str], dict[str, Host], datetime]:
    """A run on three hosts whose ``cut`` host loses every packet to and from ``peers`` for 30 s once it
    trains; then it goes on until every link the cut broke is back and the learner has trained to its
    next evaluation, and each role is stopped, the actor first (it sends what it holds), as an
    operator stops a run. Returns the logs, the hosts and
    when the cut healed."""
    logs = {name: tmp_path / f"{name}.log" for name in ROLES}
    with hosts(list(ROLES)) as net:
        peers_flags = ["--replay_host", net["replay"].address, "--learner_host", net["learner"].address]
        common = ["-n", "cut", *TINY, "--override", "sac.seed=0", "--override", "base.max_step=-1", *peers_flags]
        procs = {name: start_role(net[name], tmp_path / name, name, "gym/pendulum", common, ENV, logs[name])
                 for name in ROLES}  # fmt: skip
        try:
            wait_for(logs["actor"], r"actor \S+: index 0", 120, procs["actor"])
            wait_for(logs["learner"], r"eval at \d+ env steps, [1-9]\d* updates", 120, procs["learner"])
            with partition(net[cut], [net[p] for p in peers]):
                time.sleep(CUT_S)
            healed = datetime.now()
            for peer in peers:  # every link the cut broke, from the side that calls
                caller = cut if ROLES.index(peer) < ROLES.index(cut) else peer
                wait_for(logs[caller], link(peer, net) + " is back after", 30, procs[caller])
            deadline = time.monotonic() + 120
            while not any(at > healed for at in evaluations(logs["learner"].read_text())):
                assert procs["learner"].poll() is None and time.monotonic() < deadline, "no evaluation after the heal"
                time.sleep(0.5)
        finally:
            for name in ("actor", "learner", "replay"):
                if procs[name].poll() is None:
                    procs[name].send_signal(signal.SIGINT)
                    try:
                        procs[name].wait(timeout=60)
                    except subprocess.TimeoutExpired:
                        procs[name].kill()
    for name in ROLES:  # each stopped by its SIGINT (130), none on its own before
        assert procs[name].wait(timeout=10) == 130, logs[name].read_text()[-3000:]
    return {name: log.read_text() for name, log in logs.items()}, net, healed


def link(peer: str, net: dict[str, Host]) -> str:
    """The pattern of how a role names its link to ``peer`` in its log (``replay at ADDRESS:PORT``)."""
    return re.escape(f"{peer} at {net[peer].address}:") + r"\d+"


def told_once_each_way(text: str, pattern: str, healed: datetime) -> float:
    """The log says once that the link ``pattern`` names is unreachable and once that it is back;
    returns how long after the heal it was back."""
    down = re.findall(rf"^.*{pattern} unreachable.*$", text, re.M)
    back = re.findall(rf"^.*{pattern} is back after.*$", text, re.M)
    assert len(down) == 1 and len(back) == 1, (down, back)
    assert "WARNING" in down[0] and "Said once" in down[0]
    return (logged_at(back[0]) - healed).total_seconds()


def nothing_lost(text: dict[str, str]) -> None:
    collected = re.findall(r"actor \d+ stopped after (\d+) env steps", text["actor"])
    stored = re.findall(r"replay saved to \S+: (\d+) env steps inserted over the run", text["replay"])
    assert len(collected) == 1 and stored == collected, (collected, stored)
    for name in ROLES:
        assert "Traceback" not in text[name], text[name][-3000:]


@pytest.mark.slow
@pytest.mark.grpc
@pytest.mark.fault
def test_an_actor_cut_off_from_its_replay_and_learner_for_30_s_comes_back_and_loses_nothing(tmp_path: Path) -> None:
    reason = nft_available()
    if reason:
        pytest.skip(reason)
    text, net, healed = run_with_a_cut(tmp_path, "actor", ("replay", "learner"))
    for peer in ("replay", "learner"):
        back_after = told_once_each_way(text["actor"], link(peer, net), healed)
        print(f"actor -> {peer}: back {back_after:.1f} s after a {CUT_S:.0f} s cut healed")  # pytest -s: the figure
        assert back_after < BACK_WITHIN_S, f"the actor's link to its {peer} came back {back_after:.1f} s after the heal"
    nothing_lost(text)
    assert " unreachable" not in text["learner"] + text["replay"]  # their link was never cut


@pytest.mark.slow
@pytest.mark.grpc
@pytest.mark.fault
def test_a_learner_cut_off_from_its_replay_for_30_s_comes_back_and_loses_nothing(tmp_path: Path) -> None:
    reason = nft_available()
    if reason:
        pytest.skip(reason)
    text, net, healed = run_with_a_cut(tmp_path, "learner", ("replay",))
    back_after = told_once_each_way(text["learner"], link("replay", net), healed)
    print(f"learner -> replay: back {back_after:.1f} s after a {CUT_S:.0f} s cut healed")  # pytest -s: the figure
    assert back_after < BACK_WITHIN_S, f"the learner's link to its replay came back {back_after:.1f} s after the heal"
    nothing_lost(text)
