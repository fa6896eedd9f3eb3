"""The three SAC models: representation, batched Q ensemble, tanh-squashed Gaussian policy.

Shapes: a *state* is ``[N, state_dim]``; actions are ``[N, A]`` in model space (docs/architecture.md section 3).
Subclass :class:`Representation` for other encoders (conv for images, GRU/LSTM for ``use_rnn``):
the rest of the learner only relies on ``state_dim`` and ``forward(obs) -> state``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import cast

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from algorithm.nn.exploration import Curiosity, RandomNetworkDistillation
from algorithm.nn.layers import EnsembleLinear, activation, in_float32, mlp, relu_mlp
from algorithm.nn.noisy import NoisyEnsembleLinear, NoisyLinear
from algorithm.nn.normalization import ObservationNormalizer
from algorithm.nn.prediction import PredictionModels
from algorithm.spaces import SensorSpec

_LOG2 = math.log(2.0)
_HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)


class Representation(nn.Module):
    """``rep(obs sensors) -> state``: the input every Q head and the policy see.

    ``forward`` takes one tensor per sensor, each ``[*lead, *sensor_shape]`` with the same leading
    dims, and returns ``[*lead, state_dim]``. The learner keeps a Polyak-averaged target copy.
    """

    state_dim: int
    policy_state_dim: int  # the leading part of the state the policy sees (all of it but critic-only sensors)

    def forward(self, obs: list[Tensor]) -> Tensor:  # pragma: no cover - interface
        raise NotImplementedError

    def policy_state(self, state: Tensor) -> Tensor:
        """The policy's part of a state from :meth:`forward`: its first ``policy_state_dim`` features."""
        return state if self.policy_state_dim == self.state_dim else state[..., : self.policy_state_dim]


class VectorRepresentation(Representation):
    """Concatenation of (flattened) vector sensors; has no parameters."""

    def __init__(self, sensors: Sequence[SensorSpec]) -> None:
        super().__init__()
        if not sensors:
            raise ValueError("VectorRepresentation needs at least one sensor")
        for s in sensors:
            if s.is_image:
                raise NotImplementedError(f"image sensor {s.name!r} {s.shape}: conv encoders are not built yet")
        self.sensor_ranks = [len(s.shape) for s in sensors]
        self.state_dim = self.policy_state_dim = sum(math.prod(s.shape) for s in sensors)

    def forward(self, obs: list[Tensor]) -> Tensor:
        if len(obs) != len(self.sensor_ranks):
            raise ValueError(f"expected {len(self.sensor_ranks)} sensors, got {len(obs)}")
        flat = [o.flatten(-rank) if rank != 1 else o for o, rank in zip(obs, self.sensor_ranks, strict=True)]
        return flat[0] if len(flat) == 1 else torch.cat(flat, dim=-1)


