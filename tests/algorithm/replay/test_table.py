"""PrioritizedTable: keys, priorities, sampling statistics, eviction, validation, normalizer."""

from __future__ import annotations

import re
from dataclasses import replace
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from scipy.stats import chisquare

from algorithm.normalizer import RunningMeanStd
from algorithm.replay import InsertTimeout, PrioritizedTable, RateLimiter, SampleTimeout
from algorithm.spaces import SensorSpec

from .chunks import IMAGE, VECTOR, make_chunk
from .conftest import Connect


def table(capacity: int = 64, window: int = 1, **kwargs: Any) -> PrioritizedTable:
    kwargs.setdefault("seed", 0)
    return PrioritizedTable(capacity, kwargs.pop("sensors", (VECTOR,)), 2, window, **kwargs)


def fill(tab: Any, lengths: list[int]) -> list[np.ndarray]:
    keys = []
    for t in lengths:
        keys.append(tab.insert(make_chunk(t, tab.info()["next_key"], tab.sensors, tab.action_size)))
    return keys


def sample_counts(tab: Any, n_batches: int, batch: int = 256) -> np.ndarray:
    counts = np.zeros(tab.info()["next_key"], dtype=np.int64)
    for _ in range(n_batches):
        np.add.at(counts, tab.sample(batch).keys.astype(np.int64), 1)
    return counts


def test_keys_are_consecutive_per_chunk_and_skip_bootstrap_rows(connect: Connect) -> None:
    tab = connect(table())
    a, b = fill(tab, [3, 2])
    assert a.dtype == np.uint64 and a.tolist() == [0, 1, 2]
    assert b.tolist() == [4, 5]  # key 3 is the bootstrap row of the first chunk
    info = tab.info()
    assert (info["size"], info["inserted_steps"], info["inserted_chunks"], info["stored_rows"]) == (
        5,
        5,
        2,
        7,
    )


def test_sampled_frequencies_follow_transformed_priorities(connect: Connect) -> None:
    tab = connect(table(capacity=200, alpha=0.7, td_error_min=0.05, td_error_max=2.0))
    rng = np.random.default_rng(0)
    raw: dict[int, float] = {}
    for t in (5, 17, 30, 1, 40):
        p = rng.uniform(0.0, 3.0, t)
        keys = tab.insert(make_chunk(t, tab.info()["next_key"]), priorities=p)
        raw.update(zip(keys.tolist(), p, strict=True))
    keys = np.array(sorted(raw))
    expected_p = np.clip([raw[k] for k in keys], 0.05, 2.0) ** 0.7
    n_batches = 400
    counts = sample_counts(tab, n_batches)
    assert counts.sum() == counts[keys].sum()  # only step keys are ever drawn
    assert chisquare(counts[keys], 256 * n_batches * expected_p / expected_p.sum()).pvalue > 0.001
    batch = tab.sample(8)
    want = np.array([np.clip(raw[k], 0.05, 2.0) ** 0.7 for k in batch.keys.tolist()]) / expected_p.sum()
    np.testing.assert_allclose(batch.probabilities, want, rtol=1e-12)
    assert batch.table_size == len(keys)


def test_zero_priority_rows_are_never_drawn(connect: Connect) -> None:
    tab = connect(table(capacity=300, alpha=1.0, td_error_min=0.0))
    keys = np.concatenate(fill(tab, [50, 60, 70]))
    tab.update_priorities(keys, np.zeros(keys.shape[0]))
    live = keys[[3, 77, 150]]
    tab.update_priorities(live, np.array([1e-300, 1e-12, 1.0]))
    counts = sample_counts(tab, 20)
    assert set(np.flatnonzero(counts).tolist()) <= set(live.tolist())


def test_all_zero_priorities_sample_uniformly_among_step_rows(connect: Connect) -> None:
    tab = connect(table(capacity=100, alpha=0.5, td_error_min=0.0))
    keys = np.concatenate(fill(tab, [1, 1, 7, 3, 1, 12, 30, 2]))  # many bootstrap rows between
    tab.update_priorities(keys, np.zeros(keys.shape[0]))
    assert tab.info()["total_priority"] == 0.0
    batch = tab.sample(16)
    np.testing.assert_array_equal(batch.probabilities, np.full(16, 1.0 / keys.shape[0]))
    counts = sample_counts(tab, 200)
    assert counts.sum() == counts[keys].sum()
    assert chisquare(counts[keys]).pvalue > 0.001


