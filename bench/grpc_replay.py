"""The replay over gRPC on loopback, HalfCheetah-size steps, side by side with the dm-reverb anchor.

Run: ``.venv/bin/python -m bench.grpc_replay [--seconds 5] [--rounds 3]``.

A replay server process (prioritized, alpha 0.6, capacity 1M, windows of one step as HalfCheetah's
learner samples them, prefilled with 100k steps) and client processes, each running one kind of
call in a loop for ``--seconds``:

- insert: 1, 2 and 4 actor processes, each handing 64-step chunks (``actor_config.chunk_length``)
  to the actor's own sink (``ds.actor.actor.ReplaySink``) as fast as it takes them: up to 4 inserts in
  flight, and chunks that arrive meanwhile go together in the next request (up to 16); stored
  steps/s summed over the actors. For reference, one actor sending one chunk per request and
  waiting for each answer (``in_flight=1``);
- sample: one learner process drawing batches of 256; sampled steps/s;
- sample + update_priorities: the learner loop's pair of calls, in calls/s and steps/s.

The same calls on the in-process table are timed too, for the cost of the wire. The anchor is
dm-reverb measured on this kind of machine (issue 4): about 7k-10k inserted items/s and about 50k
sampled items/s at batch 256; an item there is one step here. Goals: inserts >= 10x Reverb's upper
figure (100k steps/s), samples >= 2x (100k steps/s). Reverb itself is not run (no wheel for this
Python); its figures are printed as given.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import statistics
import time
from collections.abc import Iterator
from contextlib import contextmanager
from multiprocessing.synchronize import Barrier, Event
from typing import Any

import numpy as np

from algorithm.replay import PrioritizedTable
from algorithm.spaces import SensorSpec
from bench.replay import ACT, BATCH, OBS, random_chunk
from ds.replay.codec import message_limit_bytes

CAPACITY, PREFILL, CHUNK = 1_000_000, 100_000, 64
SENSORS = (SensorSpec("obs", (OBS,)),)
LIMIT = message_limit_bytes(SENSORS, ACT, BATCH, window=1, max_chunk_steps=CHUNK)
REVERB = {"insert": (7_000, 10_000), "sample": (50_000, 50_000)}  # items/s, low and high (issue 4)
GOAL = {"insert": 10.0, "sample": 2.0}  # x Reverb's upper figure


def make_table(
    sensors: tuple[SensorSpec, ...] = SENSORS, action_size: int = ACT, window: int = 1, rnn_state_size: int = 0
) -> PrioritizedTable:
    """A prioritized table without the actor/learner rate limiter: benches measure capacity."""
    return PrioritizedTable(CAPACITY, sensors, action_size, window, alpha=0.6, rnn_state_size=rnn_state_size, seed=0)


def serve(
    port: Any,
    stop: Event,
    sensors: tuple[SensorSpec, ...] = SENSORS,
    action_size: int = ACT,
    limit: int = LIMIT,
    window: int = 1,
    rnn_state_size: int = 0,
) -> None:
    """A replay process: a table of ``window``-step windows prefilled with ``PREFILL`` random steps
    behind the gRPC servicer, its port put in ``port.value``, until ``stop`` is set."""
    from ds.net.heap import keep_freed_memory
    from ds.replay.service import serve_replay

    keep_freed_memory()  # as main_ds.py does for every role

    table, rng = make_table(sensors, action_size, window, rnn_state_size), np.random.default_rng(1)
    for _ in range(PREFILL // CHUNK):
        chunk = random_chunk(sensors, action_size, CHUNK, rng)
        if rnn_state_size:
            chunk.rnn_state = rng.standard_normal((CHUNK, rnn_state_size), dtype=np.float32)
        table.insert(chunk)
    server, port.value = serve_replay(table, "127.0.0.1:0", max_message_bytes=limit)
    stop.wait()
    server.stop(grace=1.0)


@contextmanager
def replay_process(
    sensors: tuple[SensorSpec, ...] = SENSORS,
    action_size: int = ACT,
    limit: int = LIMIT,
    window: int = 1,
    rnn_state_size: int = 0,
) -> Iterator[int]:
    """Run :func:`serve` in a child process for the ``with`` block; yields its port."""
    ctx = mp.get_context("spawn")
    port, stop = ctx.Value("i", 0), ctx.Event()
    args = (port, stop, sensors, action_size, limit, window, rnn_state_size)
    server = ctx.Process(target=serve, args=args, daemon=True)
    server.start()
    deadline = time.monotonic() + 120
    while port.value == 0:
        if not server.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the replay server process did not start")
        time.sleep(0.1)
    try:
        yield int(port.value)
    finally:
        stop.set()
        server.join(timeout=10)


def client(kind: str, port: int, seconds: float, start: Barrier, results: Any) -> None:
    """One actor (``insert``: the actor's own sink, with its inserts in flight while it would step
    its envs) or learner (``sample``, ``sample_update``) process: warms its channel up, waits for
    the others, then calls for ``seconds`` and reports ``(calls, steps stored, elapsed)``."""
    from ds.actor.actor import ReplaySink
    from ds.replay.client import ReplayClient

    rng = np.random.default_rng(os.getpid())
    chunks = [random_chunk(SENSORS, ACT, CHUNK, rng) for _ in range(8)]  # a few distinct payloads, as real actors send
    td = rng.uniform(0.0, 2.0, BATCH)
    with ReplayClient(f"127.0.0.1:{port}", SENSORS, ACT, max_message_bytes=LIMIT) as replay:
        one_by_one = kind == "insert_sync"  # one chunk per request, waiting for each answer
        sink = ReplaySink(replay, lambda: False, in_flight=1 if one_by_one else 4,
                          max_chunks_per_insert=1 if one_by_one else 16)  # fmt: skip

        def call(i: int) -> int:
            if kind.startswith("insert"):
                sink(chunks[i % len(chunks)])
                return CHUNK
            batch = replay.sample(BATCH, timeout=10.0)
            if kind == "sample_update":
                replay.update_priorities(batch.keys, td)
            return BATCH

        for i in range(5):
            call(i)
        start.wait()
        calls = steps = 0
        began = time.perf_counter()
        while time.perf_counter() - began < seconds:
            steps += call(calls)
            calls += 1
        sink.flush()  # count only what the replay has stored
        elapsed = time.perf_counter() - began
    results.put((calls, steps, elapsed))


def over_grpc(kind: str, processes: int, port: int, seconds: float) -> tuple[float, float]:
    """``(calls/s, steps/s)`` summed over ``processes`` client processes of one ``kind``."""
    ctx = mp.get_context("spawn")
    start, results = ctx.Barrier(processes), ctx.Queue()
    procs = [ctx.Process(target=client, args=(kind, port, seconds, start, results)) for _ in range(processes)]
    for p in procs:
        p.start()
    reports = [results.get(timeout=120 + seconds) for _ in procs]
    for p in procs:
        p.join()
        if p.exitcode != 0:
            raise RuntimeError(f"a {kind} client exited with {p.exitcode}")
    return sum(c / e for c, _, e in reports), sum(s / e for _, s, e in reports)


def in_process(kind: str, table: PrioritizedTable, seconds: float) -> tuple[float, float]:
    """The same calls on an in-process table: ``(calls/s, steps/s)``."""
    rng = np.random.default_rng(2)
    chunks, td = [random_chunk(SENSORS, ACT, CHUNK, rng) for _ in range(8)], rng.uniform(0.0, 2.0, BATCH)
    calls = steps = 0
    began = time.perf_counter()
    while (elapsed := time.perf_counter() - began) < seconds:
        if kind == "insert":
            table.insert(chunks[calls % len(chunks)])
            steps += CHUNK
        else:
            batch = table.sample(BATCH, timeout=0)
            if kind == "sample_update":
                table.update_priorities(batch.keys, td)
            steps += BATCH
        calls += 1
    return calls / elapsed, steps / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="timed seconds per measurement")
    parser.add_argument("--rounds", type=int, default=3, help="rounds; the median is reported")
    args = parser.parse_args()

    local = make_table()
    rng = np.random.default_rng(3)
    for _ in range(PREFILL // CHUNK):
        local.insert(random_chunk(SENSORS, ACT, CHUNK, rng))

    rows = [("insert_sync", 1), ("insert", 1), ("insert", 2), ("insert", 4), ("sample", 1), ("sample_update", 1)]
    grpc_rates: dict[tuple[str, int], list[tuple[float, float]]] = {row: [] for row in rows}
    local_rates: dict[str, list[tuple[float, float]]] = {"insert": [], "sample": [], "sample_update": []}
    local_kind = {"insert_sync": "insert", "insert": "insert", "sample": "sample", "sample_update": "sample_update"}
    with replay_process() as port:
        for round_ in range(args.rounds):
            for kind, n in rows:
                grpc_rates[(kind, n)].append(over_grpc(kind, n, port, args.seconds))
            for kind in local_rates:
                local_rates[kind].append(in_process(kind, local, args.seconds))
            line = ", ".join(f"{k} x{n} {r[-1][1]:,.0f}" for (k, n), r in grpc_rates.items())
            print(f"round {round_}: over gRPC, steps/s: {line}", flush=True)

    def median(values: list[tuple[float, float]]) -> tuple[float, float]:
        return statistics.median(v[0] for v in values), statistics.median(v[1] for v in values)

    print(
        f"\nReplay over gRPC on loopback: HalfCheetah-size steps (obs {OBS}, action {ACT}), {CHUNK}-step chunks, "
        f"batch {BATCH}, capacity {CAPACITY:,}; median of {args.rounds} rounds of {args.seconds:g} s, "
        f"{os.cpu_count()} cores"
    )
    print("| measure | ASAC over gRPC, steps/s | chunks or batches/s | in-process, steps/s | Reverb anchor, items/s "
          "| / Reverb | goal |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for (kind, n), values in grpc_rates.items():
        calls, steps = median(values)
        local_steps = median(local_rates[local_kind[kind]])[1]
        anchor = REVERB[local_kind[kind] if kind != "sample_update" else "sample"]
        vs = steps / anchor[1]
        goal = GOAL["insert" if kind.startswith("insert") else "sample"]
        label = {"insert": f"insert, {n} actor{'s' if n > 1 else ''}",
                 "insert_sync": "insert, 1 actor, one chunk per request, waiting for each", "sample": "sample",
                 "sample_update": "sample + update_priorities"}[kind]  # fmt: skip
        goal_text = f">= {goal:g}x: {'met' if vs >= goal else 'NOT met'}" if kind in ("insert", "sample") else "-"
        print(
            f"| {label} | {steps:,.0f} | {calls:,.0f} | {local_steps:,.0f} | {anchor[0]:,}-{anchor[1]:,} | "
            f"{vs:.1f}x | {goal_text} |"
        )


if __name__ == "__main__":
    main()
