"""sac_config.munchausen_scale: Munchausen RL's reward term (Vieillard et al. 2020) in discrete SAC's target,
``scale * clip(alpha_b log pi_b(a_b|s), floor, 0)`` added to every reward of the window."""

from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from algorithm.config.load import load_config
from algorithm.sac.equations import munchausen_bonus
from algorithm.types import Batch
from tests.algorithm.sac.test_discrete import make_batch, make_sac, masked_spec
from tests.algorithm.sac.test_equations_entropy_penalty import three_step_windows
from tests.algorithm.sac.test_learner import make_sac as make_continuous_sac

SPEC = masked_spec((3,))


def test_the_bonus_is_the_scaled_clipped_tempered_log_probability_averaged_over_branches() -> None:
    taken = torch.tensor([[-0.1, -3.0], [0.0, -0.5]])
    alpha = torch.tensor([2.0, 0.5])
    # row 0: 2 x -0.1 = -0.2 and 0.5 x -3 = -1.5, clipped to -1; row 1: 0 and -0.25
    expected = 0.9 * torch.tensor([(-0.2 - 1.0) / 2, (0.0 - 0.25) / 2])
    torch.testing.assert_close(munchausen_bonus(taken, alpha, 0.9, -1.0), expected)
    assert float(munchausen_bonus(taken, alpha, 0.9, -5.0)[0]) == pytest.approx(0.9 * (-0.2 - 1.5) / 2)


def first_metrics(scale: float, batch: Batch, **config: Any) -> dict[str, float]:
    sac = make_sac(SPEC, use_priority=False, munchausen_scale=scale, **config)
    return sac.update(batch, with_metrics=True).metrics


def hand_bonus(batch: Batch, step: int, **config: Any) -> torch.Tensor:
    """``0.9 clip(alpha log pi(a|s), -1, 0)`` of the stored action at window step ``step``, from the
    freshly built learner's policy (the weights the first update's target is computed from)."""
    sac = make_sac(SPEC, use_priority=False, **config)
    masks = torch.as_tensor(batch.obs[0][:, step]) > 0.5
    assert sac.models.discrete_policy is not None
    with torch.no_grad():
        state = sac.models.representation([torch.as_tensor(o[:, step]) for o in batch.obs])
        log_probs = sac.models.discrete_policy(sac.models.representation.policy_state(state), masks)
    taken = (log_probs * torch.as_tensor(batch.actions[:, step])).sum(dim=-1)
    return 0.9 * (math.exp(sac.log_alpha_discrete.item()) * taken).clamp(-1.0, 0.0)


def test_the_target_gains_the_bonus_of_the_stored_action_under_the_current_policy() -> None:
    batch = make_batch(SPEC, b=32, seed=4)
    hand = hand_bonus(batch, 0)
    off, on = first_metrics(0.0, batch), first_metrics(0.9, batch)
    assert "learner/munchausen_bonus" not in off
    assert on["learner/munchausen_bonus"] == pytest.approx(float(hand.mean()), rel=1e-4)
    assert float(hand.mean()) < -0.05  # the check can tell the bonus from none
    # one-step windows: the target moves by exactly the bonus of step 0
    assert on["learner/target_mean"] - off["learner/target_mean"] == pytest.approx(float(hand.mean()), abs=1e-5)


def test_in_an_n_step_window_every_steps_bonus_enters_discounted() -> None:
    """Each reward of the n-step sum carries the bonus of its own step's state and action, weighted
    gamma^k like the reward (the bootstrap value is the same with and without)."""
    batch = three_step_windows(0.0, 0.0)
    gamma = 0.99
    hand = torch.stack([gamma**k * hand_bonus(batch, k, n_step=3) for k in range(3)]).sum(dim=0)
    off, on = first_metrics(0.0, batch, n_step=3), first_metrics(0.9, batch, n_step=3)
    assert float((hand - hand_bonus(batch, 0, n_step=3)).mean()) < -0.05  # steps 1 and 2 count for something
    assert on["learner/target_mean"] - off["learner/target_mean"] == pytest.approx(float(hand.mean()), abs=1e-4)


def one_state_bandit(n: int = 64) -> Batch:
    """Every row the same state and all three actions allowed; action 0 pays 1, the others 0; every step
    ends the episode, so the targets are the rewards plus the bonus."""
    batch = make_batch(SPEC, b=n, seed=1)
    actions = np.zeros_like(batch.actions)
    actions[np.arange(n), 0, np.arange(n) % 3] = 1.0
    obs = [np.ones_like(batch.obs[0]), np.broadcast_to(batch.obs[1][:1], batch.obs[1].shape).copy()]
    return dataclasses.replace(
        batch, obs=obs, actions=actions, rewards=(actions[:, :, 0] == 1.0).astype(np.float32),
        terminated=np.ones_like(batch.terminated),
    )  # fmt: skip


def action_gap(scale: float) -> float:
    """Q of the paying action minus the best other action's, after training on the bandit with alpha fixed."""
    sac = make_sac(SPEC, use_priority=False, use_auto_alpha=False, init_log_alpha=math.log(0.5),
                   learning_rate=3e-3, munchausen_scale=scale)  # fmt: skip
    batch = one_state_bandit()
    for _ in range(400):
        sac.update(batch)
    with torch.no_grad():
        state = sac.models.representation([torch.as_tensor(o[:1, 0]) for o in batch.obs])
        q = sac.models.q(state, None, None).min(dim=0).values[0]
    return float(q[0] - q[1:].max())


