"""SAC's features as named transforms, each one thing the plain step of :mod:`algorithm.sac.losses`
is composed with (:func:`compose`, from the config):

- reward terms, added to the window's rewards before the target: :class:`CuriosityBonus` (Pathak et
  al. 2017), :class:`RndBonus` (Burda et al. 2018), :class:`MunchausenTerm` (Vieillard et al. 2020);
- the target: :class:`NStepTarget` (plain SAC at ``n_step: 1``) or :class:`VTraceTarget`
  (``use_n_step_is``, Espeholt et al. 2018);
- :class:`ClippedCritic` (``clip_epsilon``): the critic's loss kept near the target heads' values;
- :class:`DiscreteEntropyPenalty` (``discrete_entropy_penalty``, SD-SAC), a term of the policy's loss;
- :class:`PredictionLosses`: the prediction models' losses, on the same state as the critic's.

Recurrent windows and ``train_every_step`` shape the window itself (:mod:`algorithm.sac.window`).
The equations are pure functions in :mod:`algorithm.sac.equations` and :mod:`algorithm.sac.returns`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import torch
from torch import Tensor

from algorithm.nn.models import MASKED_LOG_PROB
from algorithm.nn.prediction import prediction_losses
from algorithm.sac.equations import (
    Metrics,
    PolicySample,
    critic_loss,
    entropy_penalty,
    expected_log_prob,
    munchausen_bonus,
    soft_value,
)
from algorithm.sac.parts import LearnerParts
from algorithm.sac.returns import bootstrap_index, n_step_target, vtrace_target
from algorithm.sac.window import Window


@dataclass
class Temperatures:
    """This pass's temperatures, detached: the continuous ``alpha`` and one per discrete branch."""

    alpha: Tensor
    discrete: Tensor


class RewardTerm(Protocol):
    def __call__(self, window: Window, state: Tensor, temperatures: Temperatures, metrics: Metrics) -> Tensor | None:
        """What the term adds to every window step's reward ``[B, L]`` (no gradient), None: nothing."""
        ...


class Target(Protocol):
    def __call__(
        self, window: Window, rewards: Tensor, temperatures: Temperatures, heads: Tensor | None, metrics: Metrics
    ) -> tuple[Tensor, Tensor]:
        """The critic's target ``y [B]`` for the trained step and the soft value it bootstrapped from."""
        ...


# -- reward terms ---------------------------------------------------------------------------------


@dataclass
class CuriosityBonus:
    """Curiosity (Pathak et al. 2017): the forward model's error as a reward; the forward and inverse
    models' loss in :attr:`loss` after a call."""

    parts: LearnerParts
    loss: Tensor = field(init=False)

    def __call__(self, window: Window, state: Tensor, temperatures: Temperatures, metrics: Metrics) -> Tensor:
        curiosity = self.parts.models.curiosity
        assert curiosity is not None
        states = window.online_states()
        b, p = states.shape[:2]
        forward_error, inverse_error = (
            e.view(b, p - 1)
            for e in curiosity.errors(
                states[:, :-1].flatten(0, 1), window.actions.flatten(0, 1), states[:, 1:].flatten(0, 1)
            )
        )
        intrinsic = self.parts.sac.curiosity_strength * torch.where(window.valid, forward_error.detach(), 0.0)
        self.loss = ((forward_error + inverse_error) * window.valid).sum() / window.valid.sum()
        metrics["learner/curiosity_reward"] = intrinsic[:, 0]
        return intrinsic


@dataclass
class RndBonus:
    """RND (Burda et al. 2018): the predictor's loss on the trained step in :attr:`loss` and, with
    ``rnd_strength``, novelty as a reward, as Burda et al. use it (it fades once pairs are known)."""

    parts: LearnerParts
    loss: Tensor = field(init=False)

    def __call__(self, window: Window, state: Tensor, temperatures: Temperatures, metrics: Metrics) -> Tensor | None:
        rnd, sac = self.parts.models.rnd, self.parts.sac
        assert rnd is not None
        novelty = rnd.novelty(state.detach(), window.actions[:, 0])
        self.loss = novelty.mean()
        metrics["learner/rnd_novelty"] = novelty.detach()
        if sac.rnd_strength <= 0:
            return None
        states = window.online_states()
        b, p = states.shape[:2]
        with torch.no_grad():
            every = rnd.novelty(states[:, :-1].flatten(0, 1), window.actions.flatten(0, 1)).view(b, p - 1)
            if sac.rnd_normalize:
                every = rnd.relative(every, window.valid)
        intrinsic = sac.rnd_strength * torch.where(window.valid, every, 0.0)
        metrics["learner/rnd_reward"] = intrinsic[:, 0]
        return intrinsic


