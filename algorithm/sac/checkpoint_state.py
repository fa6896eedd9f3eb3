"""The learner's state as a checkpoint holds it: the functions :class:`algorithm.sac.learner.SAC`'s
checkpoint methods call. :func:`named_optimizers` names its optimizers, :func:`learner_state` saves
everything a bit-identical resume needs and :func:`load_learner_state` restores it, and
:func:`load_model_weights` takes an evolver's weights in place of its own. What they read of the
learner is :class:`Checkpointed`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from algorithm.nn.models import SacModels


class Checkpointed(Protocol):
    """What a checkpoint holds of a learner (:class:`algorithm.sac.learner.SAC`)."""

    @property
    def models(self) -> SacModels: ...
    @property
    def target_representation(self) -> torch.nn.Module: ...
    @property
    def target_q(self) -> torch.nn.Module: ...
    @property
    def log_alpha(self) -> torch.nn.Parameter: ...
    @property
    def log_alpha_discrete(self) -> torch.nn.Parameter: ...
    @property
    def critic_optimizer(self) -> torch.optim.Optimizer: ...
    @property
    def policy_optimizer(self) -> torch.optim.Optimizer | None: ...
    @property
    def alpha_optimizer(self) -> torch.optim.Optimizer | None: ...
    @property
    def auxiliary_optimizer(self) -> torch.optim.Optimizer | None: ...
    @property
    def _learn_rng(self) -> torch.Generator: ...

    beta: float
    updates: int
    nonfinite_skipped: int
    _consecutive_nonfinite: int

    def _acting_rng_state(self) -> dict[str, Any]: ...  # algorithm.sac.policy.Policy's

    def _load_acting_rng_state(self, rng: Mapping[str, Any]) -> None: ...  # algorithm.sac.policy.Policy's


def named_optimizers(learner: Checkpointed) -> dict[str, torch.optim.Optimizer]:
    """The learner's optimizers by the names its checkpoint keeps them under."""
    named: dict[str, torch.optim.Optimizer] = {"critic": learner.critic_optimizer}
    if learner.policy_optimizer is not None:
        named["policy"] = learner.policy_optimizer
    if learner.alpha_optimizer is not None:
        named["alpha"] = learner.alpha_optimizer
    if learner.auxiliary_optimizer is not None:
        named["auxiliary"] = learner.auxiliary_optimizer
    return named


def learner_state(learner: Checkpointed) -> dict[str, Any]:
    """Everything needed to resume bit-identically: models, targets, optimizers, log_alpha,
    beta, counters and both RNG states."""
    return {
        "models": learner.models.state_dict(),
        "target_representation": learner.target_representation.state_dict(),
        "target_q": learner.target_q.state_dict(),
        "log_alpha": learner.log_alpha.detach().clone(),
        "log_alpha_discrete": learner.log_alpha_discrete.detach().clone(),
        "optimizers": {name: opt.state_dict() for name, opt in named_optimizers(learner).items()},
        "beta": learner.beta,
        "updates": learner.updates,
        "nonfinite_skipped": learner.nonfinite_skipped,
        "consecutive_nonfinite": learner._consecutive_nonfinite,
        "rng": {**learner._acting_rng_state(), "learn": learner._learn_rng.get_state()},
    }


def load_learner_state(learner: Checkpointed, state: Mapping[str, Any]) -> None:
    """Restore what :func:`learner_state` returned (from an identically configured SAC)."""
    missing = set(learner_state(learner)) - set(state)
    if missing:
        raise KeyError(f"SAC state dict lacks {sorted(missing)}")
    optimizers = named_optimizers(learner)
    if set(state["optimizers"]) != set(optimizers):
        raise ValueError(
            f"SAC state dict has optimizers {sorted(state['optimizers'])}, this SAC has "
            f"{sorted(optimizers)} (use_auto_alpha differs?)"
        )
    learner.models.load_state_dict(state["models"])
    learner.target_representation.load_state_dict(state["target_representation"])
    learner.target_q.load_state_dict(state["target_q"])
    with torch.no_grad():
        learner.log_alpha.copy_(state["log_alpha"])
        learner.log_alpha_discrete.copy_(state["log_alpha_discrete"])
    for name, opt in optimizers.items():
        opt.load_state_dict(state["optimizers"][name])
    learner.beta = float(state["beta"])
    learner.updates = int(state["updates"])
    learner.nonfinite_skipped = int(state["nonfinite_skipped"])
    learner._consecutive_nonfinite = int(state["consecutive_nonfinite"])
    learner._load_acting_rng_state(state["rng"])
    learner._learn_rng.set_state(state["rng"]["learn"])


def load_model_weights(learner: Checkpointed, weights: Mapping[str, Tensor | np.ndarray]) -> None:
    """Replace the online models' weights with ``weights`` (every name of ``models.state_dict()``,
    same shapes: an evolver's CEM sample), hard-copy them into the target networks and reset the
    moments of the optimizers that train them. ``log_alpha``, counters and RNGs stay.

    The targets are copied, not blended in at rate ``tau``: a Polyak average of the old targets
    and the new weights would bootstrap from a network that is neither. The optimizers start
    afresh because Adam's moments are running averages of the replaced weights' gradients: kept,
    they would push the first steps from the new point along the old point's momentum, scaled by
    its second moments. The alpha optimizer keeps its state (``log_alpha`` is not replaced).
    """
    state = {name: value if isinstance(value, Tensor) else torch.tensor(value) for name, value in weights.items()}
    own = learner.models.state_dict()
    wrong = sorted(set(own) ^ set(state)) or [k for k in own if own[k].shape != state[k].shape]
    if wrong:  # checked first: load_state_dict would copy the matching tensors before it raised
        raise ValueError(f"load_model_weights: tensors {wrong} are missing, unexpected or of another shape")
    learner.models.load_state_dict(state)
    learner.target_representation.load_state_dict(learner.models.representation.state_dict())
    learner.target_q.load_state_dict(learner.models.q.state_dict())
    for name, opt in named_optimizers(learner).items():
        if name != "alpha":
            opt.state.clear()
