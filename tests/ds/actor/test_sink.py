"""The actor's sink on a real loopback replay: every chunk handed in is stored exactly once, in
fewer requests when the replay is the bottleneck; a replay that holds inserts back holds the actor
back (its backlog, and the age of what it stores, within ``max_backlog``) and is waited for; once
stopping, calls return at once, nothing is retried, the last tries are stored even while the rate
limiter still holds inserts back (the learner may have stopped first), and what could not be stored
(the replay gone) is counted to the step and logged once."""

from __future__ import annotations

import contextlib
import logging
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import pytest

from algorithm.replay import ChunkIds, Inserted, PrioritizedTable, RateLimiter, SampleTimeout
from algorithm.types import Chunk
from ds.actor.sink import MAX_IN_FLIGHT, ReplaySink
from ds.launch.local import free_port
from ds.replay.client import ReplayClient
from ds.replay.service import serve_replay
from tests.algorithm.replay.chunks import VECTOR, make_chunk
from tests.ds.conftest import ServeOverGrpc

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


def test_held_back_inserts_are_retried_and_once_stopping_stored_anyway(over_grpc: ServeOverGrpc) -> None:
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
    info = client.info()
    assert sink.insert_waits >= 2 and waits
    # Nothing thrown away: the last tries were stored although nobody samples (the learner stopped first).
    assert info["inserted_steps"] == sink.inserted_steps == handed and sink.unsent_steps == 0
    assert info["stored_past_limiter"] == handed - 12  # three chunks let in while fewer than 10 steps were stored


def test_an_insert_held_back_when_stopping_is_stored_without_a_waiting_line(
    over_grpc: ServeOverGrpc, caplog: pytest.LogCaptureFixture
) -> None:
    # Sent while running, refused by the rate limiter after the user pressed Ctrl-C: the retry is the
    # final one and passes the limiter, so "waiting to insert" would only be noise in the stop's log.
    limiter = RateLimiter(samples_per_insert=1.0, min_size_to_sample=10, tolerance=0.0)
    table = PrioritizedTable(1000, (VECTOR,), 2, 1, rate_limiter=limiter, seed=0)
    table.insert(make_chunk(12, 0))  # nobody samples: from here on inserts are held back
    client = over_grpc(table)
    stopping = False
    sink = ReplaySink(client, lambda: stopping, timeout_s=0.05, in_flight=1, max_chunks_per_insert=1)
    sink(make_chunk(4, 12))
    stopping = True
    with caplog.at_level(logging.INFO, logger="asac"):
        sink.flush()
    assert sink.insert_waits >= 1 and sink.inserted_steps == 4 and client.info()["inserted_steps"] == 16
    assert "waiting to insert" not in caplog.text, caplog.text


