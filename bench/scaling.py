"""How a distributed HalfCheetah run scales with the number of actor processes.

    python -m bench.scaling [--actors 1 2 4 8 12] [-c SECTION] [--device cuda] [--limit-s 85] [--seed 0]
                            [--threshold 3000] [--out bench/results/scaling.csv]

For each actor count, ``main_ds.py mujoco/half_cheetah local --actors N`` runs with the task's
default config (one update per env step, 10,000 random steps first, evaluation of 10 episodes every
5,000 env steps) until its evaluation first reaches ``--threshold`` or ``--limit-s`` seconds pass.
Measured per count: wall seconds from launch to the threshold (or ``not reached``), env steps then,
the env steps/s and updates/s of the learning phase (the median of the rates the learner's progress
lines report once it updates, so the random-step warm-up and the launch are left out), and the env
steps/s of the warm-up (the actors alone: no update yet, so no rate limit). One row per
count is appended to ``--out`` as it lands.

One update per env step ties env steps/s to the learner's update rate: actors wait on the replay's
rate limiter once the learner is behind, so more actors raise env steps/s only until the learner is
the bottleneck. The random-step phase (no learner limit) shows what the actors alone can collect.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from bench.distributed import first_at_threshold, interrupt
from bench.rows import append_row

ROOT = Path(__file__).resolve().parents[1]
TASK = "mujoco/half_cheetah"
FIELDS = [
    "actors",
    "device",
    "seed",
    "threshold",
    "wall_s_to_threshold",
    "env_steps_at_threshold",
    "learning_env_steps_per_s",
    "learning_updates_per_s",
    "warmup_env_steps_per_s",
    "env_steps_at_last_eval",
    "best_return",
    "wall_s",
]


def eval_rows(evaluations: Path) -> list[dict[str, float]]:
    if not evaluations.exists():
        return []
    with evaluations.open() as f:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]


PROGRESS = re.compile(r"^\[learner\] .* steps \|\s*([\d.]+) steps/s \|\s*([\d,]+) updates\s+([\d.]+)/s")


def learning_rates(log: str) -> tuple[float, float]:
    """(env steps/s, updates/s) of the learning phase: the median of the rates the learner's progress
    lines report (over the last ~10 s each) once it updates, leaving out the first such line, which
    spans the random-step warm-up; nan where fewer than two lines were printed."""
    lines = [m.groups() for m in map(PROGRESS.match, log.splitlines()) if m and int(m[2].replace(",", "")) > 0]
    if len(lines) < 2:
        return float("nan"), float("nan")
    return statistics.median(float(g[0]) for g in lines[1:]), statistics.median(float(g[2]) for g in lines[1:])


def warmup_rate(rows: list[dict[str, float]]) -> float:
    """Env steps/s before the first update, from the learner's start: the last evaluation row
    without updates (the actors alone, unthrottled, as the random steps are collected)."""
    warmup = [r for r in rows if r["updates"] == 0 and r["wall_seconds"] > 0]
    return warmup[-1]["env_steps"] / warmup[-1]["wall_seconds"] if warmup else float("nan")


def _copy(stream, log) -> None:  # noqa: ANN001
    for raw in stream:
        log.write(raw.decode(errors="replace"))


def run_one(args: argparse.Namespace, actors: int, root: str, log_dir: Path) -> dict[str, object]:
    run = f"actors_{actors}"
    command = [
        sys.executable, "main_ds.py", TASK, "local", "--actors", str(actors), "--device", args.device,
        *(["-c", args.config] if args.config else []),
        "-n", run, "--model_root", root, "--override", f"sac.seed={args.seed}",
        "--override", f"base.max_step={args.max_steps}",
        *(a for o in args.override for a in ("--override", o)),
    ]  # fmt: skip
    evaluations = Path(root) / TASK / run / "evaluations.csv"
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "PYTHONUNBUFFERED": "1"}
    start = time.perf_counter()
    proc = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            start_new_session=True)  # fmt: skip
    with (log_dir / f"{run}.log").open("w") as log:
        reader = threading.Thread(target=_copy, args=(proc.stdout, log), daemon=True)
        reader.start()
        reached: tuple[float, int] | None = None
        while time.perf_counter() - start < args.limit_s and proc.poll() is None:
            steps = first_at_threshold(evaluations, args.threshold)
            if steps is not None:
                reached = (time.perf_counter() - start, steps)
                break
            time.sleep(0.5)
        wall = time.perf_counter() - start
        interrupt(proc)
        reader.join(timeout=5)
    rows = eval_rows(evaluations)
    steps_s, updates_s = learning_rates((log_dir / f"{run}.log").read_text())
    warm_s = warmup_rate(rows)
    return {
        "actors": actors,
        "device": args.device,
        "seed": args.seed,
        "threshold": args.threshold,
        "wall_s_to_threshold": f"{reached[0]:.1f}" if reached else f"not reached in {args.limit_s:.0f}",
        "env_steps_at_threshold": reached[1] if reached else "",
        "learning_env_steps_per_s": f"{steps_s:.1f}",
        "learning_updates_per_s": f"{updates_s:.1f}",
        "warmup_env_steps_per_s": f"{warm_s:.1f}",
        "env_steps_at_last_eval": int(rows[-1]["env_steps"]) if rows else 0,
        "best_return": f"{max((r['return_mean'] for r in rows), default=float('nan')):.1f}",
        "wall_s": f"{wall:.1f}",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--actors", type=int, nargs="+", default=[1, 2, 4, 8, 12])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("-c", "--config", default=None, help="the task's config section (e.g. throughput)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threshold", type=float, default=3000.0)
    parser.add_argument("--limit-s", type=float, default=85.0, help="wall seconds per actor count")
    parser.add_argument("--max-steps", type=int, default=200_000)
    parser.add_argument("--override", action="append", default=[], help="config override for every run (checks only)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "scaling.csv")
    parser.add_argument("--logs", type=Path, default=None, help="folder for each run's output (default: beside --out)")
    args = parser.parse_args()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    log_dir = args.logs or args.out.parent
    log_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as root:
        for actors in args.actors:
            row = run_one(args, actors, root, log_dir)
            append_row(args.out, FIELDS, row)
            print(" | ".join(f"{k} {v}" for k, v in row.items()), flush=True)


if __name__ == "__main__":
    main()