class QEnsemble(nn.Module):
    """``E`` independent Q heads as one batched MLP over ``[state | continuous action]``.

    Every layer is an :class:`EnsembleLinear`, so each layer is one batched matmul for all heads.
    With ``discrete_size == 0`` (continuous actions) each head outputs the scalar ``Q(s, a)`` and
    ``forward`` returns ``[E, N]``; with discrete branches each head outputs one value per discrete
    action of every branch, ``Q_b(s, a_b[, a_c])``, and ``forward`` returns ``[E, N, discrete_size]``
    (``action`` is then only the continuous part, or None when there is none). ``heads`` selects a
    subset; ``detach_params=True`` lets gradients reach ``state``/``action`` but not the heads'
    weights (the policy loss uses it to leave the critic's gradients untouched).
    """

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        hidden_units: Sequence[int],
        ensemble_size: int,
        activation_name: str = "relu",
        discrete_size: int = 0,
        noisy_sigma0: float | None = None,
    ) -> None:
        super().__init__()
        sizes = [state_dim + action_dim, *hidden_units, max(discrete_size, 1)]
        self.ensemble_size = ensemble_size
        self.discrete_size = discrete_size
        layers: list[nn.Module] = []
        for i, o in itertools.pairwise(sizes):  # noisy nets replace every layer of the value head (1706.10295)
            if noisy_sigma0 is None:
                layers.append(EnsembleLinear(ensemble_size, i, o))
            else:
                layers.append(NoisyEnsembleLinear(ensemble_size, i, o, noisy_sigma0))
        self.layers = nn.ModuleList(layers)
        self.act = activation(activation_name)
        # Plain layers with ReLU run as one autograd node (layers.relu_mlp: the same values, faster).
        self.use_relu_mlp = activation_name == "relu" and noisy_sigma0 is None

    def forward(
        self, state: Tensor, action: Tensor | None, heads: Tensor | None = None, detach_params: bool = False
    ) -> Tensor:
        h = state if action is None else torch.cat([state, action], dim=-1)
        if self.use_relu_mlp:
            layers = cast(list[EnsembleLinear], list(self.layers))
            params = [p for layer in layers for p in layer.parameters_for(heads, detach_params)]
            if h.dim() == 2:
                h = h.expand(params[0].shape[0], *h.shape)  # shared input: a stride-0 view, no copy
            out = relu_mlp(h, params)
        else:
            for layer in self.layers[:-1]:
                h = self.act(layer(h, heads, detach_params))
            out = in_float32(self.layers[-1], h, heads, detach_params)
        return out if self.discrete_size else out.squeeze(-1)


def output_layer(in_features: int, out_features: int, noisy_sigma0: float | None) -> nn.Module:
    """A policy's output layer: ``nn.Linear``, or a factorised-noise :class:`NoisyLinear` with
    ``noisy_sigma0`` (state-dependent exploration from the weights, Fortunato et al. 2018)."""
    if noisy_sigma0 is None:
        return nn.Linear(in_features, out_features)
    return NoisyLinear(in_features, out_features, noisy_sigma0)


def squashed_gaussian_log_prob(noise: Tensor, log_std: Tensor, pre_tanh: Tensor, epsilon: float = 0.0) -> Tensor:
    """``log pi(tanh(u))`` for ``u = mean + std * noise``, summed over the last dim.

    Gaussian part from the noise directly (no division by ``std``); the tanh change of variables
    uses ``log(1 - tanh(u)^2) = 2 (log 2 - u - softplus(-2u))``, which stays finite for large
    ``|u|`` where ``1 - tanh(u)^2`` rounds to zero (Haarnoja et al. 2018, 1812.05905, appendix C;
    the same identity as ``torch.distributions.transforms.TanhTransform``).

    ``epsilon > 0`` takes it as ``log(1 - tanh(u)^2 + epsilon)`` instead, as SB3 does with 1e-6
    (``sac_config.tanh_log_det_epsilon``): within 1% of exact per dimension up to ``|u|`` ~ 5, held
    near ``log(epsilon)`` beyond ~6.5, where the exact term goes on falling as ``-2|u|``.
    """
    return _squashed_gaussian_log_density(noise, log_std, pre_tanh, epsilon).sum(-1)


def _squashed_gaussian_log_density(noise: Tensor, log_std: Tensor, pre_tanh: Tensor, epsilon: float = 0.0) -> Tensor:
    gaussian = -0.5 * noise.pow(2) - log_std - _HALF_LOG_2PI
    if epsilon > 0:
        return gaussian - torch.log(1.0 - torch.tanh(pre_tanh).pow(2) + epsilon)
    log_det = 2.0 * (_LOG2 - pre_tanh - F.softplus(-2.0 * pre_tanh))
    return gaussian - log_det


# From here on a stored float32 action counts as at the edge of [-1, 1]: below it atanh of the
# float32 value is off by less than 0.003 in u; beyond it float32 tanh loses u (it is exactly 1
# from |u| ~ 9), so a density there cannot be evaluated again from the stored action.
SATURATED_ACTION = 1.0 - 1e-5
_SATURATED_PRE_TANH = math.atanh(SATURATED_ACTION)


