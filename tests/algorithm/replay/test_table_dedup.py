"""insert_once: a chunk sent again under its (producer, sequence) is answered, not stored twice;
the ids are forgotten once acknowledged, bounded (a new producer past the bound is refused), and
saved with the table."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from algorithm.replay import ChunkIds, InsertTimeout, PrioritizedTable, ProducerLimitReached, RateLimiter, dedup
from algorithm.replay.dedup import ChunkLedger

from .chunks import VECTOR, make_chunk
from .conftest import Connect

PRODUCER = 0xA5A5_0000_1234_5678


def table(capacity: int = 200, **kwargs: Any) -> PrioritizedTable:
    return PrioritizedTable(capacity, (VECTOR,), 2, 1, seed=0, **kwargs)


def refused_for_producers(error: BaseException) -> bool:
    """The refusal of a new producer past max_producers: in process :class:`ProducerLimitReached`,
    over gRPC (tests/ds/replay/test_client_contract.py) an error with status RESOURCE_EXHAUSTED."""
    code = getattr(error, "code", None)
    return isinstance(error, ProducerLimitReached) or getattr(code, "name", None) == "RESOURCE_EXHAUSTED"


def stored_observations(tab: Any) -> list[float]:
    """Every stored step's first observation value (make_chunk writes its key there), sorted."""
    batch = tab.sample(4000, timeout=0)
    return sorted(set(batch.obs[0][:, 0, 0].tolist()))


def test_a_chunk_sent_again_is_answered_with_its_keys_and_stored_once(connect: Connect) -> None:
    tab = connect(table())
    a, b, c = make_chunk(3, 0), make_chunk(2, 100), make_chunk(4, 200)
    first = tab.insert_once([a, b], ChunkIds(PRODUCER, (0, 1)))
    assert first.duplicate == [False, False]
    assert [k.tolist() for k in first.keys] == [[0, 1, 2], [4, 5]]
    assert first.inserted_steps == 5  # the table's count after it: actors stop at max_step on it
    again = tab.insert_once([a, b], ChunkIds(PRODUCER, (0, 1)))  # the reply was lost: sent again
    assert again.duplicate == [True, True]
    assert [k.tolist() for k in again.keys] == [[0, 1, 2], [4, 5]]  # the keys it got the first time
    assert again.inserted_steps == 5
    mixed = tab.insert_once([b, c], ChunkIds(PRODUCER, (1, 2)))  # only the new chunk is stored
    assert mixed.duplicate == [True, False]
    assert [k.tolist() for k in mixed.keys] == [[4, 5], [7, 8, 9, 10]]
    other = tab.insert_once([a], ChunkIds(PRODUCER + 1, (0,)))  # another producer's number 0
    assert other.duplicate == [False] and other.keys[0].tolist() == [12, 13, 14]
    info = tab.info()
    assert (info["inserted_chunks"], info["inserted_steps"], info["duplicates"], info["producers"]) == (4, 12, 3, 2)
    assert tab.insert_many([a])[0].tolist() == [16, 17, 18]  # without ids nothing is checked


def test_acknowledged_numbers_are_forgotten_and_a_stale_copy_is_not_stored(connect: Connect) -> None:
    tab = connect(table())
    tab.insert_once([make_chunk(2, 0)], ChunkIds(PRODUCER, (0,), acked_below=0))
    tab.insert_once([make_chunk(2, 10)], ChunkIds(PRODUCER, (1,), acked_below=1))  # 0 was answered
    # A copy of number 0 still on its way (its sender gave up waiting and sent it again) arrives late.
    stale = tab.insert_once([make_chunk(2, 0)], ChunkIds(PRODUCER, (0,), acked_below=0))
    assert stale.duplicate == [True] and stale.keys[0].tolist() == []  # its keys are forgotten
    assert tab.insert_once([make_chunk(2, 10)], ChunkIds(PRODUCER, (1,), acked_below=1)).keys[0].tolist() == [3, 4]
    info = tab.info()
    assert (info["inserted_chunks"], info["duplicates"]) == (2, 2)
    assert stored_observations(tab) == [0.0, 1.0, 10.0, 11.0]


