"""The reading RULE.md asks for, printed as in reading.txt.

PYTHONPATH=. python bench/results/walker2d_epsilon_alone/read.py [SEED ...]    # from the repo root; seeds 10-19
"""

import csv
import sys
from pathlib import Path

import numpy as np

from bench.suite import curve_mean, curve_returns, last_evaluations, ratio_interval

base = Path(__file__).resolve().parent
seeds = [int(s) for s in sys.argv[1:]] or list(range(10, 20))
rows = {}
for arm in ("default", "epsilon"):
    with (base / arm / "summary.csv").open(newline="") as f:
        at_end = {int(r["seed"]): float(r["return"]) for r in csv.DictReader(f)}
    at, l3, wc = [], [], []
    for s in seeds:
        path = base / arm / f"walker2d_asac_seed{s}.csv"
        assert curve_returns(path)[-1][0] == 100000, f"{path} has not reached 100k"
        at.append(at_end[s])
        l3.append(last_evaluations(path))
        wc.append(curve_mean(path))
    rows[arm] = (at, l3, wc)
    spread = f"mean {np.mean(at):.1f} median {np.median(at):.1f} worst {min(at):.1f}"
    print(arm, "at100k", [round(x, 1) for x in at], spread)
    print(arm, "last3 ", [round(x, 1) for x in l3], f"mean {np.mean(l3):.1f}")
    print(arm, "curve ", [round(x, 1) for x in wc], f"mean {np.mean(wc):.1f}")
for i, name in enumerate(("at 100k", "last 3", "whole curve")):
    eps, default = rows["epsilon"][i], rows["default"][i]
    low, high = ratio_interval(eps, default)
    print(f"{name}: epsilon/default {np.mean(eps) / np.mean(default):.2f}x (90%: {low:.2f}x-{high:.2f}x)")
