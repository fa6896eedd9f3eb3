"""What one SAC update computes from a batch, read as plain SAC first.

:meth:`SacLosses._losses` is the SAC step of Haarnoja et al. 2018 (arXiv:1812.05905): a target
``y`` from the target critic at the bootstrap state, the critic's loss toward ``y``, the policy's
loss against the online critic, and the temperature's loss. Each feature adds its part in a small
method of its own, called from there:

- recurrent windows (``use_rnn``): :meth:`_sequence_states`, the states at every window position;
- curiosity and RND (exploration bonuses and their models' losses): :meth:`_exploration_terms`;
- V-trace over the window (``use_n_step_is``) in place of the n-step target: :meth:`_vtrace`;
- clipped critic updates (``clip_epsilon``): :meth:`_clip_reference`;
- prediction models (transition, reward, observation): :meth:`_prediction_terms`.

The equations themselves are pure functions in :mod:`algorithm.sac.equations` and :mod:`algorithm.sac.returns`.
:class:`SacLosses` is a mixin of :class:`algorithm.sac.learner.SAC`, which owns the models it reads.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from algorithm.config.schema import SacConfig
from algorithm.nn.models import MASKED_LOG_PROB, SacModels
from algorithm.nn.prediction import prediction_losses
from algorithm.nn.recurrent import RecurrentRepresentation
from algorithm.sac.equations import (
    Metrics,
    PolicySample,
    alpha_loss,
    critic_loss,
    entropy_penalty,
    expected_log_prob,
    munchausen_bonus,
    policy_loss,
    soft_value,
)
from algorithm.sac.returns import (
    StepWindows,
    bootstrap_index,
    gather_positions,
    n_step_target,
    valid_steps,
    vtrace_target,
)
from algorithm.spaces import EnvSpec


@dataclass
class Losses:
    """What one pass over a batch computes (:meth:`SacLosses._losses`), all from the same parameters:
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


@dataclass
class PolicyTerms:
    """What the policy's loss is computed from besides the critic: the trained step's detached state,
    the policy's sample on it, the Q heads it is scored by and the temperatures of the pass. With
    ``sac.update_order: critic_first`` the loss is computed again from these after the critic's step."""

    state: Tensor
    pi: PolicySample
    heads: Tensor | None
    alpha: Tensor
    alpha_discrete: Tensor
    behaviour_entropy: Tensor | None = None  # discrete_entropy_penalty: -log mu(a|s) of the stored action [B]


@dataclass
class Window:
    """A batch's windows from the trained step on (``burn_in_step`` rows dropped), with the states at
    their observation positions: precomputed ``sequences`` (online, target ``[B, P, D]``) for a
    recurrent representation, else computed where asked by the feed-forward ``representation``s."""

    obs: list[Tensor]
    actions: Tensor
    rewards: Tensor
    terminated: Tensor
    mask: Tensor
    behaviour_logp: Tensor
    valid: Tensor  # [B, L]: steps that count toward the target (returns.valid_steps)
    action_masks: Tensor | None  # the action_mask sensor as bool [B, P, D], None without one
    representation: torch.nn.Module
    target_representation: torch.nn.Module
    sequences: tuple[Tensor, Tensor] | None
    _online_all: Tensor | None = None

    def online_states(self) -> Tensor:
        """The online states at every position ``[B, P, D]`` without gradients (curiosity and V-trace
        only read them), computed once."""
        if self._online_all is None:
            with torch.no_grad():
                self._online_all = self.states_at(None, False)
        return self._online_all

    def states_at(self, index: Tensor | int | None, target: bool) -> Tensor:
        """States ``[B, D]`` at position ``index`` (a ``[B]`` tensor or an int), or ``[B, P, D]`` at
        every position (None)."""
        if self.sequences is not None:
            seq = self.sequences[1] if target else self.sequences[0]
            if index is None:
                return seq
            return seq[:, index] if isinstance(index, int) else gather_positions(seq, index)
        rep = self.target_representation if target else self.representation
        if index is None:
            b, p = self.obs[0].shape[:2]
            return rep([o.flatten(0, 1) for o in self.obs]).view(b, p, -1)
        return rep([o[:, index] if isinstance(index, int) else gather_positions(o, index) for o in self.obs])

    def masks_at(self, index: Tensor | int | None) -> Tensor | None:
        if self.action_masks is None or index is None:
            return self.action_masks
        return self.action_masks[:, index] if isinstance(index, int) else gather_positions(self.action_masks, index)


