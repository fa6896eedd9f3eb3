"""Soft Actor-Critic: :class:`SAC` owns the models, optimizers and the update step.

The losses are pure functions in :mod:`algorithm.losses`; targets over windows in
:mod:`algorithm.returns`. Actions may be continuous, discrete (several branches, optional
action masks, ``discrete_dqn_like``) or both (docs/architecture.md sections 3 and 5).

Usage, in a learner loop::

    sac = SAC(spec, cfg.sac_config, cfg.nn_config, cfg.replay_config, device="cpu")
    while training:
        batch = table.sample(cfg.replay_config.batch_size)
        result = sac.update(batch, with_metrics=step % cfg.sac_config.write_summary_per_step == 0)
        if not result.skipped:
            table.update_priorities(batch.keys, result.td_abs)
        writer.write(result.metrics)

and on the acting side ``actions, behaviour_logp = sac.act(obs, deterministic=False)``.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from algorithm.config_schema import NNConfig, ReplayConfig, SacConfig
from algorithm.losses import (
    Metrics,
    PolicySample,
    alpha_loss,
    branch_matrix,
    critic_loss,
    expected_log_prob,
    importance_weights,
    policy_loss,
    soft_value,
)
from algorithm.nn.builder import build_models
from algorithm.nn.models import (
    MASKED_LOG_PROB,
    SacModels,
    masked_branch_one_hot_argmax,
    stored_action_log_prob,
)
from algorithm.nn.noisy import NoisyLayer, reset_noise, set_noise
from algorithm.nn.numpy_acting import numpy_actor_for
from algorithm.nn.prediction import gated_gradients, observation_targets, prediction_losses
from algorithm.nn.recurrent import RecurrentRepresentation
from algorithm.returns import bootstrap_index, gather_positions, n_step_target, valid_steps, vtrace_target
from algorithm.spaces import EnvSpec
from algorithm.types import Batch

# The largest extra exploration noise (a std added before the tanh) acting accepts. Far past it tanh
# saturates every action anyway; near 1e37 the float32 std overflows and log-probs become NaN.
MAX_EXPLORATION_NOISE = 1e6


def uses_bfloat16(compute_dtype: str, device: torch.device, cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """Resolve ``sac_config.compute_dtype``: ``auto`` means bfloat16 where the hardware computes it
    natively — a CUDA device that supports it, or a CPU whose flags list ``avx512_bf16`` or
    ``amx_bf16`` (elsewhere bf16 matmuls are emulated and slower than float32)."""
    if compute_dtype != "auto":
        return compute_dtype == "bfloat16"
    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    if device.type != "cpu":
        return False
    try:
        flags = next((line for line in cpuinfo.read_text().splitlines() if line.startswith("flags")), "")
    except OSError:
        return False
    return bool({"avx512_bf16", "amx_bf16"} & set(flags.split()))


@dataclass
class UpdateResult:
    """What :meth:`SAC.update` hands back: ``td_abs [B]`` float32 for priorities (mean over heads;
    non-finite entries set to 0 when the step was skipped), metrics (empty unless asked for)."""

    td_abs: np.ndarray
    metrics: dict[str, float] = field(default_factory=dict)
    skipped: bool = False
    # sac_config.refresh_rnn_states: (row keys [M] uint64, recurrent states [M, S] float32) of every
    # valid window row, computed with the weights before this update, to write back into replay.
    refreshed_rnn_states: tuple[np.ndarray, np.ndarray] | None = None


@dataclass
class Losses:
    """What one pass over a batch computes (:meth:`SAC._losses`), all from the same parameters:
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


