"""Prioritized replay throughput, ours vs cpprb and torchrl, measured interleaved in one process.

Run: ``.venv/bin/python -m bench.replay [--quick]``. HalfCheetah-like rows (obs 17 float32,
action 6) at capacity 1,000,000, all tables filled first. Reports the median over rounds of:

- insert rate (steps/s) with chunks of 1 and of 256 steps (cpprb: ``add`` of 1 and 256 transitions;
  torchrl: ``add`` of one transition, ``extend`` by 256);
- sample + update_priorities calls/s at batch 256 (ours: windows of 1 step; torchrl:
  ``sample(return_info=True)`` + ``update_priority``, on one torch thread);
- the sum-tree descent alone: our compiled descent vs a vectorised numpy descent (why numba).

Peers: cpprb 11 ``PrioritizedReplayBuffer``, and torchrl 0.14 ``PrioritizedReplayBuffer`` on a
``LazyTensorStorage`` when ``bench/torchrl_setup.sh`` installed it (otherwise one line says why it is
not measured). Each round runs every contender back to back, so machine noise hits all alike.
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import sys
import time
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np

from algorithm.replay import PrioritizedTable, SumTree
from algorithm.spaces import SensorSpec
from algorithm.types import Chunk

CAPACITY = 1_000_000
OBS, ACT, BATCH = 17, 6, 256


def random_chunk(sensors: tuple[SensorSpec, ...], action_size: int, t: int, rng: np.random.Generator) -> Chunk:
    """A chunk of ``t`` steps of random data shaped like an actor's (float sensors only)."""
    return Chunk(
        obs=[rng.standard_normal((t + 1, *s.shape), dtype=np.float32) for s in sensors],
        actions=rng.uniform(-1, 1, (t, action_size)).astype(np.float32),
        prev_actions=rng.uniform(-1, 1, (t, action_size)).astype(np.float32),
        rewards=rng.standard_normal(t, dtype=np.float32),
        terminated=np.zeros(t, dtype=bool),
        truncated=np.zeros(t, dtype=bool),
        behaviour_logp=rng.standard_normal(t, dtype=np.float32),
    )


def make_chunk(rng: np.random.Generator, t: int) -> Chunk:
    return random_chunk((SensorSpec("obs", (OBS,)),), ACT, t, rng)


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


def first_line(exc: BaseException) -> str:
    """An exception's message cut to one line (torch's C++ errors append a stack trace)."""
    return (str(exc).splitlines() or [""])[0]


def import_torchrl() -> tuple[Any, str]:
    """torchrl's ``(PrioritizedReplayBuffer, LazyTensorStorage, TensorDict)``, or None and why not.

    torchrl publishes wheels only, and the 0.14.1 wheel's C++ extension (the sum/min segment trees
    behind the prioritized sampler) was linked against a newer torch: it references two autograd
    symbols (for its ``safetanh`` op) that torch 2.13 lacks, so the usual eager-binding import fails
    and the sampler raises "SumSegmentTreeFp32 is not available". Binding lazily defers those two
    symbols to a first call that never comes; the segment trees need neither, and ``torchrl_works``
    checks them through the public API before anything is timed.
    """
    import torch  # loaded with the default flags first

    # One torch thread, as ours and cpprb run on one core: on this shared 2-core machine two OpenMP
    # threads made each 256-row extend about 5x slower than one.
    torch.set_num_threads(1)
    flags = sys.getdlopenflags()
    sys.setdlopenflags(os.RTLD_LAZY)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            from tensordict import TensorDict
            from torchrl.data import LazyTensorStorage, PrioritizedReplayBuffer
    except ImportError as exc:
        return None, f"torchrl: not installed, not measured (no module {exc.name!r}; bench/torchrl_setup.sh adds it)"
    except Exception as exc:  # a torchrl/tensordict/torch mismatch that fails at import
        return None, f"torchrl: import fails, not measured ({type(exc).__name__}: {first_line(exc)})"
    finally:
        sys.setdlopenflags(flags)
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # one INFO line per storage otherwise
    return (PrioritizedReplayBuffer, LazyTensorStorage, TensorDict), ""


def torchrl_works(classes: Any) -> str:
    """Empty if torchrl's prioritized sampler samples by priority, else why not (a one-line reason)."""
    import torch

    buffer_cls, storage_cls, tensordict_cls = classes
    try:
        rb = buffer_cls(alpha=1.0, beta=0.4, storage=storage_cls(64), batch_size=BATCH)
        rb.extend(tensordict_cls({"x": torch.arange(64.0)}, batch_size=[64]))
        rb.update_priority(torch.arange(64), torch.zeros(64))
        rb.update_priority(torch.tensor([5]), torch.tensor([1.0]))
        batch, info = rb.sample(return_info=True)
    except Exception as exc:  # e.g. RuntimeError: SumSegmentTreeFp32 is not available
        return f"torchrl: installed but its sampler fails, not measured ({type(exc).__name__}: {first_line(exc)})"
    if not (torch.all(info["index"] == 5) and torch.all(batch["x"] == 5.0)):
        return "torchrl: installed but its prioritized sampler ignores priorities, not measured"
    return ""


