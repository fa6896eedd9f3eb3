"""What the distributed roles cost and gain: the learner fed over gRPC, the actor with its gRPC sink,
and wall-clock to a Pendulum return with local roles against the single-process trainer.

    python -m bench.distributed learner [--seconds 20] [--rounds 2]
        updates/s of HalfCheetah's SAC (256x256, batch 256, prioritized) in three set-ups, one
        torch thread each: the plain single-process loop (sample, update, update_priorities on
        one thread), the distributed Learner on the in-process table, and the Learner fed over
        gRPC by a replay server process (prefetch and priority threads as deployed).
        Goal: over gRPC >= 0.9x the plain loop.
    python -m bench.distributed actor [--seconds 10] [--rounds 2] [--agents 1 8 32 64]
        HalfCheetah env steps/s of one actor process: the bare vector-env loop (uniform random
        actions, nothing stored) against the actor loop with the policy acting and every chunk
        inserted into a replay server process over gRPC. Goal: >= 0.8x the bare loop.
    python -m bench.distributed pendulum [--seeds 0 1] [--actors 1 2 4]
        wall seconds (from launching the command) and env steps until Pendulum-v1's evaluation
        (10 deterministic episodes every 500 env steps) first reaches -200: ``main.py gym/pendulum``
        against ``main_ds.py gym/pendulum local --actors N``.

Data in the learner and actor benches is random (speed only); every contender of a round runs back
to back so machine noise hits all alike, and the median over rounds is printed.
"""

from __future__ import annotations

import os

# As main.py and main_ds.py set them before torch and numpy load.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import csv
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from algorithm.config.load import load_config
from algorithm.config.schema import Config
from algorithm.replay import PrioritizedTable
from algorithm.run.actor import ActorLoop
from algorithm.sac.learner import SAC
from bench.grpc_replay import CHUNK, PREFILL, random_chunk, replay_process
from ds.actor.actor import ReplaySink
from ds.learner.learner import Learner
from ds.learner.service import ParamsStore
from ds.net.params import ParamsPublisher
from ds.replay.client import ReplayClient
from ds.replay.codec import message_limit_bytes
from envs.make import make_vector_env

ROOT = Path(__file__).resolve().parents[1]
TASK = "mujoco/half_cheetah"


def half_cheetah_config(extra: tuple[str, ...] = ()) -> Config:
    return load_config(
        ROOT / "envs" / TASK,
        "per",
        [
            "sac.seed=0",
            "base.max_step=-1",
            "eval.eval_per_step=0",
            "sac.save_model_per_step=1000000000",
            "sac.save_model_per_minute=1000",
            "replay.capacity=1000000",
            *extra,
        ],
    ).config


def timed_rate(count: Callable[[], int], seconds: float, warmup_s: float = 2.0) -> float:
    """Rate of ``count()`` over ``seconds`` after ``warmup_s``, read while something else runs."""
    time.sleep(warmup_s)
    start_count, start = count(), time.perf_counter()
    time.sleep(seconds)
    return (count() - start_count) / (time.perf_counter() - start)


# -- learner ------------------------------------------------------------------------------------
def plain_loop(config: Config, sac: SAC, table: PrioritizedTable, seconds: float) -> float:
    batch_size = config.replay_config.batch_size
    for _ in range(20):
        batch = table.sample(batch_size, timeout=0)
        table.update_priorities(batch.keys, sac.update(batch).td_abs)
    updates, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        batch = table.sample(batch_size, timeout=0)
        table.update_priorities(batch.keys, sac.update(batch).td_abs)
        updates += 1
    return updates / (time.perf_counter() - start)


def learner_rate(config: Config, sac: SAC, replay: PrioritizedTable | ReplayClient, seconds: float) -> float:
    """Updates/s of the distributed :class:`Learner` reading from ``replay``."""
    stop = threading.Event()
    publisher = ParamsPublisher("tcp://127.0.0.1:*")
    with tempfile.TemporaryDirectory() as tmp:
        learner = Learner(config, Path(tmp), sac, replay, publisher, ParamsStore(), stop=stop)
        thread = threading.Thread(target=learner.run, name="learner")
        thread.start()
        try:
            rate = timed_rate(lambda: learner.updates, seconds)
        finally:
            stop.set()
            thread.join()
            publisher.close()
    return rate


