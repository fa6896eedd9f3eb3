"""What SAC's losses read of a learner (:class:`LearnerParts`): the models, the target networks, the
policy's sampler and the temperatures, handed over once by :class:`algorithm.sac.learner.SAC`,
which owns them and moves them in place (optimizer steps, Polyak averaging, schedules, a restored
checkpoint)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from algorithm.config.schema import SacConfig
from algorithm.nn.models import SacModels
from algorithm.sac.equations import PolicySample
from algorithm.spaces import EnvSpec


@dataclass(frozen=True, eq=False)
class LearnerParts:
    """The learner's parts a loss reads. ``policy(state, noise, action_mask)`` samples the current
    policy (:meth:`algorithm.sac.policy.Policy._policy`); ``branches`` is the discrete branches'
    :func:`~algorithm.sac.equations.branch_matrix` (None without discrete actions);
    ``discrete_target_entropy`` and ``munchausen_weight`` are this update's values of their schedules;
    ``trains_alpha``: the temperatures have a loss (``use_auto_alpha``)."""

    spec: EnvSpec
    sac: SacConfig
    device: torch.device
    models: SacModels
    target_representation: torch.nn.Module
    target_q: torch.nn.Module
    policy: Callable[[Tensor, Tensor, Tensor | None], PolicySample]
    branches: Tensor | None
    mask_index: int | None
    log_alpha: torch.nn.Parameter
    log_alpha_discrete: torch.nn.Parameter
    target_entropy: float
    discrete_target_entropy: Tensor
    munchausen_weight: Tensor
    trains_alpha: bool
    observation_targets: list[int]  # the sensors a prediction model reconstructs

    def q_taken(self, q: torch.nn.Module, state: Tensor, action: Tensor, heads: Tensor | None = None) -> Tensor:
        """Each head's value of the stored ``action``: ``[E, B]``, or ``[E, B, K]`` per discrete branch."""
        d = self.spec.action.discrete_size
        values = q(state, action[..., d:] if self.models.policy is not None else None, heads)
        if self.branches is None:
            return values
        return (values * action[..., :d]) @ self.branches
