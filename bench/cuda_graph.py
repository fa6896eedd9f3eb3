"""Updates/s of SAC on a GPU with and without the CUDA graph (``sac_config.cuda_graph``), same run.

Run on a machine with CUDA: ``python -m bench.cuda_graph [--rounds 5] [--updates 300] [--out FILE]``.
HalfCheetah-v5 dimensions (obs 17, action 6), 256x256, batch 256, one-step windows, PER weights on (the
batches of bench/learner.py). Two SACs with the same seed take the same batches, round by round
alternately (machine noise hits both alike); reported: the median updates/s of each and their ratio,
per compute dtype, and the largest difference between the two SACs' weights after all the updates
(the graph should compute what eager updates compute: float rounding only).
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.sac.learner import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from bench.learner import ACT, HIDDEN, OBS, make_batch
from bench.rows import append_row

SPEC = EnvSpec((SensorSpec("obs", (OBS,)),), ActionSpec((), ACT, (-1.0,) * ACT, (1.0,) * ACT))
FIELDS = ["compute_dtype", "eager_updates_per_s", "graph_updates_per_s", "ratio", "max_weight_difference", "device"]


def build(graph: bool, dtype: str) -> SAC:
    sac = SacConfig(seed=0, use_priority=True, cuda_graph=graph, compute_dtype=dtype)
    return SAC(SPEC, sac, NNConfig(hidden_units=[HIDDEN, HIDDEN]), ReplayConfig(), device="cuda")


def rate(sac: SAC, batches: list, updates: int) -> float:
    torch.cuda.synchronize()
    start = time.perf_counter()
    for i in range(updates):
        sac.update(batches[i % len(batches)])  # td_abs comes back to the host: one sync per update, as in a learner
    torch.cuda.synchronize()
    return updates / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--updates", type=int, default=300, help="updates per contender per round")
    parser.add_argument("--out", type=Path, default=None, help="append one row per compute dtype to this CSV")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("bench.cuda_graph needs a CUDA device")
    rng = np.random.default_rng(0)
    batches = [make_batch(rng) for _ in range(16)]
    print(f"{torch.cuda.get_device_name()}, torch {torch.__version__}")
    print(f"{'compute_dtype':>14} {'eager upd/s':>12} {'graph upd/s':>12} {'ratio':>7} {'max |w diff|':>13}")
    for dtype in ("float32", "auto"):
        eager, graphed = build(False, dtype), build(True, dtype)
        for sac in (eager, graphed):  # warm-up (and the graph's recording) outside the timing
            rate(sac, batches, 20)
        rates: dict[str, list[float]] = {"eager": [], "graph": []}
        for _ in range(args.rounds):
            rates["eager"].append(rate(eager, batches, args.updates))
            rates["graph"].append(rate(graphed, batches, args.updates))
        e, g = statistics.median(rates["eager"]), statistics.median(rates["graph"])
        diff = max(
            float((a - b).abs().max())
            for a, b in zip(eager.models.state_dict().values(), graphed.models.state_dict().values(), strict=True)
            if a.is_floating_point()
        )
        print(f"{dtype:>14} {e:12.1f} {g:12.1f} {g / e:6.2f}x {diff:13.2e}")
        if args.out:
            row = {"compute_dtype": dtype, "eager_updates_per_s": f"{e:.1f}", "graph_updates_per_s": f"{g:.1f}",
                   "ratio": f"{g / e:.2f}", "max_weight_difference": f"{diff:.2e}",
                   "device": torch.cuda.get_device_name()}  # fmt: skip
            append_row(args.out, FIELDS, row)


if __name__ == "__main__":
    main()
