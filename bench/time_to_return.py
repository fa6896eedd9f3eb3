"""Wall-clock from launch to a return, per launcher and config, seed by seed, one run at a time.

    python -m bench.time_to_return mujoco/half_cheetah --threshold 3000 --seeds 0 1 2 3 4 \\
        --contender "main.py" --contender "local --actors 2 -c throughput" [--limit-s 2400] [--out FILE]
        [--summarize]

Each contender is a launcher and its arguments: ``main.py ARGS`` runs ``python main.py TASK ARGS``,
``local ARGS`` runs ``python main_ds.py TASK local ARGS``. For each seed, each contender runs alone
(``sac.seed`` fixed, a run folder of its own in a temporary model root, the task's evaluation cadence
as a user gets it) until its ``evaluations.csv`` first shows ``--threshold`` or ``--limit-s`` passes;
then it is interrupted (it saves and stops). The wall seconds count from the launch, so start-up,
warm-up and evaluations are in. Rows (one per run) go to ``--out`` as they land; the summary gives
per contender the runs that reached the threshold, the median and worst wall seconds and env steps,
and each contender's median against the first's with a 90% interval over the seeds drawn again
(a run that did not reach it counts as ``--limit-s``). ``--summarize`` runs nothing: it summarises the
rows already in ``--out`` for the task, threshold, contenders and seeds given (runs made in several
sittings).
"""

from __future__ import annotations

import argparse
import csv
import shlex
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench.distributed import time_to_threshold
from bench.rows import append_row

ROOT = Path(__file__).resolve().parents[1]
FIELDS = ["task", "contender", "seed", "threshold", "reached", "wall_s", "env_steps", "limit_s"]
LAUNCHERS = {"main.py": ["main.py"], "local": ["main_ds.py"]}


def command(task: str, contender: str, seed: int, run: str, root: str) -> list[str]:
    """The command line of ``contender`` (``main.py ARGS`` or ``local ARGS``) for ``task`` and ``seed``."""
    launcher, *args = shlex.split(contender)
    if launcher not in LAUNCHERS:
        raise SystemExit(f"--contender {contender!r}: start it with one of {sorted(LAUNCHERS)}")
    mode = ["local"] if launcher == "local" else ["--no_progress"]
    return [sys.executable, *LAUNCHERS[launcher], task, *mode, *args, "--override", f"sac.seed={seed}",
            "-n", run, "--model_root", root]  # fmt: skip


def median_ratio_interval(ours: list[float], base: list[float], draws: int = 10_000) -> tuple[float, float]:
    """The central 90% of median(ours) / median(base) with each side's seeds drawn again with replacement."""
    rng = np.random.default_rng(0)
    a, b = np.asarray(ours, dtype=np.float64), np.asarray(base, dtype=np.float64)
    ratios = np.median(a[rng.integers(0, a.size, (draws, a.size))], axis=1) / np.median(
        b[rng.integers(0, b.size, (draws, b.size))], axis=1
    )
    low, high = np.quantile(ratios, [0.05, 0.95])
    return float(low), float(high)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("task")
    parser.add_argument("--threshold", type=float, required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--contender", action="append", required=True, help='"main.py ARGS" or "local ARGS"')
    parser.add_argument("--limit-s", type=float, default=2400.0)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "time_to_return" / "rows.csv")
    parser.add_argument("--summarize", action="store_true", help="summarise the rows in --out; run nothing")
    args = parser.parse_args()

    results: dict[str, list[tuple[float, int]]] = {c: [] for c in args.contender}
    if args.summarize:
        with args.out.open(newline="") as f:
            for row in csv.DictReader(f):
                seed_matches = int(row["seed"]) in args.seeds and row["contender"] in results
                if seed_matches and (row["task"], float(row["threshold"])) == (args.task, args.threshold):
                    wall = float(row["wall_s"]) if row["reached"] == "True" else float("inf")
                    results[row["contender"]].append((wall, int(row["env_steps"])))
    else:
        run_all(args, results)
    summarize(args, results)


def run_all(args: argparse.Namespace, results: dict[str, list[tuple[float, int]]]) -> None:
    with tempfile.TemporaryDirectory() as root:
        for seed in args.seeds:
            for i, contender in enumerate(args.contender):
                run = f"c{i}_s{seed}"
                evaluations = Path(root) / args.task / run / "evaluations.csv"
                cmd = command(args.task, contender, seed, run, root)
                wall, steps = time_to_threshold(cmd, evaluations, args.threshold, args.limit_s)
                results[contender].append((wall, steps))
                reached = wall != float("inf")
                append_row(args.out, FIELDS, {"task": args.task, "contender": contender, "seed": seed,
                                              "threshold": args.threshold, "reached": reached,
                                              "wall_s": round(wall, 1) if reached else "", "env_steps": steps,
                                              "limit_s": args.limit_s})  # fmt: skip
                print(f"seed {seed}, {contender}: {f'{wall:.0f} s, {steps} env steps' if reached else 'not reached'}",
                      flush=True)  # fmt: skip


def summarize(args: argparse.Namespace, results: dict[str, list[tuple[float, int]]]) -> None:
    print(f"\n{args.task} to {args.threshold:g}, seeds {args.seeds}, one run at a time, wall seconds from launch")
    print("| contender | reached | median s (worst) | median env steps | each seed (s) | median / first's (90%) |")
    print("|---|---|---|---|---|---|")
    base = [min(w, args.limit_s) for w, _ in results[args.contender[0]]]
    for contender, values in results.items():
        walls = [min(w, args.limit_s) for w, _ in values]
        hits = sum(w != float("inf") for w, _ in values)
        median_steps = statistics.median(s for w, s in values if w != float("inf")) if hits else float("nan")
        low, high = median_ratio_interval(walls, base)
        ratio = statistics.median(walls) / statistics.median(base)
        each = ", ".join(f"{w:.0f}" if w != float("inf") else "-" for w, _ in values)
        print(f"| `{contender}` | {hits}/{len(values)} | {statistics.median(walls):.0f} ({max(walls):.0f}) | "
              f"{median_steps:,.0f} | {each} | {ratio:.2f}x ({low:.2f}x-{high:.2f}x) |")  # fmt: skip


if __name__ == "__main__":
    main()
