"""The MuJoCo comparison with SB3 SAC (issue 15, item 3): one run per (task, system, seed), each with
its learning curve, and the suite of them; the command line is bench/vs_sb3.py's ``mujoco`` and
``suite`` (its docstring).

Each run writes its curve to OUT/<task>_<asac|sb3>_seed<k>.csv as evaluations come and, when it
ends, a row to OUT/summary.csv (return, wall seconds, of which evaluating, overrides, code version);
runs already there are skipped. ASAC's runs train in a folder of their own under ``--runs``
(``$ASAC_BENCH_RUNS``, else ``~/asac_long_runs``): SIGINT or SIGTERM saves the run in progress (its
checkpoint and replay) and the same command resumes it; an SB3 run stopped so is started again.
"""

from __future__ import annotations

import argparse
import csv
import functools
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from algorithm.run.folder import RunDir
from algorithm.run.signals import stop_on_signals
from bench.children import Children
from bench.systems import EVAL_EPISODES, MUJOCO_TASKS, ROOT, RunResult, RunStopped, run_ours, run_sb3

RESULTS = ROOT / "bench" / "results"
SUITE_TASKS = ("hopper", "walker2d", "ant", "half_cheetah")  # the suite's order; HalfCheetah had 5 seeds already
SUITE_OVERRIDES = ("sac.compute_dtype=bfloat16",)  # as HalfCheetah's reported runs (and `auto` on this CPU)
SUMMARY_FIELDS = ("task", "system", "seed", "steps", "return", "wall_s", "eval_s", "overrides", "code", "finished")
CURVE_FIELDS = ("env_steps", "return_mean", "return_std", "wall_seconds")
LAST = 3  # the report also averages each run's last LAST evaluations (90k-100k of 100k)
# ... and all of a run's evaluations past the tasks' 10,000 uniformly random steps (those before score the
# untrained policy): the area under the learning curve, how fast a system learns as well as where it ends
LEARNING_FROM = 10_000
INTERVAL = 0.9  # the report's interval of the ratio of means over resampled seeds


def run_folder(runs: Path, task: str, seed: int, steps: int, overrides: str) -> Path:
    """Where ASAC's run of ``task`` and ``seed`` trains (the overrides are part of its name)."""
    label = re.sub(r"[^A-Za-z0-9.=_-]+", "_", overrides)
    return runs / "mujoco_suite" / task / (f"asac_s{seed}_{steps // 1000}k" + (f"_{label}" if label else ""))


def sb3_model_path(runs: Path, task: str, seed: int, steps: int) -> Path:
    """Where SB3's trained model of ``task`` and ``seed`` is saved, beside ASAC's run folders."""
    return runs / "mujoco_suite" / task / f"sb3_s{seed}_{steps // 1000}k.zip"


def code_version() -> str:
    """The commit the run's code is at (ASAC_BENCH_CODE when set, e.g. by a run from an exported
    snapshot), with +dirty when algorithm/, envs/ or bench/ differ from it."""
    if os.environ.get("ASAC_BENCH_CODE"):
        return os.environ["ASAC_BENCH_CODE"]
    try:
        head = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(ROOT), "status", "--porcelain", "--", "algorithm", "envs", "bench"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


def curve_path(out: Path, task: str, system: str, seed: int) -> Path:
    return out / f"{task}_{system}_seed{seed}.csv"


def write_curve(path: Path, result: RunResult) -> None:
    tmp = path.with_suffix(".csv.tmp")
    with tmp.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CURVE_FIELDS)
        w.writerows([s, f"{m:.1f}", f"{sd:.1f}", f"{wall:.0f}"] for s, m, sd, wall in result.curve)
    tmp.replace(path)


def read_summary(out: Path) -> list[dict[str, str]]:
    path = out / "summary.csv"
    return list(csv.DictReader(path.open(newline=""))) if path.exists() else []


def finished(out: Path, task: str, system: str, seed: int, steps: int, overrides: str) -> bool:
    return any(
        (r["task"], r["system"], r["seed"], r["steps"], r["overrides"])
        == (task, system, str(seed), str(steps), overrides)
        for r in read_summary(out)
    )


