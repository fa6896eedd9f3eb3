"""Window semantics: masks, padding past a chunk's end, and never reading another chunk."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from algorithm.replay import PrioritizedTable
from algorithm.types import Batch

from .chunks import VECTOR, make_chunk
from .conftest import Connect


def test_window_past_the_chunk_end_is_masked_and_repeats_the_final_observation(connect: Connect) -> None:
    tab = connect(PrioritizedTable(32, (VECTOR,), 2, window=4, alpha=0.0, seed=0))
    tab.insert(make_chunk(3, 0, terminated=True))  # keys 0, 1, 2; bootstrap row 3 holds obs[3]
    tab.insert(make_chunk(5, 4))  # keys 4..8 must never leak into the first chunk's windows
    by_key: dict[int, int] = {}
    batch = tab.sample(64)
    for b, key in enumerate(batch.keys.tolist()):
        by_key.setdefault(key, b)
    assert {0, 1, 2} <= set(by_key)

    b = by_key[1]  # steps 1, 2 valid; 2 is terminal; positions past it masked
    np.testing.assert_array_equal(batch.mask[b], [True, True, False, False])
    np.testing.assert_array_equal(batch.obs[0][b, :, 0], [1, 2, 3, 3, 3])  # o_1 o_2 o_3(final) o_3 o_3
    np.testing.assert_array_equal(batch.rewards[b], [1.5, 2.5, 0, 0])
    np.testing.assert_array_equal(batch.terminated[b], [False, True, False, False])
    np.testing.assert_array_equal(batch.actions[b, :, 0], [1, 2, 0, 0])
    np.testing.assert_array_equal(batch.prev_actions[b, :, 0], [0, 1, 0, 0])
    np.testing.assert_array_equal(batch.behaviour_logp[b], [-2, -3, 0, 0])
    assert not batch.truncated[b].any()

    b = by_key[5]  # fully inside the second chunk
    assert batch.mask[b].all()
    np.testing.assert_array_equal(batch.obs[0][b, :, 0], [5, 6, 7, 8, 9])


def check_windows(batch: Batch, chunks: dict[int, tuple[int, bool]], oldest: int) -> None:
    """Every window starts at a stored step key and reads only its own chunk; ``chunks`` maps each
    step key to its chunk's end (bootstrap) key and whether its last step ends the episode."""
    window = batch.window
    for b, s in enumerate(batch.keys.tolist()):
        assert s >= oldest and s in chunks, f"key {s} is not a stored step"
        end, ends_episode = chunks[s]
        pos = s + np.arange(window + 1)
        np.testing.assert_array_equal(batch.obs[0][b, :, 0], np.minimum(pos, end))
        valid = pos[:-1] < end
        np.testing.assert_array_equal(batch.mask[b], valid)
        np.testing.assert_array_equal(batch.rewards[b], np.where(valid, pos[:-1] + 0.5, 0))
        np.testing.assert_array_equal(batch.actions[b, :, 1], np.where(valid, pos[:-1], 0))
        np.testing.assert_array_equal(batch.behaviour_logp[b], np.where(valid, -(pos[:-1] + 1), 0))
        # flags only at the chunk's last step, which is the last valid step if the window reaches it
        last = valid & (pos[:-1] == end - 1) & ends_episode
        np.testing.assert_array_equal(batch.terminated[b] | batch.truncated[b], last)


# connect is shared by the examples on purpose: it only wraps each example's new table.
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    capacity=st.integers(2, 40),
    window=st.integers(1, 6),
    lengths=st.lists(st.integers(1, 39), min_size=1, max_size=25),
    alpha=st.sampled_from([0.0, 0.6]),
    seed=st.integers(0, 2**16),
)
def test_windows_never_span_two_chunks(
    connect: Connect, capacity: int, window: int, lengths: list[int], alpha: float, seed: int
) -> None:
    tab = connect(PrioritizedTable(capacity, (VECTOR,), 2, window, alpha=alpha, seed=seed))
    rng = np.random.default_rng(seed)
    chunks: dict[int, tuple[int, bool]] = {}
    next_key = 0
    for t in lengths:
        t = min(t, capacity - 1)
        flag = rng.integers(3)
        keys = tab.insert(make_chunk(t, next_key, terminated=flag == 1, truncated=flag == 2))
        np.testing.assert_array_equal(keys, np.arange(next_key, next_key + t))
        chunks.update((k, (next_key + t, bool(flag > 0))) for k in range(next_key, next_key + t))
        next_key += t + 1
        oldest = max(0, next_key - capacity)
        stored_steps = sum(1 for k in chunks if k >= oldest)
        assert tab.info()["size"] == stored_steps
        check_windows(tab.sample(32), chunks, oldest)
        if alpha:  # perturb priorities, including of evicted keys, to exercise the tree
            some = rng.integers(0, next_key, 8).astype(np.uint64)
            tab.update_priorities(some, rng.uniform(0.0, 2.0, 8))


def test_windows_after_a_key_are_the_oldest_stored_steps_from_it_in_key_order(connect: Connect) -> None:
    """What a learner scores for sac_config.insert_td_priorities: the stored steps from a key on,
    the same windows a sample would draw for them, without counting as sampling."""
    tab = connect(PrioritizedTable(12, (VECTOR,), 2, window=2, alpha=1.0, seed=0))
    tab.insert(make_chunk(3, 0))  # keys 0-2, bootstrap 3
    tab.insert(make_chunk(4, 4, terminated=True))  # keys 4-7, bootstrap 8
    first = tab.windows_after(0, 4)
    assert first is not None and first.keys.tolist() == [0, 1, 2, 4]  # bootstrap rows never start a window
    check_windows(first, {k: (3, False) for k in (0, 1, 2)} | {k: (8, True) for k in (4, 5, 6, 7)}, 0)
    assert first.probabilities == pytest.approx(np.full(4, 1 / 7))  # all at the maximum priority
    rest = tab.windows_after(5, 10)
    assert rest is not None and rest.keys.tolist() == [5, 6, 7]
    assert tab.windows_after(8, 10) is None and tab.windows_after(100, 1) is None
    tab.insert(make_chunk(4, 9))  # keys 9-12 and bootstrap 13 take rows 9, 10, 11, 0, 1 (capacity 12)
    after = tab.windows_after(0, 3)
    assert after is not None and after.keys.tolist() == [2, 4, 5]  # keys 0, 1 are evicted: the oldest stored first
    assert tab.info()["sampled_windows"] == 0  # not sampling
    for bad, message in [((0, 0), "limit must be >= 1"), ((-1, 2), "key must be >= 0")]:
        with pytest.raises((ValueError, RuntimeError), match=message):
            tab.windows_after(*bad)
