"""The evolver tests' ``setup``: evolvers on one state directory with their servers and clients
(tests/ds/evolver/evolver_setup.py), every one stopped after the test."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.ds.evolver.evolver_setup import Setup


@pytest.fixture
def setup(tmp_path: Path) -> Iterator[Setup]:
    """Evolvers on one state directory (``tmp_path / "evolver"``), every one stopped after the test."""
    s = Setup(tmp_path / "evolver")
    yield s
    s.close()
