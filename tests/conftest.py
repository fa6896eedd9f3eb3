"""Test-wide settings: one torch thread and a passive OpenMP wait policy.

With OpenMP's default (active) waiting, a 2-thread torch update slowed ~200x whenever another
process held a core on the 2-core CI machine (measured while writing bench/learner.py); tests run
beside each other and beside subprocesses, so they pin torch to one passive thread.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("MUJOCO_GL", "egl")

import pytest
import torch

torch.set_num_threads(1)

from hypothesis import settings  # noqa: E402

# CI explores the same examples every run (no flaky red from a newly found case); local runs keep
# hypothesis' random exploration, which is how such cases are found.
settings.register_profile("ci", derandomize=True)
settings.load_profile("ci" if os.environ.get("CI") else "default")


@pytest.fixture(autouse=True)
def _no_role_left_running() -> Iterator[None]:
    """After each test, kill the role processes a test started by hand (tests/role_runs.py) and left
    running because it failed before stopping them."""
    yield
    role_runs = sys.modules.get("tests.role_runs")
    if role_runs is not None:
        role_runs.RoleRun.kill_all_left()
