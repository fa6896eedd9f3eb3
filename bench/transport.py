"""Batches from the replay server to the learner: the learner's CPU per sampled step, the batches/s one
replay serves against what the learner consumes, and large batches.

    python -m bench.transport [--seconds 8] [--rounds 3] [--out bench/results/transport/rows.csv]

A replay server process (prefilled with 100k HalfCheetah-size steps, the bench.grpc_replay server) and,
in a client process, the learner's own prefetcher (ds/learner/feeds.py ``BatchPrefetcher`` with its
defaults, as the learner role runs it), its queue emptied for ``--seconds`` either at the learner's
pace or as fast as it fills. Each round first times the HalfCheetah default's update in the bench's
own process (its batch, dtype and net, torch's default threads, as the learner role runs it):

- **learner CPU per sampled step**: the client process's CPU time (every thread: the prefetcher's
  calls and decoding, gRPC's own threads, the consumer's gets; not the consumer's sleeps between
  gets, which stand for the learner's updates) over the windows x steps it received, taking one
  batch per update at the rate just timed. Goal <= 0.4 us at the HalfCheetah default
  (batch 256, one-step windows); also shown with one batch per call (``per_call=1``), the way a
  learner sampled before several batches went in one call;
- **served / consumed**: the batches/s that one prefetcher delivers emptied as fast as it fills,
  against the updates/s just timed. Goal >= 3x;
- **large batches**: 4,096 and 16,384 one-step windows, and 4,096 windows of 21 steps with a
  64-wide recurrent state, drawn through the server with the limits ``message_limit_bytes`` gives
  for them: no message-size error, and how many batches one call carried.

Each is measured three ways in every round: batches through a file in /dev/shm (ds/replay/shared.py,
the default where learner and replay share a host), over the socket (``shared_memory=False``, as
across hosts), and one batch per call over the socket.

Rows go to ``--out`` as they land; timings drift between runs here, so compare rows of one run.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from ds.net.grpc_env import read_replies_on_calling_thread  # noqa: E402

read_replies_on_calling_thread()  # as main_ds.py does for every role (ds/net/grpc_env.py)

import argparse  # noqa: E402
import multiprocessing as mp  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from algorithm.spaces import SensorSpec  # noqa: E402
from bench.grpc_replay import replay_process  # noqa: E402
from bench.replay import ACT, OBS  # noqa: E402
from bench.rows import append_row  # noqa: E402
from ds.replay.codec import message_limit_bytes  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FIELDS = ["case", "batch_size", "window", "per_call", "shared", "pace", "batches_per_s", "steps_per_s",
          "cpu_us_per_step", "batches_per_call", "error"]  # fmt: skip
GOAL_CPU_US, GOAL_SERVED = 0.4, 3.0
DEPTH = 16  # the learner role's prefetch queue (ds/learner/learner.py)


def drain(port: int, sensors: tuple[SensorSpec, ...], rnn: int, batch: int, one_per_call: bool, limit: int,
          seconds: float, pace: float, shared: bool, results: Any) -> None:  # fmt: skip
    """A learner's prefetcher against the server at ``port``, its queue emptied for ``seconds``, one
    batch every ``1 / pace`` seconds (0: as fast as it fills); puts ``(batches, steps, cpu seconds,
    wall seconds, batches per call, error)``. ``one_per_call``: one batch per call (the prefetcher's
    ``per_call=1``), as before batches were packed; ``shared``: batches through a file in /dev/shm
    (the default on one host), else over the socket (as across hosts)."""
    from ds.learner.feeds import BatchPrefetcher
    from ds.net.heap import keep_freed_memory
    from ds.replay.client import ReplayClient

    keep_freed_memory()  # as main_ds.py does for every role

    try:
        with ReplayClient(
            f"127.0.0.1:{port}", sensors, ACT, rnn, max_message_bytes=limit, shared_memory=shared
        ) as replay:
            per_call: dict[str, Any] = {"per_call": 1} if one_per_call else {}  # absent: the prefetcher's default
            prefetcher = BatchPrefetcher(replay, batch, DEPTH, sample_timeout_s=10.0, **per_call)
            prefetcher.start()
            for _ in range(2 * DEPTH):  # warm the channel and the caches
                prefetcher.get(timeout=30.0)
            batches = steps = 0
            getting = 0.0  # the consumer's CPU in get(): the learner's too
            cpu, mine, began = time.process_time(), time.thread_time(), time.perf_counter()
            while time.perf_counter() - began < seconds:
                if pace:  # a sleep's wake-up costs ~0.1 ms of CPU here, the learner's busy thread none
                    time.sleep(max(0.0, began + batches / pace - time.perf_counter()))
                before = time.thread_time()
                got = prefetcher.get(timeout=30.0)
                getting += time.thread_time() - before
                if got is None:
                    raise RuntimeError("no batch within 30 s")
                batches += 1
                steps += got.batch_size * got.window
            # the process's CPU but the consumer's own pacing: the prefetcher, gRPC's threads and get()
            cpu = time.process_time() - cpu - (time.thread_time() - mine) + getting
            wall = time.perf_counter() - began
            prefetcher.stop()
            ratio = prefetcher.sampled / max(getattr(prefetcher, "calls", prefetcher.sampled), 1)
        results.put((batches, steps, cpu, wall, ratio, ""))
    except Exception as e:  # reported as the row's error: a large batch that fails is a result
        results.put((0, 0, 0.0, 1.0, 0.0, f"{type(e).__name__}: {e}"))


def measure(sensors: tuple[SensorSpec, ...], rnn: int, batch: int, window: int, one_per_call: bool,
            seconds: float, pace: float = 0.0, shared: bool = True) -> dict[str, Any]:  # fmt: skip
    limit = message_limit_bytes(sensors, ACT, batch, window, rnn, max_chunk_steps=64)
    ctx = mp.get_context("spawn")
    with replay_process(sensors, ACT, limit, window=window, rnn_state_size=rnn) as port:
        results = ctx.Queue()
        client = ctx.Process(
            target=drain, args=(port, sensors, rnn, batch, one_per_call, limit, seconds, pace, shared, results)
        )
        client.start()
        batches, steps, cpu, wall, per_call, error = results.get(timeout=300 + seconds)
        client.join()
    return {
        "batch_size": batch,
        "window": window,
        "per_call": "1" if one_per_call else "default",
        "shared": shared,
        "pace": round(pace, 1),
        "batches_per_s": round(batches / wall, 1),
        "steps_per_s": round(steps / wall),
        "cpu_us_per_step": round(cpu / steps * 1e6, 3) if steps else float("nan"),
        "batches_per_call": round(per_call, 2),
        "error": error,
    }


def consumed_updates_per_s(seconds: float) -> float:
    """Updates/s of the HalfCheetah default's update (its batch, dtype and net), torch's default threads."""
    import torch

    from algorithm.config.load import load_config
    from algorithm.sac.learner import SAC
    from algorithm.spaces import ActionSpec, EnvSpec
    from bench.learner import make_batch

    config = load_config(ROOT / "envs" / "mujoco" / "half_cheetah", None, ["sac.seed=0"]).config
    spec = EnvSpec((SensorSpec("obs", (OBS,)),), ActionSpec((), ACT, (-1.0,) * ACT, (1.0,) * ACT))
    sac = SAC(spec, config.sac_config, config.nn_config, config.replay_config)
    batches = [make_batch(np.random.default_rng(i)) for i in range(4)]
    for b in batches:
        sac.update(b)
    done, began = 0, time.perf_counter()
    while time.perf_counter() - began < seconds:
        sac.update(batches[done % 4])
        done += 1
    print(f"(HalfCheetah default update: batch {config.replay_config.batch_size}, {torch.get_num_threads()} threads)")
    return done / (time.perf_counter() - began)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "transport" / "rows.csv")
    args = parser.parse_args()
    vector = (SensorSpec("obs", (OBS,)),)

    def row(case: str, **values: Any) -> dict[str, Any]:
        append_row(args.out, FIELDS, {"case": case, **values})
        print(case, values, flush=True)
        return values

    # (one batch per call, through /dev/shm): the prefetcher's default on one host, over the socket
    # (across hosts), and one batch per call over the socket (before batches were packed)
    ways = {"shared": (False, True), "socket": (False, False), "one per call": (True, False)}
    paced: dict[str, list[dict[str, Any]]] = {way: [] for way in ways}
    drained: dict[str, list[dict[str, Any]]] = {way: [] for way in ways}
    consumed = []
    for r in range(args.rounds):
        consumed.append(consumed_updates_per_s(args.seconds))
        row(f"learner update, round {r}", batches_per_s=round(consumed[-1], 1))
        for way, (one, shared) in ways.items():
            paced[way].append(row(f"halfcheetah default, {way}, at the learner's pace, round {r}",
                                  **measure(vector, 0, 256, 1, one, args.seconds, consumed[-1], shared)))  # fmt: skip
            drained[way].append(row(f"halfcheetah default, {way}, emptied as it fills, round {r}",
                                    **measure(vector, 0, 256, 1, one, args.seconds, 0.0, shared)))  # fmt: skip
    large = {shared: [row(f"large, {b} x {w}{', rnn 64' if rnn else ''}, {'shared' if shared else 'socket'}",
                          **measure(vector, rnn, b, w, False, args.seconds / 2, 0.0, shared))
                      for b, w, rnn in ((4096, 1, 0), (16384, 1, 0), (4096, 21, 64))]
             for shared in (True, False)}  # fmt: skip

    cpu = {way: statistics.median(x["cpu_us_per_step"] for x in rows) for way, rows in paced.items()}
    fast = {way: statistics.median(x["cpu_us_per_step"] for x in rows) for way, rows in drained.items()}
    served = {way: statistics.median(x["batches_per_s"] for x in rows) for way, rows in drained.items()}
    used = statistics.median(consumed)
    print(f"\nHalfCheetah default (batch 256, one-step windows), median of {args.rounds} rounds x {args.seconds:.0f} s")
    print("| measure | " + " | ".join(ways) + " | goal |\n|---|---|---|---|---|")
    print(f"| learner CPU per sampled step, at its pace ({used:.0f} updates/s) | "
          + " | ".join(f"{cpu[w]:.2f} us" for w in ways) + f" | <= {GOAL_CPU_US} us |")  # fmt: skip
    print("| the same, batches taken as fast as they come | " + " | ".join(f"{fast[w]:.2f} us" for w in ways) + " | |")
    print(f"| replay batches/s to one learner / its updates/s ({used:.0f}) | "
          + " | ".join(f"{served[w]:,.0f} = {served[w] / used:.1f}x" for w in ways)
          + f" | >= {GOAL_SERVED}x |")  # fmt: skip
    for i, case in enumerate(("4096 x 1", "16384 x 1", "4096 x 21, rnn 64")):
        outcome = [x[i]["error"] or f"{x[i]['batches_per_s']} batches/s, {x[i]['batches_per_call']} per call"
                   for x in (large[True], large[False])]  # fmt: skip
        print(f"| large batch {case} | {outcome[0]} | {outcome[1]} | | no message-size error |")


if __name__ == "__main__":
    main()
