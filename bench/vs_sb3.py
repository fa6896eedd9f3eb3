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
        runs already there are skipped. `mujoco [TASK] --report` prints the tables.
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
import functools
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from algorithm.config import load_config
from algorithm.config_schema import Config
from algorithm.evaluation import evaluate, read_evaluations
from algorithm.trainer import EmbeddedTrainer
from envs.make import make_vector_env, vector_env_factory

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"


# -- ours ---------------------------------------------------------------------------------------
def our_config(task: str, overrides: list[str]) -> Config:
    return load_config(ROOT / "envs" / task, None, overrides).config


def our_trainer(config: Config, run_dir: Path, with_eval: bool = False) -> EmbeddedTrainer:
    base = config.base_config
    return EmbeddedTrainer(
        config,
        run_dir,
        vector_env_factory(base.build_path, env_kwargs=base.env_kwargs),
        evaluate=with_eval,
        progress=False,
    )


# -- SB3 ----------------------------------------------------------------------------------------
def sb3_model(env_id: str, seed: int, learning_starts: int, buffer_size: int = 1_000_000):  # noqa: ANN201
    import gymnasium as gym
    from stable_baselines3 import SAC as SB3SAC

    env = gym.make(env_id)
    return SB3SAC(
        "MlpPolicy",
        env,
        learning_rate=3e-4,
        buffer_size=buffer_size,
        learning_starts=learning_starts,
        batch_size=256,
        tau=0.005,
        gamma=0.99,
        train_freq=1,
        gradient_steps=1,
        ent_coef="auto_1.0",
        policy_kwargs={"net_arch": [256, 256]},
        seed=seed,
        device="cpu",
        verbose=0,
    )


class SB3Policy:
    """Adapts an SB3 model to our Policy protocol so both are evaluated by the same code."""

    def __init__(self, model) -> None:  # noqa: ANN001
        self.model = model
        space = model.action_space
        self.low, self.high = space.low, space.high

    def act(self, obs: list[np.ndarray], deterministic: bool = False) -> tuple[np.ndarray, np.ndarray]:
        env_action, _ = self.model.predict(obs[0], deterministic=deterministic)
        unit = 2.0 * (env_action - self.low) / (self.high - self.low) - 1.0
        return unit.astype(np.float32), np.zeros(len(unit), np.float32)


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
        steps = [r[2] for r in table if r[0] == name and r[2] is not None]
        walls = [r[3] for r in table if r[0] == name and r[3] is not None]
        if steps:
            print(
                f"{name}: median {statistics.median(steps):.0f} steps, {statistics.median(walls):.1f} s"
                f" ({len(steps)}/{len(args.seeds)} seeds reached -200)"
            )


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.1f}"


# -- MuJoCo: one run per (task, system, seed) -----------------------------------------------------
MUJOCO_TASKS = {
    "half_cheetah": "HalfCheetah-v5",
    "hopper": "Hopper-v5",
    "walker2d": "Walker2d-v5",
    "ant": "Ant-v5",
}
SUITE_TASKS = ("hopper", "walker2d", "ant", "half_cheetah")  # the suite's order; HalfCheetah had 5 seeds already
SUITE_OVERRIDES = ("sac.compute_dtype=bfloat16",)  # as HalfCheetah's reported runs (and `auto` on this CPU)
EVAL_EPISODES = 10
EVAL_ENVS = 5
SUMMARY_FIELDS = ("task", "system", "seed", "steps", "return", "wall_s", "eval_s", "overrides", "code", "finished")
CURVE_FIELDS = ("env_steps", "return_mean", "return_std", "wall_seconds")
LAST = 3  # the report also averages each run's last LAST evaluations (90k-100k of 100k)


@dataclass
class RunResult:
    final: float  # mean deterministic return of the last evaluation (after `steps` env steps)
    curve: list[tuple[int, float, float, float]] = field(default_factory=list)  # env steps, mean, std, wall s
    eval_seconds: float = 0.0


def warmup_steps(task: str) -> int:
    """The uniformly random steps the task's config asks for; SB3's learning_starts is set to them."""
    return our_config(f"mujoco/{task}", []).actor_config.random_steps