def test_a_request_of_duplicates_only_is_not_held_back_by_the_rate_limiter(connect: Connect) -> None:
    # One sample per inserted step past 4, no tolerance, and nobody samples: after 5 steps inserts are held.
    tab = connect(table(rate_limiter=RateLimiter(1.0, min_size_to_sample=4, tolerance=0.0)))
    chunk = make_chunk(5, 0)
    tab.insert_once([chunk], ChunkIds(PRODUCER, (0,)), timeout=0)
    with pytest.raises(InsertTimeout):
        tab.insert_once([make_chunk(4, 10)], ChunkIds(PRODUCER, (1,)), timeout=0)
    assert tab.insert_once([chunk], ChunkIds(PRODUCER, (0,)), timeout=0).duplicate == [True]
    info = tab.info()
    assert (info["inserted_steps"], info["duplicates"]) == (5, 1)


def test_a_stopping_producers_last_tries_are_stored_past_the_rate_limiter_once(connect: Connect) -> None:
    # Nobody samples (the learner stopped first, at a Ctrl-C of the whole run): after 5 steps the
    # rate limiter holds inserts back. A producer's last tries (producer_stopping) are stored after
    # the wait all the same, counted, and a copy of one sent again is still stored only once.
    tab = connect(table(rate_limiter=RateLimiter(1.0, min_size_to_sample=4, tolerance=0.0)))
    tab.insert_once([make_chunk(5, 0)], ChunkIds(PRODUCER, (0,)), timeout=0)
    with pytest.raises(InsertTimeout):  # not stopping: held back as before
        tab.insert_once([make_chunk(4, 10)], ChunkIds(PRODUCER, (1,)), timeout=0)
    last = [make_chunk(4, 10), make_chunk(3, 20)]
    inserted = tab.insert_once(last, ChunkIds(PRODUCER, (1, 2)), timeout=0.05, producer_stopping=True)
    assert inserted.duplicate == [False, False] and [len(k) for k in inserted.keys] == [4, 3]
    again = tab.insert_once(last[:1], ChunkIds(PRODUCER, (1,)), timeout=0, producer_stopping=True)
    assert again.duplicate == [True]
    info = tab.info()
    assert (info["inserted_steps"], info["stored_past_limiter"], info["duplicates"]) == (12, 7, 1)
    assert stored_observations(tab) == [0.0, 1.0, 2.0, 3.0, 4.0, 10.0, 11.0, 12.0, 13.0, 20.0, 21.0, 22.0]


def test_copies_waiting_in_the_rate_limiter_store_the_chunk_once(connect: Connect) -> None:
    # The limiter holds every copy back; while they wait the lock is free, so each must look again
    # once admitted: exactly one stores the chunk, the others are duplicates.
    tab = connect(table(rate_limiter=RateLimiter(1.0, min_size_to_sample=2, tolerance=0.0)))
    tab.insert(make_chunk(3, 0))  # one window owed to the learner: inserts wait
    chunk, results, errors = make_chunk(3, 50), [], []

    def send() -> None:
        try:
            results.append(tab.insert_once([chunk], ChunkIds(PRODUCER, (7,)), timeout=30.0))
        except Exception as e:  # surfaced by the assertion below
            errors.append(e)

    threads = [threading.Thread(target=send) for _ in range(6)]
    for th in threads:
        th.start()
    while tab.info()["insert_waits"] < 6:  # all six are waiting
        threading.Event().wait(0.01)
    tab.sample(2, timeout=0)  # the learner catches up: one copy is admitted and stores 3 steps
    while not results and not errors:
        threading.Event().wait(0.01)
    tab.sample(2, timeout=0)  # and again: the other copies are admitted and find the chunk stored
    for th in threads:
        th.join(30)
    assert not errors and len(results) == 6
    assert sorted(r.duplicate[0] for r in results) == [False] + [True] * 5
    assert all(r.keys[0].tolist() == [4, 5, 6] for r in results)
    info = tab.info()
    assert (info["inserted_chunks"], info["inserted_steps"], info["duplicates"]) == (2, 6, 5)


@pytest.mark.parametrize(
    ("ids", "message"),
    [
        (ChunkIds(0, (0, 1)), r"producer must be in \[1, 2\*\*64\)"),
        (ChunkIds(PRODUCER, (0,)), "1 sequence numbers for 2 chunks"),
        (ChunkIds(PRODUCER, (3, 3)), "sequence numbers repeat within one request"),
        (ChunkIds(PRODUCER, (0, -1)), "must be in"),
        (ChunkIds(PRODUCER, (0, 1), acked_below=-5), "must be in"),
    ],
)
def test_bad_ids_are_named_and_store_nothing(connect: Connect, ids: ChunkIds, message: str) -> None:
    tab = connect(table())
    with pytest.raises(ValueError, match=message):
        tab.insert_once([make_chunk(2, 0), make_chunk(2, 10)], ids)
    info = tab.info()
    assert (info["inserted_chunks"], info["duplicates"], info["producers"]) == (0, 0, 0)