def test_alpha_zero_is_uniform_whatever_the_priorities(connect: Connect) -> None:
    tab = connect(table(capacity=100, alpha=0.0))
    keys = tab.insert(make_chunk(40), priorities=np.linspace(0.0, 5.0, 40))
    counts = sample_counts(tab, 100)
    assert chisquare(counts[keys]).pvalue > 0.001


def test_new_rows_get_the_highest_priority_seen(connect: Connect) -> None:
    tab = connect(table(alpha=0.5, td_error_max=4.0))
    a = fill(tab, [3])[0]
    assert tab.info()["max_priority"] == 1.0  # 1.0 transformed
    tab.update_priorities(a[:1], np.array([0.25]))
    assert tab.info()["max_priority"] == 1.0
    tab.update_priorities(a[1:2], np.array([9.0]))  # clipped to 4, then ** 0.5
    assert tab.info()["max_priority"] == 2.0
    b = fill(tab, [2])[0]
    batch_p: dict[int, float] = {}
    for _ in range(20):
        s = tab.sample(64)
        batch_p.update(zip(s.keys.tolist(), s.probabilities * tab.info()["total_priority"], strict=True))
    assert batch_p[int(b[0])] == pytest.approx(2.0) and batch_p[int(a[0])] == pytest.approx(0.5)


def test_fifo_eviction_and_stale_updates_are_ignored(connect: Connect) -> None:
    tab = connect(table(capacity=10, alpha=1.0, td_error_max=100.0))
    old = fill(tab, [4])[0]  # keys 0..3, bootstrap 4
    fill(tab, [3, 2])  # keys 5..7 (+8), 9..10 (+11): rows 0 and 1 overwritten
    info = tab.info()
    assert (info["evicted_rows"], info["evicted_steps"], info["size"]) == (2, 2, 7)
    total = info["total_priority"]
    never_issued = np.array([info["next_key"], 10**12, 2**64 - 1], dtype=np.uint64)
    tab.update_priorities(old[:2], np.array([50.0, 50.0]))  # evicted
    tab.update_priorities(np.array([4, 8], dtype=np.uint64), np.array([50.0, 50.0]))  # bootstrap rows
    tab.update_priorities(never_issued, np.full(3, 50.0))
    info = tab.info()
    assert info["total_priority"] == total
    assert (info["priority_updates"], info["priority_updates_ignored"]) == (0, 7)
    tab.update_priorities(old[2:], np.array([50.0, 50.0]))  # still stored: applied
    assert tab.info()["priority_updates"] == 2
    drawn = set(sample_counts(tab, 10).nonzero()[0].tolist())
    assert drawn.isdisjoint({0, 1, 4, 8, 11})


def test_sample_times_out_below_min_size(connect: Connect) -> None:
    tab = connect(table(rate_limiter=RateLimiter(1.0, min_size_to_sample=5, enforce_ratio=False)))
    fill(tab, [4])
    with pytest.raises(SampleTimeout, match="min_size_to_sample"):
        tab.sample(2, timeout=0)
    fill(tab, [1])
    assert tab.sample(2, timeout=0).batch_size == 2


def test_from_config_wires_the_rate_limiter(connect: Connect) -> None:
    cfg = SimpleNamespace(
        capacity=50,
        alpha=0.6,
        td_error_min=0.01,
        td_error_max=1.0,
        samples_per_insert=4.0,
        samples_per_insert_tolerance=0.0,
        min_size_to_sample=3,
        max_producers=7,
    )
    built = PrioritizedTable.from_config(cfg, (VECTOR,), 2, window=2, enforce_ratio=True, seed=0)
    assert (built.capacity, built.window, built.alpha, built.max_producers) == (50, 2, 0.6, 7)
    tab = connect(built)
    fill(tab, [3])
    with pytest.raises(SampleTimeout, match="rate-limited"):
        tab.sample(4, timeout=0)  # at min size, no surplus yet
    fill(tab, [1])
    assert tab.sample(4, timeout=0).window == 2
    free = connect(PrioritizedTable.from_config(cfg, (VECTOR,), 2, window=2))  # single-process default
    fill(free, [3])
    assert free.sample(100, timeout=0).batch_size == 100


