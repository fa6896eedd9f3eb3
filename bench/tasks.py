"""Learning results of the issue-3 tasks (discrete, masks, mixed, POMDP, pixels, sparse reward).

    python -m bench.tasks TASK [-c SECTION] [--seeds 0 1] [--steps N] [--threshold X] [--every K]
        [--final-episodes 100] [--override KEY=VALUE ...]
    python -m bench.tasks --report

Trains ``envs/TASK`` (a config section with ``-c``) for ``--steps`` env steps per seed,
evaluating (10 deterministic episodes) every ``--every`` steps, and appends one row per seed to
bench/results/tasks.csv: the first evaluation that reached ``--threshold`` (or none), the best and
the last evaluation's mean return, the lowest evaluation from the first that reached the threshold
on ("kept": whether a result, once found, was held to the end), the final policy's mean return over
``--final-episodes`` more deterministic episodes (100 unless told; 0 skips them), and the wall time.
One evaluation of 10 episodes is a noisy reading of a policy that fails now and then: a CartPole policy
that loses the cart on 14% of its episodes scores 500 on 10 episodes about one time in five
(bench/results/cartpole/README.md), and Gym's "solved" for CartPole-v1 is a mean of 475 over 100
episodes. ``--report`` prints every row so far as the table in bench/results/features/README.md.
Examples (BENCHMARKS.md and bench/results/ list the exact commands behind their numbers):

    python -m bench.tasks gym/cartpole --threshold 475 --steps 30000
    python -m bench.tasks gym/pendulum_novel -c feedforward --threshold -300 --steps 15000
    python -m bench.tasks gym/mountain_car -c curiosity --threshold 90 --steps 30000 --every 5000
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import csv  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from algorithm.config.load import config_from_file, load_config  # noqa: E402
from algorithm.run.checkpoint import list_checkpoints  # noqa: E402
from algorithm.run.evaluation import evaluate, read_evaluations  # noqa: E402
from algorithm.run.folder import RunDir  # noqa: E402
from algorithm.run.trainer import EmbeddedTrainer  # noqa: E402
from bench.eval_modes import checkpoint_policy  # noqa: E402
from bench.rows import append_row  # noqa: E402
from envs.make import vector_env_factory  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results" / "tasks.csv"
FIELDS = ["task", "section", "overrides", "seed", "steps", "threshold", "reached_at", "best", "last", "kept",
          "final_episodes", "final", "wall_s"]  # fmt: skip
FINAL_SEED_OFFSET = 100_000  # the final episodes' start states: a stream of their own, apart from the run's


def reached_and_kept(rows: list[dict[str, float]], threshold: float | None) -> tuple[int | None, float | None]:
    """The env steps of the first evaluation at or above ``threshold``, and the lowest mean return from
    that evaluation to the last (None, None when none reached it)."""
    first = next((i for i, r in enumerate(rows) if threshold is not None and r["return_mean"] >= threshold), None)
    if first is None:
        return None, None
    return int(rows[first]["env_steps"]), round(min(r["return_mean"] for r in rows[first:]), 1)


def final_return(run_dir: Path, episodes: int, seed: int) -> float:
    """The mean return of the run's last checkpoint over ``episodes`` deterministic episodes on one env,
    their start states drawn from one stream seeded ``seed``."""
    paths = RunDir(run_dir)
    steps = list_checkpoints(paths.model)
    if not steps:
        raise RuntimeError(f"{run_dir}: the run saved no checkpoint to score")
    env, policy = checkpoint_policy(paths, config_from_file(paths.config), steps[-1], seed)
    try:
        return evaluate(env, policy, episodes, seed).mean
    finally:
        env.close()


def run(task: str, section: str | None, seed: int, steps: int, every: int, threshold: float | None,
        overrides: list[str], final_episodes: int = 100) -> dict[str, object]:  # fmt: skip
    config = load_config(ROOT / "envs" / task, section,
                         [f"sac.seed={seed}", f"base.max_step={steps}", f"eval.eval_per_step={every}",
                          "eval.eval_episodes=10", *overrides]).config  # fmt: skip
    base = config.base_config
    limit = base.max_step_each_iter if base.max_step_each_iter > 0 else None
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        factory = vector_env_factory(base.build_path, env_kwargs=base.env_kwargs, max_episode_steps=limit)
        EmbeddedTrainer(config, Path(tmp), factory, progress=False).run()
        rows = read_evaluations(Path(tmp) / "evaluations.csv")
        final = final_return(Path(tmp), final_episodes, FINAL_SEED_OFFSET + seed) if final_episodes else None
    reached, kept = reached_and_kept(rows, threshold)
    return {
        "task": task, "section": section or "default", "overrides": " ".join(overrides), "seed": seed,
        "steps": steps, "threshold": threshold, "reached_at": reached,
        "best": round(max(r["return_mean"] for r in rows), 1), "last": round(rows[-1]["return_mean"], 1), "kept": kept,
        "final_episodes": final_episodes or None, "final": None if final is None else round(final, 1),
        "wall_s": round(time.perf_counter() - start),
    }  # fmt: skip


def report() -> None:
    rows = list(csv.DictReader(RESULTS.open())) if RESULTS.exists() else []
    print("| task | config | seed | steps | reached threshold at | best | last | lowest after reaching "
          "| final policy (episodes) | wall s |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        config = r["section"] + (f" ({r['overrides']})" if r["overrides"] else "")
        reached = f"{r['reached_at']} ({r['threshold']})" if r["reached_at"] else f"not reached ({r['threshold']})"
        print(f"| {r['task']} | {config} | {r['seed']} | {r['steps']} | {reached} | {r['best']} | {r['last']} "
              f"| {r.get('kept') or '-'} | {final_cell(r)} | {r['wall_s']} |")  # fmt: skip


def final_cell(row: dict[str, str]) -> str:
    """The report's cell for the final policy's mean return, "-" for rows run without (or before) it."""
    return f"{row['final']} ({row['final_episodes']})" if row.get("final") else "-"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("task", nargs="?")
    p.add_argument("-c", "--config", default=None)
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--steps", type=int, default=20000)
    p.add_argument("--every", type=int, default=1000)
    p.add_argument("--threshold", type=float, default=None)
    p.add_argument(
        "--final-episodes",
        type=int,
        default=100,
        metavar="N",
        help="score the final policy on N more deterministic episodes (0: skip)",
    )
    p.add_argument("--override", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--report", action="store_true")
    args = p.parse_args()
    if args.report or args.task is None:
        report()
        return
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    for seed in args.seeds:
        row = run(args.task, args.config, seed, args.steps, args.every, args.threshold, args.override,
                  args.final_episodes)  # fmt: skip
        append(row)
        print(row, flush=True)


def append(row: dict[str, object], path: Path = RESULTS) -> None:
    append_row(path, FIELDS, row)


if __name__ == "__main__":
    main()