def test_a_table_loaded_from_a_snapshot_knows_the_chunks_the_snapshot_holds(connect: Connect, tmp_path: Path) -> None:
    """What kill -9 and a restart from the last snapshot do to a producer that keeps its
    unacknowledged chunks: those stored before the snapshot come back as duplicates, those stored
    after it are stored again, and an acknowledged one stored after it is gone."""
    crashed = connect(table())
    crashed.insert_once([make_chunk(2, 0), make_chunk(2, 10)], ChunkIds(PRODUCER, (0, 1)))  # 0 acknowledged,
    crashed.insert_once([make_chunk(2, 20)], ChunkIds(PRODUCER, (2,), acked_below=1))  # 1, 2: replies lost
    crashed.save(tmp_path / "snapshot.npz")
    crashed.insert_once([make_chunk(2, 30)], ChunkIds(PRODUCER, (3,), acked_below=1))  # reply lost
    crashed.insert_once([make_chunk(2, 40)], ChunkIds(PRODUCER, (4,), acked_below=1))  # acknowledged
    restarted = connect(table())
    restarted.load(tmp_path / "snapshot.npz")
    assert restarted.info()["producers"] == 1
    resent = restarted.insert_once(
        [make_chunk(2, 10), make_chunk(2, 20), make_chunk(2, 30)], ChunkIds(PRODUCER, (1, 2, 3), acked_below=1)
    )
    assert resent.duplicate == [True, True, False]
    assert [k.tolist() for k in resent.keys] == [[3, 4], [6, 7], [9, 10]]
    info = restarted.info()
    assert (info["inserted_chunks"], info["duplicates"]) == (4, 2)
    assert stored_observations(restarted) == [0.0, 1.0, 10.0, 11.0, 20.0, 21.0, 30.0, 31.0]  # 40 is lost


def test_a_snapshot_with_a_bad_ledger_is_refused(connect: Connect, tmp_path: Path) -> None:
    tab = connect(table())
    tab.insert_once([make_chunk(2, 0)], ChunkIds(PRODUCER, (5,)))
    path = tmp_path / "replay.npz"
    tab.save(path)
    with np.load(path, allow_pickle=False) as f:
        data = {name: f[name] for name in f.files}
    meta = json.loads(str(data["meta"]))
    assert meta["ledger"] == [[PRODUCER, 0, [[5, 0]]]]
    meta["ledger"] = [[PRODUCER, 0, [[5, 99]]]]  # a key the table never issued
    data["meta"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "bad.npz", **data)
    fresh = connect(table())
    with pytest.raises(ValueError, match="keys below next_key"):
        fresh.load(tmp_path / "bad.npz")
    assert fresh.info()["producers"] == 0


def test_past_max_producers_a_new_producer_is_refused_and_no_chunk_is_stored_twice(connect: Connect) -> None:
    """Issue 17: with the bound at 4 the 5th producer used to push producer 1 out of the ledger, and
    producer 1's re-sent chunk was stored a second time. Now the 5th is refused, with a message naming
    the bound and the key, and producer 1's re-send is a duplicate."""
    tab = connect(table(max_producers=4))
    for producer in (1, 2, 3, 4):
        tab.insert_once([make_chunk(2, 10 * producer)], ChunkIds(producer, (0,)))
    with pytest.raises(RuntimeError, match=r"replay_config\.max_producers: 4\)") as refused:
        tab.insert_once([make_chunk(2, 50)], ChunkIds(5, (0,)))
    assert refused_for_producers(refused.value)
    resent = tab.insert_once([make_chunk(2, 10)], ChunkIds(1, (0,)))  # its reply was lost: sent again
    assert resent.duplicate == [True] and resent.keys[0].tolist() == [0, 1]
    info = tab.info()
    assert (info["inserted_chunks"], info["duplicates"], info["producers"]) == (4, 1, 4)
    assert stored_observations(tab) == [10.0, 11.0, 20.0, 21.0, 30.0, 31.0, 40.0, 41.0]
    # Producer 1 acknowledges its last chunk (a request naming only numbers below acked_below stores
    # nothing): it can never send it again, so it gives its place to producer 5.
    assert tab.insert_once([make_chunk(2, 10)], ChunkIds(1, (0,), acked_below=1)).duplicate == [True]
    assert tab.insert_once([make_chunk(2, 50)], ChunkIds(5, (0,))).duplicate == [False]
    assert tab.insert_once([make_chunk(2, 20)], ChunkIds(2, (0,))).duplicate == [True]  # 2 is still known
    with pytest.raises(RuntimeError, match="max_producers") as again:
        tab.insert_once([make_chunk(2, 60)], ChunkIds(6, (0,)))
    assert refused_for_producers(again.value)
    info = tab.info()
    assert (info["inserted_chunks"], info["duplicates"], info["producers"]) == (5, 3, 4)


