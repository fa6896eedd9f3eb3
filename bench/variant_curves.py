"""A config variant's learning per env step against the task's default, from the curves of
``python -m bench.vs_sb3 mujoco TASK --which ours`` (one CSV per seed, ``TASK_asac_seed<k>.csv``).

    python -m bench.variant_curves half_cheetah --variant DIR --default DIR [--seeds 0 1 2 3 4] [--threshold 3000]

Per seed: the return at the budget's end, the mean of the evaluations past 10,000 env steps (the area
under the curve, bench/suite.py) and the env steps of the first evaluation at ``--threshold``; then
the variant's mean over the default's for both, with the 90% interval of the ratio when each side's
seeds are drawn again (``bench.suite.ratio_interval``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bench.suite import LEARNING_FROM, curve_mean, curve_returns, ratio_interval


def first_at(path: Path, threshold: float) -> int | None:
    return next((steps for steps, ret in curve_returns(path) if ret >= threshold), None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("task")
    parser.add_argument("--variant", type=Path, required=True)
    parser.add_argument("--default", type=Path, required=True)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--threshold", type=float, default=3000.0)
    args = parser.parse_args()
    sides = {"variant": args.variant, "default": args.default}
    finals: dict[str, list[float]] = {}
    areas: dict[str, list[float]] = {}
    print(f"{args.task}: return at the end | mean past {LEARNING_FROM:,} steps | first at {args.threshold:g}")
    print("| seed | " + " | ".join(f"{name}: end / area / first" for name in sides) + " |\n|---|---|---|")
    for seed in args.seeds:
        cells = []
        for name, folder in sides.items():
            path = folder / f"{args.task}_asac_seed{seed}.csv"
            curve = curve_returns(path)
            finals.setdefault(name, []).append(curve[-1][1])
            areas.setdefault(name, []).append(curve_mean(path))
            first = first_at(path, args.threshold)
            cells.append(f"{curve[-1][1]:,.1f} at {curve[-1][0]:,} / {areas[name][-1]:,.1f} / "
                         f"{f'{first:,}' if first is not None else '-'}")  # fmt: skip
        print(f"| {seed} | " + " | ".join(cells) + " |")
    for what, values in (("at the end", finals), (f"over the curve (past {LEARNING_FROM:,})", areas)):
        low, high = ratio_interval(values["variant"], values["default"])
        ratio = np.mean(values["variant"]) / np.mean(values["default"])
        print(f"variant / default {what}: {np.mean(values['variant']):,.1f} / {np.mean(values['default']):,.1f} = "
              f"{ratio:.2f}x (90%: {low:.2f}x-{high:.2f}x); worst seed {min(values['variant']):,.1f} / "
              f"{min(values['default']):,.1f}")  # fmt: skip


if __name__ == "__main__":
    main()
