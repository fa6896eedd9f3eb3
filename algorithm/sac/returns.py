"""Bootstrapped targets over replay windows, as pure functions on batch-major ``[B, L]`` tensors.

A window holds steps ``0..L-1`` and ``obs`` positions ``0..L`` (position ``t + 1`` is the
observation after step ``t``; see :class:`algorithm.types.Batch`). The Q target is for step 0:

    y = sum_{k < m} gamma^k r_k  +  gamma^m (1 - terminated_{m-1}) v(o_m)

where ``m`` is the number of valid steps: the prefix of the window that is inside its chunk
(``mask``) and not past an episode end. ``terminated`` stops bootstrapping; ``truncated`` and a
masked tail bootstrap from the real next observation ``o_m`` (docs/architecture.md sections 3 and 5).

V-trace (``sac.use_n_step_is``) is :func:`vtrace_target`, a sibling of :func:`n_step_target` that
takes per-step soft values ``v(o_1..o_m)`` and ``log pi - log mu`` of steps ``1..m-1`` instead of
one bootstrap value. Step 0 is the action ``Q`` evaluates and is never importance-weighted; the
rest of the window becomes the V-trace estimate at ``o_1`` (Espeholt et al. 2018, 1802.01561,
eq. 1) with truncated ratios ``rho_t = min(rho_bar, pi_t/mu_t)`` and traces
``c_t = lambda min(c_bar, pi_t/mu_t)`` (lambda as in the remarks of 1802.01561 section 4.1):

    y = r_0 + gamma (1 - terminated_0) v_1
    v_1 = v(o_1) + sum_{t=1}^{m-1} gamma^{t-1} (prod_{i=1}^{t-1} c_i) rho_t
                   (r_t + gamma (1 - terminated_t) v(o_{t+1}) - v(o_t))

With every ratio 1, ``lambda = 1`` and ``rho_bar, c_bar >= 1`` the sum telescopes to the n-step
target above (the on-policy case below 1802.01561 eq. 1).
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


def vtrace_target(
    rewards: Tensor,
    terminated: Tensor,
    valid: Tensor,
    values: Tensor,
    log_ratios: Tensor,
    gamma: float,
    lambda_: float,
    rho_bar: float,
    c_bar: float,
) -> tuple[Tensor, Tensor]:
    """V-trace soft Q target for step 0 of each window (formula in the module docstring).

    ``rewards``/``terminated``/``valid``/``log_ratios`` are ``[B, L]``, ``log_ratios[:, t] =
    log pi(a_t|o_t) - log mu(a_t|o_t)``; ``values`` is ``[B, L + 1]``, ``v(o_t)`` at positions
    ``0..L`` (position 0 is never read). ``valid`` is as from :func:`valid_steps`, with step 0 valid
    (every window starts at a stored step); only its prefix up to the first invalid or terminated
    step is used, so ``m`` is :func:`bootstrap_index` of it. Unused entries (step 0 of
    ``log_ratios``, steps past ``m``, positions past ``m`` of ``values``, and ``v(o_m)`` after a
    termination) may hold anything, NaN and inf included: they are only read under ``torch.where``.

    Returns ``(y [B], rho [B, L])``: ``rho`` holds the truncated ratios ``min(rho_bar, pi_t/mu_t)``
    of steps ``1..m-1`` and 0 elsewhere, for logging. The sum is the backward recursion of
    1802.01561 remark 1, ``v_t - v(o_t) = delta_t + gamma c_t (v_{t+1} - v(o_{t+1}))`` with
    ``v_m = v(o_m)``, run over ``t = L-1..1`` on ``[B]`` tensors (``L`` is small).
    """
    window = rewards.shape[1]
    prefix = valid.long().cumprod(dim=1) > 0
    used = valid_steps(prefix, terminated, torch.zeros_like(terminated))
    weighted = used & (torch.arange(window, device=used.device) > 0)  # step 0 is never importance-weighted
    ratio = log_ratios.exp()
    rho_all = ratio.clamp(max=rho_bar)
    c_all = lambda_ * ratio.clamp(max=c_bar)

    # correction[b] = v_{t+1} - v(o_{t+1}); 0 at t + 1 = m (bootstrap) and wherever step t + 1 is unused
    correction = torch.zeros_like(values[:, 0])
    for t in range(window - 1, 0, -1):
        next_value = torch.where(terminated[:, t], 0.0, values[:, t + 1])  # where, not *: see n_step_target
        delta = rho_all[:, t] * (rewards[:, t] + gamma * next_value - values[:, t])
        # a used, terminated step t has no used step t + 1, so correction is already 0 there
        correction = torch.where(used[:, t], delta + gamma * c_all[:, t] * correction, 0.0)

    v_1 = values[:, 1] + correction
    y = rewards[:, 0] + gamma * torch.where(terminated[:, 0], 0.0, v_1)
    rho = torch.where(weighted, rho_all, 0.0)
    return y, rho


class StepWindows:
    """``sac_config.train_every_step``: one window of ``L`` steps read as a batch of shorter windows, one
    starting at each stored step ``t >= first``, each holding steps ``t..t+n-1`` and obs positions
    ``t..t+n`` (cut at the window's end, so the last ``n - 1`` have shorter targets; padding past it
    is masked). Every function of this module then gives each step its own target unchanged.

    ``select [B, T]`` marks the pairs ``(b, t)`` that start at a stored step (``mask``); the batch of
    short windows is those pairs in row-major order, ``M`` of them. Training every step of a
    sequence rather than one is R2D2's (Kapturowski et al. 2019); with burn-in gradients the burn-in
    steps are trained too, since their states carry gradients anyway.
    """

    def __init__(self, mask: Tensor, first: int, n_step: int, sampled: int) -> None:
        window = mask.shape[1]
        self.n_step = n_step
        self.starts = torch.arange(first, window, device=mask.device)
        self.select = mask[:, first:]
        # the row, among the M short windows, of each window's sampled step (always stored: Batch's contract)
        rows = self.select.flatten().long().cumsum(0).view_as(self.select) - 1
        self.sampled_rows = rows[:, sampled - first]

    def steps(self, x: Tensor) -> Tensor:
        """``x [B, L, ...]`` per step -> ``[M, n, ...]``."""
        return self._cut(x, self.n_step)

    def positions(self, x: Tensor) -> Tensor:
        """``x [B, L + 1, ...]`` per obs position -> ``[M, n + 1, ...]``."""
        return self._cut(x, self.n_step + 1)

    def spread(self, x: Tensor) -> Tensor:
        """``x [B, ...]``, one value per window (an importance weight) -> ``[M, ...]``."""
        return x[:, None].expand(-1, self.select.shape[1], *x.shape[1:])[self.select]

    def per_step(self, x: Tensor) -> Tensor:
        """``x [B, T, ...]``, one value per short window (noise drawn for each) -> ``[M, ...]``."""
        return x[self.select]

    def _cut(self, x: Tensor, length: int) -> Tensor:
        b, have = x.shape[:2]
        need = int(self.starts[-1]) + length
        if need > have:
            x = torch.cat([x, x.new_zeros((b, need - have, *x.shape[2:]))], dim=1)
        index = self.starts[:, None] + torch.arange(length, device=x.device)[None, :]  # [T, length]
        return x[:, index][self.select]
