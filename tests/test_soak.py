"""Soak (ISSUE 7): a replay, a learner and four actors at full speed for ten minutes, every role a
real ``main_ds.py`` process on loopback (tests/role_runs.py). Memory of every role stays flat once
warm, the replay is full and keeps turning over, and no queue the roles report grows without bound.

``ASAC_SOAK_S`` sets the duration in seconds (default 600; .ci/run sets 120 to stay in its time
budget); shorter runs are for development (the thirds below shrink with it, and so does what they can tell apart).
"""

from __future__ import annotations

import os
import signal
import statistics
import time
from pathlib import Path

import pytest

from ds.learner.feeds import BatchPrefetcher
from envs.make import make_vector_env
from tests.role_runs import RoleRun, flags, rss_mb, running, scalars

pytestmark = [pytest.mark.slow, pytest.mark.fault, pytest.mark.grpc]
DURATION_S = float(os.environ.get("ASAC_SOAK_S", "600"))
SAMPLE_EVERY_S = min(10.0, DURATION_S / 30)
ACTORS = 4
CAPACITY = 20_000  # rows: full within seconds at full speed, then every insert evicts
# Batches the learner's prefetcher may hold ahead with ds/learner/learner.py's depth (16 batches, 32 per
# call: 64, one call drawn or queued and one being handed out) and ds/learner/feeds.py's priority queue size.
PREFETCH_AHEAD, PRIORITY_DEPTH = BatchPrefetcher(None, batch_size=1, depth=16).max_ahead, 64  # type: ignore[arg-type]
# ReplaySink with the actor's defaults (actor_config.inserts_in_flight 1, chunks_per_insert = n_agents
# = 1): one insert of one chunk on its way and one waiting (ReplaySink.max_backlog).
SINK_BACKLOG = (1 + 1) * 1
# Growth allowed between the medians of the middle and the last third of the run, per role. Measured
# over the full ten minutes (two cores shared with other jobs): every role moved by at most +0.2 MB
# between those medians (from the first sample to the maximum: +3 MB replay, +4 MB learner, +1 MB
# actors, all early); over 120 s (.ci/run's length, beside two other CPU-bound jobs) +0.0 to +0.1 MB,
# warm-up over within the first third. 4 MB is 20 times that, and below what a leak of the traffic adds:
# a replay sabotaged to keep every insert request grew +10.4 MB between the medians of a 120-s run
# (40 s apart; measured, 2026-11-27) and +21.5 MB between those of a 5-minute run; a learner that kept
# one 256-window batch (~25 KB) per update, at ~60 updates/s, would grow ~300 MB in ten minutes.
GROWTH_MB = 4.0

SOAK = flags(
    "sac.seed=0",
    "base.max_step=-1",
    f"replay.capacity={CAPACITY}",
    "replay.min_size_to_sample=2000",
    "replay.samples_per_insert_tolerance=1e12",  # no rate limit: actors at full speed
    "eval.eval_per_step=500000",
    "eval.eval_episodes=2",
    "eval.eval_envs=2",
    "sac.save_model_per_minute=1",
    "sac.write_summary_per_step=100",
)


def thirds(samples: list[tuple[float, float]]) -> tuple[list[float], list[float]]:
    """The values of ``(elapsed_s, value)`` samples in the middle and the last third of the run."""
    middle = [v for t, v in samples if DURATION_S / 3 <= t < 2 * DURATION_S / 3]
    last = [v for t, v in samples if t >= 2 * DURATION_S / 3]
    return middle, last


def test_four_actors_at_full_speed_for_ten_minutes_memory_and_queues_stay_bounded(tmp_path: Path) -> None:
    run = RoleRun(tmp_path, "soak", SOAK)
    run.start("replay", "replay")
    run.start("learner", "learner")
    labels = ["replay", "learner"] + [f"actor-{k}" for k in range(ACTORS)]
    for label in labels[2:]:
        run.start(label, "actor")
    run.wait_for_line("learner", rf"registered as actor-\d-\w+ \(index \d\); {ACTORS} live", 180)
    spec = make_vector_env("Pendulum-v1", 1, seed=0).spec
    replay = run.replay_client(spec.sensors, spec.action.size)
    rss: dict[str, list[tuple[float, float]]] = {label: [] for label in labels}
    rows: list[tuple[float, int, int]] = []  # (elapsed, rows in use, steps inserted so far)
    started = time.monotonic()
    try:
        while (elapsed := time.monotonic() - started) < DURATION_S:
            for label in labels:
                value = rss_mb(run.procs[label].pid)
                assert value is not None and running(run.procs[label].pid), f"{label} is gone\n{run.logs()}"
                rss[label].append((elapsed, value))
            info = replay.info()
            rows.append((elapsed, int(info["stored_rows"]), int(info["inserted_steps"])))
            time.sleep(SAMPLE_EVERY_S)
        for label in labels[2:]:  # the actors first, so that the replay has answered every insert
            run.signal(label, signal.SIGINT)
        for label in labels[2:]:
            assert run.procs[label].wait(timeout=60) == 130, run.text(label)[-3000:]
        final = replay.info()
    finally:
        replay.close()
        codes = run.stop_all()
    assert codes == {label: 130 for label in labels}, (codes, run.logs())

    report = []
    for label, samples in rss.items():
        middle, last = thirds(samples)
        growth = statistics.median(last) - statistics.median(middle)
        report.append(
            f"{label}: first {samples[0][1]:.0f} MB, middle third median {statistics.median(middle):.1f}, last third "
            f"median {statistics.median(last):.1f} (+{growth:.1f}), max {max(v for _, v in samples):.0f}"
        )
    print("\nRSS over", f"{DURATION_S:.0f} s:\n" + "\n".join(report))
    for samples in rss.values():
        middle, last = thirds(samples)
        assert statistics.median(last) - statistics.median(middle) < GROWTH_MB, "\n".join(report)

    # The replay's ring (capacity rows: a chunk's steps and its bootstrap row) filled early and turned
    # over to the end: full, evicting, inserts going on.
    full_at = next((t for t, used, _ in rows if used == CAPACITY), None)
    assert full_at is not None and full_at < DURATION_S / 3, rows[:10]
    assert final["stored_rows"] == CAPACITY and final["evicted_steps"] > final["inserted_steps"] - CAPACITY
    middle, last = thirds([(t, inserted) for t, _, inserted in rows])
    assert last[-1] > last[0]  # inserting to the end

    # Every queue a role reports stays within its bound for the whole run.
    for tag, bound in (("learner/prefetch_queue", PREFETCH_AHEAD), ("learner/priority_queue", PRIORITY_DEPTH)):
        written = [v for _, _, v in scalars(run.run / "log/learner", tag)]
        assert written and max(written) <= bound, (tag, max(written))
    updates = [v for _, _, v in scalars(run.run / "log/learner", "learner/updates")]
    assert updates[-1] > updates[len(updates) // 2] > 0  # still training at the end
    for k in range(ACTORS):
        backlog = [v for _, _, v in scalars(run.run / f"log/actor_{k}", "actor/insert_backlog")]
        assert backlog and max(backlog) <= SINK_BACKLOG, (k, max(backlog))
        assert scalars(run.run / f"log/actor_{k}", "actor/unsent_steps")[-1][2] == 0
    print(f"replay full after {full_at:.0f} s; {final['inserted_steps']} steps inserted, {updates[-1]:.0f} updates")