class SacLosses:
    """The loss computation of :class:`algorithm.sac.learner.SAC` (which provides these attributes)."""

    spec: EnvSpec
    sac: SacConfig
    device: torch.device
    models: SacModels
    target_representation: torch.nn.Module
    target_q: torch.nn.Module
    log_alpha: torch.nn.Parameter
    log_alpha_discrete: torch.nn.Parameter
    target_entropy: float
    discrete_target_entropy: Tensor
    munchausen_weight: Tensor  # munchausen_scale, or this update's value of its schedule
    alpha_optimizer: torch.optim.Optimizer | None
    _branches: Tensor | None
    _mask_index: int | None
    _observation_targets: list[int]
    _learn_rng: torch.Generator
    _policy: Callable[[Tensor, Tensor, Tensor | None], PolicySample]  # algorithm.sac.policy.Policy's

    def _losses(
        self,
        obs: list[Tensor],
        actions: Tensor,
        prev_actions: Tensor,
        rewards: Tensor,
        terminated: Tensor,
        truncated: Tensor,
        mask: Tensor,
        behaviour_logp: Tensor,
        rnn_state: Tensor | None,
        weights: Tensor | None,
        noise: Tensor,
        target_heads: Tensor | None,
        policy_heads: Tensor | None,
    ) -> Losses:
        """The SAC losses from the current parameters (:class:`Losses`).
        Batch tensors are ``[B, L(+1), ...]``; the trained step is step ``burn_in_step`` of each
        window (the sampled key; earlier steps only warm up a recurrent state). ``noise [B,
        n_step + 2, A]`` feeds the action samples: position 0 the policy loss's, 1.. the target's
        (only ``noise[:, 1]`` without V-trace, the value at the bootstrap observation).

        With ``train_every_step`` each stored step of a window is trained as the sampled one is
        (:class:`~algorithm.sac.returns.StepWindows`): ``noise`` is ``[B, T, n_step + 2, A]``, one draw per
        trained step, the losses are means over every trained step, and ``td_abs`` is the sampled
        step's (its priority)."""
        sac = self.sac
        alpha = self.log_alpha.detach().exp()
        alpha_d = self.log_alpha_discrete.detach().exp()
        metrics: Metrics = {"learner/alpha": alpha}
        if alpha_d.numel():
            metrics["learner/alpha_discrete"] = alpha_d
        window, fed_states, every_step = self._window(
            obs, actions, prev_actions, rewards, terminated, truncated, mask, behaviour_logp, rnn_state
        )
        if every_step is not None:
            weights = None if weights is None else every_step.spread(weights)
            noise = every_step.per_step(noise)
        state = window.states_at(0, False)  # the trained step's online state, with gradients for the critic
        rewards, aux_loss = self._exploration_terms(window, state, metrics)
        if sac.munchausen_scale > 0:
            rewards = rewards + self._munchausen_terms(window, noise, alpha_d, metrics)
        action0 = window.actions[:, 0]

        # 1. Target y for the trained step: n-step return + gamma^m V(o_m) (eq. 2, 3, 5), or V-trace.
        with torch.no_grad():
            if sac.use_n_step_is:
                y, v = self._vtrace(window, rewards, noise, alpha, alpha_d, target_heads, metrics)
            else:
                m = bootstrap_index(window.valid)
                next_pi = self._policy(window.states_at(m, False), noise[:, 1], window.masks_at(m))
                next_q = self.target_q(window.states_at(m, True), next_pi.continuous, target_heads)
                v = soft_value(next_q.min(dim=0).values, next_pi, alpha, alpha_d, self._branches)
                y = n_step_target(rewards, window.terminated, window.valid, v, sac.gamma)
            old_q = self._clip_reference(window, action0)

        # 2. Critic loss on the live state; policy and temperature losses on the detached state.
        predictions = self._prediction_terms(window, state, metrics)
        q = self.models.q
        q_loss, td_abs, q_metrics = critic_loss(self._q_taken(q, state, action0), y, weights, sac.clip_epsilon, old_q)
        pi = self._policy(state.detach(), noise[:, 0], window.masks_at(0))
        behaviour_entropy = -window.behaviour_logp[:, 0] if sac.discrete_entropy_penalty > 0 else None
        terms = PolicyTerms(state.detach(), pi, policy_heads, alpha, alpha_d, behaviour_entropy)
        pi_loss, pi_metrics = self._policy_loss(terms)
        a_loss = self._temperature_loss(pi)
        metrics.update({**q_metrics, **pi_metrics, "learner/next_value": v, "learner/auxiliary_loss": aux_loss})
        if every_step is not None:
            td_abs = td_abs[every_step.sampled_rows]
        kept = terms if sac.update_order == "critic_first" else None
        return Losses(q_loss, pi_loss, a_loss, aux_loss, predictions, td_abs, metrics, fed_states, kept)

    def _policy_loss(self, terms: PolicyTerms) -> tuple[Tensor, Metrics]:
        """The policy's loss against the online critic as its parameters are now (their gradients cut)."""
        q = self.models.q(terms.state, terms.pi.continuous, terms.heads, detach_params=True)
        loss, metrics = policy_loss(q.min(dim=0).values, terms.pi, terms.alpha, terms.alpha_discrete, self._branches)
        if terms.behaviour_entropy is None:
            return loss, metrics
        assert self._branches is not None
        penalty = entropy_penalty(-expected_log_prob(terms.pi, self._branches).sum(dim=-1), terms.behaviour_entropy)
        metrics["learner/entropy_penalty"] = penalty.detach()
        return loss + self.sac.discrete_entropy_penalty * penalty, metrics

    def _temperature_loss(self, pi: PolicySample) -> Tensor:
        """``use_auto_alpha``: the continuous temperature's loss toward ``-|A_c|`` and each discrete
        branch's toward its target entropy (eq. 18; zero when alpha is fixed)."""
        loss = torch.zeros((), device=self.device)
        if self.alpha_optimizer is None:
            return loss
        if pi.continuous_log_prob is not None:
            loss = loss + alpha_loss(self.log_alpha, pi.continuous_log_prob, self.target_entropy)[0]
        if pi.log_probs is not None and self._branches is not None:
            expected = expected_log_prob(pi, self._branches)
            loss = loss + alpha_loss(self.log_alpha_discrete, expected, self.discrete_target_entropy)[0]
        return loss

    # -- windows and recurrent states ----------------------------------------------------------

    def _window(
        self,
        obs: list[Tensor],
        actions: Tensor,
        prev_actions: Tensor,
        rewards: Tensor,
        terminated: Tensor,
        truncated: Tensor,
        mask: Tensor,
        behaviour_logp: Tensor,
        rnn_state: Tensor | None,
    ) -> tuple[Window, Tensor | None, StepWindows | None]:
        """The batch from the trained step on, the online recurrent state fed in at each window
        step ``[B, L, S]`` (None without ``use_rnn``) and, with ``train_every_step``, how the window
        was cut into one short window per trained step (the :class:`Window` is then their batch). A
        recurrent representation runs over the whole window (burn-in first); a feed-forward one only
        where states are asked for."""
        burn_in = self.sac.burn_in_step
        every_step = None
        if self.sac.train_every_step:
            first = 0 if self.sac.burn_in_gradient else burn_in  # burn-in states carry gradients only then
            every_step = StepWindows(mask, first, self.sac.n_step, burn_in)
            cut_steps, cut_positions = every_step.steps, every_step.positions
        else:
            cut_steps = cut_positions = lambda x: x[:, burn_in:]  # noqa: E731
        sequences, fed_states = None, None
        if rnn_state is not None:
            online, target, fed = self._sequence_states(obs, actions, prev_actions, mask, rnn_state)
            fed_states = fed[:, :-1]
            sequences = (cut_positions(online), cut_positions(target))
        obs = [cut_positions(o) for o in obs]
        actions, rewards, terminated, truncated, mask, behaviour_logp = (
            cut_steps(x) for x in (actions, rewards, terminated, truncated, mask, behaviour_logp)
        )
        window = Window(
            obs=obs,
            actions=actions,
            rewards=rewards,
            terminated=terminated,
            mask=mask,
            behaviour_logp=behaviour_logp,
            valid=valid_steps(mask, terminated, truncated),
            action_masks=None if self._mask_index is None else obs[self._mask_index] > 0.5,
            representation=self.models.representation,
            target_representation=self.target_representation,
            sequences=sequences,
        )
        return window, fed_states, every_step

    def _sequence_states(
        self, obs: list[Tensor], actions: Tensor, prev_actions: Tensor, mask: Tensor, rnn_state: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``use_rnn``: online and target states ``[B, L + 1, H]`` at every obs position of the window,
        from the stored state at its first valid row, and the online recurrent state fed in at each
        position ``[B, L + 1, S]``. Positions before the first valid row keep the state.

        A position's previous action is the stored one on a step row; on the bootstrap position of a
        window cut short by its chunk's end (or a time-limit truncation, which ends a chunk), and on
        position ``L``, it is the action of the step before, which the window holds (the table
        stores zeros on a chunk's bootstrap row)."""
        first = mask.long().argmax(dim=1)  # the first valid step (look-back rows before it are masked)
        positions = torch.arange(mask.shape[1] + 1, device=mask.device)
        valid = positions[None, :] >= first[:, None]
        stepped = torch.where(mask[:, 1:, None], prev_actions[:, 1:], actions[:, :-1])
        prev = torch.cat([prev_actions[:, :1], stepped, actions[:, -1:]], dim=1)
        rep, target_rep = self.models.representation, self.target_representation
        assert isinstance(rep, RecurrentRepresentation) and isinstance(target_rep, RecurrentRepresentation)
        burn_in = self.sac.burn_in_step
        online, fed = rep.sequence_with_states(obs, prev, rnn_state, valid, burn_in, self.sac.burn_in_gradient)
        with torch.no_grad():
            target = target_rep.sequence(obs, prev, rnn_state, valid, burn_in)
        return online, target, fed

    # -- features -------------------------------------------------------------------------------

    def _exploration_terms(self, window: Window, state: Tensor, metrics: Metrics) -> tuple[Tensor, Tensor]:
        """Curiosity (Pathak et al. 2017) and RND (Burda et al. 2018): the rewards with their
        intrinsic bonuses added (targets only) and the exploration models' training loss."""
        sac, rewards = self.sac, window.rewards
        aux_loss = torch.zeros((), device=self.device)
        if self.models.curiosity is not None:
            states = window.online_states()
            b, p = states.shape[:2]
            forward_error, inverse_error = (
                e.view(b, p - 1)
                for e in self.models.curiosity.errors(
                    states[:, :-1].flatten(0, 1), window.actions.flatten(0, 1), states[:, 1:].flatten(0, 1)
                )
            )
            intrinsic = sac.curiosity_strength * torch.where(window.valid, forward_error.detach(), 0.0)
            rewards = rewards + intrinsic
            aux_loss = aux_loss + ((forward_error + inverse_error) * window.valid).sum() / window.valid.sum()
            metrics["learner/curiosity_reward"] = intrinsic[:, 0]
        if self.models.rnd is not None:
            novelty = self.models.rnd.novelty(state.detach(), window.actions[:, 0])
            aux_loss = aux_loss + novelty.mean()
            metrics["learner/rnd_novelty"] = novelty.detach()
            if sac.rnd_strength > 0:  # novelty as reward, as Burda et al. use it: it fades once pairs are known
                states = window.online_states()
                b, p = states.shape[:2]
                with torch.no_grad():
                    every = self.models.rnd.novelty(states[:, :-1].flatten(0, 1), window.actions.flatten(0, 1))
                    every = every.view(b, p - 1)
                    if sac.rnd_normalize:
                        every = self.models.rnd.relative(every, window.valid)
                intrinsic = sac.rnd_strength * torch.where(window.valid, every, 0.0)
                rewards = rewards + intrinsic
                metrics["learner/rnd_reward"] = intrinsic[:, 0]
        return rewards, aux_loss

    def _munchausen_terms(self, window: Window, noise: Tensor, alpha_d: Tensor, metrics: Metrics) -> Tensor:
        """``munchausen_scale``: the Munchausen term of every window step ``[B, L]`` from the current
        policy's log-probabilities of the stored actions (:func:`algorithm.sac.equations.munchausen_bonus`);
        steps past the target's end are never read (``n_step_target``)."""
        assert self._branches is not None
        with torch.no_grad():
            states = window.online_states()[:, :-1]
            b, steps = states.shape[:2]
            masks = window.masks_at(None)
            pi = self._policy(
                states.flatten(0, 1),
                noise[:, :1].expand(-1, steps, -1).flatten(0, 1),  # discrete-only: no continuous sample is drawn
                None if masks is None else masks[:, :-1].flatten(0, 1),
            )
            assert pi.log_probs is not None
            chosen = window.actions.flatten(0, 1)[:, : self.spec.action.discrete_size] > 0.5
            taken = torch.where(chosen, pi.log_probs, 0.0) @ self._branches
            bonus = munchausen_bonus(taken, alpha_d, self.munchausen_weight, self.sac.munchausen_log_floor)
        metrics["learner/munchausen_bonus"] = bonus.view(b, steps)[:, 0]
        return bonus.view(b, steps)

    def _vtrace(
        self,
        window: Window,
        rewards: Tensor,
        noise: Tensor,
        alpha: Tensor,
        alpha_d: Tensor,
        heads: Tensor | None,
        metrics: Metrics,
    ) -> tuple[Tensor, Tensor]:
        """``use_n_step_is``: the V-trace target over the window (Espeholt et al. 2018, eq. 1, with
        SAC's soft values) and the value at the step after the trained one, for its metric."""
        sac = self.sac
        values, log_pi = self._window_values(
            window.online_states(), window.states_at(None, True), window.masks_at(None),
            window.actions, noise[:, 1:], alpha, alpha_d, heads,
        )  # fmt: skip
        y, rho = vtrace_target(
            rewards, window.terminated, window.valid, values, log_pi - window.behaviour_logp,
            sac.gamma, sac.v_lambda, sac.v_rho, sac.v_c,
        )  # fmt: skip
        weighted = rho > 0
        metrics["learner/vtrace_rho"] = rho[weighted] if weighted.any() else torch.ones(1, device=self.device)
        return y, values[:, 1]

    def _window_values(
        self,
        online: Tensor,
        target: Tensor,
        action_mask: Tensor | None,
        actions: Tensor,
        noise: Tensor,
        alpha: Tensor,
        alpha_d: Tensor,
        heads: Tensor | None,
    ) -> tuple[Tensor, Tensor]:
        """For V-trace: soft values ``V(o_t) [B, P]`` at every window position (online and target
        states ``[B, P, D]``) and the current policy's ``log pi(a_t|o_t) [B, P - 1]`` of the stored
        actions (greedy dqn-like branches: 0 for the greedy action, ``MASKED_LOG_PROB`` otherwise,
        so the trace is cut where behaviour left it)."""
        b, positions = online.shape[:2]
        state = online.flatten(0, 1)
        mask = None if action_mask is None else action_mask.flatten(0, 1)
        pi = self._policy(state, noise.flatten(0, 1), mask)
        q = self.target_q(target.flatten(0, 1), pi.continuous, heads).min(dim=0).values
        values = soft_value(q, pi, alpha, alpha_d, self._branches).view(b, positions)

        taken = actions.flatten(0, 1)
        steps = torch.arange(b * positions, device=actions.device).view(b, positions)[:, :-1].flatten()
        log_pi = torch.zeros(steps.shape[0], device=actions.device)
        policy_state = self.models.representation.policy_state(state[steps])
        d = self.spec.action.discrete_size
        if self.models.policy is not None:
            log_pi = log_pi + self.models.policy.log_prob(policy_state, taken[:, d:])
        if self._branches is not None:
            assert pi.probs is not None
            chosen = taken[:, :d] > 0.5
            if pi.log_probs is not None:
                per_action = pi.log_probs[steps]
            else:
                per_action = torch.where(pi.probs[steps] > 0.5, 0.0, MASKED_LOG_PROB)
            log_pi = log_pi + torch.where(chosen, per_action, 0.0).sum(dim=-1)
        return values, log_pi.view(b, positions - 1)

    def _clip_reference(self, window: Window, action0: Tensor) -> Tensor | None:
        """``clip_epsilon``: the target critic's values of the stored action, which the clipped
        critic loss keeps the new values near (None without clipping)."""
        if self.sac.clip_epsilon is None:
            return None
        return self._q_taken(self.target_q, window.states_at(0, True), action0)

    def _prediction_terms(self, window: Window, state: Tensor, metrics: Metrics) -> dict[str, Tensor]:
        """Prediction models' losses by name (transition, reward, observation) on the live state;
        ``update`` gates their gradient into the representation (nn/prediction.py)."""
        if self.models.prediction is None:
            return {}
        with torch.no_grad():
            next_state = window.states_at(1, True)
        targets = [window.obs[i][:, 0].flatten(1) for i in self._observation_targets]
        predictions = prediction_losses(
            self.models.prediction, state, window.actions[:, 0], next_state, window.rewards[:, 0],
            torch.cat(targets, dim=-1) if targets else None, self.sac.transition_kl,
        )  # fmt: skip
        metrics.update({f"learner/prediction_{k}": v.detach() for k, v in predictions.items()})
        return predictions

    # -- helpers --------------------------------------------------------------------------------

    def _q_taken(self, q: torch.nn.Module, state: Tensor, action: Tensor, heads: Tensor | None = None) -> Tensor:
        """Each head's value of the stored ``action``: ``[E, B]``, or ``[E, B, K]`` per discrete branch."""
        d = self.spec.action.discrete_size
        values = q(state, action[..., d:] if self.models.policy is not None else None, heads)
        if self._branches is None:
            return values
        return (values * action[..., :d]) @ self._branches

    def _subset(self) -> Tensor | None:
        """A fresh random subset of ``ensemble_q_sample`` heads; None (all heads) when it is all."""
        n, k = self.sac.ensemble_q_num, self.sac.ensemble_q_sample
        if k == n:
            return None
        return torch.randperm(n, generator=self._learn_rng, device=self.device)[:k]
