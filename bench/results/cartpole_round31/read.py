"""The tallies round 31's RULE.md asks for, over the round and over every seed no CartPole round chose on.

PYTHONPATH=. python bench/results/cartpole_round31/read.py     # from the repo root

Fresh seeds: 0-9 (the default's rows in cartpole_final_policy/, the ramp's in cartpole_round29/), 25-32
(cartpole_round30/) and 33-40 (here). A seed counts only once both arms have its row.
"""

import csv
from math import comb
from pathlib import Path

import numpy as np

from bench.tasks import FIELDS

results = Path(__file__).resolve().parent.parent
SOURCES = {
    "default": [
        "cartpole_final_policy/reported_seeds.csv",
        "cartpole_final_policy/unused_seeds.csv",
        "cartpole_round30/default.csv",
        "cartpole_round31/default.csv",
    ],
    "ramp": [
        "cartpole_round29/reported_seeds.csv",
        "cartpole_round29/unused_seeds.csv",
        "cartpole_round30/ramp.csv",
        "cartpole_round31/ramp.csv",
    ],
}
THRESHOLD = 475.0


def rows(arm: str) -> dict[int, dict[str, str]]:
    by_seed: dict[int, dict[str, str]] = {}
    for name in SOURCES[arm]:
        with (results / name).open(newline="") as f:
            lines = list(csv.reader(f))
        header = lines[0] == FIELDS  # the rounds' drivers copy rows without bench.tasks' header
        for values in lines[1:] if header else lines:
            r = dict(zip(FIELDS, values, strict=True))
            by_seed[int(r["seed"])] = r
    return by_seed


def tally(label: str, seeds: list[int], arms: dict[str, dict[int, dict[str, str]]]) -> None:
    print(f"{label}: {len(seeds)} seeds")
    for reading in ("final", "last"):
        passed = {}
        for arm, by_seed in arms.items():
            values = [float(by_seed[s][reading]) for s in seeds]
            passed[arm] = {s for s, v in zip(seeds, values, strict=True) if v >= THRESHOLD}
            print(
                f"  {arm:7} {reading:5}: {len(passed[arm])} of {len(seeds)} at {THRESHOLD:g}+, mean "
                f"{np.mean(values):.1f}, median {np.median(values):.1f}, worst {min(values):.1f}"
            )
        only_ramp = sorted(passed["ramp"] - passed["default"])
        only_default = sorted(passed["default"] - passed["ramp"])
        n, k = len(only_ramp) + len(only_default), len(only_ramp)
        # one-sided sign test: the chance of k or more of n discordant pairs going the ramp's way under no difference
        p = sum(comb(n, i) for i in range(k, n + 1)) / 2**n if n else 1.0
        print(
            f"  {reading}: only the ramp at {THRESHOLD:g}+ on {only_ramp}, only the default on {only_default}; "
            f"one-sided sign test p = {p:.3f}"
        )


arms = {arm: rows(arm) for arm in SOURCES}
both = sorted(set(arms["default"]) & set(arms["ramp"]))
tally("round 31", [s for s in both if 33 <= s <= 40], arms)
tally("every fresh seed", both, arms)
# Seeds 25-40 only: neither reported (0-4) nor run by a round that chose a config; the ramp's adoption as the
# default (bench/results/cartpole_default_ramp/DECISION.md) rests on these.
tally("seeds 25-40", [s for s in both if 25 <= s <= 40], arms)