def test_the_bonus_widens_the_action_gap() -> None:
    """Without it the gap is the rewards' 1; with it the unlikely actions' values also carry their clipped
    log-probability, about -0.9 each once the policy prefers action 0 (M-DQN's action-gap effect)."""
    plain, munchausen = action_gap(0.0), action_gap(0.9)
    assert plain == pytest.approx(1.0, abs=0.1)
    assert munchausen > plain + 0.5


@pytest.mark.parametrize("case", ["continuous", "dqn_like", "vtrace"])
def test_a_task_the_bonus_cannot_take_is_refused_naming_the_key(case: str) -> None:
    with pytest.raises(ValueError, match="sac_config.munchausen_scale"):
        if case == "continuous":
            make_continuous_sac(munchausen_scale=0.9)
        elif case == "dqn_like":
            make_sac(SPEC, munchausen_scale=0.9, discrete_dqn_like=True)
        else:
            make_sac(SPEC, munchausen_scale=0.9, use_n_step_is=True, n_step=3)


@pytest.mark.parametrize("value", [1.0, -0.1])
def test_a_scale_outside_zero_to_one_is_refused_naming_the_key(value: float) -> None:
    with pytest.raises(ValueError, match="munchausen_scale"):
        make_sac(SPEC, munchausen_scale=value)


def clipped_term_now(sac: Any, batch: Batch) -> float:
    """``clip(alpha log pi(a|s), -1, 0)`` of the stored actions at step 0 under ``sac``'s current weights,
    averaged over the batch: the bonus at weight 1."""
    masks = torch.as_tensor(batch.obs[0][:, 0]) > 0.5
    with torch.no_grad():
        state = sac.models.representation([torch.as_tensor(o[:, 0]) for o in batch.obs])
        log_probs = sac.models.discrete_policy(sac.models.representation.policy_state(state), masks)
    taken = (log_probs * torch.as_tensor(batch.actions[:, 0])).sum(dim=-1)
    return float((math.exp(sac.log_alpha_discrete.item()) * taken).clamp(-1.0, 0.0).mean())


SCHEDULE = dict(use_priority=False, munchausen_scale=0.9, munchausen_scale_start=0.0, learning_rate_final=1e-4,
                learning_rate_anneal_updates=4)  # fmt: skip


def test_a_scheduled_weight_rises_from_its_start_on_the_step_sizes_schedule() -> None:
    """munchausen_scale_start: update k's targets carry k/4 of the 0.9 weight (0 at first: plain targets),
    the full weight from update 4 on; each update reports the weight it used."""
    sac = make_sac(SPEC, **SCHEDULE)
    batch = make_batch(SPEC, b=32, seed=4)
    weights, bonuses, terms = [], [], []
    for _ in range(6):
        terms.append(clipped_term_now(sac, batch))
        metrics = sac.update(batch, with_metrics=True).metrics
        weights.append(metrics["learner/munchausen_weight"])
        bonuses.append(metrics["learner/munchausen_bonus"])
    assert weights == pytest.approx([0.0, 0.225, 0.45, 0.675, 0.9, 0.9])
    assert bonuses == pytest.approx([w * t for w, t in zip(weights, terms, strict=True)], rel=1e-4, abs=1e-7)
    assert min(terms) < -0.05  # the check can tell a weighted bonus from none


def test_a_resumed_learner_goes_on_with_the_weight_where_it_was() -> None:
    sac = make_sac(SPEC, **SCHEDULE)
    for i in range(3):
        sac.update(make_batch(SPEC, b=32, seed=i))
    resumed = make_sac(SPEC, **SCHEDULE)
    resumed.load_state_dict(copy.deepcopy(sac.state_dict()))
    batch = make_batch(SPEC, b=32, seed=9)
    a, b = sac.update(batch, with_metrics=True), resumed.update(batch, with_metrics=True)
    assert a.metrics["learner/munchausen_weight"] == b.metrics["learner/munchausen_weight"] == pytest.approx(0.675)
    np.testing.assert_array_equal(a.td_abs, b.td_abs)


@pytest.mark.parametrize("missing", ["learning_rate_final", "munchausen_scale"])
def test_a_schedule_without_the_step_size_schedule_or_a_weight_is_refused_naming_both(missing: str) -> None:
    cartpole = Path(__file__).resolve().parents[3] / "envs" / "gym" / "cartpole"
    overrides = [f"sac.munchausen_scale={0 if missing == 'munchausen_scale' else 0.9}", "sac.munchausen_scale_start=0"]
    if missing == "learning_rate_final":
        overrides.append("sac.learning_rate_final=null")
    with pytest.raises(ValueError, match=r"munchausen_scale_start .*learning_rate_final set and munchausen_scale > 0"):
        load_config(cartpole, None, overrides)
    valid = load_config(cartpole, None, ["sac.munchausen_scale=0.9", "sac.munchausen_scale_start=0"]).config
    assert valid.sac_config.munchausen_scale_start == 0.0  # the task anneals its step size: the schedule loads
