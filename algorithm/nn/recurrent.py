"""Recurrent representation (``sac_config.use_rnn``): a GRU or LSTM over per-step features.

At each step the cell reads the feature vector of the observation (from any non-recurrent
:class:`~algorithm.nn.models.Representation`: concatenated vectors, conv encoders) together with
the previous action (zeros at episode start; chunks store it per step for this, docs/architecture.md
section 3), and its output is the state every Q head and the policy see.

Acting steps one observation at a time with :meth:`RecurrentRepresentation.step`, carrying the
flat recurrent state ``[N, rnn_state_size]`` (``h`` for a GRU, ``[h | c]`` for an LSTM) that the
actor stores with each step. Learning runs :meth:`RecurrentRepresentation.sequence` over a
replay window from the state stored at its first valid row (R2D2's stored-state strategy,
Kapturowski et al. 2019): the first ``burn_in`` steps only warm the state up — without gradients
unless asked — and positions before the window's first valid row leave the state untouched.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from algorithm.nn.models import Representation
from algorithm.nn.shapes import RnnType, recurrent_state_width


class RecurrentRepresentation(Representation):
    """``state_t, s_{t+1} = cell([features(o_t) | a_{t-1}], s_t)``; ``state_dim`` = ``hidden_size``."""

    def __init__(self, features: Representation, action_size: int, hidden_size: int, rnn_type: RnnType) -> None:
        super().__init__()
        if features.policy_state_dim != features.state_dim:
            raise ValueError("use_rnn with critic_only sensors is not supported: the policy would see them")
        self.features = features
        self.rnn_type = rnn_type
        self.hidden_size = hidden_size
        cell: type[nn.GRUCell] | type[nn.LSTMCell] = nn.GRUCell if rnn_type == "gru" else nn.LSTMCell
        self.cell = cell(features.state_dim + action_size, hidden_size)
        self.state_dim = self.policy_state_dim = hidden_size
        self.rnn_state_size = recurrent_state_width(hidden_size, rnn_type)

    def forward(self, obs: list[Tensor]) -> Tensor:  # pragma: no cover - a recurrent model needs its state
        raise TypeError("RecurrentRepresentation needs the previous action and state: use step() or sequence()")

    def _cell(self, x: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        """One step: ``(output [N, H], next flat state [N, rnn_state_size])``."""
        if self.rnn_type == "gru":
            h = self.cell(x, state)
            return h, h
        h, c = self.cell(x, tuple(state.chunk(2, dim=-1)))
        return h, torch.cat([h, c], dim=-1)

    def step(self, obs: list[Tensor], prev_action: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        """Acting: ``(state features [N, H], next recurrent state)`` for one observation per env."""
        x = torch.cat([self.features(obs), prev_action], dim=-1)
        return self._cell(x, state)

    def sequence(
        self,
        obs: list[Tensor],
        prev_actions: Tensor,
        initial: Tensor,
        valid: Tensor,
        burn_in: int = 0,
        burn_in_gradient: bool = False,
    ) -> Tensor:
        """States ``[B, P, H]`` for ``P`` consecutive positions (obs ``[B, P, ...]``, previous actions
        ``[B, P, A]``) from ``initial [B, rnn_state_size]``.

        Where ``valid [B, P]`` is False the recurrent state is carried unchanged (positions before
        the window's first valid row, whose stored state is ``initial``); the output there is the
        carried ``h``. The first ``burn_in`` positions run without gradients unless
        ``burn_in_gradient``.
        """
        return self.sequence_with_states(obs, prev_actions, initial, valid, burn_in, burn_in_gradient)[0]

    def sequence_with_states(
        self,
        obs: list[Tensor],
        prev_actions: Tensor,
        initial: Tensor,
        valid: Tensor,
        burn_in: int = 0,
        burn_in_gradient: bool = False,
    ) -> tuple[Tensor, Tensor]:
        """:meth:`sequence`, and the recurrent state fed in at each position ``[B, P, rnn_state_size]``
        (detached): what an actor would have stored there with these weights
        (``sac_config.refresh_rnn_states`` writes it back into replay)."""
        b, p = prev_actions.shape[:2]
        features = self.features([o.flatten(0, 1) for o in obs]).view(b, p, -1)
        x = torch.cat([features, prev_actions], dim=-1)
        state = initial
        outputs, fed = [], []
        for t in range(p):
            fed.append(state.detach())
            with torch.set_grad_enabled(torch.is_grad_enabled() and (t >= burn_in or burn_in_gradient)):
                h, next_state = self._cell(x[:, t], state)
                keep = valid[:, t, None]
                state = torch.where(keep, next_state, state)
                outputs.append(torch.where(keep, h, state[:, : self.hidden_size]))
        return torch.stack(outputs, dim=1), torch.stack(fed, dim=1)
