"""The security tests' certificates and real servers of every role (tests/ds/net/security_setup.py),
every server stopped after the test."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from ds.net.security import Credentials
from tests.ds.net.security_setup import Material, Served, serve
from tests.pki import Pki


@pytest.fixture(scope="module")
def material(tmp_path_factory: pytest.TempPathFactory) -> Material:
    """A CA, a wrong CA, certificates per role and the token, made once per module."""
    folder = tmp_path_factory.mktemp("pki")
    return Material(Pki(folder), folder / "token")


@pytest.fixture
def servers(tmp_path: Path) -> Iterator[Callable[..., Served]]:
    """``servers(role, credentials, health_port=None, port=0) -> Served``: real servers, every one stopped after
    the test."""
    started: list[Served] = []

    def start(role: str, credentials: Credentials, health_port: int | None = None, port: int = 0) -> Served:
        started.append(serve(role, credentials, tmp_path, health_port, port))
        return started[-1]

    yield start
    for served in started:
        served.stop()
