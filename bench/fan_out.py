"""One replay and one learner against 1, 4 and 16 actor processes of a cheap env: what the fan-out costs.

    python -m bench.fan_out [--actors 1 4 16] [--seconds 90] [--task gym/pendulum] [--out FILE]

For each actor count, ``main_ds.py TASK local --actors N`` runs for ``--seconds`` with 8 envs per actor
and a rate limiter that holds no one back (``samples_per_insert_tolerance`` huge: actors collect and
the learner trains as fast as each can), then is interrupted; its TensorBoard files are read back.
Rates are the slopes over the run's second half (all actors up, imports and warm-up done):

- env steps/s stored by the replay (``replay/inserted_steps``), in all and per actor;
- the learner's updates/s and publishes/s, one publish's cost (``learner/params/publish_ms``) and
  its share of the learner's time, and the bytes the PUB socket sends per second to all actors
  (bytes per publish x publishes/s x actors: ZeroMQ writes each subscriber its copy);
- the replay's sampled windows/s, and the actors' staleness (updates behind; the median over actors
  of each one's median and p95).

docs/architecture.md section 9 ("How far one replay and one learner go") turns these into how many
actors one replay and one learner serve. On this 2-core machine the processes share two cores, so
the rates past two processes show the machine's limit as much as ASAC's: read the per-actor rate
and the learner's rate together.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.distributed import interrupt
from bench.learner_rate import scalars
from bench.rows import append_row

ROOT = Path(__file__).resolve().parents[1]
FIELDS = ["task", "actors", "seconds", "env_steps_per_s", "env_steps_per_s_per_actor", "updates_per_s",
          "publishes_per_s", "publish_ms", "publish_share", "broadcast_mb_per_s", "sampled_windows_per_s",
          "staleness_median", "staleness_p95"]  # fmt: skip
# The rate limiter's tolerance counts sampled windows: at Pendulum's samples_per_insert (1,024) 1e9 held
# actors back after ~1M inserted steps (a minute of one actor); 1e15 is past anything a run here inserts.
OVERRIDES = ["base.n_agents=8", "base.max_step=-1", "replay.samples_per_insert_tolerance=1e15",
             "eval.eval_per_step=0", "sac.seed=0"]  # fmt: skip


def late_rate(points: list[tuple[float, float]]) -> float:
    """The slope of a counter over its second half in time, from the last point at or before the
    middle (a role that writes rarely, such as a starved learner, still gets one); nan with fewer than
    two points."""
    if len(points) < 2:
        return float("nan")
    middle = (points[0][0] + points[-1][0]) / 2
    start = max(i for i, p in enumerate(points) if p[0] <= middle)
    late = points[start:]
    if len(late) < 2 or late[-1][0] <= late[0][0]:
        return float("nan")
    return (late[-1][1] - late[0][1]) / (late[-1][0] - late[0][0])


def median_of(runs: list[dict[str, list[tuple[float, float]]]], tag: str) -> float:
    """The median over actors of each actor's median of ``tag`` (nan where none wrote it)."""
    values = [statistics.median(v for _, v in tags[tag]) for tags in runs if tags.get(tag)]
    return statistics.median(values) if values else float("nan")


def measure(task: str, actors: int, seconds: float, root: Path) -> dict[str, object]:
    run = f"fan_out_{actors}"
    command = [sys.executable, "main_ds.py", task, "local", "--actors", str(actors), "-n", run,
               "--model_root", str(root), *(a for o in OVERRIDES for a in ("--override", o))]  # fmt: skip
    proc = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)  # fmt: skip
    time.sleep(seconds)
    interrupt(proc)
    log = root / task / run / "log"
    learner, replay = scalars(log / "learner"), scalars(log / "replay")
    actor_tags = [scalars(folder) for folder in sorted(log.glob("actor_*"))]
    steps = late_rate(replay.get("replay/inserted_steps", []))
    publishes = late_rate(learner.get("learner/params/published", [])) + late_rate(
        learner.get("learner/params/republished", [])
    )
    sent = learner.get("learner/params/bytes_sent", [])
    sends = (learner.get("learner/params/published") or [(0, 0)])[-1][1] + (
        learner.get("learner/params/republished") or [(0, 0)]
    )[-1][1]
    per_publish = sent[-1][1] / sends if sent and sends else float("nan")
    publish_ms = statistics.median(v for _, v in learner.get("learner/params/publish_ms", [(0, float("nan"))]))
    shares = learner.get("time/publish_fraction", [])
    return {
        "task": task,
        "actors": actors,
        "seconds": seconds,
        "env_steps_per_s": round(steps),
        "env_steps_per_s_per_actor": round(steps / actors),
        "updates_per_s": round(late_rate(learner.get("learner/updates", [])), 1),
        "publishes_per_s": round(publishes, 1),
        "publish_ms": round(publish_ms, 2),
        "publish_share": round(statistics.median(v for _, v in shares), 4) if shares else float("nan"),
        "broadcast_mb_per_s": round(per_publish * publishes * actors / 1e6, 2),
        "sampled_windows_per_s": round(late_rate(replay.get("replay/sampled_windows", []))),
        "staleness_median": round(median_of(actor_tags, "actor/staleness_median"), 1),
        "staleness_p95": round(median_of(actor_tags, "actor/staleness_p95"), 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--actors", type=int, nargs="+", default=[1, 4, 16])
    parser.add_argument("--seconds", type=float, default=90.0)
    parser.add_argument("--task", default="gym/pendulum")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "fan_out" / "rows.csv")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as root:
        for n in args.actors:
            rows.append(measure(args.task, n, args.seconds, Path(root)))
            append_row(args.out, FIELDS, rows[-1])
            print(rows[-1], flush=True)
    print(
        f"\n{args.task}, 8 envs per actor, rate limiter open, {args.seconds:.0f} s per count, rates over the 2nd half"
    )
    print("| actors | env steps/s (per actor) | updates/s | publishes/s, ms each, share | broadcast MB/s | "
          "sampled windows/s | staleness median / p95 |\n|---|---|---|---|---|---|---|")  # fmt: skip
    for r in rows:
        steps = f"{r['env_steps_per_s']:,} ({r['env_steps_per_s_per_actor']:,})"
        print(f"| {r['actors']} | {steps} | {r['updates_per_s']} | "
              f"{r['publishes_per_s']}, {r['publish_ms']}, {r['publish_share']} | {r['broadcast_mb_per_s']} | "
              f"{r['sampled_windows_per_s']:,} | {r['staleness_median']} / {r['staleness_p95']} |")  # fmt: skip


if __name__ == "__main__":
    main()