def asac_run(
    args: argparse.Namespace, seed: int, on_eval: Callable[[RunResult], None], stop: threading.Event
) -> RunResult:
    """ASAC's run of ``args.task`` and ``seed`` in its folder under ``args.runs``: resumed from what
    a stopped run saved there, from scratch with ``--force``."""
    folder = run_folder(args.runs, args.task, seed, args.steps, " ".join(args.override))
    if args.force and folder.exists():
        shutil.rmtree(folder)
    result = run_ours(args.task, seed, args.steps, args.override, args.every, on_eval, run_dir=folder, stop=stop)
    RunDir(folder).replay.unlink(missing_ok=True)  # an interrupted part's snapshot: done with
    return result


def mujoco(args: argparse.Namespace) -> None:
    """Runs of one task (``--which`` ours/sb3/both, seed by seed, ours first); see the module docstring."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.report:
        report(out, args.task, args.seeds, args.also)
        return
    torch.set_num_threads(args.threads)
    label = " ".join(args.override)
    stop = stop_on_signals("saving the run: the same command resumes it")
    for seed in args.seeds:
        for system in {"both": ["asac", "sb3"], "ours": ["asac"], "sb3": ["sb3"]}[args.which]:
            overrides = label if system == "asac" else ""
            if finished(out, args.task, system, seed, args.steps, overrides) and not args.force:
                print(f"{args.task} {system} seed {seed}: in {out / 'summary.csv'} already, skipped", flush=True)
                continue
            path = curve_path(out, args.task, system, seed)
            code, start = code_version(), time.perf_counter()
            try:
                if system == "asac":
                    result = asac_run(args, seed, functools.partial(write_curve, path), stop)
                else:
                    saved = sb3_model_path(args.runs, args.task, seed, args.steps)
                    result = run_sb3(args.task, seed, args.steps, args.every, functools.partial(write_curve, path),
                                     stop=stop, save_to=saved)  # fmt: skip
            except RunStopped as e:
                then = "saved; the same command resumes it" if system == "asac" else "not resumable"
                print(f"{args.task} {system} seed {seed}: stopped at {e.env_steps} env steps, {then}", flush=True)
                sys.exit(130)
            wall = time.perf_counter() - start + result.earlier_wall_s
            summary = out / "summary.csv"
            new = not summary.exists()
            with summary.open("a", newline="") as f:
                w = csv.writer(f)
                if new:
                    w.writerow(SUMMARY_FIELDS)
                w.writerow(
                    [
                        args.task,
                        system,
                        seed,
                        args.steps,
                        f"{result.final:.1f}",
                        f"{wall:.0f}",
                        f"{result.eval_seconds:.0f}",
                        overrides,
                        code,
                        time.strftime("%Y-%m-%d %H:%M"),
                    ]
                )
            print(
                f"{args.task} {system} seed {seed}: return {result.final:.1f} after {args.steps} steps,"
                f" {wall:.0f} s ({result.eval_seconds:.0f} s evaluating)",
                flush=True,
            )


def report(out: Path, task: str | None = None, seeds: Sequence[int] | None = None, also: Sequence[Path] = ()) -> None:
    """Per task: one row per seed (the latest run of each system; only ``seeds`` when given, so that
    runs of extra seeds can share the folder with the seeds a goal is judged on), then the means and
    the ratio. Runs in the ``also`` folders count as if they were in ``out`` (e.g. extra seeds run into
    a folder of their own); a run of the same system and seed in a later folder wins."""
    rows = [
        {**r, "folder": str(folder)}
        for folder in (out, *also)
        for r in read_summary(folder)
        if seeds is None or int(r["seed"]) in seeds
    ]
    pools: dict[str, list[float]] = {}  # per task: every run's return, both systems'
    for name in [t for t in MUJOCO_TASKS if t == task or task is None]:
        runs = {(r["system"], int(r["seed"])): r for r in rows if r["task"] == name}  # the latest wins
        runs = dict(sorted(runs.items(), key=lambda run: run[0][1]))  # per-seed lists in the table's order
        if not runs:
            continue
        seeds = sorted({s for _, s in runs})
        print(f"\n{MUJOCO_TASKS[name]}, deterministic return ({EVAL_EPISODES} episodes) after N env steps")
        print("| seed | steps | ASAC | ASAC wall s | SB3 | SB3 wall s |\n|---|---|---|---|---|---|")
        for s in seeds:
            o, t = runs.get(("asac", s)), runs.get(("sb3", s))
            steps = (o or t or {}).get("steps", "")
            print(
                f"| {s} | {steps} | {o['return'] if o else 'not run'} | {o['wall_s'] if o else ''}"
                f" | {t['return'] if t else 'not run'} | {t['wall_s'] if t else ''} |"
            )
        means: dict[str, float] = {}
        lasts: dict[str, float] = {}
        finals: dict[str, list[float]] = {}
        areas: dict[str, list[float]] = {}
        for system in ("asac", "sb3"):
            rets = [float(r["return"]) for (sy, _), r in runs.items() if sy == system]
            if not rets:
                continue
            means[system], finals[system] = float(np.mean(rets)), rets
            # less noisy than one evaluation: each seed's mean of its last LAST evaluations
            curves = [curve_path(Path(r["folder"]), name, sy, s) for (sy, s), r in runs.items() if sy == system]
            last = [last_evaluations(path) for path in curves]
            lasts[system] = float(np.mean(last))
            areas[system] = [curve_mean(path) for path in curves]
            print(
                f"{system}: mean {means[system]:.1f}, min {min(rets):.1f}, max {max(rets):.1f} over {len(rets)} seeds;"
                f" mean of the last {LAST} evaluations {lasts[system]:.1f} ({' / '.join(f'{v:.1f}' for v in last)});"
                f" mean of all evaluations past {LEARNING_FROM} steps {np.mean(areas[system]):.1f}"
                f" ({' / '.join(f'{v:.1f}' for v in areas[system])})"
            )
        if len(means) == 2 and means["sb3"] != 0:
            pools[MUJOCO_TASKS[name]] = finals["asac"] + finals["sb3"]
            low, high = ratio_interval(finals["asac"], finals["sb3"])
            print(
                f"ASAC / SB3 means: {means['asac'] / means['sb3']:.2f}x (seeds resampled: {INTERVAL:.0%} of draws"
                f" between {low:.2f}x and {high:.2f}x);"
                f" of the last {LAST} evaluations {lasts['asac'] / lasts['sb3']:.2f}x"
            )
            low, high = ratio_interval(areas["asac"], areas["sb3"])
            print(
                f"ASAC / SB3 over the whole curve (mean of the evaluations past {LEARNING_FROM} steps):"
                f" {np.mean(areas['asac']) / np.mean(areas['sb3']):.2f}x ({INTERVAL:.0%}: {low:.2f}x-{high:.2f}x)"
            )
    if pools:
        print_goal_chances(pools, GOAL_SEEDS)


GOAL_SEEDS = 3  # issue 15 judges the MuJoCo goal on seeds 0-2
ADVANTAGES = (0.0, 0.05, 0.10, 0.20)


def print_goal_chances(pools: dict[str, list[float]], seeds: int) -> None:
    """The table of :func:`goal_chances` for :data:`ADVANTAGES` under the report's tasks."""
    print(
        f"\nHow often a system meets 'mean of {seeds} seeds >= SB3's mean of {seeds} seeds' when each side's runs are"
        " drawn from the two systems' pooled runs above, its own shifted up by the advantage (x the pool's mean):"
    )
    names = list(pools)
    print(f"| advantage | {' | '.join(names)} | all {len(names)} |\n|---{'|---' * (len(names) + 1)}|")
    for advantage in ADVANTAGES:
        per_task, every = goal_chances(pools, advantage, seeds)
        cells = " | ".join(f"{per_task[n]:.0%}" for n in names)
        print(f"| {advantage:+.0%} | {cells} | {every:.0%} |")


