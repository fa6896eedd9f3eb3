"""Updates/s of the recurrent and image learner paths, so later work can see regressions.

Run: ``.venv/bin/python -m bench.learner_paths [--quick]``. Measured in the same run and printed
beside the plain vector update (HalfCheetah dims, 256x256, batch 256) as a reference:

- recurrent: GRU 64 units, burn-in 20 + n-step 5 (windows of 25 steps), sequence batch 64;
- image: one 84x84x3 uint8 sensor through the Nature-DQN conv encoder, batch 256, 1-step windows.

Batches are random (contents do not change the cost). One torch thread; median of rounds.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig  # noqa: E402
from algorithm.sac.learner import SAC  # noqa: E402
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec  # noqa: E402
from algorithm.types import Batch  # noqa: E402

ACT = 6


def random_batch(rng: np.random.Generator, spec: EnvSpec, b: int, length: int, rnn: int = 0) -> Batch:
    obs = []
    for s in spec.sensors:
        shape = (b, length + 1, *s.shape)
        obs.append(
            rng.integers(0, 256, shape, dtype=np.uint8) if s.is_image else rng.standard_normal(shape, np.float32)
        )
    return Batch(
        keys=np.arange(b, dtype=np.uint64),
        probabilities=np.full(b, 1e-5),
        table_size=100_000,
        obs=obs,
        actions=rng.uniform(-1, 1, (b, length, ACT)).astype(np.float32),
        prev_actions=rng.uniform(-1, 1, (b, length, ACT)).astype(np.float32),
        rewards=rng.standard_normal((b, length), np.float32),
        terminated=np.zeros((b, length), bool),
        truncated=np.zeros((b, length), bool),
        behaviour_logp=np.zeros((b, length), np.float32),
        mask=np.ones((b, length), bool),
        rnn_state=rng.standard_normal((b, rnn), np.float32) if rnn else None,
    )


def rate(sac: SAC, batches: list[Batch], updates: int) -> float:
    start = time.perf_counter()
    for i in range(updates):
        sac.update(batches[i % len(batches)])
    return updates / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer rounds and updates (smoke run)")
    args = parser.parse_args()
    rounds, updates = (2, 5) if args.quick else (5, 20)
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    action = ActionSpec((), ACT, (-1.0,) * ACT, (1.0,) * ACT)
    vector = EnvSpec((SensorSpec("obs", (17,)),), action)
    image = EnvSpec((SensorSpec("pixels", (84, 84, 3), np.dtype(np.uint8)),), action)
    cases = {
        "vector 256x256, batch 256": (
            SAC(vector, SacConfig(seed=0), NNConfig(), ReplayConfig()),
            [random_batch(rng, vector, 256, 1) for _ in range(4)],
        ),
        "GRU 64, burn-in 20 + n-step 5, batch 64": (
            SAC(
                vector,
                SacConfig(seed=0, use_rnn=True, burn_in_step=20, n_step=5),
                NNConfig(rnn_units=64),
                ReplayConfig(),
            ),  # fmt: skip
            [random_batch(rng, vector, 64, 25, rnn=64) for _ in range(4)],
        ),
        "image 84x84x3 (Nature CNN), batch 256": (
            SAC(image, SacConfig(seed=0), NNConfig(), ReplayConfig()),
            [random_batch(rng, image, 256, 1) for _ in range(2)],
        ),
    }
    results = {}
    for name, (sac, batches) in cases.items():
        rate(sac, batches, 2)  # warm-up
        results[name] = statistics.median(rate(sac, batches, updates) for _ in range(rounds))
    reference = results["vector 256x256, batch 256"]
    print(f"SAC updates/s, 1 torch thread, median of {rounds} rounds x {updates} updates")
    print("| path | updates/s | vs vector |\n|---|---|---|")
    for name, value in results.items():
        print(f"| {name} | {value:.1f} | {value / reference:.2f}x |")


if __name__ == "__main__":
    main()
