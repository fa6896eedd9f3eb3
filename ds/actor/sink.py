"""The actor's sink (:class:`ReplaySink`): hands the actor loop's chunks to the replay, and holds the
actor back while the replay holds inserts back.

Usage (``ds/actor/actor.py`` wires it into :class:`~algorithm.run.actor.ActorLoop`)::

    sink = ReplaySink(replay_client, stopping=lambda: stop.is_set(), between=check_heartbeats)
    loop = ActorLoop(env, policy, sink, chunk_length=64)
    ...                 # loop.step() calls sink(chunk); it returns once the replay has room
    sink.flush()        # at the end: everything stored, or (once stopping) counted in unsent_steps
    sink.acknowledge_all()  # the replay may forget this producer

Back-pressure, not backlog: while the replay's rate limiter holds inserts back (the learner is
behind) the sink keeps the actor waiting, so what it holds, and so how old what it inserts is, stays
within :attr:`ReplaySink.max_backlog` chunks. An actor stepping on meanwhile would build a queue
without bound, most of it thrown away at the end and the rest minutes old when stored.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections import deque
from collections.abc import Callable

import grpc

from algorithm.replay import ChunkIds, InsertTimeout
from algorithm.run.logging import Throttle
from algorithm.types import Chunk
from ds.net.outage import BLIP_S, GRPC_DEADLINE_DETAILS, Outage, unanswered
from ds.replay.client import PendingInsert, ReplayClient, ReplayRpcError
from ds.replay.codec import chunk_payload_bytes

log = logging.getLogger("asac.actor")
SLOW_LINK_S = 0.025
"""A link whose inserts spend longer than this on the wire (round trip less the replay's time, on average) is
slow: more inserts go out at once on it (:meth:`ReplaySink._pace`). Loopback and a LAN stay well below it,
also on a loaded machine, where a busy client can take ~10 ms to see an answer that has arrived."""
MAX_IN_FLIGHT = 8
"""The most inserts a sink keeps on their way, on a link slow enough to need them (:meth:`ReplaySink._pace`)."""
KEEPING = "the actor keeps its chunks, stops stepping once it holds its backlog, and sends them again"


class ReplaySink:
    """The actor loop's sink: inserts chunks into the replay, never drops one while it runs, and
    keeps up to ``in_flight`` inserts on their way while the actor steps on (a round trip costs
    about a millisecond on loopback, as long as stepping HalfCheetah 20 times). Chunks that arrive
    while all ``in_flight`` inserts are out wait here and go together in the next request (at most
    ``max_chunks_per_insert``, and half the replay's message limit): under load the sink sends
    fewer, larger requests, which is what bounds a replay server's rate (bench/grpc_replay.py).

    Back-pressure: a call returns only while the chunks waiting here are fewer than one request's
    worth. With every insert out and a full request waiting, it waits for the oldest insert (the
    actor does not step meanwhile): the replay's rate limiter holding inserts back (the learner is
    behind) or an unreachable replay holds the actor back too, instead of a queue growing by a chunk
    per call. So, while not stopping, this sink never holds more than :attr:`max_backlog`
    ``= (in_flight + 1) * max_chunks_per_insert`` chunks (``in_flight`` requests of at most
    ``max_chunks_per_insert`` chunks on their way, and one request's worth waiting; after a call
    returns, one chunk less), and a chunk is stored at the latest ``max_backlog`` chunks after it
    was handed in. An insert held back by the rate limiter for ``timeout_s`` (``InsertTimeout``) or
    failing because the replay is gone (UNAVAILABLE, backing off up to ``max_backoff_s``) is sent
    again; meanwhile ``between()`` runs (heartbeats, done checks).

    Once ``stopping()`` is true (the run's budget is spent, or a signal came) calls return at once
    and nothing is retried: each chunk still here gets one last try; the last tries wait in the rate
    limiter until one deadline ``last_try_wait_s()`` seconds after the first (0 by default; at the
    end of a run the learner goes on training until the actors have left, so their last inserts are
    let in within the ratio: see ds/actor/actor.py), and then the replay stores them anyway (they are
    sent with ``producer_stopping``: after a Ctrl-C the learner has stopped first and draws no more,
    and what was collected is kept for a resumed run). After the first sign that the replay is gone
    no more are sent. What was not stored (the replay gone, or one from before ``producer_stopping``
    that still refuses) is counted in ``unsent_steps`` / ``unsent_chunks`` and logged once, by
    :meth:`flush`, which waits for everything on its way. Chunks may be stored out of order after a
    retry; each is self-contained (no window spans two chunks), so order does not matter.

    On a slow link (over :data:`SLOW_LINK_S`, and longer than the actor takes to fill a request) one insert in flight
    would leave each chunk waiting for another's answer, and the actor waiting with it: so the sink
    keeps as many on their way as one round trip of the link takes to fill, and one more,
    ``1 + ceil(link / fill)``,
    never fewer than ``in_flight`` nor more than :data:`MAX_IN_FLIGHT` (:meth:`_pace`). The link's
    time is the round trip less the replay's own time on the request (``InsertReply.served_s``, which
    includes waiting in the rate limiter); while the replay's time is the longer (its rate limiter
    holds inserts back) it stays at ``in_flight``: more would only wait there, each taking a worker.
    Through 50 ms round trips this kept an actor's env steps/s where one in flight lost half of them
    (bench/network_links.py).

    Delivery is at least once and storage at most once: every chunk gets a sequence number under
    this sink's random ``producer`` id when handed in and keeps it on every resend, so a chunk that
    was stored although its reply was lost is answered as a duplicate (counted in ``duplicates``)
    rather than stored twice; each request also tells the replay the lowest number still held here
    (``acked_below``), so it can forget the rest (algorithm/replay/dedup.py).
    """

    def __init__(
        self,
        replay: ReplayClient,
        stopping: Callable[[], bool],
        between: Callable[[], None] = lambda: None,
        waiting: Callable[[], None] = lambda: None,
        timeout_s: float = 2.0,
        in_flight: int = 4,
        max_chunks_per_insert: int = 16,
        max_backoff_s: float = 2.0,
        last_try_wait_s: Callable[[], float] = lambda: 0.0,
    ) -> None:
        if in_flight < 1:
            raise ValueError(f"in_flight must be >= 1, got {in_flight}")
        if max_chunks_per_insert < 1:
            raise ValueError(f"max_chunks_per_insert must be >= 1, got {max_chunks_per_insert}")
        self.replay = replay
        self.stopping = stopping
        self.between = between
        self.waiting = waiting  # called every 50 ms while an insert is waited for (new weights come in)
        self.timeout_s = timeout_s
        self.in_flight = in_flight  # now: grows on a slow link (_pace)
        self.configured_in_flight = in_flight
        self.max_chunks_per_insert = max_chunks_per_insert
        self.max_backoff_s = max_backoff_s
        self.last_try_wait_s = last_try_wait_s
        self._last_tries_until: float | None = None  # the deadline all last tries share, once stopping
        self.inserted_steps = 0
        self.requests = 0
        self.insert_waits = 0
        self.wait_seconds = 0.0
        self.unavailable = 0
        self.unsent_steps = 0
        self.unsent_chunks = 0
        self.duplicates = 0
        self.replay_inserted_steps = -1  # the replay's count after the latest answered insert
        self.producer = int.from_bytes(os.urandom(8), "little") or 1
        self._next_seq = 0
        self._pending: deque[PendingInsert] = deque()
        self._queued: list[tuple[int, Chunk]] = []
        self._backoff = 0.0
        self._replay_gone = False  # seen gone while stopping: nothing more is sent
        self._reported_unsent = 0
        self._acknowledged = 0  # every number below it acknowledged to the replay
        self._log = Throttle()
        self._replay_link = Outage(f"replay at {getattr(replay, 'address', 'in process')}", log, BLIP_S)
        self.link_s = 0.0  # the link's part of an insert's round trip (moving average)
        self.served_s = 0.0  # the replay's part, waiting in its rate limiter included (moving average)
        self._chunk_s: float | None = None  # the actor's time to make one chunk, outside this sink (moving average)
        self._returned_at: float | None = None

    @property
    def max_backlog(self) -> int:
        """The most chunks this sink holds now while not stopping (see the class docstring): at most
        ``(MAX_IN_FLIGHT + 1) * max_chunks_per_insert``, on a slow link."""
        return (max(self.in_flight, len(self._pending)) + 1) * self.max_chunks_per_insert

    def __call__(self, chunk: Chunk) -> None:
        if self._returned_at is not None:  # chunks come in bursts (one per env): a slow average evens them out
            self._chunk_s = _average(self._chunk_s, time.monotonic() - self._returned_at, 0.05)
        try:
            self._take(chunk)
        finally:
            self._returned_at = time.monotonic()

    def _take(self, chunk: Chunk) -> None:
        self._queued.append((self._next_seq, chunk))
        self._next_seq += 1
        while True:
            while self._queued and len(self._pending) < self.in_flight and not self._replay_gone:
                self._send_queued()
            if len(self._queued) < self.max_chunks_per_insert or self.stopping():
                return
            self._settle_oldest()  # every insert is out and a request's worth waits: the actor waits too

    def backlog(self) -> int:
        """Chunks handed in and not yet stored: inserts on their way plus chunks waiting to be sent
        (at most :attr:`max_backlog` while not stopping)."""
        return sum(len(p.chunks) for p in self._pending) + len(self._queued)

    def held_steps(self) -> int:
        """Env steps handed in and not yet stored (the chunks of :meth:`backlog`)."""
        return sum(p.steps() for p in self._pending) + sum(len(chunk) for _, chunk in self._queued)

    def flush(self) -> None:
        """Wait until every chunk handed in is stored or, once stopping, counted as unsent; log
        what was not stored (one line)."""
        while self._pending or self._queued:
            if self._queued and self._replay_gone:
                self._give_up([chunk for _, chunk in self._queued])
                self._queued.clear()
            elif self._queued and len(self._pending) < self.in_flight:
                self._send_queued()
            else:
                self._settle_oldest()
        if self.unsent_steps > self._reported_unsent:
            unsent, chunks = self.unsent_steps, self.unsent_chunks
            log.warning(
                "%d collected steps (%d chunks) were not inserted (the replay was gone or refused them)", unsent, chunks
            )
            self._reported_unsent = self.unsent_steps

    def acknowledge_all(self) -> None:
        """After the last :meth:`flush` (the actor stops): tell the replay that no chunk numbered so
        far will be sent again (an Insert without chunks), so it can forget this producer and give
        its place in its bounded ledger (``replay_config.max_producers``) to a new one. Best
        effort, one try."""
        if self._next_seq == 0 or self._replay_gone or self._acknowledged == self._next_seq:
            return
        try:
            self.replay.insert_async([], ids=ChunkIds(self.producer, (), self._next_seq)).result()
        except (InsertTimeout, ReplayRpcError) as e:
            log.info("could not tell the replay that every chunk is answered (its ledger keeps this actor): %s", e)
            return
        self._acknowledged = self._next_seq

    def _send_queued(self) -> None:
        """Send the waiting chunks, as many per request as the limits allow."""
        replay = self.replay
        budget = replay.max_message_bytes // 2
        count, size = 0, 0
        for _, chunk in self._queued[: self.max_chunks_per_insert]:
            size += chunk_payload_bytes(replay.sensors, replay.action_size, len(chunk), replay.rnn_state_size)
            if count and size > budget:
                break
            count += 1
        batch = self._queued[:count]
        del self._queued[:count]
        self._send(tuple(seq for seq, _ in batch), [chunk for _, chunk in batch])

    def _send(self, seqs: tuple[int, ...], chunks: list[Chunk]) -> None:
        """Send ``chunks`` numbered ``seqs``; once stopping, as their last try (no waiting in the
        rate limiter)."""
        held = [*seqs, *(seq for seq, _ in self._queued)]
        held += [seq for p in self._pending if p.ids is not None for seq in p.ids.seqs]
        ids = ChunkIds(self.producer, seqs, min(held, default=self._next_seq))
        final = self.stopping()
        timeout = self.timeout_s
        if final:  # the last tries share one deadline, however many there are
            if self._last_tries_until is None:
                self._last_tries_until = time.monotonic() + self.last_try_wait_s()
            timeout = max(0.0, self._last_tries_until - time.monotonic())
        pending = self.replay.insert_async(chunks, timeout=timeout, ids=ids, producer_stopping=final)
        pending.final = final
        self._pending.append(pending)
        self.requests += 1

    def _settle_oldest(self) -> None:
        """Wait for the oldest insert; on a refusal to wait or an unreachable replay, send it again
        (first again: it is settled before newer inserts), unless that was its last try or the
        replay is gone while stopping: then its chunks are counted as unsent."""
        start = time.monotonic()
        pending = self._pending.popleft()
        try:
            inserted = pending.result(while_waiting=self.waiting)
        except InsertTimeout as e:
            self.insert_waits += 1
            if unanswered(e):  # not the rate limiter: the replay did not answer (a partition, a stalled process)
                self._replay_link.failed(GRPC_DEADLINE_DETAILS, KEEPING)
            elif not self.stopping() and self._log():  # while stopping, the final inserts pass the limiter anyway
                log.info("waiting to insert: %s", e)
        except ReplayRpcError as e:
            if e.code != grpc.StatusCode.UNAVAILABLE:
                raise
            self.unavailable += 1
            if self.stopping():
                self._replay_gone = True  # no retries against a replay that is gone: the run is ending
            else:
                self._replay_link.failed(str(e), KEEPING)
                self._backoff = min(max(2 * self._backoff, 0.05), self.max_backoff_s)
                time.sleep(self._backoff)
        else:
            self._replay_link.ok()
            self._pace(pending)
            self.duplicates += sum(inserted.duplicate)
            self.inserted_steps += pending.steps()
            self.replay_inserted_steps = max(self.replay_inserted_steps, inserted.inserted_steps)
            self._backoff = 0.0
            return
        finally:
            self.wait_seconds += time.monotonic() - start
        if pending.final or self._replay_gone:
            self._give_up(pending.chunks)
            return
        if not self.stopping():
            self.between()
        assert pending.ids is not None
        self._send(pending.ids.seqs, pending.chunks)
        self._pending.rotate(1)

    def _pace(self, answered: PendingInsert) -> None:
        """Inserts in flight for the link as measured now: as many as the actor fills in one of its
        round trips, plus the one being filled (class docstring)."""
        link_s = answered.link_s() if hasattr(answered, "link_s") else None
        if link_s is None or self._chunk_s is None:
            return
        self.link_s = _average(self.link_s or None, link_s, 0.2)
        self.served_s = _average(self.served_s or None, answered.served_s or 0.0, 0.2)
        if self.link_s < SLOW_LINK_S or self.served_s > self.link_s:
            # A fast link (loopback, a LAN), or the replay (its rate limiter) is the slow part: more requests
            # would only wait there, each taking one of its workers.
            self.in_flight = self.configured_in_flight
            return
        fill_s = max(self._chunk_s * self.max_chunks_per_insert, 1e-6)
        self.in_flight = min(MAX_IN_FLIGHT, max(self.configured_in_flight, 1 + math.ceil(self.link_s / fill_s)))

    def _give_up(self, chunks: list[Chunk]) -> None:
        self.unsent_chunks += len(chunks)
        self.unsent_steps += sum(len(chunk) for chunk in chunks)


def _average(average: float | None, sample: float, weight: float) -> float:
    return sample if average is None else (1.0 - weight) * average + weight * sample


__all__ = ["MAX_IN_FLIGHT", "SLOW_LINK_S", "ReplaySink"]