def goal_chances(
    pools: dict[str, list[float]], advantage: float, seeds: int, draws: int = 100_000
) -> tuple[dict[str, float], float]:
    """Per task, the chance that the mean of ``seeds`` runs drawn (with replacement) from the task's pool,
    each raised by ``advantage`` times the pool's mean, is at least the mean of ``seeds`` runs drawn from
    the pool as it is; and the chance of that on every task at once (tasks independent: the product).

    The pool holds both systems' runs, so at advantage 0 it is the chance that a system no different from
    its peer meets a ">= the peer's mean" goal on a few seeds: about one half per task (more by the share
    of ties), whatever the pool, and a half to the power of the number of tasks on all of them. A larger
    advantage shows how much better a system would have to be for the goal to be met most of the time,
    with this sample's spread between seeds."""
    rng = np.random.default_rng(0)
    per_task: dict[str, float] = {}
    for name, pool in pools.items():
        runs = np.asarray(pool, dtype=np.float64)
        ours = runs[rng.integers(0, runs.size, (draws, seeds))].mean(axis=1) + advantage * abs(runs.mean())
        theirs = runs[rng.integers(0, runs.size, (draws, seeds))].mean(axis=1)
        per_task[name] = float(np.mean(ours >= theirs))
    return per_task, float(np.prod(list(per_task.values())))


