"""Learning per env step in both modes: ``main.py TASK`` against ``main_ds.py TASK local --actors A``.

    python -m bench.modes TASK --threshold X [--seeds 0 1 2 3 4] [--steps N] [--every K] [--actors 2]
        [--modes main local] [--override KEY=VALUE ...] [--timeout S]
    python -m bench.modes --report [--results CSV]

Each run is the user's command, a real subprocess in a temporary working directory (its own process
group, ``OMP_NUM_THREADS=1``, ``OMP_WAIT_POLICY=PASSIVE``), with the task's default config and only
the seed, the budget and the evaluation cadence overridden::

    python main.py TASK -n bench --no_progress --override sac.seed=S \\
        --override base_config.max_step=N --override eval_config.eval_per_step=K
    python main_ds.py TASK local --actors A -n bench --no_progress --override sac.seed=S \\
        --override base_config.max_step=N --override eval_config.eval_per_step=K

For every seed, main then local, it appends one row to bench/results/modes.csv as the run ends, read
from the run folder ``models/TASK/bench``: the first evaluation (``evaluations.csv``) that reached
``--threshold`` (env steps and wall seconds, or none), the best and last evaluation's mean return,
updates per env step (the last evaluation's updates / env_steps, which counts the steps before
``min_size_to_sample`` too, and the late rate between the evaluation at half the run and the last;
the config asks for samples_per_insert / batch_size in both modes), the age of sampled data (median over the run of the
TensorBoard scalars ``replay/sample_age_steps_median`` and ``..._p95``: ``log/`` for main.py,
``log/learner/`` distributed), the last evaluation's env steps (a distributed run may pass
``max_step``), the exit code and the wall time. A run past ``--timeout`` is stopped (SIGINT to its
process group, then SIGKILL) and recorded with its exit code; its output's last lines are printed.

``--report`` prints, per task and threshold, one row per seed (the latest run of each mode) and then
per mode the successes, the median and worst env steps to the threshold (a run that never reached
it counts as the budget) and the ratio of the medians, local / main (the issue asks for <= 1.25).
The numbers in bench/results/modes.csv come from::

    python -m bench.modes gym/pendulum --threshold -200 --seeds 0 1 2 3 4 --steps 6000 --every 250
    python -m bench.modes gym/cartpole --threshold 475 --seeds 0 1 2 3 4 --steps 30000 --every 1000
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable
from pathlib import Path

from bench.rows import append_row

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "modes.csv"
FIELDS = ["task", "mode", "actors", "seed", "steps", "threshold", "reached_at", "reached_wall_s", "best", "last",
          "updates_per_step", "late_updates_per_step", "age_median", "age_p95", "wall_s", "commit", "final_steps",
          "rc"]  # fmt: skip
AGE_TAGS = ("replay/sample_age_steps_median", "replay/sample_age_steps_p95")
RUN_NAME = "bench"


def command(task: str, mode: str, seed: int, steps: int, every: int, actors: int, overrides: list[str]) -> list[str]:
    """The user's command for one run of ``mode`` (main or local)."""
    sets = [f"sac.seed={seed}", f"base_config.max_step={steps}", f"eval_config.eval_per_step={every}", *overrides]
    flags = ["-n", RUN_NAME, "--no_progress", *[a for s in sets for a in ("--override", s)]]
    if mode == "main":
        return [sys.executable, str(ROOT / "main.py"), task, *flags]
    if mode == "local":
        return [sys.executable, str(ROOT / "main_ds.py"), task, "local", "--actors", str(actors), *flags]
    raise ValueError(f"unknown mode {mode!r}")


def first_reached(rows: list[dict[str, float]], threshold: float) -> dict[str, float] | None:
    """The first evaluation whose mean return reached ``threshold``."""
    return next((r for r in rows if r["return_mean"] >= threshold), None)


