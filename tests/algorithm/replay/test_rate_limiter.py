"""Rate limiter semantics: minimum size, ratio within tolerance, no deadlock, blocking with timeouts."""

from __future__ import annotations

import threading
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from algorithm.replay.base import SampleTimeout
from algorithm.replay.rate_limiter import InsertTimeout, RateLimiter


def test_sampling_waits_for_min_size() -> None:
    lim = RateLimiter(samples_per_insert=4.0, min_size_to_sample=10, enforce_ratio=False)
    lim.record_insert(9)
    assert not lim.can_sample(1)
    lim.record_insert(1)
    assert lim.can_sample(1000)  # ratio not enforced: any amount once the minimum is stored
    lim.record_insert(0, evicted=5)
    assert lim.size == 5 and not lim.can_sample(1)


def test_unenforced_inserts_never_block() -> None:
    lim = RateLimiter(samples_per_insert=1.0, min_size_to_sample=1, enforce_ratio=False)
    for _ in range(100):
        assert lim.can_insert(1000)
        lim.record_insert(1000)


def test_enforced_ratio_exact_with_zero_tolerance() -> None:
    """spi=2, one step per insert, two windows per sample: inserts and samples alternate."""
    lim = RateLimiter(samples_per_insert=2.0, min_size_to_sample=3)
    for _ in range(3):
        assert lim.can_insert(1)
        lim.record_insert(1)
    for _ in range(5):
        assert not lim.can_sample(2)
        assert lim.can_insert(1)
        lim.record_insert(1)
        assert not lim.can_insert(1)
        assert lim.can_sample(2)
        lim.record_sample(2)
    assert lim.sampled == 2 * (lim.inserted - 3)


def test_tolerance_lets_the_learner_run_ahead_and_behind() -> None:
    lim = RateLimiter(samples_per_insert=1.0, min_size_to_sample=1, tolerance=10.0)
    lim.record_insert(1)  # on target: surplus 0
    assert lim.can_sample(10) and not lim.can_sample(11)  # the learner may run 10 windows ahead
    lim.record_sample(10)
    assert not lim.can_sample(1) and lim.can_insert(1)
    lim.record_insert(20)  # inserters 10 windows ahead: at the edge of the band
    assert not lim.can_insert(1) and lim.can_sample(1)


@settings(max_examples=200, deadline=None)
@given(
    spi=st.floats(0.01, 500.0),
    tolerance=st.floats(0.0, 1000.0),
    min_size=st.integers(1, 50),
    chunk=st.integers(1, 300),
    batch=st.integers(1, 512),
    steps=st.integers(50, 300),
)
def test_never_deadlocks_and_tracks_the_ratio(
    spi: float, tolerance: float, min_size: int, chunk: int, batch: int, steps: int
) -> None:
    """Greedy samplers and inserters: one side can always move, and the surplus stays within the
    tolerance overshot by at most one request."""
    lim = RateLimiter(samples_per_insert=spi, min_size_to_sample=min_size, tolerance=tolerance)
    for _ in range(steps):
        moved = False
        if lim.can_sample(batch):
            lim.record_sample(batch)
            moved = True
        if lim.can_insert(chunk):
            lim.record_insert(chunk)
            moved = True
        assert moved, f"deadlock at surplus {lim.surplus}"
        if lim.size >= min_size:
            rounding = 1e-9 * (1.0 + lim.inserted * spi)  # the surplus is a float sum of inserted * spi
            assert -tolerance - batch - rounding <= lim.surplus <= tolerance + chunk * spi + rounding


def test_await_sample_times_out_with_a_reason() -> None:
    lim = RateLimiter(samples_per_insert=1.0, min_size_to_sample=5)
    with lim.condition, pytest.raises(SampleTimeout, match="min_size_to_sample"):
        lim.await_sample(1, timeout=0.01)
    lim.record_insert(5)
    with lim.condition, pytest.raises(SampleTimeout, match="rate-limited"):
        lim.await_sample(1, timeout=0.01)
    assert lim.info()["sample_waits"] == 2


def test_await_insert_times_out_when_learner_is_behind() -> None:
    lim = RateLimiter(samples_per_insert=1.0, min_size_to_sample=1)
    lim.record_insert(2)
    with lim.condition, pytest.raises(InsertTimeout, match="learner is behind"):
        lim.await_insert(1, timeout=0.01)


def test_blocked_sampler_wakes_on_insert() -> None:
    lim = RateLimiter(samples_per_insert=1.0, min_size_to_sample=2)
    done = threading.Event()

    def sampler() -> None:
        with lim.condition:
            lim.await_sample(1, timeout=5.0)
            lim.record_sample(1)
        done.set()

    thread = threading.Thread(target=sampler)
    thread.start()
    time.sleep(0.05)
    assert not done.is_set()
    with lim.condition:
        lim.record_insert(3)
    thread.join(5.0)
    assert done.is_set() and lim.sampled == 1


def test_state_dict_round_trip_and_validation() -> None:
    lim = RateLimiter(samples_per_insert=2.0, min_size_to_sample=1)
    lim.record_insert(10, evicted=3)
    lim.record_sample(4)
    other = RateLimiter(samples_per_insert=2.0, min_size_to_sample=1)
    other.load_state_dict(lim.state_dict())
    assert (other.inserted, other.evicted, other.sampled, other.surplus) == (10, 3, 4, lim.surplus)
    with pytest.raises(ValueError, match="invalid rate limiter state"):
        other.load_state_dict({"inserted": 1, "evicted": 2, "sampled": 0})


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"samples_per_insert": 0.0, "min_size_to_sample": 1}, "samples_per_insert"),
        ({"samples_per_insert": 1.0, "min_size_to_sample": 0}, "min_size_to_sample"),
        ({"samples_per_insert": 1.0, "min_size_to_sample": 1, "tolerance": -1.0}, "tolerance"),
    ],
)
def test_bad_arguments_are_named(kwargs: dict[str, float], name: str) -> None:
    with pytest.raises(ValueError, match=name):
        RateLimiter(**kwargs)  # type: ignore[arg-type]