BAD_CHUNKS = {
    "obs[0] (state)": lambda c: replace(c, obs=[c.obs[0][:, :2]]),
    "float32": lambda c: replace(c, actions=c.actions.astype(np.float64)),
    "prev_actions": lambda c: replace(c, prev_actions=c.prev_actions[:, :1]),
    "observation sensors": lambda c: replace(c, obs=[c.obs[0], c.obs[0]]),
    "rewards has non-finite": lambda c: replace(c, rewards=np.where(np.arange(4) == 2, np.nan, c.rewards)),
    "obs[0] (state) has non-finite": lambda c: replace(c, obs=[np.full_like(c.obs[0], np.inf)]),
    "terminated": lambda c: replace(c, terminated=np.array([True, False, False, False])),
    "truncated": lambda c: replace(c, truncated=np.array([False, True, False, True])),
    "rnn_state": lambda c: replace(c, rnn_state=np.zeros((4, 2), np.float32)),
    "numpy array": lambda c: replace(c, rewards=c.rewards.tolist()),
    "T >= 1": lambda c: replace(c, rewards=np.zeros(0, np.float32)),
}


@pytest.mark.parametrize("message", list(BAD_CHUNKS))
def test_bad_chunks_are_named_and_store_nothing(connect: Connect, message: str) -> None:
    tab = connect(table())
    fill(tab, [2])
    before = tab.info()
    chunk = BAD_CHUNKS[message](make_chunk(4, before["next_key"]))
    with pytest.raises(ValueError, match=re.escape(message)):
        tab.insert(chunk)
    after = tab.info()
    assert {k: after[k] for k in ("size", "next_key", "total_priority")} == {
        k: before[k] for k in ("size", "next_key", "total_priority")
    }


def test_insert_many_stores_all_chunks_or_none(connect: Connect) -> None:
    tab = connect(table())
    keys = tab.insert_many([make_chunk(3, 0), make_chunk(2, 4)], [None, np.array([0.5, 2.0])])
    assert [k.tolist() for k in keys] == [[0, 1, 2], [4, 5]]
    before = tab.info()
    bad = replace(make_chunk(2, 10), rewards=np.array([np.nan, 1.0], np.float32))
    with pytest.raises(ValueError, match=re.escape("chunks[1]")):
        tab.insert_many([make_chunk(3, 7), bad])
    after = tab.info()
    assert {k: after[k] for k in ("size", "next_key", "inserted_chunks", "total_priority")} == {
        k: before[k] for k in ("size", "next_key", "inserted_chunks", "total_priority")
    }


def test_insert_many_is_admitted_as_one_request(connect: Connect) -> None:
    # Chunk by chunk, the second would be held back (surplus 3 windows, + 4 > tolerance 5).
    tab = connect(table(rate_limiter=RateLimiter(1.0, min_size_to_sample=1, tolerance=5.0)))
    tab.insert_many([make_chunk(4, 0), make_chunk(4, 5)], timeout=0)
    assert tab.info()["size"] == 8
    with pytest.raises(InsertTimeout):
        tab.insert(make_chunk(1, 10), timeout=0)


def test_chunk_longer_than_capacity_is_refused(connect: Connect) -> None:
    tab = connect(table(capacity=8))
    tab.insert(make_chunk(7))  # exactly fills the ring
    with pytest.raises(ValueError, match="needs 9 rows but replay capacity is 8"):
        tab.insert(make_chunk(8, 8))


def test_refreshed_rnn_states_replace_the_stored_ones_of_live_keys_only(connect: Connect) -> None:
    tab = connect(table(capacity=12, window=1, rnn_state_size=2, alpha=0.0))
    tab.insert(make_chunk(5, 0, rnn_state_size=2))  # keys 0-4 (row 5 is the bootstrap row)
    fresh = np.full((3, 2), 7.5, dtype=np.float32)
    tab.update_rnn_states(np.array([1, 3, 5], dtype=np.uint64), fresh)  # 5: a bootstrap row, ignored
    tab.update_rnn_states(np.array([99], dtype=np.uint64), np.zeros((1, 2), np.float32))  # never issued
    batch = tab.sample(200)
    stored = dict(zip(batch.keys.tolist(), batch.rnn_state[:, 0].tolist(), strict=True))
    assert stored == {0: 0.0, 1: 7.5, 2: 2.0, 3: 7.5, 4: 4.0}  # make_chunk stores each key's number
    assert tab.info()["rnn_state_updates"] == 2


@pytest.mark.parametrize(
    "keys, states, message",
    [
        (np.array([1]), np.zeros((1, 3), np.float32), "states"),
        (np.array([1]), np.zeros((1, 2), np.float64), "float32"),
        (np.array([1]), np.full((1, 2), np.nan, np.float32), "non-finite|finite"),
        (np.array([[1]]), np.zeros((1, 2), np.float32), "keys"),
    ],
)
def test_bad_rnn_state_updates_are_named_and_change_nothing(
    connect: Connect, keys: np.ndarray, states: np.ndarray, message: str
) -> None:
    tab = connect(table(window=1, rnn_state_size=2, alpha=0.0))
    tab.insert(make_chunk(3, 0, rnn_state_size=2))
    with pytest.raises(ValueError, match=message):
        tab.update_rnn_states(keys, states)
    assert tab.info()["rnn_state_updates"] == 0
    batch = tab.sample(50)
    np.testing.assert_array_equal(batch.rnn_state[:, 0], batch.keys.astype(np.float32))