@dataclass
class MunchausenTerm:
    """``munchausen_scale``: the Munchausen term of every window step from the current policy's
    log-probabilities of the stored actions (:func:`algorithm.sac.equations.munchausen_bonus`); steps
    past the target's end are never read (``n_step_target``)."""

    parts: LearnerParts

    def __call__(self, window: Window, state: Tensor, temperatures: Temperatures, metrics: Metrics) -> Tensor:
        parts = self.parts
        assert parts.branches is not None
        with torch.no_grad():
            states = window.online_states()[:, :-1]
            b, steps = states.shape[:2]
            masks = window.masks_at(None)
            pi = parts.policy(
                states.flatten(0, 1),
                window.noise[:, :1].expand(-1, steps, -1).flatten(0, 1),  # discrete-only: no continuous sample
                None if masks is None else masks[:, :-1].flatten(0, 1),
            )
            assert pi.log_probs is not None
            chosen = window.actions.flatten(0, 1)[:, : parts.spec.action.discrete_size] > 0.5
            taken = torch.where(chosen, pi.log_probs, 0.0) @ parts.branches
            bonus = munchausen_bonus(
                taken, temperatures.discrete, parts.munchausen_weight, parts.sac.munchausen_log_floor
            )
        metrics["learner/munchausen_bonus"] = bonus.view(b, steps)[:, 0]
        return bonus.view(b, steps)


# -- targets --------------------------------------------------------------------------------------


@dataclass
class NStepTarget:
    """``y = sum_k gamma^k r_k + gamma^m V(o_m)`` with ``V`` from the target critic at the policy's
    action (Haarnoja et al. 2018, eq. 2, 3, 5); one step with ``n_step: 1``."""

    parts: LearnerParts

    def __call__(
        self, window: Window, rewards: Tensor, temperatures: Temperatures, heads: Tensor | None, metrics: Metrics
    ) -> tuple[Tensor, Tensor]:
        parts = self.parts
        m = bootstrap_index(window.valid)
        next_pi = parts.policy(window.states_at(m, False), window.noise[:, 1], window.masks_at(m))
        next_q = parts.target_q(window.states_at(m, True), next_pi.continuous, heads)
        v = soft_value(next_q.min(dim=0).values, next_pi, temperatures.alpha, temperatures.discrete, parts.branches)
        return n_step_target(rewards, window.terminated, window.valid, v, parts.sac.gamma), v


@dataclass
class VTraceTarget:
    """``use_n_step_is``: the V-trace target over the window (Espeholt et al. 2018, eq. 1, with SAC's
    soft values); the value it returns is the one at the step after the trained one."""

    parts: LearnerParts

    def __call__(
        self, window: Window, rewards: Tensor, temperatures: Temperatures, heads: Tensor | None, metrics: Metrics
    ) -> tuple[Tensor, Tensor]:
        sac = self.parts.sac
        values, log_pi = self.window_values(window, temperatures, heads)
        y, rho = vtrace_target(
            rewards, window.terminated, window.valid, values, log_pi - window.behaviour_logp,
            sac.gamma, sac.v_lambda, sac.v_rho, sac.v_c,
        )  # fmt: skip
        weighted = rho > 0
        metrics["learner/vtrace_rho"] = rho[weighted] if weighted.any() else torch.ones(1, device=self.parts.device)
        return y, values[:, 1]

    def window_values(self, window: Window, temperatures: Temperatures, heads: Tensor | None) -> tuple[Tensor, Tensor]:
        """Soft values ``V(o_t) [B, P]`` at every window position and the current policy's ``log
        pi(a_t|o_t) [B, P - 1]`` of the stored actions (greedy dqn-like branches: 0 for the greedy
        action, ``MASKED_LOG_PROB`` otherwise, so the trace is cut where behaviour left it)."""
        parts = self.parts
        online, target, action_mask = window.online_states(), window.states_at(None, True), window.masks_at(None)
        b, positions = online.shape[:2]
        state = online.flatten(0, 1)
        mask = None if action_mask is None else action_mask.flatten(0, 1)
        pi = parts.policy(state, window.noise[:, 1:].flatten(0, 1), mask)
        q = parts.target_q(target.flatten(0, 1), pi.continuous, heads).min(dim=0).values
        values = soft_value(q, pi, temperatures.alpha, temperatures.discrete, parts.branches).view(b, positions)

        taken = window.actions.flatten(0, 1)
        steps = torch.arange(b * positions, device=taken.device).view(b, positions)[:, :-1].flatten()
        log_pi = torch.zeros(steps.shape[0], device=taken.device)
        policy_state = parts.models.representation.policy_state(state[steps])
        d = parts.spec.action.discrete_size
        if parts.models.policy is not None:
            log_pi = log_pi + parts.models.policy.log_prob(policy_state, taken[:, d:])
        if parts.branches is not None:
            assert pi.probs is not None
            chosen = taken[:, :d] > 0.5
            if pi.log_probs is not None:
                per_action = pi.log_probs[steps]
            else:
                per_action = torch.where(pi.probs[steps] > 0.5, 0.0, MASKED_LOG_PROB)
            log_pi = log_pi + torch.where(chosen, per_action, 0.0).sum(dim=-1)
        return values, log_pi.view(b, positions - 1)


