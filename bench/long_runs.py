"""Runs longer than a working session, compared across config sections on several seeds.

    python -m bench.long_runs [TASK] [--sections default feedforward] [--seeds 0 1 2] [--steps 100000]
        [--every 5000] [--runs DIR] [--override SECTION.KEY=VALUE ...]
    python -m bench.long_runs [TASK] --report [--sections ...] [--seeds ...] [--steps ...]

Trains, one after the other, every (section, seed) run of ``envs/TASK`` as the user would: the
``main.py`` command with a fixed run name under ``--runs`` (default ``$ASAC_BENCH_RUNS``, else
``~/asac_long_runs``). Ctrl-C (or SIGTERM) reaches the run in progress, which saves its checkpoint
and replay and exits; the same command later resumes it where it stopped, and a run already at its
budget is skipped (main.py says so and exits). SIGTERM to this driver (a background run's stop)
is passed on to the run as one SIGINT, the same save. After each run its evaluations.csv is copied to
bench/results/long_runs/. The first use: issue 15's "recurrent beats feedforward on
mujoco/half_cheetah_novel at 100k steps on the mean of 3 seeds" (hours per run on two cores).

``--report`` prints, per section, each seed's evaluation at ``--steps`` (or its latest, marked with
the step it is at, and the run's training wall time so far) and the mean over the seeds that
reached ``--steps``.
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import statistics
import sys
from pathlib import Path

from bench.children import Children, default_runs

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(os.environ.get("ASAC_LONG_RUNS_RESULTS", ROOT / "bench" / "results" / "long_runs"))


def run_name(section: str, seed: int, steps: int) -> str:
    return f"long_{section}_s{seed}_{steps // 1000}k"


def result_file(task: str, section: str, seed: int, steps: int) -> Path:
    return RESULTS / f"{task.replace('/', '_')}_{run_name(section, seed, steps)}.csv"


def command(task: str, section: str, seed: int, steps: int, every: int, runs: Path, overrides: list[str]) -> list[str]:
    args = [sys.executable, str(ROOT / "main.py"), task, "-n", run_name(section, seed, steps),
            "--model_root", str(runs), "--no_progress", "--logger_in_file", "--override", f"sac.seed={seed}",
            "--override", f"base.max_step={steps}", "--override", f"eval.eval_per_step={every}",
            *(x for o in overrides for x in ("--override", o))]  # fmt: skip
    return args if section == "default" else [*args, "-c", section]


def train(
    task: str, sections: list[str], seeds: list[int], steps: int, every: int, runs: Path, overrides: list[str]
) -> int:
    RESULTS.mkdir(parents=True, exist_ok=True)
    children = Children()
    for section in sections:
        for seed in seeds:
            args = command(task, section, seed, steps, every, runs, overrides)
            print(" ".join(args[1:]), flush=True)
            code = children.run(args, cwd=ROOT)
            evaluations = runs / task / run_name(section, seed, steps) / "evaluations.csv"
            if evaluations.is_file():
                shutil.copyfile(evaluations, result_file(task, section, seed, steps))
            if code != 0 or children.stopping:
                print(f"{task} {section} seed {seed}: stopped (exit {code}); the same command resumes it", flush=True)
                return code
    return 0


def latest(path: Path, steps: int) -> tuple[int, float, float] | None:
    """(env steps, mean return, wall seconds) of the last evaluation at or before ``steps``, or None."""
    if not path.is_file():
        return None
    with path.open(newline="") as f:
        rows = [r for r in csv.DictReader(f) if int(r["env_steps"]) <= steps]
    if not rows:
        return None
    return int(rows[-1]["env_steps"]), float(rows[-1]["return_mean"]), float(rows[-1]["wall_seconds"])


def report(task: str, sections: list[str], seeds: list[int], steps: int) -> None:
    print(f"{task}, evaluation at {steps} env steps (10 deterministic episodes); {RESULTS}/")
    for section in sections:
        cells, done = [], []
        for seed in seeds:
            found = latest(result_file(task, section, seed, steps), steps)
            if found is None:
                cells.append(f"seed {seed}: -")
                continue
            at, value, wall = found
            where = "" if at == steps else f" at {at}"
            cells.append(f"seed {seed}: {value:.1f}{where} ({wall / 3600:.1f} h)")
            if at == steps:
                done.append(value)
        mean = f"mean {statistics.mean(done):.1f} over {len(done)}" if done else "no seed finished"
        print(f"  {section:<12} " + " | ".join(cells) + f" | {mean}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("task", nargs="?", default="mujoco/half_cheetah_novel")
    p.add_argument("--sections", nargs="+", default=["default", "feedforward"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--steps", type=int, default=100_000)
    p.add_argument("--every", type=int, default=5_000)
    p.add_argument("--runs", type=Path, default=default_runs(), help="where the run folders go")
    p.add_argument("--override", action="append", default=[], help="passed on to main.py (every run)")
    p.add_argument("--report", action="store_true", help="print the results so far")
    a = p.parse_args()
    if a.report:
        report(a.task, a.sections, a.seeds, a.steps)
        return 0
    return train(a.task, a.sections, a.seeds, a.steps, a.every, a.runs, a.override)


if __name__ == "__main__":
    sys.exit(main())