def stored_action_log_prob(mean: Tensor, log_std: Tensor, action: Tensor) -> Tensor:
    """``log p(action) [N]`` of stored actions in ``[-1, 1]^A`` under the squashed Gaussian
    ``tanh(N(mean, std^2))``, as the actor records it (behaviour ``log mu``) and the learner
    evaluates it again (V-trace's ``log pi``): both from the same float32 action, so on-policy
    ratios are 1 however saturated the policy is.

    Per dimension: inside ``|a| < SATURATED_ACTION`` the density at ``u = atanh(a)``; at the edge
    the probability of the edge, ``P(u >= atanh(SATURATED_ACTION))`` (or ``<= -``), i.e. the
    importance ratio of the action as stored, which is all the env receives either way. Inverting
    tanh of a saturated action instead gave ratios of ~1e-14 on-policy at a pre-tanh mean of 10.
    """
    inside = action.abs() < SATURATED_ACTION
    pre_tanh = torch.atanh(action.clamp(-SATURATED_ACTION, SATURATED_ACTION))
    density = _squashed_gaussian_log_density((pre_tanh - mean) * torch.exp(-log_std), log_std, pre_tanh)
    std = log_std.exp()
    upper = torch.special.log_ndtr((mean - _SATURATED_PRE_TANH) / std)  # log P(u >= edge)
    lower = torch.special.log_ndtr((-_SATURATED_PRE_TANH - mean) / std)  # log P(u <= -edge)
    return torch.where(inside, density, torch.where(action > 0, upper, lower)).sum(-1)


class TanhGaussianPolicy(nn.Module):
    """``pi(a|s)``: a Gaussian over ``u`` squashed by ``tanh`` into ``[-1, 1]^A``.

    ``log_std`` is clamped to ``[log_std_min, log_std_max]`` (as in the authors' code and SB3).
    """

    def __init__(
        self,
        state_dim: int,
        action_dim: int,
        hidden_units: Sequence[int],
        activation_name: str = "relu",
        log_std_min: float = -20.0,
        log_std_max: float = 2.0,
        noisy_sigma0: float | None = None,
    ) -> None:
        super().__init__()
        if log_std_min >= log_std_max:
            raise ValueError(f"nn_config: log_std_min ({log_std_min}) must be < log_std_max ({log_std_max})")
        self.action_dim = action_dim
        self.log_std_min = log_std_min
        self.log_std_max = log_std_max
        self.trunk = mlp(state_dim, hidden_units, activation_name)
        last = hidden_units[-1] if hidden_units else state_dim
        self.head = output_layer(last, 2 * action_dim, noisy_sigma0)

    def forward(self, state: Tensor) -> tuple[Tensor, Tensor]:
        """``(mean, log_std)`` of the pre-tanh Gaussian, each ``[N, A]``."""
        mean, log_std = in_float32(self.head, self.trunk(state)).chunk(2, dim=-1)
        return mean, log_std.clamp(self.log_std_min, self.log_std_max)

    def log_prob(self, state: Tensor, action: Tensor) -> Tensor:
        """``log pi(action|state) [N]`` of stored actions in ``[-1, 1]`` (V-trace needs it), in the
        measure the actor recorded them with (:func:`stored_action_log_prob`)."""
        mean, log_std = self(state)
        return stored_action_log_prob(mean, log_std, action)

    def sample(self, state: Tensor, noise: Tensor | None, log_det_epsilon: float = 0.0) -> tuple[Tensor, Tensor]:
        """Reparameterised ``(action [N, A], log_prob [N])`` with ``u = mean + std * noise``.

        ``noise`` is standard normal ``[N, A]`` drawn by the caller (so the caller owns the RNG);
        ``None`` gives the deterministic action ``tanh(mean)`` and the density at it;
        ``log_det_epsilon``: :func:`squashed_gaussian_log_prob`'s ``epsilon`` (the learner's losses).
        """
        mean, log_std = self(state)
        if noise is None:
            noise = torch.zeros_like(mean)
            pre_tanh = mean
        else:
            pre_tanh = mean + log_std.exp() * noise
        return torch.tanh(pre_tanh), squashed_gaussian_log_prob(noise, log_std, pre_tanh, log_det_epsilon)


