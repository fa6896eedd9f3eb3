"""ASAC against Stable-Baselines3 SAC with identical hyper-parameters, measured in the same run.

    python -m bench.vs_sb3 throughput [--steps 3000] [--rounds 2] [--threads 1]
        env steps/s training HalfCheetah-v5 with one update per env step (after a random warm-up),
        ASAC in float32 and with sac.compute_dtype=bfloat16; rounds alternate ASAC/SB3 so machine
        noise hits all alike. Goal: ours >= 1.5x SB3.
    python -m bench.vs_sb3 pendulum [--seeds 0 1 2] [--max-steps 20000]
        env steps and wall seconds until the mean deterministic return (10 episodes, every 250
        steps) first reaches -200. Goal: fewer steps than SB3 and < 60 s.
    python -m bench.vs_sb3 half_cheetah [--seeds 0 1] [--steps 100000] [--which ours|sb3|both]
                                        [--override sac.compute_dtype=bfloat16]
        deterministic return (10 episodes) after 100k env steps. Goal: ours >= SB3's mean.
        Results are appended to bench/results/half_cheetah.csv, so runs can go in the background
        one by one and `--report` prints the table afterwards.
    python -m bench.vs_sb3 mujoco TASK [--seeds 0 1 2] [--steps 100000] [--every 5000]
                                  [--which ours|sb3|both] [--override sac.compute_dtype=bfloat16]
        TASK is half_cheetah, hopper, walker2d or ant (envs/mujoco/TASK/config.yaml; SB3 gets the
        same hyper-parameters and warm-up). Both sides are evaluated by the same code every
        --every env steps (10 deterministic episodes on 5 envs seeded seed + 100000 once, then one
        stream), the last evaluation at --steps being the run's return. Each run writes its curve to
        bench/results/mujoco/TASK_<asac|sb3>_seed<k>.csv as it goes and, at its end, a row (return,
        wall seconds, of which evaluating, overrides, code version) to bench/results/mujoco/summary.csv;
        runs already there are skipped. `mujoco [TASK] --report [--seeds 0 1 2] [--also DIR]` prints the
        tables of those seeds (0-2 unless told, the seeds the goal is judged on), taking runs from the
        folders --also names as well (extra seeds run into a folder of their own), and ends with how
        often a system meets the goal (mean of 3 seeds >= SB3's) when both sides' runs are drawn from
        the two systems' pooled runs, its own raised by 0-20% (bench/suite.py goal_chances). ASAC's runs train
        in folders under --runs ($ASAC_BENCH_RUNS, else ~/asac_long_runs): Ctrl-C or SIGTERM saves the
        run in progress and the same command resumes it (bench/suite.py). SB3's trained model is saved
        there too (mujoco_suite/TASK/sb3_s<k>_<steps>k.zip), for `python -m bench.saturation`.
    python -m bench.vs_sb3 suite [--tasks hopper walker2d ant half_cheetah] [--seeds 0 1 2]
                                 [--out DIR] [--override sac.compute_dtype=float32]
        every `mujoco` run of the comparison, one process at a time, task by task and per seed ASAC
        then SB3, ASAC with sac.compute_dtype=bfloat16 unless --override says otherwise; finished
        runs are skipped, so starting it again resumes it. `python -m bench.curves` draws the learning curves.

SB3 is an optional peer (pip install -e '.[bench]'). Both sides use 256x256 MLPs, batch 256,
lr 3e-4, gamma 0.99, tau 0.005, automatic entropy (alpha initialised at 1, target -|A|), uniform
replay, one gradient step per env step, the same number of uniformly random warm-up steps, one
env, and torch limited to the same number of threads.
"""

from __future__ import annotations

import os

# As main.py sets them before torch and numpy load (both sides run under them).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import csv
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from algorithm.run.evaluation import evaluate
from bench.children import default_runs
from bench.suite import RESULTS, SUITE_OVERRIDES, SUITE_TASKS, mujoco, suite
from bench.systems import MUJOCO_TASKS, SB3Policy, our_config, our_trainer, run_ours, run_sb3, sb3_model
from envs.make import make_vector_env