def run_ours(
    task: str,
    seed: int,
    steps: int,
    overrides: list[str],
    every: int = 0,
    on_eval: Callable[[RunResult], None] | None = None,
) -> RunResult:
    """ASAC with the task's config. ``every`` > 0: the trainer's own evaluations every ``every`` env
    steps (its evaluations.csv: EVAL_EPISODES deterministic episodes on EVAL_ENVS envs seeded
    seed + 100000 at the first evaluation only), the last at ``steps``. ``every`` == 0: none during
    training, one at the end on fresh envs seeded the same way."""
    config = our_config(
        f"mujoco/{task}",
        [
            f"sac.seed={seed}",
            f"base.max_step={steps}",
            f"eval.eval_per_step={every}",
            f"eval.eval_episodes={EVAL_EPISODES}",
            f"eval.eval_envs={EVAL_ENVS}",
            *overrides,
        ],
    )
    result = RunResult(float("nan"))
    with tempfile.TemporaryDirectory() as tmp:
        trainer = our_trainer(config, Path(tmp), with_eval=every > 0)
        if every == 0:
            trainer.run()
            env = make_vector_env(MUJOCO_TASKS[task], EVAL_ENVS, seed=seed + 100_000)
            result.final = evaluate(env, trainer.sac, EVAL_EPISODES, seed + 100_000).mean
            return result
        while not trainer.done():
            trainer.run(until_step=trainer.env_steps + every)
            rows = read_evaluations(trainer.paths.evaluations) if trainer.paths.evaluations.exists() else []
            result.curve = [(int(r["env_steps"]), r["return_mean"], r["return_std"], r["wall_seconds"]) for r in rows]
            result.eval_seconds = trainer.core.timers.seconds().get("time/eval_seconds", 0.0)
            if on_eval is not None:
                on_eval(result)
    if not result.curve or result.curve[-1][0] != steps:
        raise RuntimeError(f"ASAC {task} seed {seed}: last evaluation at {result.curve[-1:]} rather than {steps} steps")
    result.final = result.curve[-1][1]
    return result


def run_sb3(
    task: str, seed: int, steps: int, every: int = 0, on_eval: Callable[[RunResult], None] | None = None
) -> RunResult:
    """SB3 SAC with the same hyper-parameters and warm-up, evaluated by the same code on the same
    envs at the same cadence as :func:`run_ours` (``every`` == 0: once at the end)."""
    env_id = MUJOCO_TASKS[task]
    model = sb3_model(env_id, seed, learning_starts=warmup_steps(task))
    env = make_vector_env(env_id, EVAL_ENVS, seed=seed + 100_000)
    policy = SB3Policy(model)
    result = RunResult(float("nan"))
    start = time.perf_counter()
    while model.num_timesteps < steps:
        model.learn(total_timesteps=min(every or steps, steps - model.num_timesteps), reset_num_timesteps=False)
        if every == 0 and model.num_timesteps < steps:
            continue
        eval_start = time.perf_counter()
        r = evaluate(env, policy, EVAL_EPISODES, seed + 100_000 if not result.curve else None)
        result.eval_seconds += time.perf_counter() - eval_start
        result.curve.append((model.num_timesteps, r.mean, r.std, time.perf_counter() - start))
        if on_eval is not None:
            on_eval(result)
    result.final = result.curve[-1][1]
    return result


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
            ["git", "-C", str(ROOT), "status", "--porcelain", "--", "algorithm", "envs", "bench/vs_sb3.py"],
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