MASKED_LOG_PROB = -1e9  # finite: exp() of it is exactly 0 in float32, and 0 * it is 0


def masked_branch_log_softmax(logits: Tensor, branches: Sequence[int], mask: Tensor | None) -> Tensor:
    """Per-branch ``log_softmax`` of ``logits [..., D]`` (``D = sum(branches)``), with masked
    actions (``mask`` False) at ``log p = MASKED_LOG_PROB``: their probability is exactly 0 and
    ``p * log p`` stays 0 (no ``-inf * 0 = nan``). Every branch needs one allowed action."""
    if mask is not None:
        logits = logits.masked_fill(~mask, MASKED_LOG_PROB)
    return torch.cat([part.log_softmax(-1) for part in logits.split(list(branches), dim=-1)], dim=-1)


def masked_branch_one_hot_argmax(values: Tensor, branches: Sequence[int], mask: Tensor | None) -> Tensor:
    """``[..., D]`` one-hot of each branch's largest *allowed* entry of ``values [..., D]``."""
    if mask is not None:
        values = values.masked_fill(~mask, float("-inf"))
    parts = [F.one_hot(part.argmax(-1), part.shape[-1]) for part in values.split(list(branches), dim=-1)]
    return torch.cat(parts, dim=-1).to(values.dtype if values.is_floating_point() else torch.float32)


class DiscretePolicy(nn.Module):
    """``pi_b(a | s)``: one categorical distribution per discrete branch, from one MLP whose head
    outputs the logits of every branch side by side (``[N, sum(branches)]``)."""

    def __init__(
        self,
        state_dim: int,
        branches: Sequence[int],
        hidden_units: Sequence[int],
        activation_name: str = "relu",
        noisy_sigma0: float | None = None,
    ) -> None:
        super().__init__()
        self.branches = tuple(branches)
        self.trunk = mlp(state_dim, hidden_units, activation_name)
        last = hidden_units[-1] if hidden_units else state_dim
        self.head = output_layer(last, sum(self.branches), noisy_sigma0)

    def forward(self, state: Tensor, mask: Tensor | None = None) -> Tensor:
        """``log pi [N, D]``, normalised within each branch; masked actions get probability 0."""
        return masked_branch_log_softmax(in_float32(self.head, self.trunk(state)), self.branches, mask)


class SacModels(nn.Module):
    """Container of the online models; the learner derives target copies from it.

    ``policy`` acts on the continuous part, ``discrete_policy`` on the discrete branches; either is
    None when the action space has no such part (``discrete_policy`` also with
    ``discrete_dqn_like``, where the Q heads choose the discrete actions)."""

    def __init__(
        self,
        representation: Representation,
        q: QEnsemble,
        policy: TanhGaussianPolicy | None,
        discrete_policy: DiscretePolicy | None = None,
        normalizer: ObservationNormalizer | None = None,
        curiosity: Curiosity | None = None,
        rnd: RandomNetworkDistillation | None = None,
        prediction: PredictionModels | None = None,
    ) -> None:
        super().__init__()
        self.prediction = prediction  # with use_prediction
        self.curiosity = curiosity  # with use_curiosity
        self.rnd = rnd  # with use_rnd
        self.normalizer = normalizer  # ObservationNormalizer with use_normalization, applied before representation
        self.representation = representation
        self.q = q
        self.policy = policy
        self.discrete_policy = discrete_policy
