"""The actor's sink on a real loopback replay: every chunk handed in is stored exactly once, in
fewer requests when the replay is the bottleneck; a replay that holds inserts back is waited for;
once stopping, what could not be stored is counted to the step."""

from __future__ import annotations

import numpy as np
import pytest

from algorithm.replay import PrioritizedTable, RateLimiter
from ds.actor import ReplaySink
from tests.algorithm.replay.chunks import VECTOR, make_chunk

from .conftest import ServeOverGrpc

pytestmark = pytest.mark.grpc


def test_every_chunk_is_stored_once_and_a_busy_replay_gets_them_batched(over_grpc: ServeOverGrpc) -> None:
    table = PrioritizedTable(10_000, (VECTOR,), 2, 1, alpha=0.0, seed=0)
    client = over_grpc(table)
    sink = ReplaySink(client, lambda: False, in_flight=2, max_chunks_per_insert=8)
    chunks = [make_chunk(5, 5 * i) for i in range(200)]
    for c in chunks:  # handed over far faster than round trips complete
        sink(c)
    sink.flush()
    info = table.info()
    assert info["inserted_chunks"] == 200 and info["inserted_steps"] == 1000
    assert sink.inserted_steps == 1000 and sink.unsent_steps == 0
    assert sink.requests < 200  # chunks that waited for a free slot went together
    # Every step's payload is there: make_chunk writes step k's number into its observation, and
    # 20,000 uniform draws over 1,000 steps miss one with probability ~1000 * e^-20.
    seen = np.unique(table.sample(20_000, timeout=0).obs[0][:, 0, 0])
    np.testing.assert_array_equal(seen, np.arange(1000, dtype=np.float32))


def test_one_chunk_per_request_when_nothing_waits(over_grpc: ServeOverGrpc) -> None:
    client = over_grpc(PrioritizedTable(1000, (VECTOR,), 2, 1, seed=0))
    sink = ReplaySink(client, lambda: False, in_flight=4)
    for i in range(3):
        sink(make_chunk(4, 4 * i))
    sink.flush()
    assert sink.requests == 3 and client.info()["inserted_steps"] == 12


def test_held_back_inserts_are_retried_and_once_stopping_counted(over_grpc: ServeOverGrpc) -> None:
    # 1 sample per inserted step, no tolerance, and nobody samples: after 10 steps inserts are held.
    limiter = RateLimiter(samples_per_insert=1.0, min_size_to_sample=10, tolerance=0.0)
    table = PrioritizedTable(1000, (VECTOR,), 2, 1, rate_limiter=limiter, seed=0)
    client = over_grpc(table)
    stopping = False
    waits = []

    def between() -> None:
        waits.append(1)
        if len(waits) >= 2:  # the user pressed Ctrl-C while the actor waited
            nonlocal stopping
            stopping = True

    sink = ReplaySink(client, lambda: stopping, between=between, timeout_s=0.05, in_flight=1, max_chunks_per_insert=1)
    handed = 0
    for i in range(6):
        sink(make_chunk(4, 4 * i))
        handed += 4
    sink.flush()
    stored = client.info()["inserted_steps"]
    assert sink.insert_waits >= 2 and waits
    assert stored + sink.unsent_steps == handed  # nothing vanished: stored or counted
    assert sink.unsent_steps > 0 and sink.inserted_steps == stored