def to_tensordict(tensordict_cls: Any, transitions: dict[str, np.ndarray], single: bool = False) -> Any:
    """cpprb's transition dict as a TensorDict (batch of t rows, or one unbatched row with ``single``)."""
    import torch

    fields = {name: torch.from_numpy(value) for name, value in transitions.items()}
    if single:
        return tensordict_cls({name: value[0] for name, value in fields.items()}, batch_size=[])
    return tensordict_cls(fields, batch_size=[len(transitions["rew"])])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 short rounds (a smoke run, a few seconds)")
    args = parser.parse_args()
    rounds, calls = (3, 100) if args.quick else (9, 1000)

    import cpprb  # a bench-only peer (pyproject extra "bench")

    torchrl_classes, torchrl_note = import_torchrl()
    if torchrl_classes is not None:
        torchrl_note = torchrl_works(torchrl_classes)
    trl: Any = None  # torchrl's buffer, when measured
    if not torchrl_note:
        buffer_cls, storage_cls, tensordict_cls = torchrl_classes
        trl = buffer_cls(alpha=0.6, beta=0.4, storage=storage_cls(CAPACITY), batch_size=BATCH)

    rng = np.random.default_rng(0)
    ours = PrioritizedTable(CAPACITY, (SensorSpec("obs", (OBS,)),), ACT, window=1, alpha=0.6, seed=0)
    peer = cpprb.PrioritizedReplayBuffer(
        CAPACITY,
        {"obs": {"shape": OBS}, "act": {"shape": ACT}, "rew": {}, "next_obs": {"shape": OBS}, "done": {}},
        alpha=0.6,
    )
    fill_chunk, fill_tr = make_chunk(rng, 255), make_transitions(rng, 256)
    fill_td = None if trl is None else to_tensordict(tensordict_cls, fill_tr)
    start = time.perf_counter()
    for _ in range(CAPACITY // 256 + 1):
        ours.insert(fill_chunk)
        peer.add(**fill_tr)
        if trl is not None:
            trl.extend(fill_td)
    print(f"filled all to capacity {CAPACITY:,} in {time.perf_counter() - start:.1f} s")

    c1, c256 = make_chunk(rng, 1), make_chunk(rng, 256)
    t1, t256 = make_transitions(rng, 1), make_transitions(rng, 256)
    td = rng.uniform(0.0, 2.0, BATCH)

    def ours_sample_update() -> None:
        batch = ours.sample(BATCH, timeout=0)
        ours.update_priorities(batch.keys, td)

    def peer_sample_update() -> None:
        batch = peer.sample(BATCH)
        peer.update_priorities(batch["indexes"], td)

    if trl is not None:
        import torch

        trl_t1, trl_t256 = to_tensordict(tensordict_cls, t1, single=True), to_tensordict(tensordict_cls, t256)
        trl_td = torch.from_numpy(td.astype(np.float32))  # its segment trees take float32 priorities

    def trl_sample_update() -> None:
        _, info = trl.sample(return_info=True)
        trl.update_priority(info["index"], trl_td)

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
        ("insert 1-step chunks, steps/s", "torchrl"): (lambda: trl.add(trl_t1), calls * 10, 1),
        ("insert 256-step chunks, steps/s", "ours"): (lambda: ours.insert(c256), calls, 256),
        ("insert 256-step chunks, steps/s", "cpprb"): (lambda: peer.add(**t256), calls, 256),
        ("insert 256-step chunks, steps/s", "torchrl"): (lambda: trl.extend(trl_t256), calls, 256),
        ("sample+update B=256, calls/s", "ours"): (ours_sample_update, calls, 1),
        ("sample+update B=256, calls/s", "cpprb"): (peer_sample_update, calls, 1),
        ("sample+update B=256, calls/s", "torchrl"): (trl_sample_update, calls, 1),
        ("tree descent B=256, calls/s", "ours (numba)"): (lambda: tree.find(next_targets()), calls * 5, 1),
        ("tree descent B=256, calls/s", "numpy"): (
            lambda: numpy_descent(tree._tree, tree._base, next_targets()),
            calls * 5,
            1,
        ),
    }
    if trl is None:  # the torchrl entries above are never called then
        contenders = {key: value for key, value in contenders.items() if key[1] != "torchrl"}
    results: dict[tuple[str, str], list[float]] = {key: [] for key in contenders}
    for _ in range(rounds):
        for key, (fn, n, per_call) in contenders.items():
            results[key].append(rate(fn, n, per_call))

    # measure -> contender -> median; each measure lists ours, then its peer, then torchrl if measured.
    medians: dict[str, dict[str, float]] = {}
    for (measure, who), values in results.items():
        medians.setdefault(measure, {})[who] = statistics.median(values)
    print(f"\nmedian of {rounds} interleaved rounds; capacity {CAPACITY:,}, obs {OBS} float32, action {ACT}")
    header = f"{'measure':34s} {'ours':>12s} {'peer':>12s} {'ours/peer':>10s}  {'peer':12s}"
    print((header + (f" {'torchrl':>12s} {'ours/torchrl':>12s}" if trl is not None else "")).rstrip())
    for measure, row in medians.items():
        (_, a), (peer_name, b) = list(row.items())[:2]
        line = f"{measure:34s} {a:12,.0f} {b:12,.0f} {a / b:9.2f}x  {peer_name:12s}"
        if "torchrl" in row:
            line += f" {row['torchrl']:12,.0f} {a / row['torchrl']:11.2f}x"
        print(line.rstrip())
    if torchrl_note:
        print(torchrl_note)


if __name__ == "__main__":
    main()
