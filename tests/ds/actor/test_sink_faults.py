"""Network faults between an actor's sink and a real replay server on loopback: calls failing with
UNAVAILABLE before the server or after it stored the chunks (the reply lost), and a replay that
dies and comes back from its snapshot. Exact counts: every chunk stored exactly once, and the
replay's duplicate count equals the chunks whose reply was lost."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from algorithm.replay import ChunkIds, PrioritizedTable
from algorithm.types import Chunk
from ds.actor.sink import ReplaySink
from ds.replay.client import ReplayClient
from ds.replay.service import serve_replay
from tests.algorithm.replay.chunks import VECTOR, make_chunk
from tests.ds.actor.faults import FlakyCalls

pytestmark = [pytest.mark.grpc, pytest.mark.fault]
STRIDE = 16  # chunk i holds payload ids 16 i .. 16 i + T: no two chunks share one


def table() -> PrioritizedTable:
    return PrioritizedTable(20_000, (VECTOR,), 2, 1, alpha=0.0, seed=0)


def chunks(n: int) -> list[Chunk]:
    return [make_chunk(1 + i % 8, STRIDE * i) for i in range(n)]


def stored_payloads(tab: PrioritizedTable, path: Path) -> list[int]:
    """The payload id of every stored step row, sorted, read from the table's saved file."""
    tab.save(path)
    with np.load(path, allow_pickle=False) as f:
        row_key, end_key, obs = f["row_key"], f["end_key"], f["obs_0"]
    steps = (row_key >= 0) & (row_key != end_key)
    return sorted(obs[steps, 0].astype(np.int64).tolist())


def payloads(sent: list[Chunk]) -> list[int]:
    return sorted(int(v) for c in sent for v in c.obs[0][:-1, 0])


def until(condition: Callable[[], bool], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out waiting for the condition"
        time.sleep(0.01)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_unavailable_before_or_after_the_server_loses_and_doubles_nothing(tmp_path: Path) -> None:
    tab = table()
    flaky = FlakyCalls("Insert", before=0.2, after=0.2, seed=0)
    server, port = serve_replay(tab, interceptors=[flaky])
    client = ReplayClient(f"127.0.0.1:{port}", (VECTOR,), 2)
    try:
        sink = ReplaySink(client, lambda: False, in_flight=4, max_chunks_per_insert=2, max_backoff_s=0.02)
        sent = chunks(300)
        for c in sent:
            sink(c)
        sink.flush()
        info = tab.info()
    finally:
        client.close()
        server.stop(None)
    print(f"{flaky.calls} inserts, {flaky.failed_before} failed before the servicer, {flaky.failed_after} after")
    assert flaky.failed_before >= 5 and flaky.failed_after >= 5  # the faults did happen, both kinds
    assert sink.unavailable == flaky.failed_before + flaky.failed_after  # each seen and retried
    steps = sum(len(c) for c in sent)
    assert (info["inserted_chunks"], info["inserted_steps"]) == (300, steps)  # no loss, no double
    assert info["duplicates"] == flaky.lost_chunks  # every chunk whose reply was lost came back once
    assert sink.duplicates == flaky.delivered_duplicates
    assert (sink.inserted_steps, sink.unsent_steps) == (steps, 0)
    assert stored_payloads(tab, tmp_path / "replay.npz") == payloads(sent)  # each step's data exactly once


def test_a_replay_restarted_from_its_snapshot_gets_back_what_was_not_acknowledged(tmp_path: Path) -> None:
    """The replay dies (without saving) and a new one loads its last snapshot. The actor's sink
    sends again every chunk whose reply it never got: those the snapshot holds are duplicates, the
    one stored after it is stored again. Another actor's chunk acknowledged after the snapshot is
    gone: its sender had its answer and will not send it again (at least once ends there)."""
    port, snapshot = free_port(), tmp_path / "snapshot.npz"
    address = f"127.0.0.1:{port}"
    first, flaky = table(), FlakyCalls("Insert")
    server, _ = serve_replay(first, address, interceptors=[flaky])
    client = ReplayClient(address, (VECTOR,), 2)
    sent = chunks(14)
    try:
        sink = ReplaySink(client, lambda: False, in_flight=4, max_chunks_per_insert=1, max_backoff_s=0.05)
        for c in sent[:10]:
            sink(c)
        sink.flush()  # 0-9 stored and acknowledged
        flaky.after = 1.0  # from now on every reply is lost after the chunk is stored
        sink(sent[10])
        sink(sent[11])
        until(lambda: first.info()["inserted_chunks"] == 12)
        first.save(snapshot)  # holds 10 and 11, which the sink still waits for
        sink(sent[12])
        until(lambda: first.info()["inserted_chunks"] == 13)  # 12: stored after the snapshot
        flaky.after = 0.0
        other = ChunkIds(producer=12345, seqs=(0,))
        assert client.insert_once([sent[13]], other).duplicate == [False]  # acknowledged after the snapshot
        assert first.info()["inserted_chunks"] == 14
        server.stop(None)  # the replay dies without saving

        second = table()
        second.load(snapshot)
        assert second.info()["inserted_chunks"] == 12
        server, _ = serve_replay(second, address)
        sink.flush()  # 10, 11, 12 again: the sink kept them
        info = second.info()
    finally:
        client.close()
        server.stop(None)
    assert flaky.lost_chunks == 3 and sink.unavailable >= 3
    assert (info["inserted_chunks"], info["duplicates"], sink.duplicates, sink.unsent_steps) == (13, 2, 2, 0)
    assert stored_payloads(second, tmp_path / "after.npz") == payloads(sent[:13])  # 13 is lost