# -- throughput ---------------------------------------------------------------------------------
def throughput(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    warmup = 1000
    variants = {"ASAC float32": ["sac.compute_dtype=float32"], "ASAC bf16": ["sac.compute_dtype=bfloat16"]}
    rates: dict[str, list[float]] = {name: [] for name in [*variants, "SB3"]}
    for round_ in range(args.rounds):
        for name, extra in variants.items():
            config = our_config(
                "mujoco/half_cheetah",
                [
                    f"sac.seed={round_}",
                    f"actor.random_steps={warmup}",
                    f"replay.min_size_to_sample={warmup}",
                    f"base.max_step={warmup + args.steps}",
                    f"base.torch_threads={args.threads}",
                    "eval.eval_per_step=0",
                    "sac.save_model_per_step=100000000",
                    "sac.save_model_per_minute=1000",
                    *extra,
                ],
            )
            with tempfile.TemporaryDirectory() as tmp:
                trainer = our_trainer(config, Path(tmp))
                trainer.run(until_step=warmup + 64)  # random phase and the first updates
                start_steps, start = trainer.env_steps, time.perf_counter()
                trainer.run()
                rates[name].append((trainer.env_steps - start_steps) / (time.perf_counter() - start))

        model = sb3_model("HalfCheetah-v5", round_, learning_starts=warmup)
        model.learn(total_timesteps=warmup + 64)
        start = time.perf_counter()
        model.learn(total_timesteps=args.steps - 64, reset_num_timesteps=False)
        rates["SB3"].append((args.steps - 64) / (time.perf_counter() - start))
        print(f"round {round_}: " + ", ".join(f"{n} {r[-1]:.1f}" for n, r in rates.items()) + " steps/s", flush=True)
    median = {name: statistics.median(r) for name, r in rates.items()}
    print(f"\nHalfCheetah-v5, 1 update/env step, {args.threads} thread(s), median of {args.rounds} rounds")
    print("| impl | env steps/s | / SB3 |\n|---|---|---|")
    for name, value in median.items():
        print(f"| {name} | {value:.1f} | {value / median['SB3']:.2f}x |")


# -- pendulum -----------------------------------------------------------------------------------
def steps_to_threshold(rows: list[tuple[int, float, float]], threshold: float) -> tuple[int | None, float | None]:
    for steps, wall, ret in rows:
        if ret >= threshold:
            return steps, wall
    return None, None


def pendulum_ours(seed: int, max_steps: int, every: int) -> list[tuple[int, float, float]]:
    config = our_config(
        "gym/pendulum", [f"sac.seed={seed}", f"base.max_step={max_steps}", f"eval.eval_per_step={every}"]
    )
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        trainer = our_trainer(config, Path(tmp), with_eval=True)
        start = time.perf_counter()
        while trainer.env_steps < max_steps:
            trainer.run(until_step=trainer.env_steps + every)
            assert trainer.last_eval_mean is not None
            rows.append((trainer.env_steps, time.perf_counter() - start, trainer.last_eval_mean))
            if trainer.last_eval_mean >= -200:
                break
    return rows


def pendulum_sb3(seed: int, max_steps: int, every: int) -> list[tuple[int, float, float]]:
    model = sb3_model("Pendulum-v1", seed, learning_starts=100, buffer_size=100_000)
    eval_env = make_vector_env("Pendulum-v1", 5, seed=seed + 100_000)
    policy = SB3Policy(model)
    rows: list[tuple[int, float, float]] = []
    start = time.perf_counter()
    while model.num_timesteps < max_steps:
        model.learn(total_timesteps=every, reset_num_timesteps=False)
        result = evaluate(eval_env, policy, 10, seed + 100_000 if not rows else None)
        rows.append((model.num_timesteps, time.perf_counter() - start, result.mean))
        if result.mean >= -200:
            break
    return rows


def pendulum(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    table = []
    for seed in args.seeds:
        for name, fn in (("ASAC", pendulum_ours), ("SB3", pendulum_sb3)):
            steps, wall = steps_to_threshold(fn(seed, args.max_steps, args.every), -200.0)
            table.append((name, seed, steps, wall))
            print(f"{name} seed {seed}: -200 reached at {steps} steps, {wall and round(wall, 1)} s", flush=True)
    print("\nPendulum-v1, env steps / wall seconds to mean deterministic return >= -200 (10 episodes)")
    print("| seed | ASAC steps | ASAC s | SB3 steps | SB3 s |\n|---|---|---|---|---|")
    for seed in args.seeds:
        o = next(r for r in table if r[0] == "ASAC" and r[1] == seed)
        t = next(r for r in table if r[0] == "SB3" and r[1] == seed)
        print(f"| {seed} | {o[2]} | {_fmt(o[3])} | {t[2]} | {_fmt(t[3])} |")
    for name in ("ASAC", "SB3"):
        reached = [r[2] for r in table if r[0] == name and r[2] is not None]
        walls = [r[3] for r in table if r[0] == name and r[3] is not None]
        if reached:
            print(
                f"{name}: median {statistics.median(reached):.0f} steps, {statistics.median(walls):.1f} s"
                f" ({len(reached)}/{len(args.seeds)} seeds reached -200)"
            )


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.1f}"


# -- half cheetah (its first comparison: one evaluation at the end) -----------------------------
def half_cheetah(args: argparse.Namespace) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / "half_cheetah.csv"
    if not args.report:
        torch.set_num_threads(args.threads)
        ours = "ASAC" + "".join(f" {o}" for o in args.override)  # the label names what differs
        for seed in args.seeds:
            for name in {"both": [ours, "SB3"], "ours": [ours], "sb3": ["SB3"]}[args.which]:
                start = time.perf_counter()
                if name == "SB3":
                    ret = run_sb3("half_cheetah", seed, args.steps).final
                else:
                    ret = run_ours("half_cheetah", seed, args.steps, args.override).final
                with out.open("a", newline="") as f:
                    csv.writer(f).writerow([name, seed, args.steps, f"{ret:.1f}", f"{time.perf_counter() - start:.0f}"])
                print(f"{name} seed {seed}: return {ret:.1f} after {args.steps} steps", flush=True)
    rows = list(csv.reader(out.open())) if out.exists() else []
    print("\nHalfCheetah-v5 deterministic return (10 episodes) after N env steps")
    print("| impl | seed | steps | return | wall s |\n|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")
    for name in dict.fromkeys(r[0] for r in rows):
        rets = [float(r[3]) for r in rows if r[0] == name]
        print(
            f"{name}: mean {np.mean(rets):.1f}, std {np.std(rets, ddof=1) if len(rets) > 1 else 0:.1f}"
            f" over {len(rets)} runs"
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="what", required=True)
    t = sub.add_parser("throughput")
    t.add_argument("--steps", type=int, default=3000)
    t.add_argument("--rounds", type=int, default=2)
    t.add_argument("--threads", type=int, default=1)
    pe = sub.add_parser("pendulum")
    pe.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    pe.add_argument("--max-steps", type=int, default=20000)
    pe.add_argument("--every", type=int, default=250)
    pe.add_argument("--threads", type=int, default=2)
    hc = sub.add_parser("half_cheetah")
    hc.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    hc.add_argument("--steps", type=int, default=100_000)
    hc.add_argument("--which", choices=["ours", "sb3", "both"], default="both")
    hc.add_argument("--threads", type=int, default=1)
    hc.add_argument(
        "--override",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra config override for ASAC (repeatable); runs are labelled with it",
    )
    hc.add_argument("--report", action="store_true", help="only print the table of runs so far")
    mj = sub.add_parser("mujoco")
    mj.add_argument("task", nargs="?", choices=list(MUJOCO_TASKS), help="omitted: --report of every task")
    mj.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    mj.add_argument("--steps", type=int, default=100_000)
    mj.add_argument("--every", type=int, default=5000, help="evaluate every N env steps (0: once at the end)")
    mj.add_argument("--which", choices=["ours", "sb3", "both"], default="both")
    mj.add_argument("--threads", type=int, default=1)
    mj.add_argument("--out", default=str(RESULTS / "mujoco"), help="curves and summary.csv go here")
    mj.add_argument("--force", action="store_true", help="run even when summary.csv has the run (from scratch)")
    mj.add_argument("--runs", type=Path, default=default_runs(), help="ASAC's run folders go under RUNS/mujoco_suite")
    mj.add_argument(
        "--override",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra config override for ASAC (repeatable); recorded with the run",
    )
    mj.add_argument("--report", action="store_true", help="only print the table of runs so far")
    mj.add_argument(
        "--also", type=Path, action="append", default=[], metavar="DIR", help="--report: runs in DIR too (repeatable)"
    )
    su = sub.add_parser("suite")
    su.add_argument("--tasks", nargs="+", choices=list(MUJOCO_TASKS), default=list(SUITE_TASKS))
    su.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    su.add_argument("--steps", type=int, default=100_000)
    su.add_argument("--every", type=int, default=5000)
    su.add_argument("--threads", type=int, default=1)
    su.add_argument("--out", default=str(RESULTS / "mujoco"))
    su.add_argument("--runs", type=Path, default=default_runs(), help="ASAC's run folders go under RUNS/mujoco_suite")
    su.add_argument(
        "--override",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=f"ASAC's config overrides instead of {' '.join(SUITE_OVERRIDES)} (repeatable; e.g."
        " sac.compute_dtype=float32 on a CPU without native bfloat16)",
    )
    args = p.parse_args()
    if args.what == "mujoco" and args.task is None:
        args.report = True
    {"throughput": throughput, "pendulum": pendulum, "half_cheetah": half_cheetah, "mujoco": mujoco, "suite": suite}[
        args.what
    ](args)


if __name__ == "__main__":
    main()
