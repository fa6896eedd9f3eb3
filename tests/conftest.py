"""Test-wide settings: one torch thread and a passive OpenMP wait policy.

With OpenMP's default (active) waiting, a 2-thread torch update slowed ~200x whenever another
process held a core on the 2-core CI machine (measured while writing bench/learner.py); tests run
beside each other and beside subprocesses, so they pin torch to one passive thread.

Two workers: see SERIAL below.
"""

from __future__ import annotations

import os
from typing import Any

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("MUJOCO_GL", "egl")

import torch

torch.set_num_threads(1)

from hypothesis import settings  # noqa: E402

# CI explores the same examples every run (no flaky red from a newly found case); local runs keep
# hypothesis' random exploration, which is how such cases are found.
settings.register_profile("ci", derandomize=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")


# ---------------------------------------------------------------------- two workers (make test)

# `make test` runs the suite on two pytest-xdist workers (the Makefile's PYTEST_WORKERS: -n 2 --dist
# loadgroup); a plain `pytest` runs it in one process. The tests (or modules) of one group below run on
# one worker, one after the other; everything else goes to whichever worker is free.
#
# "roles": tests that start several role processes (replay, learner, actors, evolver), or time waits of
# a few seconds inside the test. One at a time, such a test never shares the two cores with another of
# its kind: beside it runs at most the other worker's test (one main.py process, or one in-process test),
# as a CPU job beside the old one-process suite did. A new test of that kind belongs here.
# "journeys", "main": a module fixture trains a run; one worker runs the module, so it is trained once.
#
# Entries are a file, or a file::test (all its parameters). The table, not xdist_group marks: with
# pytest 9.2, xdist 3.8's loadgroup no longer sees the marks (pytest-dev/pytest-xdist#1386), so
# pytest_xdist_make_scheduler below groups by this table (tests/test_layout.py checks every entry names
# a test).
SERIAL: dict[str, tuple[str, ...]] = {
    "roles": (
        "tests/test_soak.py",
        "tests/test_population.py",
        "tests/test_local_journeys.py",
        "tests/test_faults_roles.py",
        "tests/test_faults_replay.py",
        "tests/test_cross_host.py",
        "tests/test_token_by_default.py",
        "tests/test_main_ds.py::test_local_run_trains_to_its_budget_and_every_role_logs",
        "tests/test_main_ds.py::test_sigint_stops_every_child_and_the_same_command_resumes",
        "tests/test_main_ds.py::test_replay_learner_and_two_actors_learn_pendulum",
        "tests/test_main_ds.py::test_local_run_with_a_token_and_mutual_tls_trains",
        # ~15 processes side by side (the processes fixture), and the tests sharing its trained fixture
        "tests/test_bad_input.py::test_a_damaged_run_is_refused_naming_the_file_and_left_as_it_was",
        "tests/test_bad_input.py::test_a_bad_command_line_is_one_line_exit_2_and_creates_nothing",
        "tests/test_bad_input.py::test_a_run_with_a_damaged_config_is_refused_naming_it_and_left_as_it_was",
        # timed waits: a replay role through a full disk; in-process servers timed to tenths of a second
        "tests/test_full_disk.py::test_the_replay_role_serves_on_through_a_full_disk_and_snapshots_again_once_space_is_back",
        "tests/test_backpressure.py",
        "tests/ds/test_replay_sink.py",
        "tests/ds/test_replay_files.py",
        "tests/ds/test_replay_service.py",
    ),
    "journeys": ("tests/test_journeys.py",),
    "main": ("tests/test_main.py",),
}


def serial_group(nodeid: str) -> str | None:
    """The SERIAL group of a test's node id, or None."""
    for group, entries in SERIAL.items():
        for entry in entries:
            if "::" in entry:  # one test, all its parameters
                if nodeid == entry or nodeid.startswith(entry + "["):
                    return group
            elif nodeid.startswith(entry + "::"):
                return group
    return None


def pytest_xdist_make_scheduler(config: Any, log: Any) -> Any:
    """With --dist loadgroup: xdist's scheduler by scope, a scope being a SERIAL group or one test."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class SerialGroups(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return serial_group(nodeid) or nodeid

    return SerialGroups(config, log)