def test_a_table_without_rnn_state_refuses_rnn_state_updates(connect: Connect) -> None:
    tab = connect(table(window=1))
    tab.insert(make_chunk(3, 0))
    with pytest.raises(ValueError, match="no recurrent state"):
        tab.update_rnn_states(np.array([1], np.uint64), np.zeros((1, 2), np.float32))


@pytest.mark.parametrize(
    ("keys", "priorities", "message"),
    [
        (np.array([0, 1]), np.array([1.0]), "shape"),
        (np.array([0]), np.array([np.nan]), "finite"),
        (np.array([0]), np.array([-1.0]), ">= 0"),
        (np.array([0.0]), np.array([1.0]), "integer"),
    ],
)
def test_bad_priority_updates_are_named(
    connect: Connect, keys: np.ndarray, priorities: np.ndarray, message: str
) -> None:
    tab = connect(table())
    fill(tab, [3])
    with pytest.raises(ValueError, match=message):
        tab.update_priorities(keys, priorities)
    with pytest.raises(ValueError, match="priorities"):
        tab.insert(make_chunk(2, 4), priorities=np.ones(3))


def test_constructor_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="capacity"):
        table(capacity=1)
    with pytest.raises(ValueError, match="window"):
        table(window=0)
    with pytest.raises(ValueError, match="alpha"):
        table(alpha=1.5)
    with pytest.raises(ValueError, match="td_error_min"):
        table(td_error_min=2.0, td_error_max=1.0)
    with pytest.raises(ValueError, match="unique sensor names"):
        table(sensors=(VECTOR, VECTOR))
    with pytest.raises(ValueError, match="min_size_to_sample 64 can never be reached"):
        table(rate_limiter=RateLimiter(1.0, 64))


def test_normalizer_sees_every_inserted_observation_of_vector_sensors(connect: Connect) -> None:
    two = SensorSpec("two_d", (2, 2))
    tab = connect(table(sensors=(VECTOR, IMAGE, two), capacity=20))
    rng = np.random.default_rng(0)
    seen: list[np.ndarray] = []
    # The last chunk wraps and evicts: statistics still cover everything. A chunk cut mid-episode
    # (the first two) passes its final observation on to the next chunk, so it is counted once.
    for t, ended in ((3, False), (9, False), (15, True)):
        chunk = make_chunk(t, 0, tab.sensors, truncated=ended)
        chunk.obs[2] = rng.normal(3.0, 2.0, (t + 1, 2, 2)).astype(np.float32)
        seen.append(chunk.obs[2] if ended else chunk.obs[2][:-1])
        tab.insert(chunk)
    stats = tab.info()["normalizer"]
    assert set(stats) == {"state", "two_d"}  # images are not normalized
    data = np.concatenate(seen).astype(np.float64)
    assert stats["two_d"]["count"] == data.shape[0] == 3 + 9 + 15 + 1
    np.testing.assert_allclose(stats["two_d"]["mean"], data.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(stats["two_d"]["var"], data.var(axis=0), rtol=1e-12)
    rms = RunningMeanStd((2, 2))
    rms.load_state_dict(tab.normalizer_stats()["two_d"])
    np.testing.assert_allclose(rms.normalize(data), np.clip((data - data.mean(0)) / data.std(0), -5, 5), rtol=1e-5)


def test_images_stay_uint8_and_rnn_state_comes_from_the_window_start(connect: Connect) -> None:
    tab = connect(table(sensors=(VECTOR, IMAGE), window=3, rnn_state_size=4, alpha=0.0))
    tab.insert(make_chunk(5, 0, tab.sensors, rnn_state_size=4))
    batch = tab.sample(32)
    assert batch.obs[1].dtype == np.uint8 and batch.obs[1].shape == (32, 4, 4, 4, 3)
    assert batch.rnn_state is not None and batch.rnn_state.shape == (32, 4)
    np.testing.assert_array_equal(batch.rnn_state[:, 0], batch.keys.astype(np.float32))
    np.testing.assert_array_equal(batch.obs[1][:, 0, 0, 0, 0], batch.keys.astype(np.uint8))
