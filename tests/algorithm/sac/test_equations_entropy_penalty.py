"""sac_config.discrete_entropy_penalty: SD-SAC's penalty (Zhou et al. 2022) on the distance between each
state's policy entropy and the entropy of the policy that acted there, estimated from the stored
behaviour log-probability."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
import torch

from algorithm.sac.equations import entropy_penalty
from tests.algorithm.sac.test_discrete import make_batch, make_sac, masked_spec
from tests.algorithm.sac.test_learner import make_sac as make_continuous_sac

SPEC = masked_spec((3,))


def test_the_stored_actions_log_probability_gives_the_penaltys_gradient_in_expectation() -> None:
    mu = torch.tensor([0.6, 0.3, 0.1], dtype=torch.float64)
    h_mu = float(-(mu * mu.log()).sum())
    entropy = torch.tensor([0.4], dtype=torch.float64, requires_grad=True)
    expected = sum(p * entropy_penalty(entropy, -torch.log(p).view(1)) for p in mu)  # over a ~ mu
    (grad,) = torch.autograd.grad(expected, entropy)
    torch.testing.assert_close(grad, 2 * (entropy.detach() - h_mu))


def behaviour(batch: Any, logp: float) -> Any:
    return dataclasses.replace(batch, behaviour_logp=np.full_like(batch.behaviour_logp, logp))


def trained_entropy(penalty: float, logp: float) -> float:
    """The policy's mean entropy on the batch after 60 updates with the behaviour's entropy estimate
    ``-logp`` on every row, the temperature fixed and small (so only Q and the penalty shape it)."""
    sac = make_sac(SPEC, use_priority=False, use_auto_alpha=False, init_log_alpha=-6.0,
                   learning_rate=3e-3, discrete_entropy_penalty=penalty)  # fmt: skip
    batch = behaviour(make_batch(SPEC, b=32, seed=5), logp)
    for _ in range(60):
        metrics = sac.update(batch, with_metrics=True).metrics
    assert ("learner/entropy_penalty" in metrics) == (penalty > 0)
    return metrics["learner/entropy_discrete"]


def test_the_penalty_pulls_the_policys_entropy_toward_the_behaviours() -> None:
    free = trained_entropy(0.0, 0.0)
    assert trained_entropy(5.0, math.log(1 / 3)) > free + 0.05  # a uniform behaviour: entropy log 3
    assert trained_entropy(5.0, 0.0) < free - 0.05  # a deterministic behaviour: entropy 0


def three_step_windows(first: float, later: float) -> Any:
    """make_batch's windows stretched to 3 steps (every action allowed, every step valid), the behaviour's
    log-probability ``first`` at the trained step (position 0) and ``later`` at the bootstrap steps."""
    one = make_batch(SPEC, b=32, seed=5)
    b, size = one.actions.shape[0], one.actions.shape[-1]
    masks = np.ones((b, 4, one.obs[0].shape[-1]), np.float32)
    logp = np.full((b, 3), later, np.float32)
    logp[:, 0] = first
    return dataclasses.replace(
        one, obs=[masks, one.obs[1][:, [0, 1, 1, 1]]], actions=np.repeat(one.actions, 3, axis=1),
        prev_actions=np.zeros((b, 3, size), np.float32), rewards=np.repeat(one.rewards, 3, axis=1),
        terminated=np.zeros((b, 3), bool), truncated=np.zeros((b, 3), bool), behaviour_logp=logp,
        mask=np.ones((b, 3), bool),
    )  # fmt: skip


def trained_entropy_on_windows(penalty: float, first: float, later: float) -> float:
    sac = make_sac(SPEC, use_priority=False, use_auto_alpha=False, init_log_alpha=-6.0, learning_rate=3e-3,
                   discrete_entropy_penalty=penalty, n_step=3)  # fmt: skip
    batch = three_step_windows(first, later)
    for _ in range(60):
        metrics = sac.update(batch, with_metrics=True).metrics
    return metrics["learner/entropy_discrete"]


def test_in_an_n_step_window_the_penalty_takes_the_behaviour_of_the_trained_step() -> None:
    """The policy is trained on position 0's state, so the acting entropy there is position 0's estimate;
    the bootstrap steps' log-probabilities (another state each) must not enter."""
    free = trained_entropy_on_windows(0.0, 0.0, 0.0)
    uniform = math.log(1 / 3)
    assert trained_entropy_on_windows(5.0, uniform, 0.0) > free + 0.05
    assert trained_entropy_on_windows(5.0, 0.0, uniform) < free - 0.05


def policy_grads(penalty: float) -> list[torch.Tensor]:
    sac = make_sac(SPEC, use_priority=False, discrete_entropy_penalty=penalty)
    rng = np.random.default_rng(1)
    batch = make_batch(SPEC, seed=2)
    logp = np.log(rng.uniform(0.1, 0.9, batch.behaviour_logp.shape)).astype(np.float32)
    batch = dataclasses.replace(batch, behaviour_logp=logp)
    sac.policy_optimizer.step = lambda *a, **k: None  # keep the gradients of one pass, weights unchanged
    sac.update(batch)
    return [p.grad.clone() for p in sac._policy_params]


def test_the_penalty_enters_the_policys_gradient_scaled_by_its_weight_and_nothing_else() -> None:
    g0, g1, g2 = policy_grads(0.0), policy_grads(0.5), policy_grads(1.0)
    for a, b, c in zip(g0, g1, g2, strict=True):
        torch.testing.assert_close(c - a, 2 * (b - a), rtol=1e-4, atol=1e-6)
    assert max(float((b - a).abs().max()) for a, b in zip(g0, g1, strict=True)) > 1e-5


@pytest.mark.parametrize("case", ["continuous", "dqn_like"])
def test_a_task_the_penalty_cannot_take_is_refused_naming_the_key(case: str) -> None:
    with pytest.raises(ValueError, match="sac_config.discrete_entropy_penalty"):
        if case == "continuous":
            make_continuous_sac(discrete_entropy_penalty=0.5)
        else:
            make_sac(SPEC, discrete_entropy_penalty=0.5, discrete_dqn_like=True)
