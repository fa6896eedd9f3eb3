"""Prioritized replay throughput, ours vs cpprb, measured interleaved in one process.

Run: ``.venv/bin/python -m bench.replay [--quick]``. HalfCheetah-like rows (obs 17 float32,
action 6) at capacity 1,000,000, both tables filled first. Reports the median over rounds of:

- insert rate (steps/s) with chunks of 1 and of 256 steps (cpprb: ``add`` of 1 and 256 transitions);
- sample + update_priorities calls/s at batch 256 (ours: windows of 1 step);
- the sum-tree descent alone: our compiled descent vs a vectorised numpy descent (why numba).

Peers: cpprb 11 ``PrioritizedReplayBuffer``. torchrl is reported when importable (it is not
installed here). Each round runs every contender back to back, so machine noise hits all alike.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np

from algorithm.replay import PrioritizedTable, SumTree
from algorithm.spaces import SensorSpec
from algorithm.types import Chunk

CAPACITY = 1_000_000
OBS, ACT, BATCH = 17, 6, 256


def make_chunk(rng: np.random.Generator, t: int) -> Chunk:
    return Chunk(
        obs=[rng.standard_normal((t + 1, OBS), dtype=np.float32)],
        actions=rng.uniform(-1, 1, (t, ACT)).astype(np.float32),
        prev_actions=rng.uniform(-1, 1, (t, ACT)).astype(np.float32),
        rewards=rng.standard_normal(t, dtype=np.float32),
        terminated=np.zeros(t, dtype=bool),
        truncated=np.zeros(t, dtype=bool),
        behaviour_logp=rng.standard_normal(t, dtype=np.float32),
    )


def make_transitions(rng: np.random.Generator, t: int) -> dict[str, np.ndarray]:
    return {
        "obs": rng.standard_normal((t, OBS), dtype=np.float32),
        "act": rng.uniform(-1, 1, (t, ACT)).astype(np.float32),
        "rew": rng.standard_normal(t, dtype=np.float32),
        "next_obs": rng.standard_normal((t, OBS), dtype=np.float32),
        "done": np.zeros(t, dtype=np.float32),
    }


def numpy_descent(tree: np.ndarray, base: int, targets: np.ndarray) -> np.ndarray:
    """The vectorised alternative to the compiled descent: one numpy pass per tree level."""
    node = np.ones(targets.shape[0], dtype=np.int64)
    u = targets.copy()
    while node[0] < base:
        left = tree[2 * node]
        right_ok = (u >= left) & (tree[2 * node + 1] > 0)
        u = np.where(right_ok, u - left, u)
        node = 2 * node + right_ok
    return node - base


def rate(fn: Callable[[], object], calls: int, per_call: float) -> float:
    """Items per second over ``calls`` calls of ``fn`` (each handling ``per_call`` items)."""
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return calls * per_call / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 short rounds (a smoke run, a few seconds)")
    args = parser.parse_args()
    rounds, calls = (3, 100) if args.quick else (9, 1000)

    import cpprb  # a bench-only peer (pyproject extra "bench")

    try:
        import torchrl  # noqa: F401

        torchrl_note = "torchrl: importable but not measured here"
    except ImportError:
        torchrl_note = "torchrl: not installed, not measured"

    rng = np.random.default_rng(0)
    ours = PrioritizedTable(CAPACITY, (SensorSpec("obs", (OBS,)),), ACT, window=1, alpha=0.6, seed=0)
    peer = cpprb.PrioritizedReplayBuffer(
        CAPACITY,
        {"obs": {"shape": OBS}, "act": {"shape": ACT}, "rew": {}, "next_obs": {"shape": OBS}, "done": {}},
        alpha=0.6,
    )
    fill_chunk, fill_tr = make_chunk(rng, 255), make_transitions(rng, 256)
    start = time.perf_counter()
    for _ in range(CAPACITY // 256 + 1):
        ours.insert(fill_chunk)
        peer.add(**fill_tr)
    print(f"filled both to capacity {CAPACITY:,} in {time.perf_counter() - start:.1f} s")

    c1, c256 = make_chunk(rng, 1), make_chunk(rng, 256)
    t1, t256 = make_transitions(rng, 1), make_transitions(rng, 256)
    td = rng.uniform(0.0, 2.0, BATCH)

    def ours_sample_update() -> None:
        batch = ours.sample(BATCH, timeout=0)
        ours.update_priorities(batch.keys, td)

    def peer_sample_update() -> None:
        batch = peer.sample(BATCH)
        peer.update_priorities(batch["indexes"], td)

    tree = SumTree(CAPACITY)
    tree.set(np.arange(CAPACITY), rng.uniform(0.0, 1.0, CAPACITY))
    # Fresh stratified targets per call, as in real sampling (repeating one set would stay in cache).
    pool = [np.sort(rng.uniform(0.0, tree.total, BATCH)) for _ in range(1024)]
    assert all(np.array_equal(tree.find(t), numpy_descent(tree._tree, tree._base, t)) for t in pool[:8])
    cursor = iter(range(1 << 62))

    def next_targets() -> np.ndarray:
        return pool[next(cursor) % len(pool)]

    # (measure, contender) -> (one call, calls per round, items per call)
    contenders: dict[tuple[str, str], tuple[Callable[[], object], int, float]] = {
        ("insert 1-step chunks, steps/s", "ours"): (lambda: ours.insert(c1), calls * 10, 1),
        ("insert 1-step chunks, steps/s", "cpprb"): (lambda: peer.add(**t1), calls * 10, 1),
        ("insert 256-step chunks, steps/s", "ours"): (lambda: ours.insert(c256), calls, 256),
        ("insert 256-step chunks, steps/s", "cpprb"): (lambda: peer.add(**t256), calls, 256),
        ("sample+update B=256, calls/s", "ours"): (ours_sample_update, calls, 1),
        ("sample+update B=256, calls/s", "cpprb"): (peer_sample_update, calls, 1),
        ("tree descent B=256, calls/s", "ours (numba)"): (lambda: tree.find(next_targets()), calls * 5, 1),
        ("tree descent B=256, calls/s", "numpy"): (
            lambda: numpy_descent(tree._tree, tree._base, next_targets()),
            calls * 5,
            1,
        ),
    }
    results: dict[tuple[str, str], list[float]] = {key: [] for key in contenders}
    for _ in range(rounds):
        for key, (fn, n, per_call) in contenders.items():
            results[key].append(rate(fn, n, per_call))

    print(f"\nmedian of {rounds} interleaved rounds; capacity {CAPACITY:,}, obs {OBS} float32, action {ACT}")
    print(f"{'measure':34s} {'ours':>12s} {'peer':>12s} {'ours/peer':>10s}  peer")
    keys = list(contenders)
    for ours_key, peer_key in zip(keys[::2], keys[1::2], strict=True):
        a, b = statistics.median(results[ours_key]), statistics.median(results[peer_key])
        print(f"{ours_key[0]:34s} {a:12,.0f} {b:12,.0f} {a / b:9.2f}x  {peer_key[1]}")
    print(torchrl_note)


if __name__ == "__main__":
    main()
