"""`make test` on two pytest-xdist workers: which tests run one at a time, and which run alone.

The hooks below are registered by the repository's conftest.py."""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from collections.abc import Iterator
from typing import Any

import pytest

# `make test` runs the suite on two pytest-xdist workers (the Makefile's PYTEST_WORKERS: -n 2 --dist
# loadgroup); a plain `pytest` runs it in one process. The tests (or modules) of one group below run on
# one worker, one after the other; everything else goes to whichever worker is free.
#
# "roles": tests that start several role processes (replay, learner, actors, evolver), or time waits of
# seconds inside the test. One at a time, such a test never shares the two cores with another of its
# kind: beside it runs at most the other worker's test (one main.py process, or one in-process test), as
# a CPU job beside the old one-process suite did. A new test of that kind belongs here.
# ALONE: tests that time calls to tenths of a second (70 calls with 0.5 s deadlines, "answered within
# 0.05 s"): they run first in "roles", one after the other, and the other worker waits meanwhile (a lock,
# pytest_runtest_protocol below), so they run as in the one-process suite.
# "journeys", "main": a module fixture trains a run; one worker runs the module, so it is trained once.
#
# Entries are a file, or a file::test (all its parameters). The table, not xdist_group marks: with
# pytest 9.2, xdist 3.8's loadgroup no longer sees the marks (pytest-dev/pytest-xdist#1386), so
# pytest_xdist_make_scheduler below groups by this table (tests/test_layout.py checks every entry names
# a test). The repository's conftest.py registers these hooks.
ALONE = (
    "tests/ds/actor/test_sink.py",
    "tests/ds/replay/test_files.py",
    "tests/ds/replay/test_service.py",
    "tests/test_backpressure.py",
)
SERIAL: dict[str, tuple[str, ...]] = {
    "roles": (
        "tests/test_soak.py",
        "tests/test_population.py",
        "tests/test_local_journeys.py",
        "tests/test_local_stop_order.py",
        "tests/test_faults_roles.py",
        "tests/test_faults_replay.py",
        "tests/test_cross_host.py",
        "tests/test_partitions.py",
        "tests/test_slow_links.py",
        "tests/test_rotation.py",
        "tests/test_token_by_default.py",
        "tests/test_main_ds.py::test_replay_learner_and_two_actors_learn_pendulum",
        "tests/test_main_ds.py::test_roles_started_by_hand_without_a_name_share_one_run_and_the_same_commands_resume_it",
        "tests/test_main_ds.py::test_local_run_with_a_token_and_mutual_tls_trains",
        "tests/test_original_task_files.py",
        # the feature matrix's distributed half: a local run (replay, learner, actor) per README row
        "tests/test_features.py::test_feature_trains_and_plays_through_main_ds_local",
        # a local run of HalfCheetah with 2 actors of 4 envs, then the same section in main.py
        "tests/test_tasks.py::test_the_throughput_variant_trains_through_both_launchers",
        # a user's own task folder: main.py, then a local run (replay, learner, actor)
        "tests/test_own_environment.py::test_a_task_folder_of_ones_own_trains_and_plays_through_both_launchers",
        # ~15 processes side by side (the processes fixture), and the tests sharing its trained fixture
        "tests/test_bad_input.py::test_a_damaged_run_is_refused_naming_the_file_and_left_as_it_was",
        "tests/test_bad_input.py::test_a_bad_command_line_is_one_line_exit_2_and_creates_nothing",
        "tests/test_bad_input.py::test_a_run_with_a_damaged_config_is_refused_naming_it_and_left_as_it_was",
        # timed waits on a replay role through a full disk
        "tests/test_full_disk.py::test_the_replay_role_serves_on_through_a_full_disk_and_snapshots_again_once_space_is_back",
        *ALONE,  # first: the files of tests/ds come before tests/test_*
    ),
    "journeys": ("tests/test_journeys.py",),
    "main": ("tests/test_main.py",),
}


def names(entry: str, nodeid: str) -> bool:
    """Whether a SERIAL or ALONE entry (a file, or a file::test with all its parameters) names a test."""
    if "::" in entry:
        return nodeid == entry or nodeid.startswith(entry + "[")
    return nodeid.startswith(entry + "::")


def serial_group(nodeid: str) -> str | None:
    """The SERIAL group of a test's node id, or None."""
    return next((group for group, entries in SERIAL.items() for e in entries if names(e, nodeid)), None)


def alone(item: pytest.Item | None) -> bool:
    return item is not None and any(names(entry, item.nodeid) for entry in ALONE)


_HELD: list[Any] = []  # the exclusive lock's file while this worker runs a stretch of ALONE tests


def _locked(path: str, mode: int) -> Any:
    file = open(path, "a")  # noqa: SIM115 (held beyond this function)
    fcntl.flock(file, mode)
    return file


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """On a worker, every test holds a shared lock while it runs (its fixtures included), and a stretch
    of ALONE tests an exclusive one, from the first to the last. Either is taken through a gate, which
    a waiting ALONE test holds: the other worker starts no test before it has run."""
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if run is None:  # one process: nothing runs beside a test
        yield
        return
    gate_path, lock_path = _lock_files(run)
    held = None
    if not _HELD:
        gate = _locked(gate_path, fcntl.LOCK_EX)
        held = _locked(lock_path, fcntl.LOCK_EX if alone(item) else fcntl.LOCK_SH)
        gate.close()
        if alone(item):
            _HELD.append(held)
    try:
        yield
    finally:
        if _HELD and not alone(nextitem):
            _HELD.pop().close()
        elif held is not None and not _HELD:
            held.close()


_LIVE_WORKERS: set[str] = set()  # on the controller: the workers up now


def _lock_files(run: str) -> list[str]:
    base = os.path.join(tempfile.gettempdir(), f"asac-tests-{run}")
    return [base + ".gate", base + ".lock"]


def pytest_testnodeready(node: Any) -> None:
    """On the controller: a worker is up."""
    _LIVE_WORKERS.add(node.gateway.id)


def pytest_testnodedown(node: Any, error: object) -> None:
    """On the controller, once the last worker is down: remove the run's lock files (a worker still
    running must keep them: a file made again after an unlink would be another lock)."""
    _LIVE_WORKERS.discard(node.gateway.id)
    run = getattr(node, "workerinput", {}).get("testrunuid")
    if run and not _LIVE_WORKERS:
        for path in _lock_files(run):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """With --dist loadgroup: xdist's scheduler by scope, a scope being a SERIAL group or one test."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class SerialGroups(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return serial_group(nodeid) or nodeid

    return SerialGroups(config, log)
