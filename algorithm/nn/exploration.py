"""Exploration models: curiosity (forward and inverse dynamics) and random network distillation.

Curiosity (``sac_config.use_curiosity``; Pathak et al. 2017, arXiv:1705.05363): a forward model
``F(phi(s), a)`` predicts ``phi(s')`` and its squared error, scaled by ``curiosity_strength``,
is an intrinsic reward added to the Q targets only (stored rewards never change). ``phi`` is
the learner's (detached) state; with ``curiosity_inverse`` it is a small feature network
trained by an inverse model ``I(phi(s), phi(s')) -> a``, which keeps in ``phi`` only what the
agent's actions can influence (the ICM of the paper).

RND (``sac_config.use_rnd``; Burda et al. 2018, arXiv:1810.12894, applied to state-action pairs
as the revived system did): a frozen random network ``f*(s, a)`` and a predictor ``f(s, a)``
trained on replayed pairs; ``||f - f*||^2`` is high for pairs seldom seen. At acting time the
policy draws ``rnd_n_sample`` actions per env and takes the most novel one (the revived system's
use); with ``rnd_strength`` > 0 the novelty, scaled, is also an intrinsic reward added to the Q
targets only (the paper's use), which fades as the pairs become familiar. With ``rnd_normalize``
the bonus is ``rnd_strength x (novelty / m - 1)``, ``m`` a running mean of the replayed pairs'
novelty: its scale no longer depends on how far the predictor has come (the paper divides by a
running deviation of the intrinsic return; here targets are formed at learning time from replay,
and a per-pair mean is the simpler scale), and it is zero on average, so pairs newer than the rest
are rewarded and the familiar ones cost a little. An uncentred positive bonus would pay an agent
for every step it does not end its episode, which on a goal task (MountainCar) is a pay for not
reaching the goal; the paper avoids that with a non-episodic intrinsic value head instead.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from algorithm.nn.layers import mlp


def _net(in_features: int, hidden_units: Sequence[int], out_features: int) -> nn.Sequential:
    trunk = mlp(in_features, hidden_units, "relu")
    return nn.Sequential(*trunk, nn.Linear(hidden_units[-1] if hidden_units else in_features, out_features))


class Curiosity(nn.Module):
    """Forward model over features ``phi(s)``; with ``inverse``, ``phi`` is learned by an inverse model."""

    def __init__(
        self, state_dim: int, action_dim: int, hidden_units: Sequence[int], inverse: bool, feature_dim: int = 32
    ) -> None:
        super().__init__()
        self.inverse = inverse
        self.features = _net(state_dim, hidden_units, feature_dim) if inverse else nn.Identity()
        phi_dim = feature_dim if inverse else state_dim
        self.forward_model = _net(phi_dim + action_dim, hidden_units, phi_dim)
        self.inverse_model = _net(2 * phi_dim, hidden_units, action_dim) if inverse else None

    def errors(self, state: Tensor, action: Tensor, next_state: Tensor) -> tuple[Tensor, Tensor]:
        """``(forward error [N], inverse error [N])``, each ``0.5 ||.||^2`` summed over features; the
        inverse error is 0 without ``inverse``. States should come in detached."""
        phi, next_phi = self.features(state), self.features(next_state)
        # The forward model must not move phi toward easy predictions (the collapse the paper warns
        # of): phi learns from the inverse model only.
        predicted = self.forward_model(torch.cat([phi.detach(), action], dim=-1))
        forward_error = 0.5 * (predicted - next_phi.detach()).pow(2).sum(dim=-1)
        if self.inverse_model is None:
            return forward_error, torch.zeros_like(forward_error)
        guessed = self.inverse_model(torch.cat([phi, next_phi], dim=-1))
        return forward_error, 0.5 * (guessed - action).pow(2).sum(dim=-1)


class RandomNetworkDistillation(nn.Module):
    """``novelty(s, a) = ||f(s, a) - f*(s, a)||^2 / 2`` with ``f*`` random and frozen (its weights are
    still in ``state_dict``, so a checkpoint restores the same target)."""

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        hidden_units: Sequence[int],
        out_features: int = 32,
        normalize: bool = False,
    ) -> None:
        super().__init__()
        self.target = _net(state_dim + action_dim, hidden_units, out_features).requires_grad_(False)
        self.predictor = _net(state_dim + action_dim, hidden_units, out_features)
        if normalize:  # only then, so that checkpoints of runs without it keep their keys
            self.register_buffer("novelty_mean", torch.zeros(()))

    def novelty(self, state: Tensor, action: Tensor) -> Tensor:
        x = torch.cat([state, action], dim=-1)
        return 0.5 * (self.predictor(x) - self.target(x)).pow(2).sum(dim=-1)

    def relative(self, novelty: Tensor, counted: Tensor, momentum: float = 0.01) -> Tensor:
        """``novelty / m - 1`` for replayed pairs, ``m`` the running mean of such novelty, which the
        pairs where ``counted`` is True update first (an exponential average at rate ``momentum``,
        started at the first batch's mean)."""
        mean = self.get_buffer("novelty_mean")
        batch_mean = novelty.detach()[counted].mean()
        mean.copy_(torch.where(mean > 0, torch.lerp(mean, batch_mean, momentum), batch_mean))
        return novelty / mean.clamp_min(1e-12) - 1.0
