"""Credentials rotate while a run goes on (ds/net/credentials.py; docs/security.md section 5): every role a
real ``main_ds.py`` process with token and mutual TLS files of its own, as on hosts of their own. The
token is rotated and the CA rolled over in the documented steps, one role after the other; no role
restarts or exits, the actor keeps taking the learner's weights, an actor started afterwards with
only the new token and a certificate of the new CA joins, and every step collected is stored."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from ds.net.security import ROLES
from tests.pki import Pki, RoleFiles
from tests.role_runs import TINY_OVERRIDES, RoleRun, flags, scalars

pytestmark = [pytest.mark.slow, pytest.mark.grpc]
LABELS = {"replay": "replay", "learner": "learner", "actor-0": "actor"}
TAKEN_UP_S = 30.0  # a role looks at its files every 2 s while it uses them; a loaded machine is slow


def wait_taken_up(run: RoleRun, labels: list[str], pattern: str, count: int) -> None:
    """Each role's log says ``count`` times that a changed file matching ``pattern`` was taken up."""
    for label in labels:
        run.wait_for(f"{label} taking up {pattern!r} {count} times",
                     lambda label=label: len(re.findall(pattern, run.text(label))) >= count, TAKEN_UP_S)  # fmt: skip


def newer_weights(events: Path, since: float) -> bool:
    """Whether the actor whose TensorBoard folder is ``events`` acted, some seconds after ``since``, with a
    weights version newer than any it had by then."""
    versions = scalars(events, "actor/params_version")
    before = max((value for wall, _, value in versions if wall <= since), default=0.0)
    return any(wall > since + 5 and value > before for wall, _, value in versions)


def test_a_token_rotation_and_a_ca_rollover_reach_every_role_of_a_running_run_and_nothing_is_lost(
    tmp_path: Path,
) -> None:
    pki = Pki(tmp_path / "pki")
    old_ca, new_ca = pki.ca, pki.wrong_ca
    old_cert = pki.issue("local", *sorted(ROLES))
    new_cert = pki.issue("local", *sorted(ROLES), ca="wrong")
    files = {label: RoleFiles(tmp_path / "hosts" / label, old_cert, old_ca, b"old-token") for label in LABELS}
    run = RoleRun(tmp_path, "rotated", flags(*TINY_OVERRIDES, "sac.seed=0", "base.max_step=-1"))
    try:
        for label, role in LABELS.items():
            run.start(label, role, *files[label].flags())
        run.wait_for_line("actor-0", r"actor \S+: index 0", 120)
        run.wait_for_line("learner", r"eval at \d+ env steps, [1-9]\d* updates", 180)
        labels = list(LABELS)
        token_taken, tls_taken = r"token_file .* changed: taken up \((\d) token", r"TLS files .* changed: taken up"
        # Step 1, one role after the other: both tokens, both CAs.
        for label in labels:
            files[label].tokens(b"old-token", b"new-token")
            files[label].trust(old_ca, new_ca)
            time.sleep(1.0)
        wait_taken_up(run, labels, token_taken, 1)
        wait_taken_up(run, labels, tls_taken, 1)
        # Step 2: the new token alone, certificates of the new CA.
        for label in labels:
            files[label].tokens(b"new-token")
            files[label].use(new_cert)
            time.sleep(1.0)
        wait_taken_up(run, labels, token_taken, 2)
        wait_taken_up(run, labels, tls_taken, 2)
        # Step 3: the old CA no longer trusted.
        for label in labels:
            files[label].trust(new_ca)
            time.sleep(1.0)
        rotated = time.time()
        wait_taken_up(run, labels, tls_taken, 3)
        # An actor that only knows the new credentials joins; the first actor goes on taking weights.
        joined = RoleFiles(tmp_path / "hosts" / "actor-1", new_cert, new_ca, b"new-token")
        run.start("actor-1", "actor", *joined.flags())
        run.wait_for_line("actor-1", r"actor \S+: index 1", 120)
        actors = [run.run / "log" / f"actor_{i}" for i in (0, 1)]
        run.wait_for("both actors acting with weights published after the rotation",
                     lambda: all(newer_weights(events, rotated) for events in actors), 180)  # fmt: skip
    finally:
        codes = run.stop_all()
    assert set(codes.values()) == {130}, f"{codes}\n{run.logs()}"  # none exited before its SIGINT
    texts = {label: run.text(label) for label in run.procs}
    for label, text in texts.items():
        assert "Traceback" not in text and "rejected" not in text and "UNAUTHENTICATED" not in text, text[-3000:]
        if label != "actor-1":
            assert len(re.findall(r"token_file .* changed: taken up", text)) == 2, text[-3000:]
    collected = sum(int(n) for t in texts.values() for n in re.findall(r"actor \d+ stopped after (\d+) env steps", t))
    stored = re.findall(r"replay saved to \S+: (\d+) env steps inserted over the run", texts["replay"])
    assert stored == [str(collected)] and collected > 0, (collected, stored)
