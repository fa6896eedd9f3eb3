"""The two-worker scheduling of `make test` (tests/workers.py), registered here because pytest loads
this file before the workers start; the tests' own settings are in tests/conftest.py."""

from tests.workers import pytest_runtest_protocol, pytest_xdist_make_scheduler

__all__ = ["pytest_runtest_protocol", "pytest_xdist_make_scheduler"]
