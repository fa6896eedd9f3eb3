"""Plain SAC on one page (algorithm/sac/losses.py): with no feature on, the losses are the textbook
step (Haarnoja et al. 2018) written out here by hand from the models, and each feature the config
turns on is a transform the step is composed with (algorithm/sac/features.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from algorithm.sac.features import (
    ClippedCritic,
    CuriosityBonus,
    DiscreteEntropyPenalty,
    MunchausenTerm,
    NStepTarget,
    VTraceTarget,
)
from algorithm.sac.window import PassInputs
from tests.algorithm.sac.test_learner import ACT, make_batch, make_sac


def test_plain_sac_computes_the_textbook_losses() -> None:
    """y = r + gamma (1 - d) (min_i Qbar_i(s', a') - alpha log pi(a'|s')), a' ~ pi(s'); critic
    sum_i 1/2 (Q_i(s, a) - y)^2; policy alpha log pi(a~|s) - min_i Q_i(s, a~); temperature
    -log alpha (log pi(a~|s) + H_target); |TD| the mean over heads of |Q_i(s, a) - y|."""
    sac = make_sac()
    features = sac.losses.features
    assert features.rewards == [] and features.policy_terms == [] and isinstance(features.target, NStepTarget)
    assert features.clipped_critic is None and features.predictions is None
    with torch.no_grad():  # targets that differ from the online networks, as after training
        for p in sac.target_q.parameters():
            p.add_(0.1 * torch.randn_like(p))
    b = 8
    terminated = np.zeros((b, 1), dtype=bool)
    terminated[::3] = True
    batch = make_batch(b=b, terminated=terminated)
    noise = torch.randn(b, 2, ACT, generator=torch.Generator().manual_seed(3))
    host = sac._pass_inputs(batch, None, noise, None, None)
    losses = sac.losses(
        PassInputs.from_flat([torch.from_numpy(x) if isinstance(x, np.ndarray) else x for x in host], 1)
    )

    models, eps, gamma = sac.models, sac.sac.tanh_log_det_epsilon, sac.sac.gamma
    obs = torch.from_numpy(batch.obs[0])
    action, reward = torch.from_numpy(batch.actions[:, 0]), torch.from_numpy(batch.rewards[:, 0])
    alpha = sac.log_alpha.detach().exp()
    assert models.policy is not None
    with torch.no_grad():
        next_state = models.representation([obs[:, 1]])
        next_action, next_log_prob = models.policy.sample(next_state, noise[:, 1], eps)
        next_q = sac.target_q(sac.target_representation([obs[:, 1]]), next_action).min(dim=0).values
        y = reward + gamma * (1.0 - torch.from_numpy(terminated[:, 0]).float()) * (next_q - alpha * next_log_prob)
        state = models.representation([obs[:, 0]])
        q = models.q(state, action)
        new_action, log_prob = models.policy.sample(state, noise[:, 0], eps)
        policy = (alpha * log_prob - models.q(state, new_action).min(dim=0).values).mean()
        temperature = -(sac.log_alpha * (log_prob + sac.target_entropy)).mean()

    torch.testing.assert_close(losses.q, (0.5 * (q - y).square().sum(dim=0)).mean())
    torch.testing.assert_close(losses.td_abs, (q - y).abs().mean(dim=0))
    torch.testing.assert_close(losses.policy, policy)
    torch.testing.assert_close(losses.alpha, temperature)
    torch.testing.assert_close(losses.metrics["learner/next_value"], next_q - alpha * next_log_prob)
    assert float(losses.auxiliary) == 0.0 and losses.predictions == {}


@pytest.mark.parametrize(
    ("config", "feature"),
    [
        ({"use_n_step_is": True, "n_step": 3}, VTraceTarget),
        ({"clip_epsilon": 0.2}, ClippedCritic),
    ],
    ids=["vtrace", "clipping"],
)
def test_a_feature_is_a_transform_the_step_is_composed_with(config: dict[str, object], feature: type) -> None:
    features = make_sac(**config).losses.features
    chosen = [features.target, features.clipped_critic, *features.rewards, *features.policy_terms]
    assert any(isinstance(t, feature) for t in chosen), chosen
    assert not any(isinstance(t, CuriosityBonus | MunchausenTerm | DiscreteEntropyPenalty) for t in chosen)