def test_a_new_producer_forgotten_while_it_waits_in_the_rate_limiter_comes_back_in(connect: Connect) -> None:
    # A new producer holds a place with nothing stored (settled) while the rate limiter holds its first
    # insert back, so another new producer may take that place meanwhile: once admitted, the first one
    # must claim a place again, not store its chunk under ids the ledger no longer holds.
    tab = connect(table(rate_limiter=RateLimiter(1.0, min_size_to_sample=2, tolerance=0.0), max_producers=1))
    tab.insert(make_chunk(3, 0))  # one window owed to the learner: inserts wait
    results: list[Any] = []
    waiting = threading.Thread(
        target=lambda: results.append(tab.insert_once([make_chunk(3, 50)], ChunkIds(1, (0,)), timeout=30.0))
    )
    waiting.start()
    while tab.info()["insert_waits"] < 1:
        threading.Event().wait(0.01)
    with pytest.raises(InsertTimeout):  # producer 2 takes the place of producer 1, then is held back too
        tab.insert_once([make_chunk(3, 70)], ChunkIds(2, (0,)), timeout=0)
    tab.sample(2, timeout=0)  # the learner catches up: producer 1 is admitted, takes the place of 2, stores
    waiting.join(30)
    assert len(results) == 1 and results[0].duplicate == [False] and results[0].keys[0].tolist() == [4, 5, 6]
    with pytest.raises(RuntimeError, match="max_producers") as refused:  # 1 holds a stored chunk now
        tab.insert_once([make_chunk(3, 70)], ChunkIds(2, (0,)), timeout=0)
    assert refused_for_producers(refused.value)
    again = tab.insert_once([make_chunk(3, 50)], ChunkIds(1, (0,)), timeout=0)
    assert again.duplicate == [True] and again.keys[0].tolist() == [4, 5, 6]
    info = tab.info()
    assert (info["inserted_chunks"], info["duplicates"], info["producers"]) == (2, 1, 1)


# ---------------------------------------------------------------------- the ledger's bounds


def store(ledger: ChunkLedger, ids: ChunkIds, first_key: int) -> None:
    """What the table does for a request of one new chunk: settle, then record it."""
    ledger.settle(ids)
    ledger.record(ids, ids.seqs[0], first_key)


