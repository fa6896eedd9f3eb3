"""Learning on a real task with fixed seeds: the default Pendulum-v1 config must reach a mean
deterministic return >= -250 (10 episodes) within 10,000 env steps for each seed."""

from __future__ import annotations

from pathlib import Path

import pytest

from algorithm.config.load import load_config
from algorithm.run.evaluation import read_evaluations
from algorithm.run.trainer import EmbeddedTrainer
from envs.make import vector_env_factory

ROOT = Path(__file__).resolve().parents[1]
THRESHOLD = -250.0
BUDGET = 10_000


@pytest.mark.slow
@pytest.mark.learning
@pytest.mark.parametrize("seed", [0, 1])
def test_pendulum_learns_within_10k_steps(seed: int, tmp_path: Path) -> None:
    config = load_config(
        ROOT / "envs/gym/pendulum", None, [f"sac.seed={seed}", f"base.max_step={BUDGET}", "eval.eval_per_step=500"]
    ).config
    trainer = EmbeddedTrainer(config, tmp_path, vector_env_factory(config.base_config.build_path), progress=False)
    while trainer.env_steps < BUDGET:
        trainer.run(until_step=trainer.env_steps + 500)  # stop as soon as an evaluation passes
        if trainer.last_eval_mean is not None and trainer.last_eval_mean >= THRESHOLD:
            break
    rows = read_evaluations(tmp_path / "evaluations.csv")
    best = max(rows, key=lambda r: r["return_mean"])
    assert best["return_mean"] >= THRESHOLD, f"seed {seed}: best {best} of {len(rows)} evaluations"
    assert best["env_steps"] <= BUDGET


def train_until(
    task: str, seed: int, budget: int, threshold: float, run_dir: Path, every: int = 500
) -> EmbeddedTrainer:
    """Train ``task``'s default config, evaluating every ``every`` steps, until an evaluation reaches
    ``threshold`` or ``budget`` env steps pass; returns the trainer (paused, not closed)."""
    overrides = [f"sac.seed={seed}", f"base.max_step={budget}", f"eval.eval_per_step={every}"]
    config = load_config(ROOT / "envs" / task, None, overrides).config
    trainer = EmbeddedTrainer(config, run_dir, vector_env_factory(config.base_config.build_path), progress=False)
    while trainer.env_steps < budget:
        trainer.run(until_step=trainer.env_steps + every)
        if trainer.last_eval_mean is not None and trainer.last_eval_mean >= threshold:
            break
    return trainer


@pytest.mark.slow
@pytest.mark.learning
def test_masked_grid_is_solved_and_no_masked_action_is_ever_taken(tmp_path: Path) -> None:
    """Masked actions end the episode with -10; the optimum is +8 (random, mask-respecting: +1.3)."""
    taken_masked = 0

    def count(chunk):  # noqa: ANN001, ANN202
        nonlocal taken_masked
        mask, chosen = chunk.obs[0][:-1], chunk.actions > 0.5  # sensors sorted: action_mask first
        taken_masked += int((chosen & (mask < 0.5)).sum())
        return insert(chunk)

    config = load_config(ROOT / "envs/toy/masked_grid", None, ["sac.seed=0", "eval.eval_per_step=500"]).config
    trainer = EmbeddedTrainer(config, tmp_path, vector_env_factory(config.base_config.build_path), progress=False)
    insert = trainer.actor.sink
    trainer.actor.sink = count
    while trainer.env_steps < 3000 and (trainer.last_eval_mean or -100) < 7.5:
        trainer.run(until_step=trainer.env_steps + 500)
    assert trainer.last_eval_mean is not None and trainer.last_eval_mean >= 7.5, trainer.last_eval_mean
    assert trainer.env_steps > 0 and taken_masked == 0


@pytest.mark.slow
@pytest.mark.learning
def test_mixed_discrete_and_continuous_actions_are_learned(tmp_path: Path) -> None:
    """One discrete choice and a continuous magnitude per step: optimum 10, random 1.4."""
    trainer = train_until("toy/mixed_target", 0, 3000, 9.0, tmp_path)
    assert trainer.last_eval_mean is not None and trainer.last_eval_mean >= 9.0, trainer.last_eval_mean
