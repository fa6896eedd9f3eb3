"""Real gRPC replay servers on loopback (port 0: the OS picks), always stopped after the test: the
``over_grpc`` fixture the actor, learner, replay and evolver tests share. The evolver tests' ``setup``
is in tests/ds/evolver/conftest.py, the security tests' certificates and servers in
tests/ds/net/conftest.py."""

from __future__ import annotations

import weakref
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from algorithm.replay import PrioritizedTable
from ds.replay.client import ReplayClient
from ds.replay.service import serve_replay

ServeOverGrpc = Callable[..., ReplayClient]


class FolderClient(ReplayClient):
    """A replay client whose ``save``/``load`` take paths inside the server's snapshot folder, as the
    in-process table's do, and send them as the relative names the server accepts (a path outside
    the folder is sent as it is, to be refused)."""

    snapshot_dir: Path

    def save(self, path: str | Path = "") -> None:
        super().save(self._name(path))

    def load(self, path: str | Path = "") -> None:
        super().load(self._name(path))

    def _name(self, path: str | Path) -> str:
        path = Path(path)
        return str(path.relative_to(self.snapshot_dir)) if path.is_relative_to(self.snapshot_dir) else str(path)


@pytest.fixture
def over_grpc(tmp_path: Path) -> Iterator[ServeOverGrpc]:
    """``over_grpc(table, **serve_kwargs) -> ReplayClient`` connected to a new server for ``table``.

    The server's snapshot folder is the test's ``tmp_path``, and the client takes paths in it for
    ``save``/``load`` (:class:`FolderClient`), so the contract tests name files as they do in-process.
    A server stops when its client is garbage-collected (so that hypothesis examples, which each
    build a table, do not pile servers up) and at the latest when the test ends.
    """
    stops: list[weakref.finalize] = []

    def serve(table: PrioritizedTable, **kwargs: Any) -> ReplayClient:
        kwargs.setdefault("snapshot_dir", tmp_path)
        server, port = serve_replay(table, "127.0.0.1:0", **kwargs)
        limit = kwargs.get("max_message_bytes")
        client = FolderClient(
            f"127.0.0.1:{port}",
            table.sensors,
            table.action_size,
            table.rnn_state_size,
            **({} if limit is None else {"max_message_bytes": limit}),
        )
        client.snapshot_dir = Path(kwargs["snapshot_dir"])
        stops.append(weakref.finalize(client, server.stop, None))
        return client

    yield serve
    for stop in stops:
        stop()