def test_past_the_cap_the_oldest_numbers_are_forgotten_so_a_resend_is_stored_again_not_lost(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(dedup, "MAX_OPEN_PER_PRODUCER", 3)
    ledger = ChunkLedger()
    for seq in range(5):
        store(ledger, ChunkIds(PRODUCER, (seq,)), 10 * seq)
    assert ledger.lookup(ChunkIds(PRODUCER, (0, 1, 2, 3, 4, 5))) == [None, None, 20, 30, 40, None]


def test_a_full_ledger_refuses_a_new_producer_rather_than_forget_one_that_may_send_again() -> None:
    """Issue 17: past 1,024 producers the least recently seen one was forgotten, so its re-sent chunk
    was stored twice; any client with Insert rights could make that happen to every actor."""
    ledger = ChunkLedger(max_producers=2)
    for producer in (1, 2, 1):
        store(ledger, ChunkIds(producer, (0,)), 10 * producer)
    for refused_call in (lambda: ledger.settle(ChunkIds(3, (0,))), lambda: ledger.record(ChunkIds(3, (0,)), 0, 30)):
        with pytest.raises(ProducerLimitReached, match=r"replay_config\.max_producers: 2\)") as refused:
            refused_call()
        assert "raise replay_config.max_producers" in str(refused.value)
    assert len(ledger) == 2
    assert [ledger.lookup(ChunkIds(p, (0,)))[0] for p in (1, 2, 3)] == [10, 20, None]


def test_a_producer_takes_a_place_only_when_a_chunk_of_it_is_stored() -> None:
    """A request that stores nothing (refused, timed out in the rate limiter, or an acknowledgement
    from a producer the table never stored anything of) leaves the ledger as it was: random bytes
    that happen to decode as an acknowledge-only Insert must not fill the ledger (CI found this)."""
    ledger = ChunkLedger(max_producers=2)
    store(ledger, ChunkIds(1, (0,)), 10)
    ledger.settle(ChunkIds(2, (), acked_below=7))  # an acknowledgement from an unknown producer
    ledger.settle(ChunkIds(3, (0,)))  # admitted, then its wait timed out: nothing recorded
    assert len(ledger) == 1 and ledger.state_dict() == [[1, 0, [(0, 10)]]]
    store(ledger, ChunkIds(2, (7,), acked_below=7), 70)  # its floor is the acked_below it came with
    assert ledger.lookup(ChunkIds(2, (6, 7))) == [dedup.FORGOTTEN, 70]


def test_only_a_producer_with_every_stored_chunk_acknowledged_makes_room_least_recent_first() -> None:
    ledger = ChunkLedger(max_producers=3)
    for producer in (1, 2, 3):
        store(ledger, ChunkIds(producer, (0,)), 10 * producer)
    store(ledger, ChunkIds(2, (1,), acked_below=1), 25)  # 2 acknowledged its chunk 0 and sends 1
    with pytest.raises(ProducerLimitReached):
        ledger.settle(ChunkIds(4, (0,)))  # 2's chunk 1 is stored and not acknowledged: not settled
    ledger.settle(ChunkIds(2, (1,), acked_below=2))  # a stale copy of 1 acknowledging everything of 2
    ledger.settle(ChunkIds(1, (0,), acked_below=1))  # and everything of 1, after 2: 2 is the least recent
    store(ledger, ChunkIds(4, (0,)), 40)
    assert len(ledger) == 3 and ledger.lookup(ChunkIds(2, (0, 1))) == [None, None]  # 2 is forgotten
    assert ledger.lookup(ChunkIds(1, (0,))) == [dedup.FORGOTTEN]  # 1 is known, its chunk 0 acknowledged
    assert ledger.lookup(ChunkIds(3, (0,))) == [30]
    store(ledger, ChunkIds(5, (0,)), 50)  # 1 is settled: it makes room
    with pytest.raises(ProducerLimitReached):
        ledger.settle(ChunkIds(6, (0,)))  # 3, 4 and 5 each hold a chunk they may send again
    assert [ledger.lookup(ChunkIds(p, (0,)))[0] for p in (1, 3, 4, 5, 6)] == [None, 30, 40, 50, None]


def test_a_ledger_saved_under_a_larger_bound_keeps_every_producer(tmp_path: Path) -> None:
    big = ChunkLedger(max_producers=4)
    for producer in (1, 2, 3, 4):
        store(big, ChunkIds(producer, (0,)), producer)
    big.settle(ChunkIds(2, (1,), acked_below=1))  # 2 acknowledged its chunk: settled
    small = ChunkLedger.from_state(big.state_dict(), next_key=10, max_producers=2)
    assert len(small) == 4 and small.lookup(ChunkIds(3, (0,))) == [3]
    with pytest.raises(ProducerLimitReached):  # only 2 is settled: it cannot make room for 3 more
        small.settle(ChunkIds(5, (0,)))
    assert len(small) == 4
    small.settle(ChunkIds(1, (1,), acked_below=1))  # acknowledged: 1 and 2 are settled, 2 the least recent
    small.settle(ChunkIds(3, (1,), acked_below=1))  # and 3
    store(small, ChunkIds(5, (0,)), 5)  # 4 producers + 5 > 2: all three settled ones are forgotten
    assert len(small) == 2 and small.lookup(ChunkIds(4, (0,))) == [4]
    with pytest.raises(ValueError, match="max_producers must be >= 1"):
        ChunkLedger(max_producers=0)


@pytest.mark.parametrize(
    ("state", "message"),
    [
        ([[0, 0, []]], "integer in"),
        ([[1, "0", []]], "integer in"),
        ([[1, 5, [[4, 0]]]], ">= its floor 5"),
        ([[1, 0, [[4, 0], [4, 1]]]], "unique"),
        ([[1, 0, []], [1, 0, []]], "listed twice"),
    ],
)
def test_a_malformed_ledger_state_is_named(state: list[Any], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ChunkLedger.from_state(state, next_key=10)
