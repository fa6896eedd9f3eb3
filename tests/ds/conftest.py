"""Real gRPC replay servers on loopback (port 0: the OS picks), always stopped after the test."""

from __future__ import annotations

import weakref
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from algorithm.replay import PrioritizedTable
from ds.replay_service import ReplayClient, serve_replay

ServeOverGrpc = Callable[..., ReplayClient]


@pytest.fixture
def over_grpc() -> Iterator[ServeOverGrpc]:
    """``over_grpc(table, **serve_kwargs) -> ReplayClient`` connected to a new server for ``table``.

    A server stops when its client is garbage-collected (so that hypothesis examples, which each
    build a table, do not pile servers up) and at the latest when the test ends.
    """
    stops: list[weakref.finalize] = []

    def serve(table: PrioritizedTable, **kwargs: Any) -> ReplayClient:
        server, port = serve_replay(table, "127.0.0.1:0", **kwargs)
        limit = kwargs.get("max_message_bytes")
        client = ReplayClient(
            f"127.0.0.1:{port}",
            table.sensors,
            table.action_size,
            table.rnn_state_size,
            **({} if limit is None else {"max_message_bytes": limit}),
        )
        stops.append(weakref.finalize(client, server.stop, None))
        return client

    yield serve
    for stop in stops:
        stop()
