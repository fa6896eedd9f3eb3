"""What one SAC pass reads: :class:`PassInputs`, a batch as the update hands it over (typed, in the
order a CUDA graph records it), and :class:`Window`, that batch from the trained step on with the
states at its observation positions.

:func:`cut_window` makes the :class:`Window`. It is where two features live: a recurrent
representation (``use_rnn``) runs over the whole window, burn-in first (:func:`sequence_states`), and
``train_every_step`` cuts each window into one short window per stored step
(:class:`~algorithm.sac.returns.StepWindows`), so every step is trained as the sampled one is.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from algorithm.config.schema import SacConfig
from algorithm.nn.models import SacModels
from algorithm.nn.recurrent import RecurrentRepresentation
from algorithm.sac.returns import StepWindows, gather_positions, valid_steps


@dataclass
class PassInputs:
    """One pass's inputs (batch tensors ``[B, L(+1), ...]``; see :class:`algorithm.types.Batch`): the
    sensors' observations, the window's steps, the recurrent state at its start (``use_rnn``), PER
    weights ``[B]`` (``use_priority``), the standard normal ``noise`` the policy samples are made of
    (:meth:`algorithm.sac.learner.SAC._noise`) and the Q-head subsets of the target and the policy
    loss (None: every head). :meth:`flat` and :meth:`from_flat` are the list a CUDA graph records."""

    obs: list[Tensor]
    actions: Tensor
    prev_actions: Tensor
    rewards: Tensor
    terminated: Tensor
    truncated: Tensor
    mask: Tensor
    behaviour_logp: Tensor
    rnn_state: Tensor | None
    weights: Tensor | None
    noise: Tensor
    target_heads: Tensor | None
    policy_heads: Tensor | None

    def flat(self) -> list[Tensor | None]:
        return [*self.obs, *(getattr(self, f.name) for f in fields(self)[1:])]

    @classmethod
    def from_flat(cls, values: Sequence[Tensor | None], n_sensors: int) -> PassInputs:
        obs = [o for o in values[:n_sensors] if o is not None]
        return cls(obs, *values[n_sensors:])  # type: ignore[arg-type]


@dataclass
class Window:
    """A batch's windows from the trained step on (``burn_in_step`` rows dropped), with the states at
    their observation positions: precomputed ``sequences`` (online, target ``[B, P, D]``) for a
    recurrent representation, else computed where asked by the feed-forward ``representation``s.
    ``weights`` and ``noise`` are the pass's, one per trained step; ``steps`` says how the window was
    cut with ``train_every_step`` (None: one trained step per window)."""

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
    weights: Tensor | None
    noise: Tensor
    steps: StepWindows | None
    fed_states: Tensor | None  # use_rnn: the online recurrent state fed in at each window step [B, L, S]
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

    def sampled(self, per_trained_step: Tensor) -> Tensor:
        """The values ``[B]`` of the sampled steps (their priorities) from one per trained step."""
        return per_trained_step if self.steps is None else per_trained_step[self.steps.sampled_rows]


def cut_window(
    inputs: PassInputs, sac: SacConfig, models: SacModels, target_representation: torch.nn.Module,
    mask_index: int | None,
) -> Window:  # fmt: skip
    """The :class:`Window` of ``inputs``. A recurrent representation runs over the whole window
    (burn-in first); a feed-forward one only where states are asked for."""
    burn_in = sac.burn_in_step
    steps, weights, noise = None, inputs.weights, inputs.noise
    if sac.train_every_step:
        first = 0 if sac.burn_in_gradient else burn_in  # burn-in states carry gradients only then
        steps = StepWindows(inputs.mask, first, sac.n_step, burn_in)
        cut_steps, cut_positions = steps.steps, steps.positions
    else:
        cut_steps = cut_positions = lambda x: x[:, burn_in:]  # noqa: E731
    sequences, fed_states = None, None
    if inputs.rnn_state is not None:
        online, target, fed = sequence_states(
            inputs.obs, inputs.actions, inputs.prev_actions, inputs.mask, inputs.rnn_state, sac, models,
            target_representation,
        )  # fmt: skip
        fed_states = fed[:, :-1]
        sequences = (cut_positions(online), cut_positions(target))
    obs = [cut_positions(o) for o in inputs.obs]
    actions, rewards, terminated, truncated, mask, behaviour_logp = (
        cut_steps(x)
        for x in (inputs.actions, inputs.rewards, inputs.terminated, inputs.truncated, inputs.mask,
                  inputs.behaviour_logp)
    )  # fmt: skip
    if steps is not None:
        weights = None if weights is None else steps.spread(weights)
        noise = steps.per_step(noise)
    return Window(
        obs=obs,
        actions=actions,
        rewards=rewards,
        terminated=terminated,
        mask=mask,
        behaviour_logp=behaviour_logp,
        valid=valid_steps(mask, terminated, truncated),
        action_masks=None if mask_index is None else obs[mask_index] > 0.5,
        representation=models.representation,
        target_representation=target_representation,
        sequences=sequences,
        weights=weights,
        noise=noise,
        steps=steps,
        fed_states=fed_states,
    )


def sequence_states(
    obs: list[Tensor], actions: Tensor, prev_actions: Tensor, mask: Tensor, rnn_state: Tensor, sac: SacConfig,
    models: SacModels, target_representation: torch.nn.Module,
) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
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
    rep = models.representation
    assert isinstance(rep, RecurrentRepresentation) and isinstance(target_representation, RecurrentRepresentation)
    burn_in = sac.burn_in_step
    online, fed = rep.sequence_with_states(obs, prev, rnn_state, valid, burn_in, sac.burn_in_gradient)
    with torch.no_grad():
        target = target_representation.sequence(obs, prev, rnn_state, valid, burn_in)
    return online, target, fed
