"""Prediction models (``sac_config.use_prediction``): auxiliary tasks that shape the representation.

From the state ``s = rep(o)`` and action ``a``: a transition model predicts a Gaussian over the
next state (the target representation's, as a fixed regression target), a reward model predicts
``r``, and an observation model reconstructs the vector observations (with ``use_extra_data``
also the privileged ``critic_only`` sensors, which the representation may not see directly in
the policy's part). Their losses train the models; each loss's gradient reaches the
representation only when its cosine with the Q loss's gradient there is positive (the gradient
similarity test of Du et al. 2018, arXiv:1812.02224), so an auxiliary task never pulls the
representation against the critic. :meth:`algorithm.sac.learner.SAC.update` applies the gate.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from algorithm.nn.layers import mlp
from algorithm.spaces import ACTION_MASK_SENSOR, SensorSpec

_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


def _head(in_features: int, hidden_units: Sequence[int], out_features: int) -> nn.Sequential:
    return nn.Sequential(*mlp(in_features, hidden_units, "relu"), nn.Linear(hidden_units[-1], out_features))


class PredictionModels(nn.Module):
    """Transition ``p(s'|s, a)`` (diagonal Gaussian), reward ``r(s, a)`` and observation ``o(s)`` models."""

    def __init__(self, state_dim: int, action_dim: int, observation_dim: int, hidden_units: Sequence[int]) -> None:
        super().__init__()
        self.transition = _head(state_dim + action_dim, hidden_units, 2 * state_dim)
        self.reward = _head(state_dim + action_dim, hidden_units, 1)
        self.observation = _head(state_dim, hidden_units, observation_dim) if observation_dim else None


def observation_targets(sensors: Sequence[SensorSpec], critic_only: Sequence[str], use_extra_data: bool) -> list[int]:
    """Indices of the sensors the observation model reconstructs: vector sensors (not images, not
    the action mask), the privileged ``critic_only`` ones only with ``use_extra_data``."""
    return [
        i
        for i, s in enumerate(sensors)
        if not s.is_image and s.name != ACTION_MASK_SENSOR and (use_extra_data or s.name not in critic_only)
    ]


def prediction_losses(
    models: PredictionModels,
    state: Tensor,
    action: Tensor,
    next_state: Tensor,
    reward: Tensor,
    observation: Tensor | None,
    transition_kl: float,
) -> dict[str, Tensor]:
    """Scalar losses, batch means: ``transition`` = Gaussian NLL of ``next_state`` (held fixed) plus
    ``transition_kl`` times ``KL(N(mu, sigma) || N(0, I))``, which keeps the predicted distribution
    from shrinking onto the targets; ``reward`` and ``observation`` = half squared errors."""
    x = torch.cat([state, action], dim=-1)
    mean, log_std = models.transition(x).chunk(2, dim=-1)
    log_std = log_std.clamp(-5.0, 2.0)
    target = next_state.detach()
    nll = (0.5 * ((target - mean) * torch.exp(-log_std)).pow(2) + log_std + _HALF_LOG_2PI).sum(-1)
    kl = 0.5 * (mean.pow(2) + torch.exp(2 * log_std) - 1.0 - 2 * log_std).sum(-1)
    losses = {
        "transition": (nll + transition_kl * kl).mean(),
        "reward": 0.5 * (models.reward(x).squeeze(-1) - reward).pow(2).mean(),
    }
    if models.observation is not None and observation is not None:
        losses["observation"] = 0.5 * (models.observation(state) - observation).pow(2).sum(-1).mean()
    return losses


def gated_gradients(
    losses: dict[str, Tensor], critic_grads: Sequence[Tensor], params: Sequence[Tensor]
) -> tuple[list[Tensor], dict[str, Tensor]]:
    """The sum over ``losses`` of each loss's gradient on ``params`` (the representation's), each
    kept only where its cosine with ``critic_grads`` is positive; also each cosine (no host sync)."""
    total = [torch.zeros_like(p) for p in params]
    critic = torch.cat([g.flatten() for g in critic_grads])
    cosines = {}
    for name, loss in losses.items():
        raw = torch.autograd.grad(loss, list(params), retain_graph=True, allow_unused=True)
        grads = [torch.zeros_like(p) if g is None else g for g, p in zip(raw, params, strict=True)]
        flat = torch.cat([g.flatten() for g in grads])
        cosine = torch.nn.functional.cosine_similarity(flat, critic, dim=0)
        keep = (cosine > 0).to(flat.dtype)
        total = [t + keep * g for t, g in zip(total, grads, strict=True)]
        cosines[name] = cosine.detach()
    return total, cosines