def median_scalar(folder: Path, tag: str) -> float | None:
    """Median over the run of a TensorBoard scalar in the event files directly under ``folder``."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    values = []
    for events in sorted(folder.glob("events.out.tfevents.*")):
        acc = EventAccumulator(str(events), size_guidance={"scalars": 0})
        acc.Reload()
        if tag in acc.Tags()["scalars"]:
            values += [e.value for e in acc.Scalars(tag)]
    return statistics.median(values) if values else None


def summarize(evaluations: list[dict[str, float]], threshold: float) -> dict[str, object]:
    """The row's fields read from ``evaluations.csv``'s rows."""
    if not evaluations:
        return {"reached_at": None, "reached_wall_s": None, "best": None, "last": None, "updates_per_step": None,
                "late_updates_per_step": None, "final_steps": None}  # fmt: skip
    hit, last = first_reached(evaluations, threshold), evaluations[-1]
    mid = next(r for r in evaluations if r["env_steps"] >= last["env_steps"] / 2)
    late = last["env_steps"] - mid["env_steps"]
    return {
        "reached_at": int(hit["env_steps"]) if hit else None,
        "reached_wall_s": round(hit["wall_seconds"]) if hit else None,
        "best": round(max(r["return_mean"] for r in evaluations), 1),
        "last": round(last["return_mean"], 1),
        "updates_per_step": round(last["updates"] / last["env_steps"], 2) if last["env_steps"] else None,
        "late_updates_per_step": round((last["updates"] - mid["updates"]) / late, 2) if late else None,
        "final_steps": int(last["env_steps"]),
    }


def run(task: str, mode: str, seed: int, steps: int, every: int, threshold: float, actors: int,
        overrides: list[str], timeout_s: float, commit: str) -> dict[str, object]:  # fmt: skip
    from algorithm.run.evaluation import read_evaluations

    env = {**os.environ, "OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE", "MUJOCO_GL": "egl"}
    cmd = command(task, mode, seed, steps, every, actors, overrides)
    print("$", " ".join(cmd[1:]), flush=True)
    with tempfile.TemporaryDirectory(prefix="bench_modes_") as tmp:
        log = Path(tmp) / "output.log"
        start = time.perf_counter()
        with log.open("wb") as out:
            proc = subprocess.Popen(cmd, cwd=tmp, env=env, stdout=out, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, process_group=0)  # fmt: skip
            try:
                rc = proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                rc = stop(proc)
        wall = time.perf_counter() - start
        folder = Path(tmp) / "models" / task / RUN_NAME
        evaluations = read_evaluations(folder / "evaluations.csv") if (folder / "evaluations.csv").exists() else []
        logs = folder / "log" / ("learner" if mode == "local" else "")
        ages = [median_scalar(logs, tag) for tag in AGE_TAGS]
        if rc != 0 or not evaluations:
            tail = log.read_text(errors="replace").splitlines()[-40:]
            print(f"--- {mode} seed {seed}: exit {rc}, {len(evaluations)} evaluations; last lines:", *tail, "---",
                  sep="\n", flush=True)  # fmt: skip
    return {
        "task": task, "mode": mode, "actors": actors if mode == "local" else 0, "seed": seed, "steps": steps,
        "threshold": threshold, **summarize(evaluations, threshold),
        "age_median": None if ages[0] is None else round(ages[0]),
        "age_p95": None if ages[1] is None else round(ages[1]),
        "wall_s": round(wall), "commit": commit, "rc": rc,
    }  # fmt: skip


def stop(proc: subprocess.Popen[bytes]) -> int:
    """Stop a run past its time: SIGINT to its process group (the orderly stop), SIGKILL after 60 s."""
    print(f"timeout: stopping process group {proc.pid}", flush=True)
    for sig, grace in ((signal.SIGINT, 60), (signal.SIGKILL, 30)):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        try:
            return proc.wait(grace)
        except subprocess.TimeoutExpired:
            continue
    return proc.wait()


def append(row: dict[str, object], path: Path = RESULTS) -> None:
    append_row(path, FIELDS, row)


# --- report ---------------------------------------------------------------------------------------


def steps_to(row: dict[str, str]) -> int:
    """Env steps to the threshold; the budget for a run that never reached it."""
    return int(row["reached_at"]) if row["reached_at"] else int(row["steps"])


def latest(rows: Iterable[dict[str, str]]) -> dict[tuple[str, str, str], dict[str, str]]:
    """The latest row of each (task and threshold, mode, seed)."""
    out = {}
    for r in rows:
        out[(f"{r['task']} (threshold {r['threshold']}, budget {r['steps']})", r["mode"], r["seed"])] = r
    return out


def cell(row: dict[str, str] | None) -> str:
    if row is None:
        return "| - | - | - | -"
    reached = f"{row['reached_at']} ({row['reached_wall_s']} s)"
    if not row["reached_at"]:
        reached = f"not reached (best {row['best']})"
    if row.get("rc") not in ("0", "", None):
        reached += f" exit {row['rc']}"
    ages = f"{row['age_median'] or '-'} / {row['age_p95'] or '-'}"
    rate = f"{row['updates_per_step'] or '-'} / {row.get('late_updates_per_step') or '-'}"
    return f"| {reached} | {row['wall_s']} | {ages} | {rate}"


def summary_lines(rows: list[dict[str, str]], modes: list[str]) -> list[str]:
    """Per mode: successes, median and worst steps to the threshold; then the ratio of the medians."""
    lines = ["| mode | reached | median steps | worst steps | median wall s to threshold |", "|---|---|---|---|---|"]
    medians = {}
    for mode in modes:
        runs = [r for r in rows if r["mode"] == mode]
        if not runs:
            continue
        steps = [steps_to(r) for r in runs]
        medians[mode] = statistics.median(steps)
        walls = [float(r["reached_wall_s"]) for r in runs if r["reached_wall_s"]]
        wall = f"{statistics.median(walls):.0f}" if walls else "-"
        label = mode if mode == "main" else f"{mode} --actors {runs[0]['actors']}"
        ok = sum(1 for r in runs if r["reached_at"])
        lines.append(f"| {label} | {ok}/{len(runs)} | {medians[mode]:.0f} | {max(steps)} | {wall} |")
    if "main" in medians and "local" in medians:
        lines.append("")
        lines.append(f"local / main median steps to threshold: {medians['local'] / medians['main']:.2f} (goal <= 1.25)")
    return lines


def report(path: Path = RESULTS) -> str:
    rows = list(csv.DictReader(path.open())) if path.exists() else []
    table = latest(rows)
    out = []
    for task in dict.fromkeys(k[0] for k in table):
        modes = list(dict.fromkeys(k[1] for k in table if k[0] == task))
        seeds = sorted({k[2] for k in table if k[0] == task}, key=int)
        out += [f"### {task}", ""]
        columns = ["steps to threshold (wall s)", "run wall s", "age median / p95", "updates/step (all / late)"]
        head = "| seed " + "".join(f"| {m} {c} " for m in modes for c in columns)
        out += [head + "|", "|---" * (1 + 4 * len(modes)) + "|"]
        for seed in seeds:
            out.append(f"| {seed} " + "".join(cell(table.get((task, m, seed))) + " " for m in modes) + "|")
        out += [""] + summary_lines([r for k, r in table.items() if k[0] == task], modes) + [""]
    return "\n".join(out)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("task", nargs="?")
    p.add_argument("--threshold", type=float)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    p.add_argument("--steps", type=int, default=10000)
    p.add_argument("--every", type=int, default=500)
    p.add_argument("--actors", type=int, default=2)
    p.add_argument("--modes", nargs="+", choices=["main", "local"], default=["main", "local"])
    p.add_argument("--override", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--timeout", type=float, default=1800, help="seconds per run before it is stopped")
    p.add_argument("--report", action="store_true")
    p.add_argument(
        "--results",
        type=Path,
        default=RESULTS,
        help="the CSV to append rows to and report from (a variant's runs in a file of their own)",
    )
    args = p.parse_args()
    if args.report or args.task is None:
        print(report(args.results))
        return
    if args.threshold is None:
        p.error("--threshold is required with a task")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout
    for seed in args.seeds:
        for mode in args.modes:
            row = run(args.task, mode, seed, args.steps, args.every, args.threshold, args.actors, args.override,
                      args.timeout, commit.strip())  # fmt: skip
            append(row, args.results)
            print(row, flush=True)


if __name__ == "__main__":
    main()
