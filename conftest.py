"""The two-worker scheduling of `make test` (tests/workers.py: no torch import, for the controller of
the workers); the tests' own settings are in tests/conftest.py."""

from tests.workers import (
    pytest_runtest_protocol,
    pytest_testnodedown,
    pytest_testnodeready,
    pytest_xdist_make_scheduler,
)

__all__ = ["pytest_runtest_protocol", "pytest_testnodedown", "pytest_testnodeready", "pytest_xdist_make_scheduler"]
