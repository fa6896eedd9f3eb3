"""Concurrent inserts, samples, priority updates and saves from many threads."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from algorithm.replay import InsertTimeout, PrioritizedTable, RateLimiter, SampleTimeout

from .chunks import VECTOR, make_chunk


def run_threads(
    workers: list[Callable[[], None]], seconds: float, until: Callable[[], bool], limit: float = 60.0
) -> list[BaseException]:
    """Runs every worker in its own thread, over and over, for at least ``seconds`` and then until
    ``until()`` holds (at most ``limit`` seconds in all): on a loaded machine the storm lasts longer
    rather than the test asserting on how much a fixed time allowed."""
    errors: list[BaseException] = []
    start = time.monotonic()

    def going() -> bool:
        elapsed = time.monotonic() - start
        return not errors and elapsed < limit and (elapsed < seconds or not until())

    def loop(work: Callable[[], None]) -> None:
        try:
            while going():
                work()
        except BaseException as e:  # collected and reported by the test
            errors.append(e)

    threads = [threading.Thread(target=loop, args=(w,)) for w in workers]
    for t in threads:
        t.start()
    for t in threads:
        t.join(limit + 30.0)
    assert not any(t.is_alive() for t in threads), "a worker hung"
    return errors


def test_concurrent_insert_sample_update_and_save(tmp_path: Path) -> None:
    limiter = RateLimiter(samples_per_insert=16.0, min_size_to_sample=32, tolerance=2000.0)
    tab = PrioritizedTable(500, (VECTOR,), 2, window=4, alpha=0.8, rate_limiter=limiter, seed=0)
    next_first = [0]
    key_lock = threading.Lock()
    count_lock = threading.Lock()
    sampled = [0]

    def inserter(seed: int) -> Callable[[], None]:
        rng = np.random.default_rng(seed)

        def work() -> None:
            t = int(rng.integers(1, 40))
            # Chunk contents name their keys, so two inserters must not interleave first-key choice
            # and insert: the lock serialises them, the table's own lock is what is under test.
            with key_lock:
                try:
                    tab.insert(make_chunk(t, next_first[0]), timeout=0.05)
                except InsertTimeout:
                    return
                next_first[0] += t + 1

        return work

    def sampler(seed: int) -> Callable[[], None]:
        rng = np.random.default_rng(seed)

        def work() -> None:
            try:
                batch = tab.sample(64, timeout=0.05)
            except SampleTimeout:
                return
            # a window reads its own chunk only: observations never decrease and stop at the end
            obs = batch.obs[0][:, :, 0]
            assert (np.diff(obs, axis=1) >= 0).all() and (np.diff(obs, axis=1) <= 1).all()
            np.testing.assert_array_equal(obs[:, 0], batch.keys.astype(np.float32))
            assert (batch.probabilities > 0).all()
            tab.update_priorities(batch.keys, rng.uniform(0.0, 2.0, 64))
            with count_lock:
                sampled[0] += 1

        return work

    def saver() -> None:
        tab.save(tmp_path / "replay.npz")
        time.sleep(0.05)

    def enough() -> bool:
        return sampled[0] > 10 and tab.info()["inserted_chunks"] > 10

    workers = [inserter(1), inserter(2), sampler(3), sampler(4), sampler(5), saver]
    errors = run_threads(workers, seconds=2.0, until=enough)
    assert not errors, errors

    info = tab.info()
    assert sampled[0] > 10 and info["inserted_chunks"] > 10, "the storm did not get going in 60 s"
    assert info["sampled_windows"] == 64 * sampled[0]
    # surplus stays within the tolerance band, overshot by at most one request
    assert -2000.0 - 64 <= limiter.surplus <= 2000.0 + 39 * 16.0
    # the tree, the key ring and the counters agree after the storm
    leaves = np.asarray(tab._tree.leaves)
    assert math.isclose(info["total_priority"], math.fsum(leaves), rel_tol=1e-12)
    row_key, end_key = tab._ring.row_key, tab._ring.end_key
    steps = (row_key >= 0) & (row_key != end_key)
    assert info["size"] == int(steps.sum())
    assert (leaves[~steps] == 0).all() and (leaves[steps] > 0).all()
    restored = PrioritizedTable(500, (VECTOR,), 2, window=4, alpha=0.8, rate_limiter=RateLimiter(16.0, 32, 2000.0))
    restored.load(tmp_path / "replay.npz")  # a save taken mid-storm is consistent
