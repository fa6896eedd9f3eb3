"""The learner's state as a checkpoint holds it: :class:`SacCheckpoint` is the mixin of
:class:`algorithm.sac.learner.SAC` that names its optimizers, saves and restores everything a bit-identical
resume needs (:meth:`~SacCheckpoint.state_dict`), and takes an evolver's weights in place of its own
(:meth:`~SacCheckpoint.load_model_weights`). :class:`~algorithm.sac.learner.SAC` owns the attributes it reads.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor

from algorithm.nn.models import SacModels


class SacCheckpoint:
    """Checkpoint state and optimizers of :class:`algorithm.sac.learner.SAC` (which provides these attributes)."""

    models: SacModels
    target_representation: torch.nn.Module
    target_q: torch.nn.Module
    log_alpha: torch.nn.Parameter
    log_alpha_discrete: torch.nn.Parameter
    critic_optimizer: torch.optim.Optimizer
    policy_optimizer: torch.optim.Optimizer | None
    alpha_optimizer: torch.optim.Optimizer | None
    auxiliary_optimizer: torch.optim.Optimizer | None
    beta: float
    updates: int
    nonfinite_skipped: int
    _consecutive_nonfinite: int
    _learn_rng: torch.Generator

    _acting_rng_state: Callable[[], dict[str, Any]]  # algorithm.sac.policy.Policy's
    _load_acting_rng_state: Callable[[Mapping[str, Any]], None]  # algorithm.sac.policy.Policy's

    def _named_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        named: dict[str, torch.optim.Optimizer] = {"critic": self.critic_optimizer}
        if self.policy_optimizer is not None:
            named["policy"] = self.policy_optimizer
        if self.alpha_optimizer is not None:
            named["alpha"] = self.alpha_optimizer
        if self.auxiliary_optimizer is not None:
            named["auxiliary"] = self.auxiliary_optimizer
        return named

    def _optimizers(self) -> list[torch.optim.Optimizer]:
        return list(self._named_optimizers().values())

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume bit-identically: models, targets, optimizers, log_alpha,
        beta, counters and both RNG states."""
        return {
            "models": self.models.state_dict(),
            "target_representation": self.target_representation.state_dict(),
            "target_q": self.target_q.state_dict(),
            "log_alpha": self.log_alpha.detach().clone(),
            "log_alpha_discrete": self.log_alpha_discrete.detach().clone(),
            "optimizers": {name: opt.state_dict() for name, opt in self._named_optimizers().items()},
            "beta": self.beta,
            "updates": self.updates,
            "nonfinite_skipped": self.nonfinite_skipped,
            "consecutive_nonfinite": self._consecutive_nonfinite,
            "rng": {**self._acting_rng_state(), "learn": self._learn_rng.get_state()},
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned (from an identically configured SAC)."""
        missing = set(self.state_dict()) - set(state)
        if missing:
            raise KeyError(f"SAC state dict lacks {sorted(missing)}")
        optimizers = self._named_optimizers()
        if set(state["optimizers"]) != set(optimizers):
            raise ValueError(
                f"SAC state dict has optimizers {sorted(state['optimizers'])}, this SAC has "
                f"{sorted(optimizers)} (use_auto_alpha differs?)"
            )
        self.models.load_state_dict(state["models"])
        self.target_representation.load_state_dict(state["target_representation"])
        self.target_q.load_state_dict(state["target_q"])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
            self.log_alpha_discrete.copy_(state["log_alpha_discrete"])
        for name, opt in optimizers.items():
            opt.load_state_dict(state["optimizers"][name])
        self.beta = float(state["beta"])
        self.updates = int(state["updates"])
        self.nonfinite_skipped = int(state["nonfinite_skipped"])
        self._consecutive_nonfinite = int(state["consecutive_nonfinite"])
        self._load_acting_rng_state(state["rng"])
        self._learn_rng.set_state(state["rng"]["learn"])

    def load_model_weights(self, weights: Mapping[str, Tensor | np.ndarray]) -> None:
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
        own = self.models.state_dict()
        wrong = sorted(set(own) ^ set(state)) or [k for k in own if own[k].shape != state[k].shape]
        if wrong:  # checked first: load_state_dict would copy the matching tensors before it raised
            raise ValueError(f"load_model_weights: tensors {wrong} are missing, unexpected or of another shape")
        self.models.load_state_dict(state)
        self.target_representation.load_state_dict(self.models.representation.state_dict())
        self.target_q.load_state_dict(self.models.q.state_dict())
        for name, opt in self._named_optimizers().items():
            if name != "alpha":
                opt.state.clear()
