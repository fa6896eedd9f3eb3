"""Learning curves of the MuJoCo comparison (``python -m bench.vs_sb3 mujoco``/``suite``), one PNG per task.

    python -m bench.curves [--tasks hopper walker2d ant half_cheetah] [--out bench/results/mujoco] [--seeds 0 1 2]

Reads the runs' evaluation records OUT/<task>_<asac|sb3>_seed<k>.csv (env steps, mean deterministic
return of 10 episodes) of the runs OUT/summary.csv lists as finished, and draws per system the mean
over seeds and the min-max band into OUT/<task>.png. With --seeds, only those seeds' runs, into
OUT/<task>_seeds<a>_<b>_....png (a goal's seeds and extra seeds share a folder). A task without
finished runs is skipped.
Needs matplotlib (not a dependency of asac).
"""

from __future__ import annotations

import argparse
import csv
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from bench.suite import RESULTS, SUITE_TASKS, curve_path, read_summary
from bench.systems import MUJOCO_TASKS

STYLE = {"asac": ("ASAC", "tab:blue"), "sb3": ("SB3 SAC", "tab:orange")}


def read_curve(path: Path) -> dict[int, float]:
    with path.open(newline="") as f:
        return {int(r["env_steps"]): float(r["return_mean"]) for r in csv.DictReader(f)}


def curves(out: Path, task: str, seeds: Sequence[int] | None = None) -> dict[str, dict[int, dict[int, float]]]:
    """{system: {seed: {env steps: mean return}}} of the finished runs (the latest row per seed), of
    ``seeds`` only when given."""
    runs = {
        (r["system"], int(r["seed"])): r
        for r in read_summary(out)
        if r["task"] == task and (seeds is None or int(r["seed"]) in seeds)
    }
    found: dict[str, dict[int, dict[int, float]]] = {}
    for system, seed in sorted(runs):
        path = curve_path(out, task, system, seed)
        if path.exists():
            found.setdefault(system, {})[seed] = read_curve(path)
    return found


def figure_path(out: Path, task: str, seeds: Sequence[int] | None = None) -> Path:
    return out / (f"{task}.png" if seeds is None else f"{task}_seeds{'_'.join(str(s) for s in seeds)}.png")


def plot(out: Path, task: str, seeds: Sequence[int] | None = None) -> Path | None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = figure_path(out, task, seeds)
    data = curves(out, task, seeds)
    if not data:
        return None
    fig, ax = plt.subplots(figsize=(6.0, 3.8), dpi=100)
    steps_max = 0
    for system, runs in data.items():
        common = sorted(set.intersection(*(set(c) for c in runs.values())))  # steps every seed evaluated
        if not common:
            continue
        values = np.array([[c[s] for s in common] for c in runs.values()])
        x = np.array(common) / 1000
        label, color = STYLE.get(system, (system, None))
        names = ",".join(str(s) for s in runs)
        ax.plot(x, values.mean(axis=0), color=color, label=f"{label} (mean of seeds {names})")
        if len(runs) > 1:
            ax.fill_between(x, values.min(axis=0), values.max(axis=0), color=color, alpha=0.2, linewidth=0)
        steps_max = max(steps_max, common[-1])
    ax.set_title(f"{MUJOCO_TASKS[task]}: deterministic return (10 episodes), band = min-max over seeds", fontsize=9)
    ax.set_xlabel("env steps (thousands)")
    ax.set_ylabel("mean return")
    ax.set_xlim(0, steps_max / 1000)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--tasks", nargs="+", choices=list(MUJOCO_TASKS), default=list(SUITE_TASKS))
    p.add_argument("--out", default=str(RESULTS / "mujoco"))
    p.add_argument("--seeds", type=int, nargs="+", help="only these seeds' runs (default: every finished run)")
    args = p.parse_args()
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        p.exit(2, "bench.curves: error: drawing needs matplotlib, not a dependency of asac: pip install matplotlib\n")
    for task in args.tasks:
        path = plot(Path(args.out), task, args.seeds)
        print(f"{task}: {path or 'no finished runs'}" + (f" ({path.stat().st_size // 1024} KB)" if path else ""))


if __name__ == "__main__":
    main()
