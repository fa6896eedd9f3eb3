"""The learner role's update rate against the in-process loop's, with the same config, side by side.

    python -m bench.learner_rate gym/pendulum mujoco/half_cheetah [--seeds 0 1] [--steps N] [--device cuda]
        [--override KEY=VALUE] [--out FILE]

For each task and seed, ``main.py TASK`` and ``main_ds.py TASK local --actors 1`` run one after the
other with the task's default config (``base.max_step`` cut to ``--steps``; a seed fixed), and each
run's TensorBoard files are read back: the learning phase's updates/s (the slope of
``learner/updates`` from its first to its last point), the learner's time shares (``time/*``: the
update, waiting for batches, publishing, evaluating), the cost of one publish and of its MAC
(``learner/params/publish_ms``, ``mac_ms``) and actor 0's staleness (``actor/staleness_*``: the
learner's updates at a step minus those of the weights it acted with; the medians over the run of
each metrics interval's median and p95). Goal (issue: distributed that pays off): local >= 0.9x main.py's updates/s, the
learner's time outside the update <= 5%, publishing <= 2%.

Rows go to ``--out`` (CSV, appended as they land); a summary with the ratio per task is printed.
Timings drift 20-35% between runs on a shared machine: compare only the rows of one invocation.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARES = ("update", "wait", "priorities", "publish", "eval")
FIELDS = ["task", "seed", "mode", "updates", "updates_per_s", "wall_s", *(f"{p}_share" for p in SHARES),
          "publish_ms", "mac_ms", "staleness_median", "staleness_p95"]  # fmt: skip


def scalars(folder: Path) -> dict[str, list[tuple[float, float]]]:
    """Every scalar tag under ``folder`` (all event files) as ``[(wall_time, value), ...]`` in time order."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out: dict[str, list[tuple[float, float]]] = {}
    for events in sorted(folder.glob("events.out.tfevents.*")):
        acc = EventAccumulator(str(events), size_guidance={"scalars": 0})
        acc.Reload()
        for tag in acc.Tags()["scalars"]:
            out.setdefault(tag, []).extend((e.wall_time, e.value) for e in acc.Scalars(tag))
    return {tag: sorted(points) for tag, points in out.items()}


def rate(points: list[tuple[float, float]]) -> float:
    """Updates/s between the first point past 0 updates and the last (the learning phase)."""
    learning = [(t, v) for t, v in points if v > 0]
    if len(learning) < 2 or learning[-1][0] <= learning[0][0]:
        return float("nan")
    (t0, v0), (t1, v1) = learning[0], learning[-1]
    return (v1 - v0) / (t1 - t0)


def last(tags: dict[str, list[tuple[float, float]]], tag: str) -> float:
    return tags[tag][-1][1] if tag in tags else float("nan")


def over_run(tags: dict[str, list[tuple[float, float]]], tag: str) -> float:
    """The median of a per-interval scalar over the run (nan when the run did not write it)."""
    return round(statistics.median(v for _, v in tags[tag]), 1) if tag in tags else float("nan")


def run(task: str, seed: int, mode: str, root: Path, overrides: list[str], device: str = "cpu") -> dict[str, object]:
    """One run of ``mode`` (main or local) and what its TensorBoard files say (see the module docstring)."""
    name = f"{mode}_{seed}"
    flags = [arg for o in overrides for arg in ("--override", o)]
    entry = ["main.py", task] if mode == "main" else ["main_ds.py", task, "local", "--actors", "1"]
    command = [sys.executable, str(ROOT / entry[0]), *entry[1:], "-n", name, "--model_root", str(root),
               "--no_progress", "--device", device, *flags]  # fmt: skip
    started = time.perf_counter()
    done = subprocess.run(command, cwd=root, capture_output=True, text=True)
    wall = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} exited {done.returncode}:\n{done.stderr[-3000:]}")
    log = root / task / name / "log"
    tags = scalars(log if mode == "main" else log / "learner")
    actor = {} if mode == "main" else scalars(log / "actor_0")
    updates = tags.get("learner/updates", [])
    return {
        "task": task, "seed": seed, "mode": mode, "updates": int(updates[-1][1]) if updates else 0,
        "updates_per_s": round(rate(updates), 2), "wall_s": round(wall, 1),
        **{f"{p}_share": round(last(tags, f"time/{p}_fraction"), 4) for p in SHARES},
        "publish_ms": round(last(tags, "learner/params/publish_ms"), 3),
        "mac_ms": round(last(tags, "learner/params/mac_ms"), 3),
        "staleness_median": over_run(actor, "actor/staleness_median"),
        "staleness_p95": over_run(actor, "actor/staleness_p95"),
    }  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.learner_rate", description=__doc__.split("\n\n")[0])
    p.add_argument("tasks", nargs="+")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--steps", type=int, default=None, help="base.max_step of every run (default: the task's)")
    p.add_argument("--override", action="append", default=[], help="for both modes, e.g. sac.publish_budget=0")
    p.add_argument("--device", default="cpu", help="the learner's torch device in both modes (cuda: the CUDA graph)")
    p.add_argument("--out", type=Path, default=ROOT / "bench/results/learner_rate/rows.csv")
    args = p.parse_args(argv)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    new = not args.out.exists()
    rows = []
    with tempfile.TemporaryDirectory(prefix="asac-learner-rate-") as tmp, args.out.open("a", newline="") as f:
        writer = csv.DictWriter(f, FIELDS, extrasaction="ignore")
        if new:
            writer.writeheader()
        budget = [] if args.steps is None else [f"base.max_step={args.steps}"]
        for task in args.tasks:
            for seed in args.seeds:
                for mode in ("main", "local"):  # back to back: machine noise hits both alike
                    row = run(task, seed, mode, Path(tmp), [*budget, f"sac.seed={seed}", *args.override], args.device)
                    rows.append(row)
                    writer.writerow(row)
                    f.flush()
                    print(row, flush=True)
    for task in args.tasks:
        ratios = []
        for seed in args.seeds:
            by_mode = {r["mode"]: r for r in rows if r["task"] == task and r["seed"] == seed}
            ratios.append(float(by_mode["local"]["updates_per_s"]) / float(by_mode["main"]["updates_per_s"]))  # type: ignore[arg-type]
        print(f"{task}: local / main.py updates/s {statistics.median(ratios):.2f}x (per seed "
              f"{', '.join(f'{r:.2f}' for r in ratios)})")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