class AgeRecordingTable(PrioritizedTable):
    """A table that records, for every chunk it stores, how many chunks the actor handed to its sink
    after that one before it was stored (``make_chunk(5, 5 * i)`` is chunk ``i``)."""

    def __init__(self, handed: list[int], *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.handed = handed  # handed[0]: chunks handed to the sink so far, set by the test's actor
        self.ages: list[int] = []

    def insert_once(self, chunks: Sequence[Chunk], ids: ChunkIds, *args: Any, **kwargs: Any) -> Inserted:
        inserted = super().insert_once(chunks, ids, *args, **kwargs)
        handed = self.handed[0]
        for chunk, duplicate in zip(chunks, inserted.duplicate, strict=True):
            if not duplicate:
                self.ages.append(handed - 1 - int(chunk.obs[0][0, 0]) // 5)
        return inserted


def test_a_slow_learner_holds_fast_actors_back_within_the_stated_backlog(over_grpc: ServeOverGrpc) -> None:
    # The learner draws 64 windows every 0.2 s, one per inserted step: about 64 five-step chunks/s,
    # in bursts, while the actor hands chunks in as fast as it can. The rate limiter holds inserts
    # back, for longer than the sink's timeout_s between bursts, so the sink must hold the actor
    # back: its backlog, and the age of what is stored, stay within the stated bound.
    handed = [0]
    limiter = RateLimiter(samples_per_insert=1.0, min_size_to_sample=20, tolerance=40.0)
    table = AgeRecordingTable(handed, 10_000, (VECTOR,), 2, 1, alpha=0.0, rate_limiter=limiter, seed=0)
    client = over_grpc(table)
    learning = threading.Event()

    def learner() -> None:
        while not learning.wait(0.2):
            with contextlib.suppress(SampleTimeout):
                table.sample(64, timeout=0)

    sampler = threading.Thread(target=learner, daemon=True)
    sampler.start()
    checks = []
    sink = ReplaySink(
        client, lambda: False, lambda: checks.append(1), timeout_s=0.01, in_flight=2, max_chunks_per_insert=4
    )
    assert sink.max_backlog == (2 + 1) * 4
    backlog, bounds = [], []
    try:
        for i in range(100):
            handed[0] = i + 1
            sink(make_chunk(5, 5 * i))
            backlog.append(sink.backlog())
            bounds.append(sink.max_backlog)
        sink.flush()
    finally:
        learning.set()
        sampler.join()
    assert sink.insert_waits > 0 and len(checks) >= sink.insert_waits  # held back; between() ran meanwhile
    # After a call returns: one chunk less than the bound, which stays near in_flight=2's (the rate limiter
    # is what holds the actor back here, not the link: ds/actor/sink.py _pace).
    assert all(held <= bound - 1 for held, bound in zip(backlog, bounds, strict=True)), (backlog, bounds)
    assert max(table.ages) <= max(bounds) <= (MAX_IN_FLIGHT + 1) * 4
    info = table.info()
    assert (info["inserted_chunks"], info["inserted_steps"], sink.inserted_steps) == (100, 500, 500)
    assert sink.unsent_steps == 0 and len(table.ages) == 100  # every chunk stored, once


def test_a_held_back_actor_waits_checks_in_between_and_returns_once_stopping(
    over_grpc: ServeOverGrpc, caplog: pytest.LogCaptureFixture
) -> None:
    # Nobody samples: after 16 steps the rate limiter holds every insert back for good. What is
    # asserted is what the sink asks of the replay (each request's wait in the rate limiter) and
    # whether it waits itself, not wall-clock times, which a loaded machine stretches.
    limiter = RateLimiter(samples_per_insert=1.0, min_size_to_sample=8, tolerance=0.0)
    client = over_grpc(PrioritizedTable(1000, (VECTOR,), 2, 1, rate_limiter=limiter, seed=0))
    stopping = False
    checks = 0
    sends: list[tuple[bool, float, bool]] = []  # per request: (stopping when sent, its wait in the limiter, final)
    send = client.insert_async

    def recording_send(chunks: Sequence[Chunk], timeout: float = 0.0, **kwargs: Any) -> Any:
        sends.append((stopping, timeout, kwargs.get("producer_stopping", False)))
        return send(chunks, timeout, **kwargs)

    client.insert_async = recording_send  # type: ignore[method-assign,assignment]

    def between() -> None:  # the actor's heartbeat and done checks; the 3rd sees the budget spent
        nonlocal checks, stopping
        assert not stopping, "between() runs only while the run goes on"
        checks += 1
        stopping = checks >= 3

    waits: list[float] = []  # while an insert is held back, the actor takes new weights (every 50 ms)
    sink = ReplaySink(client, lambda: stopping, between=between, waiting=lambda: waits.append(time.monotonic()),
                      timeout_s=0.2, in_flight=2, max_chunks_per_insert=2)  # fmt: skip
    backlog, settled, stopped_after = [], [], []
    for i in range(20):
        waited_before = sink.wait_seconds
        sink(make_chunk(4, 4 * i))
        settled.append(sink.wait_seconds != waited_before)  # the call waited for an insert's answer
        backlog.append(sink.backlog())
        stopped_after.append(stopping)
    waited = stopped_after.index(True)  # the call that waited for the replay until the run stopped
    assert checks == 3 and stopping
    assert settled[waited] and sink.insert_waits >= 3  # it waited: three refusals, a check after each
    assert len(waits) >= 3  # three refusals of 0.2 s each: the actor's weights kept coming in meanwhile
    assert max(backlog[:waited]) <= sink.max_backlog - 1 == 5  # (the calls after it do not wait: stopping)
    assert backlog[waited] <= sink.max_backlog
    assert not any(settled[waited + 1 :])  # once stopping, calls return at once: no insert is waited for
    while_running = len([s for s in sends if not s[0]])
    with caplog.at_level(logging.INFO, logger="asac.actor"):
        sink.flush()
    # Every request sent once stopping is a last try that the rate limiter answers at once (a wait of
    # 0 s; the replay stores it past the limiter); only the requests sent before could still wait.
    last_tries = sends[while_running:]
    assert last_tries and all(stop and timeout == 0.0 and final for stop, timeout, final in last_tries), sends
    assert all(timeout == 0.2 and not final for _, timeout, final in sends[:while_running]), sends
    info = client.info()
    # Requests are let in while the table holds at most min_size_to_sample (8) steps: 12 to 16 steps, as the
    # sink batches up to two chunks a request, which depends on when the answers come (a loaded machine
    # made it 12 where 16 is usual). Every other step is a last try of a stopping producer, stored past
    # the limiter, not thrown away.
    assert info["inserted_steps"] == sink.inserted_steps == 20 * 4 and sink.unsent_steps == 0
    assert 80 - 16 <= info["stored_past_limiter"] <= 80 - 12
    assert not [r.getMessage() for r in caplog.records if "were not inserted" in r.getMessage()]


def test_once_stopping_a_replay_that_is_gone_is_not_retried(caplog: pytest.LogCaptureFixture) -> None:
    # Nobody samples: inserts wait in the rate limiter (for 5 s each) until the replay goes away.
    limiter = RateLimiter(samples_per_insert=1.0, min_size_to_sample=1, tolerance=0.0)
    table = PrioritizedTable(1000, (VECTOR,), 2, 1, rate_limiter=limiter, seed=0)
    table.insert(make_chunk(4))  # the one step that lets nothing else in until someone samples
    server, port = serve_replay(table, "127.0.0.1:0")
    stopping = False
    with ReplayClient(f"127.0.0.1:{port}", (VECTOR,), 2) as client:
        sink = ReplaySink(client, lambda: stopping, timeout_s=5.0, in_flight=2, max_chunks_per_insert=4)
        for i in range(5):  # two inserts wait in the rate limiter, three chunks wait here
            sink(make_chunk(4, 4 * i))
        until = time.monotonic() + 5.0
        while limiter.insert_waits < 2:
            assert time.monotonic() < until, "the inserts never reached the rate limiter"
            time.sleep(0.01)
        server.stop(None).wait()  # the replay is gone (its process stopped at the end of the run)
        stopping, requests = True, sink.requests
        with caplog.at_level(logging.INFO, logger="asac.actor"):
            sink.flush()
    assert sink.requests == requests  # nothing sent again, the waiting chunks not sent at all
    assert "retrying" not in caplog.text, caplog.text  # no backoff before a retry
    assert (sink.inserted_steps, sink.unsent_steps, sink.unsent_chunks, sink.backlog()) == (0, 20, 5, 0)
    assert sink.unavailable >= 1


def test_a_stopping_actor_acknowledges_everything_so_the_replay_can_forget_it(over_grpc: ServeOverGrpc) -> None:
    # The replay keeps the ids of at most max_producers producers, forgetting only those whose
    # every stored chunk is acknowledged. A sink acknowledged a request's chunks only in its next
    # request, so every actor that ever ran kept a place and, past the bound, new actors were refused.
    table = PrioritizedTable(1000, (VECTOR,), 2, 1, seed=0, max_producers=2)
    client = over_grpc(table)
    for actor in range(5):  # five actor processes, one after the other
        sink = ReplaySink(client, lambda: False)
        for i in range(3):
            sink(make_chunk(4, 100 * actor + 4 * i))
        sink.flush()
        sink.acknowledge_all()
    assert client.info()["inserted_steps"] == 5 * 12


@contextlib.contextmanager
def relayed(port: int, delay_ms: float) -> Iterator[str]:
    """tests/relay.py on loopback, holding every byte ``delay_ms`` each way on its way to ``port``."""
    listen = free_port()
    command = [sys.executable, "-m", "tests.relay", "--listen", f"127.0.0.1:{listen}", "--to", f"127.0.0.1:{port}",
               "--delay-ms", str(delay_ms)]  # fmt: skip
    relay = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    try:
        assert relay.stdout is not None and "relay listening" in relay.stdout.readline()
        yield f"127.0.0.1:{listen}"
    finally:
        relay.terminate()
        relay.wait(timeout=10)


@pytest.mark.parametrize(("delay_ms", "limiter_holds"), [(0.0, False), (25.0, False), (25.0, True)])
def test_a_slow_link_gets_more_inserts_in_flight_and_a_holding_rate_limiter_does_not(
    delay_ms: float, limiter_holds: bool
) -> None:
    """An actor making a 4-chunk request every ~12 ms: through 50 ms round trips (a relay) one insert in
    flight would keep it waiting; the sink sends ``1 + ceil(link / fill)`` at once (6 here), and every chunk
    is stored once. On loopback it keeps the configured one; so it does when the replay's rate limiter,
    not the link, is what holds inserts back (its time on each request is longer than the link's)."""
    limiter = RateLimiter(samples_per_insert=1.0, min_size_to_sample=8, tolerance=2.0) if limiter_holds else None
    table = PrioritizedTable(10_000, (VECTOR,), 2, 1, alpha=0.0, seed=0, rate_limiter=limiter)
    server, port = serve_replay(table, "127.0.0.1:0")
    learning = threading.Event()

    def learner() -> None:  # with the rate limiter: 8 windows every 0.2 s, a tenth of the actor's pace
        while not learning.wait(0.2):
            with contextlib.suppress(SampleTimeout):
                table.sample(8, timeout=0)

    sampler = threading.Thread(target=learner, daemon=True)
    sampler.start()
    try:
        with contextlib.ExitStack() as stack:
            address = f"127.0.0.1:{port}" if delay_ms == 0 else stack.enter_context(relayed(port, delay_ms))
            client = stack.enter_context(ReplayClient(address, (VECTOR,), 2))
            sink = ReplaySink(client, lambda: False, in_flight=1, max_chunks_per_insert=4, timeout_s=2.0)
            in_flight = []
            for i in range(120 if limiter is None else 40):
                time.sleep(0.003)  # the actor stepping: a chunk every ~3 ms
                sink(make_chunk(5, 5 * i))
                in_flight.append(sink.in_flight)
            sink.flush()
    finally:
        learning.set()
        sampler.join()
        server.stop(None)
    assert table.info()["inserted_steps"] == 5 * len(in_flight) and sink.unsent_steps == 0 and sink.duplicates == 0
    late = in_flight[len(in_flight) // 2 :]
    if delay_ms and not limiter_holds:
        assert 40 <= 1e3 * sink.link_s <= 200 and max(late) >= 3, (sink.link_s, in_flight)
    else:
        assert set(late) == {1}, (sink.link_s, in_flight)
