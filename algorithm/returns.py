"""Bootstrapped targets over replay windows, as pure functions on batch-major ``[B, L]`` tensors.

A window holds steps ``0..L-1`` and ``obs`` positions ``0..L`` (position ``t + 1`` is the
observation after step ``t``; see :class:`algorithm.types.Batch`). The Q target is for step 0:

    y = sum_{k < m} gamma^k r_k  +  gamma^m (1 - terminated_{m-1}) v(o_m)

where ``m`` is the number of valid steps: the prefix of the window that is inside its chunk
(``mask``) and not past an episode end. ``terminated`` stops bootstrapping; ``truncated`` and a
masked tail bootstrap from the real next observation ``o_m`` (ARCHITECTURE.md 3-4).

V-trace (``sac.use_n_step_is``) belongs here as a sibling of :func:`n_step_target`: it will take
per-step soft values ``v(o_1..o_m)`` and truncated ratios ``min(rho_bar, pi/mu)`` for steps
``1..m-1`` (the first action is never importance-weighted) instead of one bootstrap value.
"""

from __future__ import annotations

import torch
from torch import Tensor


def valid_steps(mask: Tensor, terminated: Tensor, truncated: Tensor) -> Tensor:
    """``[B, L]`` bool: steps inside the chunk (``mask``) that do not come after an episode end.

    By the replay contract an episode end is the last masked step anyway; cutting here as well
    keeps the target right if a window ever ran on past one.
    """
    done = (terminated | truncated).to(torch.int32)
    ended_before = (done.cumsum(dim=1) - done) > 0
    return mask & ~ended_before


def bootstrap_index(valid: Tensor) -> Tensor:
    """``[B]`` int64: position ``m`` of the observation after the last valid step."""
    return valid.sum(dim=1)


def gather_positions(x: Tensor, index: Tensor) -> Tensor:
    """``x[b, index[b]]`` for ``x`` of shape ``[B, L + 1, ...]``: one observation per window."""
    return x[torch.arange(x.shape[0], device=x.device), index]


def n_step_target(rewards: Tensor, terminated: Tensor, valid: Tensor, next_value: Tensor, gamma: float) -> Tensor:
    """``[B]`` n-step soft Q target for step 0 of each window (formula in the module docstring).

    ``rewards``/``terminated``/``valid`` are ``[B, L]``; ``next_value`` is ``[B]``, the soft value
    of the observation at :func:`bootstrap_index` (``v(o_m)``). ``n_step = 1`` reduces to
    ``r_0 + gamma (1 - terminated_0) v(o_1)`` (Haarnoja et al. 2018, 1812.05905, eq. 2 and 5).
    """
    window = rewards.shape[1]
    powers = gamma ** torch.arange(window + 1, device=rewards.device, dtype=rewards.dtype)  # gamma^0..gamma^L
    m = bootstrap_index(valid)
    discounted = torch.where(valid, rewards, 0.0) * powers[:window]
    terminal = (terminated & valid).any(dim=1)
    bootstrap = torch.where(terminal, 0.0, powers[m] * next_value)  # where, not *: v of a terminal obs is never read
    return discounted.sum(dim=1) + bootstrap
