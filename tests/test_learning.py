"""Learning on a real task with fixed seeds: the default Pendulum-v1 config must reach a mean
deterministic return >= -250 (10 episodes) within 10,000 env steps for each seed."""

from __future__ import annotations

from pathlib import Path

import pytest

from algorithm.config import load_config
from algorithm.evaluation import read_evaluations
from algorithm.trainer import EmbeddedTrainer
from envs.make import vector_env_factory

ROOT = Path(__file__).resolve().parents[1]
THRESHOLD = -250.0
BUDGET = 10_000


@pytest.mark.slow
@pytest.mark.learning
@pytest.mark.parametrize("seed", [0, 1])
def test_pendulum_learns_within_10k_steps(seed: int, tmp_path: Path) -> None:
    config = load_config(ROOT / "envs/gym/pendulum", None,
                         [f"sac.seed={seed}", f"base.max_step={BUDGET}", "eval.eval_per_step=500"]).config
    trainer = EmbeddedTrainer(config, tmp_path, vector_env_factory(config.base_config.build_path), progress=False)
    while trainer.env_steps < BUDGET:
        trainer.run(until_step=trainer.env_steps + 500)  # stop as soon as an evaluation passes
        if trainer.last_eval_mean is not None and trainer.last_eval_mean >= THRESHOLD:
            break
    rows = read_evaluations(tmp_path / "evaluations.csv")
    best = max(rows, key=lambda r: r["return_mean"])
    assert best["return_mean"] >= THRESHOLD, f"seed {seed}: best {best} of {len(rows)} evaluations"
    assert best["env_steps"] <= BUDGET
