"""The SAC losses as pure functions of tensors: ``(loss, ..., metrics)``.

Equations are from Haarnoja et al. 2018, "Soft Actor-Critic Algorithms and Applications"
(arXiv:1812.05905) for continuous actions and Christodoulou 2019, "Soft Actor-Critic for
Discrete Action Settings" (arXiv:1910.07207) for discrete ones, where expectations over the
policy are computed exactly instead of sampled. Metrics are *unreduced* detached tensors,
reduced only when a caller asks for them, so the hot path never syncs per metric.

Actions may be continuous, discrete with several branches, or both (docs/architecture.md section 3). Each
discrete branch ``b`` has its own Q values ``Q_b(s, a_b[, a_c])``, trained toward the same
target, and the value of a state averages the branches (the action-branching scheme of
Tavakoli et al. 2018, arXiv:1711.08946, with SAC's soft values in place of the max):

    V(s) = mean_b sum_a pi_b(a|s) [min_i Q_i,b(s, a, a_c) - alpha_b log pi_b(a|s)] - alpha_c log pi_c(a_c|s)

with ``a_c ~ pi_c(.|s)`` one reparameterised sample. Without discrete branches the first term
is ``min_i Q_i(s, a_c)``; without a continuous part ``a_c`` and its entropy term drop out.
``discrete_dqn_like`` makes ``pi_b`` the greedy one-hot of the online Q and ``alpha_b = 0``,
which turns the same formula into the double-DQN target (van Hasselt et al. 2016).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

Metrics = dict[str, Tensor]


@dataclass
class PolicySample:
    """What the policy does at ``N`` states.

    ``continuous [N, A_c]`` is a reparameterised sample in ``[-1, 1]`` with ``continuous_log_prob
    [N]``; ``probs``/``log_probs [N, D]`` are the discrete branches' full distributions (masked
    actions at probability 0). ``log_probs`` is None when the discrete part is greedy
    (``discrete_dqn_like``): it has no entropy and no policy to train.
    """

    continuous: Tensor | None = None
    continuous_log_prob: Tensor | None = None
    probs: Tensor | None = None
    log_probs: Tensor | None = None


def branch_matrix(branches: tuple[int, ...], device: torch.device | str = "cpu") -> Tensor:
    """``[D, K]`` float 0/1: entry ``(d, b)`` is 1 when flat discrete action ``d`` belongs to branch
    ``b``. ``x @ M`` sums ``x [..., D]`` within each branch."""
    owner = torch.repeat_interleave(torch.arange(len(branches)), torch.tensor(branches, dtype=torch.long))
    return torch.nn.functional.one_hot(owner, len(branches)).float().to(device)


def importance_weights(probabilities: Tensor, table_size: int, beta: float) -> Tensor:
    """PER weights ``(table_size * p) ** -beta`` divided by the batch maximum (Schaul et al. 2016,
    section 3.4), computed in float64 and returned as float32 ``[B]``."""
    w = (table_size * probabilities.double()).pow(-beta)
    return (w / w.max()).float()


def soft_value(
    q_min: Tensor,
    pi: PolicySample,
    alpha: Tensor,
    alpha_discrete: Tensor | None,
    branches: Tensor | None,
) -> Tensor:
    """``V(s) [N]`` from the formula in the module docstring.

    ``q_min`` is ``min_i Q_i`` over a head subset at ``(s, pi.continuous)``: ``[N]`` without
    discrete branches, else ``[N, D]``. ``alpha_discrete [K]`` and ``branches`` (the
    :func:`branch_matrix`) are needed only with discrete branches."""
    if pi.probs is None:
        v = q_min
    else:
        assert branches is not None
        inner = q_min
        if pi.log_probs is not None:
            assert alpha_discrete is not None
            inner = q_min - (branches @ alpha_discrete) * pi.log_probs
        v = ((pi.probs * inner) @ branches).mean(dim=-1)
    if pi.continuous_log_prob is not None:
        v = v - alpha * pi.continuous_log_prob
    return v


def critic_loss(
    q_taken: Tensor,
    target: Tensor,
    weights: Tensor | None,
    clip_epsilon: float | None = None,
    old_q: Tensor | None = None,
) -> tuple[Tensor, Tensor, Metrics]:
    """``J_Q = mean_b w_b sum_i 1/2 (Q_i(s_b, a_b) - y_b)^2`` (eq. 5, PER-weighted per sample).

    ``q_taken`` is each head's value of the taken action: ``[E, B]``, or ``[E, B, K]`` with one value
    per discrete branch (each regresses to the same ``y``; branches are averaged). Heads are summed,
    so every head's error reaches the representation with full weight. With ``clip_epsilon``, each
    squared error is the max of the plain one and the one of ``old_q + clip(Q - old_q, -eps, eps)``,
    ``old_q`` being the *target* heads' value of the same action (PPO-style value clipping, as the
    revived system did). Returns ``(loss, td_abs [B], metrics)``, ``td_abs`` = ``|Q - y|`` averaged
    over heads (and branches) from this same forward pass.
    """
    y = target if q_taken.dim() == 2 else target.unsqueeze(-1)
    td = q_taken - y
    squared = td.pow(2)
    if clip_epsilon is not None:
        if old_q is None:
            raise ValueError("critic_loss: clip_epsilon needs old_q, the target heads' Q(s, a)")
        clipped = old_q + (q_taken - old_q).clamp(-clip_epsilon, clip_epsilon)
        squared = torch.maximum(squared, (clipped - y).pow(2))
    per_sample = 0.5 * squared.sum(dim=0)
    td_abs = td.detach().abs().mean(dim=0)
    if per_sample.dim() == 2:  # branches
        per_sample, td_abs = per_sample.mean(dim=-1), td_abs.mean(dim=-1)
    loss = (per_sample * weights).mean() if weights is not None else per_sample.mean()
    return loss, td_abs, {"learner/q_mean": q_taken.detach(), "learner/target_mean": target}


def policy_loss(
    q_min: Tensor,
    pi: PolicySample,
    alpha: Tensor,
    alpha_discrete: Tensor | None,
    branches: Tensor | None,
) -> tuple[Tensor, Metrics]:
    """``J_pi = J_c + sum_b J_b`` on states the caller detached, with ``q_min`` from heads run with
    detached parameters (so no gradient reaches the critic or the representation).

    Continuous (eq. 7, reparameterised): ``J_c = mean [alpha_c log pi_c(a_c|s) - Qbar(s, a_c)]``
    where ``Qbar`` is ``min_i Q_i`` or, with branches, ``mean_b sum_a pi_b(a|s) min_i Q_i,b`` with
    ``pi_b`` held fixed. Discrete (Christodoulou 2019, eq. 12): ``J_b = mean sum_a pi_b(a|s)
    [alpha_b log pi_b(a|s) - min_i Q_i,b(s, a, a_c)]`` with ``Q`` held fixed; a greedy
    (``dqn_like``) discrete part has no ``J_b``.
    """
    loss = torch.zeros((), device=q_min.device)
    metrics: Metrics = {}
    q_bar = q_min
    if pi.probs is not None:
        assert branches is not None
        q_bar = ((pi.probs.detach() * q_min) @ branches).mean(dim=-1)
        if pi.log_probs is not None:
            assert alpha_discrete is not None
            per_action = pi.probs * ((branches @ alpha_discrete) * pi.log_probs - q_min.detach())
            loss = loss + (per_action @ branches).sum(dim=-1).mean()
            metrics["learner/entropy_discrete"] = -((pi.probs * pi.log_probs).detach() @ branches)
    if pi.continuous_log_prob is not None:
        loss = loss + (alpha * pi.continuous_log_prob - q_bar).mean()
        metrics["learner/entropy"] = -pi.continuous_log_prob.detach()
    return loss, metrics


def alpha_loss(log_alpha: Tensor, log_prob: Tensor, target_entropy: float | Tensor) -> tuple[Tensor, Metrics]:
    """``J(alpha) = mean_b [-alpha (log pi(a_b|s_b) + H_target)]`` (eq. 18), written in ``log alpha``
    as SB3 does (docs/architecture.md section 5): entropy above the target lowers alpha, below raises it.

    ``log_alpha`` is a scalar with ``log_prob [B]``, or one entry per discrete branch with the
    branches' expected log-probabilities ``sum_a pi_b log pi_b`` ``[B, K]`` and ``target_entropy [K]``.
    """
    return -(log_alpha * (log_prob.detach() + target_entropy).mean(dim=0)).sum(), {}


def entropy_penalty(entropy: Tensor, behaviour_entropy: Tensor) -> Tensor:
    """``mean_b (H(pi(s_b)) - X_b)^2``: SD-SAC's entropy penalty (Zhou et al., "Revisiting Discrete Soft
    Actor-Critic", 2022), which holds each state's policy entropy near the entropy of the policy that
    acted there, against the swings of a discrete policy's entropy that come with its returns' collapses.

    SD-SAC stores ``H(mu(s))`` with each step; here ``X_b = -log mu(a_b|s_b)`` of the stored action,
    whose mean over ``a ~ mu`` is ``H(mu(s))``: ``E[(H - X)^2] = (H - H(mu))^2 + Var X``, so the
    gradient in ``H`` is SD-SAC's in expectation and nothing but the behaviour log-probability that
    replay already keeps is needed. ``entropy [B]`` carries the gradient; ``behaviour_entropy`` none."""
    return (entropy - behaviour_entropy.detach()).square().mean()


def expected_log_prob(pi: PolicySample, branches: Tensor) -> Tensor:
    """``sum_a pi_b(a|s) log pi_b(a|s)`` per branch, ``[N, K]`` (minus each branch's entropy)."""
    assert pi.probs is not None and pi.log_probs is not None
    return (pi.probs * pi.log_probs) @ branches


def munchausen_bonus(taken_log_prob: Tensor, alpha_discrete: Tensor, scale: float | Tensor, floor: float) -> Tensor:
    """Munchausen RL's reward term (Vieillard et al. 2020, arXiv:2007.14430, eq. 2), one per step:
    ``scale * clip(alpha_b log pi_b(a_b|s), floor, 0)`` averaged over the discrete branches ``b``, as
    :func:`soft_value` averages their values. ``taken_log_prob [..., K]`` is each branch's current
    log-probability of the stored action, ``alpha_discrete [K]``. Added to each reward of a target, it
    makes the policy a softmax of the sum of its past Q estimates (a KL penalty toward the previous
    policy), which averages the critic's errors and widens the action gaps."""
    return scale * (alpha_discrete * taken_log_prob).clamp(min=floor, max=0.0).mean(dim=-1)
