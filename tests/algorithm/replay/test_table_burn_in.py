"""Burn-in windows look back from the sampled step: ``burn_in`` steps before it in the same chunk,
zeros (masked) before the chunk's first live row, never another chunk's rows."""

from __future__ import annotations

from typing import Any

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from algorithm.replay import PrioritizedTable

from .chunks import VECTOR, make_chunk
from .conftest import Connect

BURN_IN, N_STEP = 3, 2


def by_key(tab: Any, n: int = 256) -> tuple[dict[int, int], object]:
    batch = tab.sample(n)
    first: dict[int, int] = {}
    for b, key in enumerate(batch.keys.tolist()):
        first.setdefault(key, b)
    return first, batch


def test_the_sampled_step_sits_after_the_burn_in_and_early_steps_get_zero_rows(connect: Connect) -> None:
    tab = connect(PrioritizedTable(64, (VECTOR,), 2, window=BURN_IN + N_STEP, alpha=0.0, rnn_state_size=2, seed=0,
                                   burn_in=BURN_IN))  # fmt: skip
    tab.insert(make_chunk(6, 0, terminated=True, rnn_state_size=2))  # keys 0..5, bootstrap 6
    tab.insert(make_chunk(4, 7, rnn_state_size=2))  # keys 7..10
    index, batch = by_key(tab)
    assert set(index) == {0, 1, 2, 3, 4, 5, 7, 8, 9, 10}

    b = index[4]  # steps 1..5: all inside the first chunk
    assert batch.mask[b].all()
    np.testing.assert_array_equal(batch.obs[0][b, :, 0], [1, 2, 3, 4, 5, 6])
    np.testing.assert_array_equal(batch.rewards[b], [1.5, 2.5, 3.5, 4.5, 5.5])
    np.testing.assert_array_equal(batch.rnn_state[b], [1, 1])  # the stored state at the window's first row

    b = index[1]  # key 1: two look-back rows before key 0 are zeros, masked
    np.testing.assert_array_equal(batch.mask[b], [False, False, True, True, True])
    np.testing.assert_array_equal(batch.obs[0][b, :, 0], [0, 0, 0, 1, 2, 3])
    np.testing.assert_array_equal(batch.actions[b, :, 0], [0, 0, 0, 1, 2])
    np.testing.assert_array_equal(batch.rnn_state[b], [0, 0])  # state at key 0, the first valid row

    b = index[8]  # second chunk: never reads the first chunk's rows (keys <= 6)
    np.testing.assert_array_equal(batch.mask[b], [False, False, True, True, True])
    np.testing.assert_array_equal(batch.obs[0][b, :, 0], [0, 0, 7, 8, 9, 10])
    np.testing.assert_array_equal(batch.rnn_state[b], [7, 7])

    b = index[5]  # terminal step: the tail past it is masked as before
    np.testing.assert_array_equal(batch.mask[b], [True, True, True, True, False])
    np.testing.assert_array_equal(batch.obs[0][b, :, 0], [2, 3, 4, 5, 6, 6])


# connect is shared by the examples on purpose: it only wraps each example's new table.
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    lengths=st.lists(st.integers(1, 9), min_size=1, max_size=12),
    capacity=st.integers(12, 40),
    burn_in=st.integers(1, 4),
)
def test_look_back_windows_never_leave_the_sampled_chunk(
    connect: Connect, lengths: list[int], capacity: int, burn_in: int
) -> None:
    tab = connect(PrioritizedTable(capacity, (VECTOR,), 2, window=burn_in + 2, alpha=0.0, seed=1, burn_in=burn_in))
    chunk_of: dict[int, tuple[int, int]] = {}  # key -> (chunk's first key, its bootstrap key)
    key = 0
    for t in lengths:
        if t > capacity - 1:
            continue
        tab.insert(make_chunk(t, key))
        for k in range(key, key + t):
            chunk_of[k] = (key, key + t)
        key += t + 1
    if tab.info()["size"] == 0:
        return
    oldest = key - capacity
    batch = tab.sample(64)
    for b, k in enumerate(batch.keys.tolist()):
        first, boot = chunk_of[k]
        first = max(first, oldest)
        for t in range(burn_in + 2):
            pos = k - burn_in + t
            valid = first <= pos < boot
            assert batch.mask[b, t] == valid
            expected = pos if valid else (0 if pos < first else boot)
            assert batch.obs[0][b, t, 0] == expected
        assert batch.mask[b, burn_in]
