"""sac_config.tanh_log_det_epsilon: the learner's losses take the policy's tanh change of variables as
log(1 - tanh(u)^2 + epsilon), as SB3 does with 1e-6; 0 (the default) keeps it exact. Acting is untouched."""

from __future__ import annotations

import math
from typing import Any

import pytest
import torch

from algorithm.nn.models import squashed_gaussian_log_prob
from algorithm.sac.learner import SAC
from tests.algorithm.sac.test_learner import make_batch, make_sac


def test_the_density_with_epsilon_is_sb3s_formula_exact_inside_and_held_near_log_epsilon_at_the_edge() -> None:
    noise, log_std = torch.randn(32, 3), torch.full((32, 3), -0.3)
    pre_tanh = torch.linspace(-3.0, 3.0, 32)[:, None].expand(32, 3)
    gaussian = (-0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)).sum(-1)
    sb3 = gaussian - torch.log(1 - torch.tanh(pre_tanh).pow(2) + 1e-6).sum(-1)
    torch.testing.assert_close(squashed_gaussian_log_prob(noise, log_std, pre_tanh, 1e-6), sb3)
    torch.testing.assert_close(squashed_gaussian_log_prob(noise, log_std, pre_tanh), sb3, rtol=1e-4, atol=2e-3)
    edge = torch.full((1, 1), 12.0)  # 1 - tanh^2 = 1.5e-10 there
    zeros = torch.zeros(1, 1)
    log_det_sb3 = -float(squashed_gaussian_log_prob(zeros, zeros, edge, 1e-6)) - 0.5 * math.log(2 * math.pi)
    log_det_exact = -float(squashed_gaussian_log_prob(zeros, zeros, edge)) - 0.5 * math.log(2 * math.pi)
    assert log_det_sb3 == pytest.approx(math.log(1e-6), abs=1e-3)
    assert log_det_exact == pytest.approx(math.log(4) - 24.0, abs=1e-3)


def saturated_pair(push: float, **config: Any) -> tuple[SAC, SAC]:
    """Two learners with the same weights, exact and SB3's epsilon, their policy means pushed to ``push``."""
    exact = make_sac(use_priority=False, **config)
    sb3 = make_sac(use_priority=False, tanh_log_det_epsilon=1e-6, **config)
    with torch.no_grad():
        for sac in (exact, sb3):
            assert sac.models.policy is not None
            head = sac.models.policy.head
            head.weight.zero_()
            head.bias.zero_()
            head.bias[: sac.spec.action.continuous_dim] = push
    sb3.load_state_dict(exact.state_dict())
    return exact, sb3


@pytest.mark.parametrize("push, differs", [(0.5, False), (10.0, True)])
def test_the_epsilon_reaches_the_learners_losses_only_where_the_policy_saturates(push: float, differs: bool) -> None:
    exact, sb3 = saturated_pair(push)
    for sac in (exact, sb3):
        sac.update(make_batch(seed=3))
    assert exact.models.policy is not None and sb3.models.policy is not None
    pairs = zip(exact.models.policy.parameters(), sb3.models.policy.parameters(), strict=True)
    gap = max(float((a - b).detach().abs().max()) for a, b in pairs)
    if differs:  # the exact term pulls the mean back from the edge (~ -2|u|); SB3's is held near log(1e-6)
        assert gap > 1e-4
    else:
        assert gap < 1e-6


@pytest.mark.parametrize("numpy_acting", [False, True])  # torch's acting path and the NumPy copy of the policy
def test_acting_keeps_the_exact_density(numpy_acting: bool) -> None:
    exact, sb3 = saturated_pair(10.0, numpy_acting=numpy_acting)
    state = torch.randn(4, 3)
    for deterministic in (True, False):
        torch.manual_seed(0)
        a = exact.act([state.numpy()], deterministic=deterministic)
        torch.manual_seed(0)
        b = sb3.act([state.numpy()], deterministic=deterministic)
        assert all((x == y).all() for x, y in zip(a[:2], b[:2], strict=True))
