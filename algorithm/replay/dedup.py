"""Idempotent inserts: which chunks of which producer a table has stored, so that a chunk sent again
is answered with the keys it already got instead of being stored twice.

Usage (:meth:`PrioritizedTable.insert_once` does this under the table's lock)::

    ids = ChunkIds(producer=0x5EED, seqs=(12, 13), acked_below=12)
    ledger.settle(ids)                 # forget what the producer says it will never send again;
                                       # a new producer past max_producers: ProducerLimitReached
    known = ledger.lookup(ids)         # per chunk: None (new), a first key, or FORGOTTEN
    ...store the new chunks...
    ledger.record(ids, 12, first_key)   # a new producer takes its place here

Delivery from an actor to the replay is at least once: the actor's sink (ds/actor/sink.py) keeps every
chunk until a reply says it is stored and sends it again, with the same producer id and sequence
number, when the reply does not come (the replay was unreachable, or the reply was lost after the
chunk was stored). The ledger turns the second case from a double insert into a duplicate answer.
It is saved with the table, so a replay restarted from its snapshot still recognises every chunk
the snapshot holds. What a snapshot cannot hold is a chunk stored after it: after a crash that
chunk is gone, and if its reply had reached the actor the actor will not send it again (it cannot
know); only unacknowledged chunks come back.

Memory is bounded by what producers have in flight, not by what they ever sent: each request
carries ``acked_below``, the producer's promise that every chunk numbered lower has had its answer
(stored, or given up when stopping) and will not be sent again. The ledger keeps, per producer,
that floor plus the first key of each stored chunk at or above it; a chunk below the floor that
still arrives (a stale copy of a request the producer already gave up waiting for) is a duplicate
whose keys are forgotten. Past :data:`MAX_OPEN_PER_PRODUCER` stored chunks above one producer's
floor its oldest are dropped: a chunk of it sent again after that would be stored twice, never
lost. The actor's sink has at most ``in_flight * max_chunks_per_insert`` (64) chunks on their way,
far below that cap.

Producers are bounded by ``max_producers`` (``replay_config.max_producers``, default
:data:`MAX_PRODUCERS`), and reaching the bound never forgets a producer that may still send a chunk
again: a new producer that would exceed it is refused (:class:`ProducerLimitReached`, nothing
stored; over gRPC RESOURCE_EXHAUSTED) unless a *settled* producer can make room. Settled: nothing
of it is stored above its floor, so every chunk it ever had stored is acknowledged and will not be
sent again; the least recently seen settled producer is forgotten (a chunk of it at or above its
floor was never stored, so storing it later is its first time). What is not done is forgetting
producers that have been quiet for a long time: an actor cut off from the replay keeps its
unacknowledged chunks and sends them again whenever it gets through, however long that takes, so
no idle time makes forgetting it safe. An actor's sink acknowledges a request's chunks in its
next request, and when it stops an Insert without chunks acknowledges the rest
(``ReplaySink.acknowledge_all``), so a finished actor is settled; a killed one (a restarted actor is
a new producer) holds its place for the life of the replay and its snapshots: ``max_producers``
bounds the live and killed actor processes a replay serves. Residual: a stale copy of a settled
producer's chunk below its floor that arrives after the producer was forgotten is stored again.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

MAX_PRODUCERS = 1024  # the default of replay_config.max_producers
MAX_OPEN_PER_PRODUCER = 4096
FORGOTTEN = -1  # lookup(): stored once, below the producer's floor, keys no longer known
_U64 = 1 << 64


@dataclass(frozen=True)
class ChunkIds:
    """Names the chunks of one insert request so that sending it again is harmless.

    ``producer``: a random nonzero 64-bit id of the sending process (a restarted actor is a new
    producer). ``seqs``: one number per chunk, unique per producer, the same every time the chunk
    is sent. ``acked_below``: every chunk of this producer numbered below it has had its answer and
    will never be sent again, so the table may forget it.
    """

    producer: int
    seqs: tuple[int, ...]
    acked_below: int = 0

    def check(self, n_chunks: int) -> None:
        """Raise ``ValueError`` naming what is wrong for a request of ``n_chunks`` chunks."""
        if not 0 < self.producer < _U64:
            raise ValueError(f"insert ids: producer must be in [1, 2**64), got {self.producer}")
        if len(self.seqs) != n_chunks:
            raise ValueError(f"insert ids: {len(self.seqs)} sequence numbers for {n_chunks} chunks")
        if any(not 0 <= s < _U64 for s in self.seqs) or not 0 <= self.acked_below < _U64:
            raise ValueError("insert ids: sequence numbers and acked_below must be in [0, 2**64)")
        if len(set(self.seqs)) != len(self.seqs):
            raise ValueError(f"insert ids: sequence numbers repeat within one request: {list(self.seqs)}")


class Inserted(NamedTuple):
    """What an idempotent insert returns: each chunk's ``T`` uint64 keys (for a duplicate the keys
    it was stored under, or an empty array when the table no longer knows them) and whether it was
    a duplicate (already stored, not stored again); ``inserted_steps``: the table's count of
    inserted steps after this insert (-1: not known), which actors read to stop at ``max_step``
    without asking."""

    keys: list[np.ndarray]
    duplicate: list[bool]
    inserted_steps: int = -1


@dataclass
class _Producer:
    floor: int = 0
    stored: dict[int, int] = field(default_factory=dict)  # seq -> first key, for stored seqs >= floor


class ProducerLimitReached(RuntimeError):
    """A new producer was refused: the ledger holds ``max_producers`` producers and none of them is
    settled (see the module docstring). Nothing was stored; the message names the bound and the
    config key that raises it. Over gRPC: RESOURCE_EXHAUSTED with the same message."""


class ChunkLedger:
    """Per producer: the floor it acknowledged and the first key of each stored chunk above it, for
    at most ``max_producers`` producers. Not thread-safe: the table calls it under its own lock."""

    def __init__(self, max_producers: int = MAX_PRODUCERS) -> None:
        if int(max_producers) < 1:
            raise ValueError(f"max_producers must be >= 1, got {max_producers}")
        self.max_producers = int(max_producers)
        self._producers: OrderedDict[int, _Producer] = OrderedDict()  # least recently seen first
        self._settled: OrderedDict[int, None] = OrderedDict()  # those with nothing stored above the floor, ditto

    def __len__(self) -> int:
        return len(self._producers)

    def settle(self, ids: ChunkIds) -> None:
        """Raise a known producer's floor to ``ids.acked_below`` and forget its chunks below it. A new
        producer takes no place yet (it does when :meth:`record` stores its first chunk, so a request
        that stores nothing, refused, timed out or acknowledge-only, leaves the ledger as it was);
        raises :class:`ProducerLimitReached`, changing nothing, when the ledger is full and none of
        its producers is settled."""
        p = self._producers.get(ids.producer)
        if p is None:
            self._check_room(ids.producer)
            return
        self._producers.move_to_end(ids.producer)
        if ids.acked_below > p.floor:
            p.floor = ids.acked_below
            p.stored = {s: k for s, k in p.stored.items() if s >= p.floor}
        if p.stored:
            self._settled.pop(ids.producer, None)
        else:
            self._settled[ids.producer] = None
            self._settled.move_to_end(ids.producer)

    def _excess(self) -> int:
        """How many producers must be forgotten before a new one fits (a ledger loaded from a table
        saved with a larger bound may hold more than ``max_producers``)."""
        return max(0, len(self._producers) + 1 - self.max_producers)

    def _check_room(self, producer: int) -> None:
        if self._excess() > len(self._settled):
            raise ProducerLimitReached(
                f"replay refuses a new producer (an actor process, id {producer:#x}): it keeps the chunk ids of "
                f"{len(self._producers)} producers (replay_config.max_producers: {self.max_producers}) and each "
                "may still send a chunk again, which would be stored twice if its ids were forgotten; raise "
                "replay_config.max_producers in the replay's config (every actor process started over the "
                "replay's life takes a place, restarts included)"
            )

    def lookup(self, ids: ChunkIds) -> list[int | None]:
        """Per chunk: None if it is new, else the first key it was stored under (:data:`FORGOTTEN`
        when below the producer's floor)."""
        p = self._producers.get(ids.producer)
        if p is None:
            return [None] * len(ids.seqs)
        return [FORGOTTEN if s < p.floor else p.stored.get(s) for s in ids.seqs]

    def record(self, ids: ChunkIds, seq: int, first_key: int) -> None:
        """Remember that chunk ``seq`` of ``ids.producer`` (admitted by :meth:`settle` since the table
        last released its lock) is stored from key ``first_key`` on. A new producer takes its place
        here, with ``ids.acked_below`` as its floor, forgetting the least recently seen settled
        producers when the ledger is full."""
        p = self._producers.get(ids.producer)
        if p is None:
            self._check_room(ids.producer)
            for _ in range(self._excess()):
                forgotten, _ = self._settled.popitem(last=False)
                del self._producers[forgotten]
            p = self._producers[ids.producer] = _Producer(floor=ids.acked_below)
        p.stored[seq] = first_key
        self._settled.pop(ids.producer, None)
        while len(p.stored) > MAX_OPEN_PER_PRODUCER:
            del p.stored[min(p.stored)]

    def state_dict(self) -> list[list[Any]]:
        """JSON-friendly: ``[[producer, floor, [[seq, first_key], ...]], ...]``, least recent first."""
        return [[pid, p.floor, sorted(p.stored.items())] for pid, p in self._producers.items()]

    @classmethod
    def from_state(cls, state: Sequence[Any], next_key: int, max_producers: int = MAX_PRODUCERS) -> ChunkLedger:
        """A ledger from :meth:`state_dict`; raises ``ValueError`` if it is malformed or names keys
        the table has not issued (``>= next_key``). Every producer of ``state`` is kept, even past
        ``max_producers`` (a file saved under a larger bound): new producers then wait for room."""
        ledger = cls(max_producers)
        for entry in state:
            producer, floor, stored = entry
            ids = [producer, floor] + [x for pair in stored for x in pair]
            if not all(isinstance(x, int) and 0 <= x < _U64 for x in ids) or producer == 0:
                raise ValueError(f"ledger entry {entry!r}: every number must be an integer in [0, 2**64)")
            seqs = {int(s): int(k) for s, k in stored}
            if len(seqs) != len(stored) or any(s < floor for s in seqs) or any(k >= next_key for k in seqs.values()):
                raise ValueError(f"ledger of producer {producer}: sequence numbers must be unique and >= its "
                                 f"floor {floor}, keys below next_key {next_key}")  # fmt: skip
            if producer in ledger._producers:
                raise ValueError(f"ledger: producer {producer} listed twice")
            ledger._producers[int(producer)] = _Producer(int(floor), seqs)
            if not seqs:
                ledger._settled[int(producer)] = None
        return ledger