def bench_learner(args: argparse.Namespace) -> None:
    torch.set_num_threads(1)
    config = half_cheetah_config()
    spec = make_vector_env(config.base_config.build_path, 1, seed=0).spec
    sensors, action_size = spec.sensors, spec.action.size
    sac_cfg, replay_cfg = config.sac_config, config.replay_config
    limit = message_limit_bytes(sensors, action_size, replay_cfg.batch_size, window=1, max_chunk_steps=CHUNK)
    table = PrioritizedTable(replay_cfg.capacity, sensors, action_size, window=1, alpha=replay_cfg.alpha, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(PREFILL // CHUNK):
        table.insert(random_chunk(sensors, action_size, CHUNK, rng))
    rates: dict[str, list[float]] = {"plain loop, in-process": [], "Learner, in-process table": [],
                                     "Learner over gRPC": []}  # fmt: skip
    with replay_process(sensors, action_size, limit) as port:
        for round_ in range(args.rounds):
            sac = SAC(spec, sac_cfg, config.nn_config, replay_cfg)
            rates["plain loop, in-process"].append(plain_loop(config, sac, table, args.seconds))
            sac = SAC(spec, sac_cfg, config.nn_config, replay_cfg)
            rates["Learner, in-process table"].append(learner_rate(config, sac, table, args.seconds))
            sac = SAC(spec, sac_cfg, config.nn_config, replay_cfg)
            with ReplayClient(f"127.0.0.1:{port}", sensors, action_size, max_message_bytes=limit) as client:
                rates["Learner over gRPC"].append(learner_rate(config, sac, client, args.seconds))
            print(f"round {round_}: " + ", ".join(f"{k} {v[-1]:.1f}" for k, v in rates.items()) + " updates/s")
    median = {k: statistics.median(v) for k, v in rates.items()}
    base = median["plain loop, in-process"]
    dtype = sac_cfg.compute_dtype
    print(f"\nLearner updates/s, HalfCheetah SAC (compute_dtype {dtype}, prioritized), 1 torch thread, "
          f"median of {args.rounds} rounds")  # fmt: skip
    print("| set-up | updates/s | / plain loop |\n|---|---|---|")
    for name, value in median.items():
        print(f"| {name} | {value:.1f} | {value / base:.2f}x |")
    ratio = median["Learner over gRPC"] / base
    print(f"goal: over gRPC >= 0.9x the plain loop: {'met' if ratio >= 0.9 else 'NOT met'} ({ratio:.2f}x)")


# -- actor --------------------------------------------------------------------------------------
def bare_env_rate(agents: int, seconds: float) -> float:
    env = make_vector_env("HalfCheetah-v5", agents, seed=0)
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        env.step(rng.uniform(-1, 1, (agents, env.spec.action.size)).astype(np.float32))
        steps += agents
    env.close()
    return steps / (time.perf_counter() - start)


def actor_rate(config: Config, agents: int, seconds: float, replay: ReplayClient | None) -> float:
    """Env steps/s of the actor loop acting with a SAC policy; chunks go to ``replay`` over gRPC
    (None: dropped, to see the policy's share)."""
    env = make_vector_env("HalfCheetah-v5", agents, seed=0)
    sac = SAC(env.spec, config.sac_config, config.nn_config, config.replay_config)
    actor_cfg = config.actor_config  # the sink as DistributedActor builds it (ds/actor/actor.py)
    sink = (lambda chunk: None) if replay is None else ReplaySink(
        replay, stopping=lambda: False, in_flight=actor_cfg.inserts_in_flight,
        max_chunks_per_insert=actor_cfg.chunks_per_insert or agents,
    )  # fmt: skip
    loop = ActorLoop(env, sac, sink, chunk_length=config.actor_config.chunk_length, seed=0)
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        steps += loop.step().env_steps
    env.close()
    return steps / (time.perf_counter() - start)


def bench_actor(args: argparse.Namespace) -> None:
    torch.set_num_threads(1)  # as actors run (ds/actor/role.py)
    config = half_cheetah_config()
    spec = make_vector_env("HalfCheetah-v5", 1, seed=0).spec
    sensors, action_size = spec.sensors, spec.action.size
    chunk = config.actor_config.chunk_length
    limit = message_limit_bytes(sensors, action_size, config.replay_config.batch_size, window=1, max_chunk_steps=chunk)
    names = ("bare env loop", "policy, no sink", "policy + gRPC sink")
    rates: dict[tuple[int, str], list[float]] = {(n, name): [] for n in args.agents for name in names}
    with replay_process(sensors, action_size, limit) as port:
        client = ReplayClient(f"127.0.0.1:{port}", sensors, action_size, max_message_bytes=limit)
        for round_ in range(args.rounds):
            for n in args.agents:
                rates[(n, names[0])].append(bare_env_rate(n, args.seconds))
                rates[(n, names[1])].append(actor_rate(config, n, args.seconds, None))
                rates[(n, names[2])].append(actor_rate(config, n, args.seconds, client))
                line = ", ".join(f"{name} {rates[(n, name)][-1]:,.0f}" for name in names)
                print(f"round {round_}, {n} envs: {line} env steps/s", flush=True)
        client.close()
    print(f"\nActor env steps/s, HalfCheetah-v5, {chunk}-step chunks, 1 torch thread, median of {args.rounds} rounds")
    print("| envs per actor | bare env loop | policy, no sink | policy + gRPC sink | / bare (goal >= 0.8x) "
          "| / no sink (the sink's cost) |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for n in args.agents:
        bare, policy, full = (statistics.median(rates[(n, name)]) for name in names)
        ratio = full / bare
        verdict = "met" if ratio >= 0.8 else "NOT met"
        print(f"| {n} | {bare:,.0f} | {policy:,.0f} | {full:,.0f} | {ratio:.2f}x {verdict} | {full / policy:.2f}x |")


# -- pendulum -----------------------------------------------------------------------------------
def first_at_threshold(evaluations: Path, threshold: float) -> int | None:
    """The env steps of the first evaluation row at or above ``threshold``, if any yet."""
    if not evaluations.exists():
        return None
    with evaluations.open() as f:
        for row in csv.DictReader(f):
            if float(row["return_mean"]) >= threshold:
                return int(row["env_steps"])
    return None


def time_to_threshold(command: list[str], evaluations: Path, threshold: float, limit_s: float) -> tuple[float, int]:
    """Launch ``command`` in its own process group, wait for ``evaluations`` to show ``threshold``,
    then interrupt it; returns (wall seconds from launch, env steps), or (inf, -1) on timeout."""
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    start = time.perf_counter()
    proc = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)  # fmt: skip
    result: tuple[float, int] = (float("inf"), -1)
    try:
        while time.perf_counter() - start < limit_s and proc.poll() is None:
            steps = first_at_threshold(evaluations, threshold)
            if steps is not None:
                result = (time.perf_counter() - start, steps)
                break
            time.sleep(0.2)
        else:
            steps = first_at_threshold(evaluations, threshold)  # finished between two polls
            if steps is not None:
                result = (time.perf_counter() - start, steps)
    finally:
        interrupt(proc)
    return result


def interrupt(proc: subprocess.Popen) -> None:
    """SIGINT to ``proc``'s process group if it still runs (it saves and stops), SIGKILL after 60 s."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def bench_pendulum(args: argparse.Namespace) -> None:
    overrides = ["--override", "eval.eval_per_step=500", "--override", f"base.max_step={args.max_steps}"]
    contenders = {"main.py": None, **{f"local, {n} actor{'s' if n > 1 else ''}": n for n in args.actors}}
    results: dict[str, list[tuple[float, int]]] = {name: [] for name in contenders}
    with tempfile.TemporaryDirectory() as root:
        for seed in args.seeds:
            for name, actors in contenders.items():
                run = f"{name.replace(' ', '_').replace(',', '')}_{seed}"
                seeded = [*overrides, "--override", f"sac.seed={seed}", "-n", run, "--model_root", root]
                if actors is None:
                    command = [sys.executable, "main.py", "gym/pendulum", "--no_progress", *seeded]
                else:
                    command = [sys.executable, "main_ds.py", "gym/pendulum", "local", "--actors", str(actors), *seeded]
                evaluations = Path(root) / "gym/pendulum" / run / "evaluations.csv"
                results[name].append(time_to_threshold(command, evaluations, -200.0, args.limit_s))
                wall, steps = results[name][-1]
                print(f"seed {seed}, {name}: -200 after {wall:.1f} s, {steps} env steps", flush=True)
    print(f"\nPendulum-v1 to -200 (10 deterministic episodes every 500 env steps), seeds {args.seeds}, 2 cores")
    print("| run | median wall s (from launch) | median env steps | each seed (s / steps) |\n|---|---|---|---|")
    for name, values in results.items():
        wall = statistics.median(v[0] for v in values)
        median_steps = statistics.median(v[1] for v in values)
        each = ", ".join(f"{w:.0f} / {s}" for w, s in values)
        print(f"| {name} | {wall:.1f} | {median_steps:.0f} | {each} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="which", required=True)
    p = sub.add_parser("learner")
    p.add_argument("--seconds", type=float, default=20.0)
    p.add_argument("--rounds", type=int, default=2)
    p = sub.add_parser("actor")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--agents", type=int, nargs="+", default=[1, 8, 32, 64])
    p = sub.add_parser("pendulum")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--actors", type=int, nargs="+", default=[1, 2, 4])
    p.add_argument("--max-steps", type=int, default=30000)
    p.add_argument("--limit-s", type=float, default=300.0)
    args = parser.parse_args()
    {"learner": bench_learner, "actor": bench_actor, "pendulum": bench_pendulum}[args.which](args)


if __name__ == "__main__":
    main()