class SAC:
    """Models, target copies, optimizers, ``log_alpha``, PER ``beta`` and counters of one learner.

    Three Adam optimizers with separate parameters: critic (Q heads + representation), policy,
    and ``log_alpha`` (only with ``use_auto_alpha``). Adam runs ``fused``: for 256x256 models on
    CPU its three steps took 0.26 ms against 0.66 ms ``foreach`` and 0.62 ms single-tensor.
    ``compile=True`` wraps the loss computation in ``torch.compile``; on CPU it did not pay
    (5-10% slower than eager in bench/learner.py), so it is off by default.

    Randomness: model initialisation uses torch's global RNG, forked and seeded with
    ``sac.seed`` when it is set (the global state is left as it was). Action noise for
    :meth:`act` and the noise and head subsets of :meth:`update` come from two
    ``torch.Generator`` objects owned here (acting in NumPy: a ``numpy.random.Generator``),
    seeded from ``sac.seed`` (or, when it is None, drawn from torch's global RNG, so
    ``torch.manual_seed`` makes a run reproducible); all are in :meth:`state_dict`.
    """

    def __init__(
        self,
        spec: EnvSpec,
        sac: SacConfig,
        nn: NNConfig,
        replay: ReplayConfig,
        device: str | torch.device = "cpu",
        compile: bool = False,
        build: Callable[[EnvSpec, SacConfig, NNConfig], SacModels] = build_models,
    ) -> None:
        self.spec = spec
        self.sac = sac
        self.device = torch.device(device)
        self.beta = float(replay.beta)
        self.beta_increment = float(replay.beta_increment_per_sampling)
        act = spec.action
        self.target_entropy = -float(act.continuous_dim)
        # Discrete: a fraction of each branch's maximum entropy log|A_b| (Christodoulou 2019 used 0.98).
        self.discrete_target_entropy = torch.tensor(
            [sac.discrete_target_entropy_ratio * math.log(n) for n in act.discrete_branches], device=self.device
        )
        self._branches = branch_matrix(act.discrete_branches, self.device) if act.discrete_branches else None
        self._mask_index = spec.action_mask_index
        self._observation_targets = observation_targets(spec.sensors, nn.critic_only, sac.use_extra_data)

        if sac.seed is None:
            init_seed, act_seed, learn_seed = (int(s) for s in torch.randint(0, 2**62, (3,)))
        else:
            init_seed, act_seed, learn_seed = (int(s) for s in np.random.SeedSequence(sac.seed).generate_state(3))
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(init_seed)
            self.models = build(spec, sac, nn).to(self.device)
        self.target_representation = copy.deepcopy(self.models.representation).requires_grad_(False)
        self.target_q = copy.deepcopy(self.models.q).requires_grad_(False)
        self._act_rng = torch.Generator(device=self.device)
        self._act_rng.manual_seed(act_seed)
        # numpy_acting's noise: drawing it with torch cost as much as the NumPy forward itself
        # (13 vs 2 us per call inside an actor loop, and the env step after it 8 us more).
        self._act_np_rng = np.random.default_rng(act_seed)
        self._learn_rng = torch.Generator(device=self.device)
        self._learn_rng.manual_seed(learn_seed)
        self._score_rng = torch.Generator(device=self.device)  # td_errors(): scoring new data
        self._score_rng.manual_seed(learn_seed + 1)

        # One temperature for the continuous part, one per discrete branch (none when greedy).
        self.log_alpha = torch.nn.Parameter(
            torch.tensor(float(sac.init_log_alpha), device=self.device), requires_grad=sac.use_auto_alpha
        )
        n_discrete_alphas = len(act.discrete_branches) if self.models.discrete_policy is not None else 0
        self.log_alpha_discrete = torch.nn.Parameter(
            torch.full((n_discrete_alphas,), float(sac.init_log_alpha), device=self.device),
            requires_grad=sac.use_auto_alpha,
        )
        self._critic_params: list[Tensor] = [
            *self.models.representation.parameters(),
            *self.models.q.parameters(),
        ]
        acting: dict[str, torch.nn.Module] = {"representation": self.models.representation}
        if self.models.normalizer is not None:
            acting["normalizer"] = self.models.normalizer
        for name in ("policy", "discrete_policy"):
            module = getattr(self.models, name)
            if module is not None:
                acting[name] = module
        self._policy_params: list[Tensor] = [
            p for name, m in acting.items() if name.endswith("policy") for p in m.parameters()
        ]
        if self._branches is not None and self.models.discrete_policy is None:
            acting["q"] = self.models.q  # dqn_like: the Q heads pick the discrete actions
        self._acting = torch.nn.ModuleDict(acting)
        # Noisy layers (nn_config.noisy_q / noisy_policy) draw fresh noise for every update and every
        # stochastic act() call, from this SAC's generators; deterministic acting uses the mean weights.
        self._noisy = any(isinstance(m, NoisyLayer) for m in self.models.modules())
        rep = self.models.representation
        self.rnn_state_size = rep.rnn_state_size if isinstance(rep, RecurrentRepresentation) else 0
        # act() in NumPy where that computes what torch would (nn/numpy_acting.py), else None.
        self._numpy_actor = None
        if sac.numpy_acting:
            discrete = bool(act.discrete_branches)
            self._numpy_actor = numpy_actor_for(self.models, self.device.type, bool(self.rnn_state_size), discrete)
        alpha_params = [p for p, used in ((self.log_alpha, act.continuous_dim > 0),
                                          (self.log_alpha_discrete, n_discrete_alphas > 0)) if used]  # fmt: skip
        self.critic_optimizer = self._adam(self._critic_params)
        self.policy_optimizer = self._adam(self._policy_params) if self._policy_params else None
        self.alpha_optimizer = self._adam(alpha_params) if sac.use_auto_alpha and alpha_params else None
        auxiliary = [m for m in (self.models.curiosity, self.models.rnd, self.models.prediction) if m is not None]
        self._auxiliary_params: list[Tensor] = [p for m in auxiliary for p in m.parameters() if p.requires_grad]
        self.auxiliary_optimizer = self._adam(self._auxiliary_params) if self._auxiliary_params else None
        if self.models.rnd is not None:
            self._acting["rnd"] = self.models.rnd  # actors choose by novelty
        self._target_params: list[Tensor] = [
            *self.target_representation.parameters(),
            *self.target_q.parameters(),
        ]

        # torch.compile of the loss computation (forward and, through AOTAutograd, backward);
        # its first update compiles for ~20 s on CPU. See bench/learner.py for what it gains.
        self._compute_losses = torch.compile(self._losses) if compile else self._losses
        # Hidden layers in bfloat16 (sac.compute_dtype): 2.2x faster matmuls on this project's AVX512-BF16
        # CPUs, 1.4x faster updates (bench/learner.py); output layers stay float32 (nn.layers.in_float32).
        self._low_precision = uses_bfloat16(sac.compute_dtype, self.device)
        # Extra exploration of one distributed actor, min(noise_increasing_rate * i, noise_max)
        # (docs/architecture.md section 9): stochastic acting widens the pre-tanh Gaussian to
        # std' = sqrt(std^2 + noise^2) and mixes each discrete branch with the uniform distribution
        # over allowed actions (weight min(noise, 1)).
        # The log-prob returned is the widened policy's, so the stored behaviour mu stays exact.
        self.exploration_noise = 0.0
        self.updates = 0  # applied (not skipped) updates
        self.nonfinite_skipped = 0
        self._consecutive_nonfinite = 0

    def _adam(self, params: Sequence[Tensor]) -> torch.optim.Adam:
        return torch.optim.Adam(params, lr=self.sac.learning_rate, fused=True)

    # -- acting ---------------------------------------------------------------------------------

    def act(self, obs: list[np.ndarray], deterministic: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Actions ``[N, A]`` float32 (``[one-hot per branch | continuous in [-1, 1]]``) and their
        behaviour log-probability ``[N]`` under the current policy, exploration included, for ``N``
        observations given as one ``[N, *sensor_shape]`` array per sensor.

        ``deterministic`` acts with ``tanh(mean)`` and each branch's most probable (or, dqn-like,
        greedy) allowed action; the log-prob is then the density at that point. Stochastic acting
        samples the policy, or with ``discrete_dqn_like`` acts epsilon-greedily among allowed actions
        (``discrete_dqn_epsilon``), and reports the true probability of the mixture."""
        if self.rnn_state_size:
            raise TypeError("a recurrent policy (use_rnn) acts with act_recurrent(obs, prev_actions, rnn_state)")
        if self._numpy_actor is None:
            return self._act_torch(obs, deterministic)
        self._check_obs(obs)
        noise = None
        if not deterministic:
            noise = self._act_np_rng.standard_normal((obs[0].shape[0], self.spec.action.continuous_dim), np.float32)
        return self._numpy_actor.act(obs, noise, 0.0 if deterministic else self.exploration_noise)

    @torch.inference_mode()
    def _act_torch(self, obs: list[np.ndarray], deterministic: bool) -> tuple[np.ndarray, np.ndarray]:
        return self._act_with_noise(self._obs_tensors(obs), deterministic, None)

    @torch.inference_mode()
    def act_recurrent(
        self, obs: list[np.ndarray], prev_actions: np.ndarray, rnn_state: np.ndarray, deterministic: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`act` for ``use_rnn``: also takes each env's previous action ``[N, A]`` (zeros at
        episode start) and recurrent state ``[N, rnn_state_size]`` (zeros at episode start), and
        returns the next state as a third array. The next state does not depend on the action
        chosen now (the cell reads ``a_{t-1}``), so an actor may replace the action (random warm-up)."""
        n = prev_actions.shape[0]
        if prev_actions.shape != (n, self.spec.action.size) or rnn_state.shape != (n, self.rnn_state_size):
            raise ValueError(
                f"act_recurrent: prev_actions must be [N, {self.spec.action.size}] and rnn_state "
                f"[N, {self.rnn_state_size}], got {prev_actions.shape} and {rnn_state.shape}"
            )
        tensors = self._obs_tensors(obs)
        prev = torch.as_tensor(prev_actions, dtype=torch.float32, device=self.device)
        state = torch.as_tensor(rnn_state, dtype=torch.float32, device=self.device)
        rep = self.models.representation
        assert isinstance(rep, RecurrentRepresentation)
        full_state, next_state = rep.step(tensors, prev, state)
        actions, log_prob = self._act_with_noise(tensors, deterministic, full_state)
        return actions, log_prob, next_state.cpu().numpy()

    def initial_rnn_state(self, n: int) -> np.ndarray:
        """The recurrent state an episode starts from (zeros ``[n, rnn_state_size]``)."""
        return np.zeros((n, self.rnn_state_size), dtype=np.float32)

    def _check_obs(self, obs: list[np.ndarray]) -> None:
        sensors = self.spec.sensors
        if len(obs) != len(sensors):
            raise ValueError(f"act: expected {len(sensors)} sensors {[s.name for s in sensors]}, got {len(obs)}")
        for o, s in zip(obs, sensors, strict=True):
            if o.ndim != len(s.shape) + 1 or tuple(o.shape[1:]) != s.shape:
                raise ValueError(f"act: sensor {s.name!r} must be [N, {', '.join(map(str, s.shape))}], got {o.shape}")

    def _obs_tensors(self, obs: list[np.ndarray]) -> list[Tensor]:
        self._check_obs(obs)
        tensors = [torch.as_tensor(o, dtype=torch.float32, device=self.device) for o in obs]
        return self._normalize(tensors)

    def _act_with_noise(
        self, tensors: list[Tensor], deterministic: bool, full_state: Tensor | None
    ) -> tuple[np.ndarray, np.ndarray]:
        if self._noisy:
            if deterministic:
                set_noise(self._acting, False)
            else:
                reset_noise(self._acting, self._act_rng)
        try:
            if full_state is None:
                full_state = self.models.representation(tensors)
            if self.models.rnd is None or deterministic:
                action, log_prob = self._act(full_state, tensors, deterministic)
            else:  # the most novel of rnd_n_sample policy actions per env
                n, k = full_state.shape[0], self.sac.rnd_n_sample
                repeated = full_state.repeat_interleave(k, dim=0)
                candidates, log_probs = self._act(repeated, [t.repeat_interleave(k, dim=0) for t in tensors], False)
                novelty = self.models.rnd.novelty(repeated, candidates).view(n, k)
                pick = novelty.argmax(dim=1) + torch.arange(n, device=self.device) * k
                # log-prob under the policy alone: the selection's own probability has no closed form
                action, log_prob = candidates[pick], log_probs[pick]
            return action.cpu().numpy(), log_prob.cpu().numpy()
        finally:
            if self._noisy and deterministic:
                set_noise(self._acting, True)

    def _act(self, full_state: Tensor, tensors: list[Tensor], deterministic: bool) -> tuple[Tensor, Tensor]:
        state = self.models.representation.policy_state(full_state)
        n, spec = state.shape[0], self.spec.action
        log_prob = torch.zeros(n, device=self.device)
        continuous = None
        extra = 0.0 if deterministic else self.exploration_noise
        if self.models.policy is not None:
            if deterministic:
                continuous, log_prob = self.models.policy.sample(state, None)
            else:
                noise = torch.randn(n, spec.continuous_dim, generator=self._act_rng, device=self.device)
                continuous, log_prob = self._behaviour_sample(state, noise, extra)
        parts = []
        if self._branches is not None:
            mask = self._mask(tensors)
            allowed = torch.ones(n, spec.discrete_size, device=self.device) if mask is None else mask.float()
            uniform = allowed / (allowed @ self._branches @ self._branches.T)
            if self.models.discrete_policy is not None:
                probs = self.models.discrete_policy(state, mask).exp()
            else:
                probs = self._greedy(full_state, continuous, mask)
                if not deterministic:
                    eps = self.sac.discrete_dqn_epsilon
                    probs = (1.0 - eps) * probs + eps * uniform
            if extra > 0:
                probs = (1.0 - min(extra, 1.0)) * probs + min(extra, 1.0) * uniform
            for branch_probs in probs.split(list(spec.discrete_branches), dim=-1):
                if deterministic:
                    choice = branch_probs.argmax(dim=-1)
                else:
                    choice = torch.multinomial(branch_probs, 1, generator=self._act_rng).squeeze(-1)
                log_prob = log_prob + branch_probs.gather(-1, choice[:, None]).squeeze(-1).log()
                parts.append(torch.nn.functional.one_hot(choice, branch_probs.shape[-1]).float())
        if continuous is not None:
            parts.append(continuous)
        action = parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)
        return action, log_prob

    def _behaviour_sample(self, state: Tensor, noise: Tensor, extra: float) -> tuple[Tensor, Tensor]:
        """An exploring action and its behaviour log-prob, as the learner will evaluate it again
        from the stored action (:func:`stored_action_log_prob`). With ``extra`` Gaussian noise added
        before the tanh, ``u ~ N(mean, std^2 + extra^2)`` (log std' = logaddexp(2 log std, 2 log
        extra) / 2), and the log-prob is that of the widened Gaussian."""
        assert self.models.policy is not None
        mean, log_std = self.models.policy(state)
        if extra > 0:
            log_std = 0.5 * torch.logaddexp(2.0 * log_std, torch.full_like(log_std, 2.0 * math.log(extra)))
        action = torch.tanh(mean + log_std.exp() * noise)
        return action, stored_action_log_prob(mean, log_std, action)

    def _normalize(self, obs: list[Tensor]) -> list[Tensor]:
        return obs if self.models.normalizer is None else self.models.normalizer(obs)

    def load_normalizer_stats(self, stats: Mapping[str, Mapping[str, Any]]) -> None:
        """With ``use_normalization``: take the replay's running statistics (``table.normalizer_stats()``)
        for acting and learning from now on; a no-op otherwise."""
        if self.models.normalizer is not None:
            self.models.normalizer.load_stats(stats)

    def _mask(self, obs: list[Tensor]) -> Tensor | None:
        """The ``action_mask`` sensor as bool (True = allowed), or None when the task has none."""
        return None if self._mask_index is None else obs[self._mask_index] > 0.5

    def _greedy(self, state: Tensor, continuous: Tensor | None, mask: Tensor | None) -> Tensor:
        """``discrete_dqn_like``: one-hot of each branch's allowed argmax of ``min_i Q_i`` (online heads)."""
        assert self._branches is not None
        with torch.no_grad():
            q = self.models.q(state, continuous).min(dim=0).values
        return masked_branch_one_hot_argmax(q, self.spec.action.discrete_branches, mask)

    def _policy(self, state: Tensor, noise: Tensor, mask: Tensor | None) -> PolicySample:
        """The policy at ``state``: a reparameterised continuous sample from ``noise`` and each
        discrete branch's full distribution (greedy one-hots with ``discrete_dqn_like``)."""
        pi = PolicySample()
        policy_state = self.models.representation.policy_state(state)
        if self.models.policy is not None:
            pi.continuous, pi.continuous_log_prob = self.models.policy.sample(policy_state, noise)
        if self.models.discrete_policy is not None:
            pi.log_probs = self.models.discrete_policy(policy_state, mask)
            pi.probs = pi.log_probs.exp()
        elif self._branches is not None:
            pi.probs = self._greedy(state, pi.continuous, mask)
        return pi

    def _q_taken(self, q: torch.nn.Module, state: Tensor, action: Tensor, heads: Tensor | None = None) -> Tensor:
        """Each head's value of the stored ``action``: ``[E, B]``, or ``[E, B, K]`` per discrete branch."""
        d = self.spec.action.discrete_size
        values = q(state, action[..., d:] if self.models.policy is not None else None, heads)
        if self._branches is None:
            return values
        return (values * action[..., :d]) @ self._branches

    # -- learning -------------------------------------------------------------------------------

    def _subset(self) -> Tensor | None:
        """A fresh random subset of ``ensemble_q_sample`` heads; None (all heads) when it is all."""
        n, k = self.sac.ensemble_q_num, self.sac.ensemble_q_sample
        if k == n:
            return None
        return torch.randperm(n, generator=self._learn_rng, device=self.device)[:k]

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
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, dict[str, Tensor], Tensor, Metrics, Tensor | None]:
        """The SAC losses from the current parameters: ``(q_loss, policy_loss, alpha_loss,
        auxiliary_loss, prediction_losses, td_abs, metrics, fed_states)``, where ``fed_states`` is
        the online recurrent state fed in at each window step ``[B, L, S]`` (None without
        ``use_rnn``). Batch tensors are ``[B, L(+1), ...]``; the trained step is step
        ``burn_in_step`` of each window (the sampled key; earlier steps only warm up a recurrent
        state). ``noise [B, n_step + 2, A]`` feeds the action samples: position 0 the policy loss's,
        1.. the target's (only ``noise[:, 1]`` without V-trace, the value at the bootstrap observation)."""
        sac, dev, branches = self.sac, self.device, self._branches
        q = self.models.q
        alpha = self.log_alpha.detach().exp()
        alpha_d = self.log_alpha_discrete.detach().exp()
        metrics: Metrics = {"learner/alpha": alpha}
        if alpha_d.numel():
            metrics["learner/alpha_discrete"] = alpha_d

        # 0. States at the window's observation positions from the trained step on. A recurrent
        #    representation runs over the whole window (burn-in first); otherwise states are computed
        #    only where they are needed: at the trained step and at the bootstrap position.
        burn_in = sac.burn_in_step
        sequences, fed_states = None, None
        if rnn_state is not None:
            online_seq, target_seq, fed = self._sequence_states(obs, actions, prev_actions, mask, rnn_state)
            fed_states = fed[:, :-1]
            sequences = (online_seq[:, burn_in:], target_seq[:, burn_in:])
        obs = [o[:, burn_in:] for o in obs]
        actions, rewards, terminated, truncated, mask, behaviour_logp = (
            x[:, burn_in:] for x in (actions, rewards, terminated, truncated, mask, behaviour_logp)
        )
        action_masks = None if self._mask_index is None else obs[self._mask_index] > 0.5

        def states_at(index: Tensor | int | None, target: bool) -> Tensor:
            """States ``[B, D]`` at position ``index`` (a ``[B]`` tensor or an int), or ``[B, P, D]``
            at every position (None)."""
            if sequences is not None:
                seq = sequences[1] if target else sequences[0]
                if index is None:
                    return seq
                return seq[:, index] if isinstance(index, int) else gather_positions(seq, index)
            rep = self.target_representation if target else self.models.representation
            if index is None:
                b, p = obs[0].shape[:2]
                return rep([o.flatten(0, 1) for o in obs]).view(b, p, -1)
            return rep([o[:, index] if isinstance(index, int) else gather_positions(o, index) for o in obs])

        def masks_at(index: Tensor | int | None) -> Tensor | None:
            if action_masks is None or index is None:
                return action_masks
            return action_masks[:, index] if isinstance(index, int) else gather_positions(action_masks, index)

        # Computed once and shared below: the trained steps, the online state at the trained step
        # (with gradients, for the critic), and, for curiosity and V-trace, the online states at
        # every position (no gradients: both only read them).
        valid = valid_steps(mask, terminated, truncated)
        state = states_at(0, False)
        online_all = None
        if self.models.curiosity is not None or sac.use_n_step_is:
            with torch.no_grad():
                online_all = states_at(None, False)

        # Exploration models: curiosity rewards (targets only) and their training losses.
        aux_loss = torch.zeros((), device=dev)
        if self.models.curiosity is not None:
            assert online_all is not None
            states = online_all
            b, p = states.shape[:2]
            forward_error, inverse_error = (
                e.view(b, p - 1)
                for e in self.models.curiosity.errors(
                    states[:, :-1].flatten(0, 1), actions.flatten(0, 1), states[:, 1:].flatten(0, 1)
                )
            )
            intrinsic = sac.curiosity_strength * torch.where(valid, forward_error.detach(), 0.0)
            rewards = rewards + intrinsic
            aux_loss = aux_loss + ((forward_error + inverse_error) * valid).sum() / valid.sum()
            metrics["learner/curiosity_reward"] = intrinsic[:, 0]
        if self.models.rnd is not None:
            novelty = self.models.rnd.novelty(state.detach(), actions[:, 0])
            aux_loss = aux_loss + novelty.mean()
            metrics["learner/rnd_novelty"] = novelty.detach()

        # 1. Target y for the trained step: n-step return + gamma^m V(o_m)  (eq. 2, 3, 5), or the
        #    V-trace estimate over the window (returns.vtrace_target).
        with torch.no_grad():
            if sac.use_n_step_is:
                assert online_all is not None
                values, log_pi = self._window_values(
                    online_all, states_at(None, True), masks_at(None),
                    actions, noise[:, 1:], alpha, alpha_d, target_heads,
                )  # fmt: skip
                y, rho = vtrace_target(
                    rewards, terminated, valid, values, log_pi - behaviour_logp,
                    sac.gamma, sac.v_lambda, sac.v_rho, sac.v_c,
                )  # fmt: skip
                weighted = rho > 0
                metrics["learner/vtrace_rho"] = rho[weighted] if weighted.any() else torch.ones(1, device=dev)
                v = values[:, 1]
            else:
                m = bootstrap_index(valid)
                next_pi = self._policy(states_at(m, False), noise[:, 1], masks_at(m))
                next_q = self.target_q(states_at(m, True), next_pi.continuous, target_heads)
                v = soft_value(next_q.min(dim=0).values, next_pi, alpha, alpha_d, branches)
                y = n_step_target(rewards, terminated, valid, v, sac.gamma)
            action0 = actions[:, 0]
            old_q = None
            if sac.clip_epsilon is not None:
                old_q = self._q_taken(self.target_q, states_at(0, True), action0)

        # 2. Critic loss; the policy and alpha losses on the detached state; prediction losses on the
        #    live state (update() gates their gradient into the representation).
        predictions: dict[str, Tensor] = {}
        if self.models.prediction is not None:
            with torch.no_grad():
                next_state = states_at(1, True)
            targets = [obs[i][:, 0].flatten(1) for i in self._observation_targets]
            predictions = prediction_losses(
                self.models.prediction, state, actions[:, 0], next_state, rewards[:, 0],
                torch.cat(targets, dim=-1) if targets else None, sac.transition_kl,
            )  # fmt: skip
            metrics.update({f"learner/prediction_{k}": v.detach() for k, v in predictions.items()})
        q_loss, td_abs, q_metrics = critic_loss(self._q_taken(q, state, action0), y, weights, sac.clip_epsilon, old_q)
        pi = self._policy(state.detach(), noise[:, 0], masks_at(0))
        q_pi = q(state.detach(), pi.continuous, policy_heads, detach_params=True).min(dim=0).values
        pi_loss, pi_metrics = policy_loss(q_pi, pi, alpha, alpha_d, branches)
        a_loss = torch.zeros((), device=dev)
        if self.alpha_optimizer is not None:
            if pi.continuous_log_prob is not None:
                a_loss = a_loss + alpha_loss(self.log_alpha, pi.continuous_log_prob, self.target_entropy)[0]
            if pi.log_probs is not None and branches is not None:
                expected = expected_log_prob(pi, branches)
                a_loss = a_loss + alpha_loss(self.log_alpha_discrete, expected, self.discrete_target_entropy)[0]
        metrics.update({**q_metrics, **pi_metrics, "learner/next_value": v, "learner/auxiliary_loss": aux_loss})
        return q_loss, pi_loss, a_loss, aux_loss, predictions, td_abs, metrics, fed_states

    def update(self, batch: Batch, with_metrics: bool = False) -> UpdateResult:
        """One gradient step on every part from one batch (docs/architecture.md section 5).

        All losses are computed from the same parameters (:meth:`_losses`) and applied together
        (as Acme's SAC learner does), which lets the whole step be skipped when anything is
        non-finite: no optimizer step, no target update, weights and optimizer state unchanged.
        After ``sac.max_nonfinite_steps`` consecutive skips this raises RuntimeError. PER ``beta``
        advances once per call, skipped or not (it counts sampled batches).
        """
        self._check_batch(batch)
        sac, dev = self.sac, self.device
        weights = None
        if sac.use_priority:  # on the CPU: float64 is not available on every device
            weights = importance_weights(torch.from_numpy(batch.probabilities), batch.table_size, self.beta)
            weights = weights.to(dev)
        beta_used = self.beta
        self.beta = min(1.0, self.beta + self.beta_increment)
        if self._noisy:
            reset_noise(self.models, self._learn_rng)
            reset_noise(self.target_q, self._learn_rng)
        samples = sac.n_step + 2 if sac.use_n_step_is else 2  # see _losses
        noise = torch.randn(
            batch.batch_size, samples, self.spec.action.continuous_dim, generator=self._learn_rng, device=dev
        )
        losses = self._batch_losses(batch, weights, noise, self._subset(), self._subset())

        # 3. One backward: the losses touch disjoint parameters (policy_loss detaches the critic,
        #    alpha_loss detaches log_prob, the target is no-grad), so each gets exactly its own grads.
        for opt in self._optimizers():
            opt.zero_grad(set_to_none=True)
        predictions = losses.predictions
        (losses.q + losses.policy + losses.alpha + losses.auxiliary).backward(retain_graph=bool(predictions))
        if predictions:
            self._apply_prediction_gradients(predictions, losses.metrics)
        critic_norm, policy_norm = _grad_norm(self._critic_params), _grad_norm(self._policy_params)
        prediction_loss = (
            torch.stack(list(predictions.values())).sum().detach() if predictions else losses.auxiliary.detach()
        )
        checks = torch.stack(
            [losses.q.detach(), losses.policy.detach(), losses.alpha.detach(), losses.auxiliary.detach(),
             prediction_loss, critic_norm, policy_norm]
        )  # fmt: skip

        # 4. Apply, or skip the whole step if anything is non-finite.
        skipped = not bool(torch.isfinite(checks).all())  # the one host sync of the step
        if skipped:
            self._skip(checks)
        else:
            self._consecutive_nonfinite = 0
            for opt in self._optimizers():
                opt.step()
            self.updates += 1
            if self.updates % sac.update_target_per_step == 0:
                with torch.no_grad():
                    torch._foreach_lerp_(self._target_params, self._critic_params, sac.tau)

        td_abs = losses.td_abs
        td = torch.nan_to_num(td_abs, nan=0.0, posinf=0.0, neginf=0.0) if skipped else td_abs
        metrics: dict[str, float] = {}
        if with_metrics:
            tensors = {
                **losses.metrics,
                "learner/td_abs_mean": td_abs,
                "learner/q_loss": losses.q,
                "learner/policy_loss": losses.policy,
                "learner/alpha_loss": losses.alpha,
                "learner/grad_norm_critic": critic_norm,
                "learner/grad_norm_policy": policy_norm,
                "learner/is_weight_mean": weights if weights is not None else torch.ones(()),
            }
            values = torch.stack([t.detach().float().mean().cpu() for t in tensors.values()]).tolist()
            metrics = dict(zip(tensors, values, strict=True))
            metrics.update(
                {
                    "learner/beta": beta_used,
                    "learner/nonfinite_skipped": float(self.nonfinite_skipped),
                    "learner/updates": float(self.updates),
                }
            )
        refreshed = None
        if sac.refresh_rnn_states and losses.fed_states is not None and not skipped:
            refreshed = self._window_rows(batch, losses.fed_states)
        return UpdateResult(td_abs=td.cpu().numpy(), metrics=metrics, skipped=skipped, refreshed_rnn_states=refreshed)

    def td_errors(self, batch: Batch) -> np.ndarray:
        """``|TD| [B]`` float32 of each window's trained step under the current weights (mean over all
        Q heads, as :meth:`update` reports it), without training: how the learner scores new data
        for ``sac_config.insert_td_priorities``. Its noise comes from a generator of its own, so
        scoring does not change the updates' random stream."""
        self._check_batch(batch)
        samples = self.sac.n_step + 2 if self.sac.use_n_step_is else 2
        noise = torch.randn(
            batch.batch_size, samples, self.spec.action.continuous_dim, generator=self._score_rng, device=self.device
        )
        with torch.no_grad():
            td_abs = self._batch_losses(batch, None, noise, None, None).td_abs
        return torch.nan_to_num(td_abs.float(), nan=0.0, posinf=0.0, neginf=0.0).cpu().numpy()

    def _batch_losses(
        self,
        batch: Batch,
        weights: Tensor | None,
        noise: Tensor,
        target_heads: Tensor | None,
        policy_heads: Tensor | None,
    ) -> Losses:
        """:meth:`_losses` of a sampled batch (its arrays moved to the device, observations normalized),
        named (``_losses`` returns a plain tuple: what torch.compile traces most simply)."""
        dev = self.device
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=self._low_precision):
            return Losses(
                *self._compute_losses(
                    self._normalize([torch.from_numpy(o).to(dev) for o in batch.obs]),
                    torch.from_numpy(batch.actions).to(dev),
                    torch.from_numpy(batch.prev_actions).to(dev),
                    torch.from_numpy(batch.rewards).to(dev),
                    torch.from_numpy(batch.terminated).to(dev),
                    torch.from_numpy(batch.truncated).to(dev),
                    torch.from_numpy(batch.mask).to(dev),
                    torch.from_numpy(batch.behaviour_logp).to(dev),
                    torch.from_numpy(batch.rnn_state).to(dev) if self.rnn_state_size else None,
                    weights,
                    noise,
                    target_heads,
                    policy_heads,
                )
            )

    def _window_rows(self, batch: Batch, fed_states: Tensor) -> tuple[np.ndarray, np.ndarray]:
        """Row keys and fed states of every valid window step: window step ``j`` of a window whose
        trained step has key ``k`` is row ``k - burn_in_step + j`` (masked steps, before the chunk
        or past its end, are left out)."""
        offsets = np.arange(batch.mask.shape[1], dtype=np.int64) - self.sac.burn_in_step
        keys = batch.keys.astype(np.int64)[:, None] + offsets[None, :]
        valid = batch.mask
        return keys[valid].astype(np.uint64), fed_states.float().cpu().numpy()[valid]

    def _apply_prediction_gradients(self, predictions: dict[str, Tensor], metrics: Metrics) -> None:
        """Prediction models get their losses' full gradients; the representation gets each loss's
        gradient only where its cosine with the critic's gradient there is positive (nn/prediction.py)."""
        assert self.models.prediction is not None
        model_params = list(self.models.prediction.parameters())
        total = torch.stack(list(predictions.values())).sum()
        grads = torch.autograd.grad(total, model_params, retain_graph=True, allow_unused=True)
        for p, g in zip(model_params, grads, strict=True):
            if g is not None:
                p.grad = g if p.grad is None else p.grad + g
        rep_params = [p for p in self.models.representation.parameters() if p.requires_grad]
        if not rep_params:
            return
        critic = [torch.zeros_like(p) if p.grad is None else p.grad for p in rep_params]  # the Q loss's alone
        gated, cosines = gated_gradients(predictions, critic, rep_params)
        for p, g in zip(rep_params, gated, strict=True):
            p.grad = g if p.grad is None else p.grad + g
        metrics.update({f"learner/prediction_{k}_cosine": v for k, v in cosines.items()})

    def _optimizers(self) -> list[torch.optim.Optimizer]:
        return list(self._named_optimizers().values())

    def _skip(self, checks: Tensor) -> None:
        for opt in self._optimizers():
            opt.zero_grad(set_to_none=True)
        self.nonfinite_skipped += 1
        self._consecutive_nonfinite += 1
        if self._consecutive_nonfinite >= self.sac.max_nonfinite_steps:
            names = (
                "q_loss", "policy_loss", "alpha_loss", "auxiliary_loss", "prediction_loss", "grad_norm_critic",
                "grad_norm_policy",
            )  # fmt: skip
            values = ", ".join(f"{n}={v:.4g}" for n, v in zip(names, checks.tolist(), strict=True))
            raise RuntimeError(
                f"{self._consecutive_nonfinite} consecutive SAC updates had non-finite losses or gradients "
                f"(sac_config.max_nonfinite_steps={self.sac.max_nonfinite_steps}); last step: {values}. "
                "Check rewards and observations for NaN/inf, or lower the learning rate."
            )

    def _check_batch(self, batch: Batch) -> None:
        sensors, n_b, n_l = self.spec.sensors, batch.batch_size, batch.window
        window = self.sac.burn_in_step + self.sac.n_step
        if n_l != window:
            raise ValueError(f"batch window is {n_l} steps, expected burn_in_step + n_step = {window}")
        if len(batch.obs) != len(sensors):
            raise ValueError(f"batch.obs has {len(batch.obs)} sensors, the spec has {len(sensors)}")
        for o, s in zip(batch.obs, sensors, strict=True):
            if o.shape != (n_b, n_l + 1, *s.shape) or o.dtype != s.dtype:
                raise ValueError(
                    f"batch.obs for sensor {s.name!r} must be {s.dtype} {(n_b, n_l + 1, *s.shape)}, "
                    f"got {o.dtype} {o.shape}"
                )
        expected = {
            "actions": (n_b, n_l, self.spec.action.size),
            "rewards": (n_b, n_l),
            "terminated": (n_b, n_l),
            "truncated": (n_b, n_l),
            "mask": (n_b, n_l),
            "probabilities": (n_b,),
        }
        for name, shape in expected.items():
            got = getattr(batch, name).shape
            if got != shape:
                raise ValueError(f"batch.{name} must have shape {shape}, got {got}")
        burn_in = self.sac.burn_in_step
        if not batch.mask[:, burn_in].all():
            raise ValueError(f"batch.mask[:, {burn_in}] must be True: the sampled step of every window is stored")
        if self.rnn_state_size and (batch.rnn_state is None or batch.rnn_state.shape != (n_b, self.rnn_state_size)):
            got = None if batch.rnn_state is None else batch.rnn_state.shape
            raise ValueError(f"batch.rnn_state must have shape {(n_b, self.rnn_state_size)} with use_rnn, got {got}")
        if self.sac.use_priority and batch.table_size < 1:
            raise ValueError(f"batch.table_size must be >= 1 with use_priority, got {batch.table_size}")

    # -- checkpoints ----------------------------------------------------------------------------

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
            "rng": {
                "act": self._act_rng.get_state(),
                "learn": self._learn_rng.get_state(),
                "act_numpy": self._act_np_rng.bit_generator.state,
            },
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
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
        self._act_rng.set_state(state["rng"]["act"])
        self._learn_rng.set_state(state["rng"]["learn"])
        if "act_numpy" in state["rng"]:  # checkpoints from before numpy_acting have none
            self._act_np_rng.bit_generator.state = state["rng"]["act_numpy"]

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

    def _named_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        named: dict[str, torch.optim.Optimizer] = {"critic": self.critic_optimizer}
        if self.policy_optimizer is not None:
            named["policy"] = self.policy_optimizer
        if self.alpha_optimizer is not None:
            named["alpha"] = self.alpha_optimizer
        if self.auxiliary_optimizer is not None:
            named["auxiliary"] = self.auxiliary_optimizer
        return named

    def acting_state_dict(self) -> dict[str, Tensor]:
        """The parameters :meth:`act` uses (``representation.*`` and ``policy.*``), flat name ->
        tensor: what a learner publishes to actors."""
        return self._acting.state_dict()

    def load_acting_state_dict(self, state: dict[str, Tensor]) -> None:
        """Load what :meth:`acting_state_dict` returned (an actor receiving published weights);
        missing or unexpected names raise, naming them."""
        self._acting.load_state_dict(state)


def _grad_norm(params: list[Tensor]) -> Tensor:
    """The 2-norm of all gradients of ``params`` together (one foreach kernel)."""
    return torch.nn.utils.get_total_norm([p.grad for p in params if p.grad is not None])
