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

from algorithm.config import load_config
from algorithm.config_schema import Config
from algorithm.evaluation import evaluate
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


# -- half cheetah -------------------------------------------------------------------------------
def half_cheetah(args: argparse.Namespace) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / "half_cheetah.csv"
    if not args.report:
        torch.set_num_threads(args.threads)
        ours = "ASAC" + "".join(f" {o}" for o in args.override)  # the label names what differs
        for seed in args.seeds:
            for name in {"both": [ours, "SB3"], "ours": [ours], "sb3": ["SB3"]}[args.which]:
                start = time.perf_counter()
                ret = cheetah_sb3(seed, args.steps) if name == "SB3" else cheetah_ours(seed, args.steps, args.override)
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


def cheetah_ours(seed: int, steps: int, overrides: list[str]) -> float:
    config = our_config(
        "mujoco/half_cheetah", [f"sac.seed={seed}", f"base.max_step={steps}", "eval.eval_per_step=0", *overrides]
    )
    with tempfile.TemporaryDirectory() as tmp:
        trainer = our_trainer(config, Path(tmp))
        trainer.run()
        env = make_vector_env("HalfCheetah-v5", 5, seed=seed + 100_000)
        return evaluate(env, trainer.sac, 10, seed + 100_000).mean


def cheetah_sb3(seed: int, steps: int) -> float:
    model = sb3_model("HalfCheetah-v5", seed, learning_starts=10_000)
    model.learn(total_timesteps=steps)
    env = make_vector_env("HalfCheetah-v5", 5, seed=seed + 100_000)
    return evaluate(env, SB3Policy(model), 10, seed + 100_000).mean


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
    args = p.parse_args()
    {"throughput": throughput, "pendulum": pendulum, "half_cheetah": half_cheetah}[args.what](args)


if __name__ == "__main__":
    main()
