"""A run across hosts on a perfect wire against the same run on links with latency, loss and a bandwidth
cap: what the actor keeps of its env steps/s, how stale its weights get, what the learner keeps of its
updates/s (issue: hosts that are really apart).

    python -m bench.network_links [--seconds 60] [--rounds 1] [--task gym/pendulum] [--out FILE]

Replay, learner and actor each run in a Linux network namespace of their own (tests/network.py; root,
``ip`` and ``nft`` needed). Conditions, one run each per round, in turn so that the machine's noise
hits all alike:

- ``perfect``: the bare veth bridge;
- ``50ms``: the actor reaches replay and learner, and the learner's weights stream (ZeroMQ), through
  relays that hold every byte 25 ms each way (tests/relay.py; the kernel here has no netem);
- ``50ms+1%``: also 1% of the actor's TCP packets dropped at random, each way (nftables);
- ``50ms+1%+20mbit``: also the actor's sending side capped at 20 Mbit/s (``tc ... tbf``).

Each run is ``main_ds.py TASK replay|learner|actor`` with 8 envs on the actor and a rate limiter that
holds no one back, for ``--seconds`` after the actor registered. Rates are over its second half:
env steps/s the replay stored (bench/fan_out.py's ``late_rate``), the learner's updates/s (the median
of what it wrote), the actor's staleness (updates behind the learner: median and p95 of what it
wrote). Every run is checked to store exactly what the actor collected. Goal: env steps/s at 50 ms
>= 0.8x the perfect wire's.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import signal
import statistics
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from bench.fan_out import late_rate, median_of
from bench.learner_rate import scalars
from bench.rows import append_row
from tests.network import Host, capped, hosts, lossy, nft_available, slow_link, start_role

ROOT = Path(__file__).resolve().parents[1]
FIELDS = ["task", "condition", "round", "seconds", "env_steps_per_s", "ratio_to_perfect", "updates_per_s",
          "staleness_median", "staleness_p95", "collected", "stored"]  # fmt: skip
CONDITIONS = ("perfect", "50ms", "50ms+1%", "50ms+1%+20mbit")
OVERRIDES = ["base.n_agents=8", "base.max_step=-1", "replay.samples_per_insert_tolerance=1e15",
             "eval.eval_per_step=0", "sac.seed=0"]  # fmt: skip
PARAMS_PORT = 61003  # net_config.params_port's default: where the learner publishes its weights
ENV = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1", "GRPC_VERBOSITY": "ERROR"}


@contextlib.contextmanager
def actor_links(condition: str, net: dict[str, Host], folder: Path) -> Iterator[list[str]]:
    """The actor's flags to reach replay and learner under ``condition``, with its relays, loss and cap on."""
    if condition == "perfect":
        yield ["--replay_host", net["replay"].address, "--learner_host", net["learner"].address]
        return
    with contextlib.ExitStack() as stack:
        replay = stack.enter_context(slow_link(net["actor"], f"{net['replay'].address}:61002", 25.0,
                                               folder / "relay_replay.log"))  # fmt: skip
        learner = stack.enter_context(slow_link(net["actor"], f"{net['learner'].address}:61001", 25.0,
                                                folder / "relay_learner.log"))  # fmt: skip
        # The weights stream: the actor connects to the learner's host as it knows it (here the relays'
        # 127.0.0.1) at the port the learner announces (61003), so a relay listens there too.
        stack.enter_context(slow_link(net["actor"], f"{net['learner'].address}:{PARAMS_PORT}", 25.0,
                                      folder / "relay_params.log", port=PARAMS_PORT))  # fmt: skip
        if "1%" in condition:
            stack.enter_context(lossy(net["actor"], 1))
        if "20mbit" in condition:
            stack.enter_context(capped(net["actor"], 20))
        yield ["--replay_host", "127.0.0.1", "--replay_port", replay.rsplit(":", 1)[1],
               "--learner_host", "127.0.0.1", "--learner_port", learner.rsplit(":", 1)[1]]  # fmt: skip


def late_median(points: list[tuple[float, float]]) -> float:
    """The median of a rate the role writes itself, over its second half in time (nan without points)."""
    if not points:
        return float("nan")
    middle = (points[0][0] + points[-1][0]) / 2
    return round(statistics.median(v for t, v in points if t >= middle), 1)


def measure(task: str, condition: str, seconds: float, folder: Path) -> dict[str, object]:
    roles = ("replay", "learner", "actor")
    logs = {name: folder / f"{name}.log" for name in roles}
    common = ["-n", "links", "--no_progress", *(a for o in OVERRIDES for a in ("--override", o))]
    with hosts(list(roles)) as net:
        peers = ["--replay_host", net["replay"].address, "--learner_host", net["learner"].address]
        procs = {name: start_role(net[name], folder / name, name, task, [*common, *peers], ENV, logs[name])
                 for name in ("replay", "learner")}  # fmt: skip
        try:
            with actor_links(condition, net, folder) as near:
                procs["actor"] = start_role(net["actor"], folder / "actor", "actor", task, [*common, *near], ENV,
                                            logs["actor"])  # fmt: skip
                deadline = time.monotonic() + 180
                while not re.search(r"actor \S+: index 0", logs["actor"].read_text()):
                    if procs["actor"].poll() is not None or time.monotonic() > deadline:
                        raise RuntimeError(
                            f"{condition}: the actor did not register:\n{logs['actor'].read_text()[-2000:]}"
                        )
                    time.sleep(0.5)
                time.sleep(seconds)
                for name in ("actor", "learner", "replay"):  # as an operator stops a run: the actor first
                    procs[name].send_signal(signal.SIGINT)
                    procs[name].wait(timeout=120)
        finally:
            for proc in procs.values():
                if proc.poll() is None:
                    proc.kill()
    run = Path(task) / "links" / "log"
    learner, replay = scalars(folder / "learner" / run / "learner"), scalars(folder / "replay" / run / "replay")
    actor = [scalars(f) for f in sorted((folder / "actor" / run).glob("actor_*"))]
    text = {name: log.read_text() for name, log in logs.items()}
    collected = re.findall(r"actor \d+ stopped after (\d+) env steps", text["actor"])
    stored = re.findall(r": (\d+) env steps inserted over the run", text["replay"])
    return {
        "task": task,
        "condition": condition,
        "seconds": seconds,
        "env_steps_per_s": round(late_rate(replay.get("replay/inserted_steps", []))),
        "updates_per_s": late_median(learner.get("time/updates_per_second", [])),
        "staleness_median": round(median_of(actor, "actor/staleness_median"), 1),
        "staleness_p95": round(median_of(actor, "actor/staleness_p95"), 1),
        "collected": collected[0] if collected else "",
        "stored": stored[0] if stored else "",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--task", default="gym/pendulum")
    parser.add_argument("--conditions", nargs="+", default=list(CONDITIONS), choices=CONDITIONS)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "network_links" / "rows.csv")
    args = parser.parse_args()
    missing = nft_available()
    if missing:
        raise SystemExit(f"bench.network_links: {missing}")
    for round_ in range(args.rounds):
        perfect = float("nan")
        for condition in args.conditions:
            with tempfile.TemporaryDirectory() as folder:
                row = measure(args.task, condition, args.seconds, Path(folder))
            if condition == "perfect":
                perfect = float(row["env_steps_per_s"])  # type: ignore[arg-type]
            row["round"] = round_
            row["ratio_to_perfect"] = round(float(row["env_steps_per_s"]) / perfect, 2)  # type: ignore[arg-type]
            append_row(args.out, FIELDS, row)
            print(row, flush=True)


if __name__ == "__main__":
    main()