def mujoco(args: argparse.Namespace) -> None:
    """Runs of one task (``--which`` ours/sb3/both, seed by seed, ours first), each storing its curve
    in OUT/<task>_<asac|sb3>_seed<k>.csv as evaluations come and, when it ends, a row in
    OUT/summary.csv; a run whose row exists (same task, system, seed, steps and overrides) is skipped."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.report:
        report(out, args.task)
        return
    torch.set_num_threads(args.threads)
    label = " ".join(args.override)
    for seed in args.seeds:
        for system in {"both": ["asac", "sb3"], "ours": ["asac"], "sb3": ["sb3"]}[args.which]:
            overrides = label if system == "asac" else ""
            if finished(out, args.task, system, seed, args.steps, overrides) and not args.force:
                print(f"{args.task} {system} seed {seed}: in {out / 'summary.csv'} already, skipped", flush=True)
                continue
            path = curve_path(out, args.task, system, seed)
            code, start = code_version(), time.perf_counter()
            if system == "asac":
                result = run_ours(
                    args.task, seed, args.steps, args.override, args.every, functools.partial(write_curve, path)
                )
            else:
                result = run_sb3(args.task, seed, args.steps, args.every, functools.partial(write_curve, path))
            wall = time.perf_counter() - start
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


def report(out: Path, task: str | None = None) -> None:
    """Per task: one row per seed (the latest run of each system), then the means and the ratio."""
    rows = read_summary(out)
    for name in [t for t in MUJOCO_TASKS if t == task or task is None]:
        runs = {(r["system"], int(r["seed"])): r for r in rows if r["task"] == name}  # the latest wins
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
        for system in ("asac", "sb3"):
            rets = [float(r["return"]) for (sy, _), r in runs.items() if sy == system]
            if not rets:
                continue
            means[system] = float(np.mean(rets))
            # less noisy than one evaluation: each seed's mean of its last LAST evaluations
            last = [last_evaluations(curve_path(out, name, sy, s)) for (sy, s) in runs if sy == system]
            lasts[system] = float(np.mean(last))
            print(
                f"{system}: mean {means[system]:.1f}, min {min(rets):.1f}, max {max(rets):.1f} over {len(rets)} seeds;"
                f" mean of the last {LAST} evaluations {lasts[system]:.1f} ({' / '.join(f'{v:.1f}' for v in last)})"
            )
        if len(means) == 2 and means["sb3"] != 0:
            print(
                f"ASAC / SB3 means: {means['asac'] / means['sb3']:.2f}x;"
                f" of the last {LAST} evaluations {lasts['asac'] / lasts['sb3']:.2f}x"
            )


def last_evaluations(path: Path) -> float:
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    return float(np.mean([float(r["return_mean"]) for r in rows[-LAST:]]))


def suite(args: argparse.Namespace) -> None:
    """The whole comparison, one run at a time, interleaved (task by task; per seed ASAC then SB3),
    each run its own process; runs already in OUT/summary.csv are skipped, so a stopped suite is
    resumed by starting it again."""
    out = Path(args.out)
    overrides = args.override or list(SUITE_OVERRIDES)
    for task in args.tasks:
        for seed in args.seeds:
            for which, system in (("ours", "asac"), ("sb3", "sb3")):
                extra = overrides if system == "asac" else []
                if finished(out, task, system, seed, args.steps, " ".join(extra)):
                    continue
                cmd = [sys.executable, "-m", "bench.vs_sb3", "mujoco", task, "--seeds", str(seed), "--which", which]
                cmd += ["--steps", str(args.steps), "--every", str(args.every), "--threads", str(args.threads)]
                cmd += ["--out", str(out), *[a for o in extra for a in ("--override", o)]]
                print(time.strftime("%H:%M:%S"), " ".join(cmd[1:]), flush=True)
                rc = subprocess.run(cmd, cwd=ROOT, check=False).returncode
                print(time.strftime("%H:%M:%S"), f"{task} {system} seed {seed}: exit {rc}", flush=True)
                if rc != 0:
                    sys.exit(rc)


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
    mj.add_argument("--force", action="store_true", help="run even when summary.csv has the run")
    mj.add_argument(
        "--override",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra config override for ASAC (repeatable); recorded with the run",
    )
    mj.add_argument("--report", action="store_true", help="only print the table of runs so far")
    su = sub.add_parser("suite")
    su.add_argument("--tasks", nargs="+", choices=list(MUJOCO_TASKS), default=list(SUITE_TASKS))
    su.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    su.add_argument("--steps", type=int, default=100_000)
    su.add_argument("--every", type=int, default=5000)
    su.add_argument("--threads", type=int, default=1)
    su.add_argument("--out", default=str(RESULTS / "mujoco"))
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