# -- critic, policy and side losses ---------------------------------------------------------------


@dataclass
class ClippedCritic:
    """``clip_epsilon``: each squared error is the larger of the plain one and the one of the target
    heads' value of the stored action moved at most ``clip_epsilon`` toward the online value
    (:func:`algorithm.sac.equations.critic_loss`)."""

    parts: LearnerParts

    def __call__(self, window: Window, q_taken: Tensor, y: Tensor) -> tuple[Tensor, Tensor, Metrics]:
        parts = self.parts
        with torch.no_grad():
            old_q = parts.q_taken(parts.target_q, window.states_at(0, True), window.actions[:, 0])
        return critic_loss(q_taken, y, window.weights, parts.sac.clip_epsilon, old_q)


@dataclass
class PolicyTerms:
    """What the policy's loss is computed from besides the critic: the trained step's detached state,
    the policy's sample on it, the Q heads it is scored by, the temperatures of the pass and ``-log
    mu(a|s)`` of the stored action ``[B]``. With ``sac.update_order: critic_first`` the loss is
    computed again from these after the critic's step."""

    state: Tensor
    pi: PolicySample
    heads: Tensor | None
    temperatures: Temperatures
    behaviour_entropy: Tensor


@dataclass
class DiscreteEntropyPenalty:
    """SD-SAC's entropy penalty (:func:`algorithm.sac.equations.entropy_penalty`), weighted by
    ``discrete_entropy_penalty``: each state's policy entropy held near that of the policy that acted."""

    parts: LearnerParts

    def __call__(self, terms: PolicyTerms, metrics: Metrics) -> Tensor:
        assert self.parts.branches is not None
        entropy = -expected_log_prob(terms.pi, self.parts.branches).sum(dim=-1)
        penalty = entropy_penalty(entropy, terms.behaviour_entropy)
        metrics["learner/entropy_penalty"] = penalty.detach()
        return self.parts.sac.discrete_entropy_penalty * penalty


@dataclass
class PredictionLosses:
    """Prediction models' losses by name (transition, reward, observation) on the critic's live
    state; the learner gates their gradient into the representation (nn/prediction.py)."""

    parts: LearnerParts

    def __call__(self, window: Window, state: Tensor, metrics: Metrics) -> dict[str, Tensor]:
        parts = self.parts
        assert parts.models.prediction is not None
        with torch.no_grad():
            next_state = window.states_at(1, True)
        targets = [window.obs[i][:, 0].flatten(1) for i in parts.observation_targets]
        predictions = prediction_losses(
            parts.models.prediction, state, window.actions[:, 0], next_state, window.rewards[:, 0],
            torch.cat(targets, dim=-1) if targets else None, parts.sac.transition_kl,
        )  # fmt: skip
        metrics.update({f"learner/prediction_{k}": v.detach() for k, v in predictions.items()})
        return predictions


@dataclass
class Features:
    """The transforms a config turns on (:func:`compose`); plain SAC has none but its target."""

    rewards: list[RewardTerm]
    losses_beside: list[CuriosityBonus | RndBonus]  # reward terms whose models have a loss of their own
    target: Target
    clipped_critic: ClippedCritic | None
    policy_terms: list[DiscreteEntropyPenalty]
    predictions: PredictionLosses | None


def compose(parts: LearnerParts) -> Features:
    """The transforms ``parts.sac`` and the models turn on, in the order the pass applies them."""
    sac, models = parts.sac, parts.models
    exploration: list[CuriosityBonus | RndBonus] = []
    if models.curiosity is not None:
        exploration.append(CuriosityBonus(parts))
    if models.rnd is not None:
        exploration.append(RndBonus(parts))
    rewards: list[RewardTerm] = [*exploration]
    if sac.munchausen_scale > 0:
        rewards.append(MunchausenTerm(parts))
    return Features(
        rewards=rewards,
        losses_beside=exploration,
        target=VTraceTarget(parts) if sac.use_n_step_is else NStepTarget(parts),
        clipped_critic=ClippedCritic(parts) if sac.clip_epsilon is not None else None,
        policy_terms=[DiscreteEntropyPenalty(parts)] if sac.discrete_entropy_penalty > 0 else [],
        predictions=PredictionLosses(parts) if models.prediction is not None else None,
    )