def ratio_interval(ours: list[float], theirs: list[float], draws: int = 10_000) -> tuple[float, float]:
    """The central ``INTERVAL`` of mean(ours) / mean(theirs) when each side's seeds are drawn again with
    replacement (a percentile bootstrap, fixed generator): how far the ratio of a few seeds' means
    moves with the seeds alone. Three seeds give a crude interval, but one that shows whether a
    ratio's distance from 1 is more than the seeds' spread."""
    rng = np.random.default_rng(0)
    a, b = np.asarray(ours, dtype=np.float64), np.asarray(theirs, dtype=np.float64)
    mean_a = a[rng.integers(0, a.size, (draws, a.size))].mean(axis=1)
    mean_b = b[rng.integers(0, b.size, (draws, b.size))].mean(axis=1)
    ratios = mean_a[mean_b != 0] / mean_b[mean_b != 0]
    tail = (1.0 - INTERVAL) / 2
    low, high = np.quantile(ratios, [tail, 1.0 - tail])
    return float(low), float(high)


def curve_returns(path: Path) -> list[tuple[int, float]]:
    """A run's curve: ``(env_steps, return_mean)`` of each evaluation, in order."""
    with path.open(newline="") as f:
        return [(int(float(r["env_steps"])), float(r["return_mean"])) for r in csv.DictReader(f)]


def curve_mean(path: Path) -> float:
    """The mean of a run's evaluations past ``LEARNING_FROM`` env steps (the area under its curve)."""
    return float(np.mean([ret for steps, ret in curve_returns(path) if steps > LEARNING_FROM]))


def last_evaluations(path: Path) -> float:
    return float(np.mean([ret for _, ret in curve_returns(path)[-LAST:]]))


def suite(args: argparse.Namespace) -> None:
    """The whole comparison, one run at a time, interleaved (task by task; per seed ASAC then SB3),
    each run its own process; runs already in OUT/summary.csv are skipped, so a stopped suite is
    resumed by starting it again (SIGTERM to it saves ASAC's run in progress: bench/children.py)."""
    out = Path(args.out)
    overrides = args.override or list(SUITE_OVERRIDES)
    children = Children()
    for task in args.tasks:
        for seed in args.seeds:
            for which, system in (("ours", "asac"), ("sb3", "sb3")):
                extra = overrides if system == "asac" else []
                if finished(out, task, system, seed, args.steps, " ".join(extra)):
                    continue
                cmd = [sys.executable, "-m", "bench.vs_sb3", "mujoco", task, "--seeds", str(seed), "--which", which]
                cmd += ["--steps", str(args.steps), "--every", str(args.every), "--threads", str(args.threads)]
                cmd += ["--out", str(out), "--runs", str(args.runs), *[a for o in extra for a in ("--override", o)]]
                print(time.strftime("%H:%M:%S"), " ".join(cmd[1:]), flush=True)
                rc = children.run(cmd, cwd=ROOT)
                print(time.strftime("%H:%M:%S"), f"{task} {system} seed {seed}: exit {rc}", flush=True)
                if rc != 0 or children.stopping:
                    sys.exit(rc)
