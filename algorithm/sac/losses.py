"""What one SAC update computes from a batch: :meth:`SacLosses.__call__` is the SAC step of Haarnoja
et al. 2018 (arXiv:1812.05905), read top to bottom: the target ``y`` from the target critic at the
bootstrap state, the critic's loss toward ``y``, the policy's loss against the online critic, the
temperature's loss. The features a config turns on are transforms it is composed with
(:mod:`algorithm.sac.features`); with none of them on, it is plain SAC.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from algorithm.sac.equations import Metrics, PolicySample, alpha_loss, critic_loss, expected_log_prob, policy_loss
from algorithm.sac.features import Features, PolicyTerms, Temperatures, compose
from algorithm.sac.parts import LearnerParts
from algorithm.sac.window import PassInputs, cut_window


@dataclass
class Losses:
    """What one pass over a batch computes (:meth:`SacLosses.__call__`), all from the same parameters:
    the critic's, policy's, temperature's and exploration models' losses, the prediction models'
    losses by name, ``td_abs [B]`` (mean |TD| over heads, for priorities), the pass's metrics, and
    the online recurrent state fed in at each window step ``[B, L, S]`` (None without ``use_rnn``)."""

    q: Tensor
    policy: Tensor
    alpha: Tensor
    auxiliary: Tensor
    predictions: dict[str, Tensor]
    td_abs: Tensor
    metrics: Metrics
    fed_states: Tensor | None
    policy_terms: PolicyTerms | None = None  # sac.update_order critic_first: what the policy loss is redone from


class SacLosses:
    """SAC's losses over the learner's ``parts``, composed with the ``features`` its config turns on."""

    def __init__(self, parts: LearnerParts, features: Features | None = None) -> None:
        self.parts = parts
        self.features = compose(parts) if features is None else features

    def __call__(self, batch: PassInputs) -> Losses:
        """The SAC losses from the current parameters (:class:`Losses`). The trained step is step
        ``burn_in_step`` of each window (the sampled key; earlier steps only warm up a recurrent
        state). ``batch.noise [B, samples, A]`` feeds the policy's samples: position 0 the policy
        loss's, 1.. the target's."""
        parts, features = self.parts, self.features
        temperatures = Temperatures(parts.log_alpha.detach().exp(), parts.log_alpha_discrete.detach().exp())
        metrics: Metrics = {"learner/alpha": temperatures.alpha}
        if temperatures.discrete.numel():
            metrics["learner/alpha_discrete"] = temperatures.discrete
        window = cut_window(batch, parts.sac, parts.models, parts.target_representation, parts.mask_index)
        state = window.states_at(0, False)  # s: the trained step's online state, with gradients for the critic
        action = window.actions[:, 0]  # a: the stored action

        # 0. Rewards, with what the reward features add (exploration bonuses, Munchausen).
        rewards = window.rewards
        for term in features.rewards:
            added = term(window, state, temperatures, metrics)
            if added is not None:
                rewards = rewards + added
        auxiliary = torch.zeros((), device=parts.device)
        for model in features.losses_beside:
            auxiliary = auxiliary + model.loss

        # 1. Target: y = r + gamma V(s') with V(s') = min_i Qbar_i(s', a') - alpha log pi(a'|s'), a' ~ pi.
        with torch.no_grad():
            y, next_value = features.target(window, rewards, temperatures, batch.target_heads, metrics)
        predictions = {} if features.predictions is None else features.predictions(window, state, metrics)

        # 2. Critic: 1/2 (Q_i(s, a) - y)^2 for each head i.
        q_taken = parts.q_taken(parts.models.q, state, action)
        if features.clipped_critic is None:
            q_loss, td_abs, q_metrics = critic_loss(q_taken, y, window.weights)
        else:
            q_loss, td_abs, q_metrics = features.clipped_critic(window, q_taken, y)

        # 3. Policy: alpha log pi(a~|s) - min_i Q_i(s, a~), a~ ~ pi, on the detached state.
        pi = parts.policy(state.detach(), window.noise[:, 0], window.masks_at(0))
        terms = PolicyTerms(state.detach(), pi, batch.policy_heads, temperatures, -window.behaviour_logp[:, 0])
        pi_loss, pi_metrics = self.policy_loss(terms)

        # 4. Temperature: -alpha (log pi(a~|s) + target entropy).
        a_loss = self.temperature_loss(pi)

        metrics.update(
            {**q_metrics, **pi_metrics, "learner/next_value": next_value, "learner/auxiliary_loss": auxiliary}
        )
        kept = terms if parts.sac.update_order == "critic_first" else None
        return Losses(q_loss, pi_loss, a_loss, auxiliary, predictions, window.sampled(td_abs), metrics,
                      window.fed_states, kept)  # fmt: skip

    def policy_loss(self, terms: PolicyTerms) -> tuple[Tensor, Metrics]:
        """The policy's loss against the online critic as its parameters are now (their gradients cut),
        with the terms of the policy features."""
        parts = self.parts
        q = parts.models.q(terms.state, terms.pi.continuous, terms.heads, detach_params=True)
        t = terms.temperatures
        loss, metrics = policy_loss(q.min(dim=0).values, terms.pi, t.alpha, t.discrete, parts.branches)
        for term in self.features.policy_terms:
            loss = loss + term(terms, metrics)
        return loss, metrics

    def temperature_loss(self, pi: PolicySample) -> Tensor:
        """``use_auto_alpha``: the continuous temperature's loss toward ``-|A_c|`` and each discrete
        branch's toward its target entropy (eq. 18; zero when alpha is fixed)."""
        parts = self.parts
        loss = torch.zeros((), device=parts.device)
        if not parts.trains_alpha:
            return loss
        if pi.continuous_log_prob is not None:
            loss = loss + alpha_loss(parts.log_alpha, pi.continuous_log_prob, parts.target_entropy)[0]
        if pi.log_probs is not None and parts.branches is not None:
            expected = expected_log_prob(pi, parts.branches)
            loss = loss + alpha_loss(parts.log_alpha_discrete, expected, parts.discrete_target_entropy)[0]
        return loss
