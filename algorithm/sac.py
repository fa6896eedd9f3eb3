"""Soft Actor-Critic: the losses as pure functions, and :class:`SAC`, which owns the update.

Equations are from Haarnoja et al. 2018, "Soft Actor-Critic Algorithms and Applications"
(arXiv:1812.05905). The losses take modules and tensors and return ``(loss, ..., metrics)``;
metrics are *unreduced* detached tensors, reduced only when a caller asks for them, so the hot
path never syncs per metric.

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
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from algorithm.config_schema import NNConfig, ReplayConfig, SacConfig
from algorithm.nn.builder import build_models
from algorithm.nn.models import QEnsemble, TanhGaussianPolicy
from algorithm.returns import bootstrap_index, gather_positions, n_step_target, valid_steps
from algorithm.spaces import EnvSpec
from algorithm.types import Batch

Metrics = dict[str, Tensor]


# ----------------------------------------------------------------------------------------------
# Losses: pure functions
# ----------------------------------------------------------------------------------------------


def importance_weights(probabilities: Tensor, table_size: int, beta: float) -> Tensor:
    """PER weights ``(table_size * p) ** -beta`` divided by the batch maximum (Schaul et al. 2016,
    section 3.4), computed in float64 and returned as float32 ``[B]``."""
    w = (table_size * probabilities.double()).pow(-beta)
    return (w / w.max()).float()


def soft_value(
    q_target: QEnsemble,
    policy: TanhGaussianPolicy,
    target_state: Tensor,
    policy_state: Tensor,
    alpha: Tensor,
    noise: Tensor,
    heads: Tensor | None,
) -> tuple[Tensor, Metrics]:
    """``V(s) = min_{i in heads} Q_target_i(s, a) - alpha log pi(a|s)``, ``a ~ pi(.|s)`` (eq. 3, one
    reparameterised sample). ``target_state`` comes from the target representation and feeds the
    target heads; ``policy_state`` from the online one feeds the policy. Returns ``[B]``."""
    action, log_prob = policy.sample(policy_state, noise)
    q = q_target(target_state, action, heads).min(dim=0).values
    return q - alpha * log_prob, {"learner/next_entropy": -log_prob}


def critic_loss(
    q: QEnsemble,
    state: Tensor,
    action: Tensor,
    target: Tensor,
    weights: Tensor | None,
    clip_epsilon: float | None = None,
    old_q: Tensor | None = None,
) -> tuple[Tensor, Tensor, Metrics]:
    """``J_Q = sum_i mean_b w_b 1/2 (Q_i(s_b, a_b) - y_b)^2`` (eq. 5, PER-weighted per sample).

    Heads are summed, so every head's error reaches ``state`` (and the representation behind it)
    with full weight. With ``clip_epsilon``, each head's squared error is the max of the plain one
    and the one of ``old_q + clip(Q - old_q, -eps, eps)``, ``old_q`` being the *target* head's value
    at ``(s, a)`` (PPO-style value clipping, as the revived system did). Returns ``(loss, td_abs,
    metrics)`` where ``td_abs [B]`` is ``|Q_i - y|`` averaged over heads from this same forward pass.
    """
    q_values = q(state, action)  # [E, B]
    td = q_values - target
    squared = td.pow(2)
    if clip_epsilon is not None:
        if old_q is None:
            raise ValueError("critic_loss: clip_epsilon needs old_q, the target heads' Q(s, a)")
        clipped = old_q + (q_values - old_q).clamp(-clip_epsilon, clip_epsilon)
        squared = torch.maximum(squared, (clipped - target).pow(2))
    per_sample = 0.5 * squared.sum(dim=0)
    loss = (per_sample * weights).mean() if weights is not None else per_sample.mean()
    td_abs = td.detach().abs().mean(dim=0)
    return loss, td_abs, {"learner/q_mean": q_values.detach(), "learner/target_mean": target}


def policy_loss(
    policy: TanhGaussianPolicy,
    q: QEnsemble,
    state: Tensor,
    alpha: Tensor,
    noise: Tensor,
    heads: Tensor | None,
) -> tuple[Tensor, Tensor, Metrics]:
    """``J_pi = mean_b [alpha log pi(a_b|s_b) - min_{i in heads} Q_i(s_b, a_b)]``, ``a = f(noise; s)``
    (eq. 7 with the reparameterisation of section 4.2).

    ``state`` is detached here and the heads run with detached parameters, so this loss moves the
    policy only: no gradient reaches the critic or the representation. Returns ``(loss,
    log_prob [B], metrics)``; the alpha loss reuses ``log_prob``.
    """
    action, log_prob = policy.sample(state.detach(), noise)
    q_pi = q(state.detach(), action, heads, detach_params=True).min(dim=0).values
    loss = (alpha * log_prob - q_pi).mean()
    return loss, log_prob, {"learner/entropy": -log_prob.detach()}


def alpha_loss(log_alpha: Tensor, log_prob: Tensor, target_entropy: float) -> tuple[Tensor, Metrics]:
    """``J(alpha) = mean_b [-alpha (log pi(a_b|s_b) + H_target)]`` (eq. 18), written in ``log alpha``
    as SB3 does (ARCHITECTURE.md 4): entropy above the target lowers alpha, below raises it."""
    return -(log_alpha * (log_prob.detach() + target_entropy).mean()), {}


# ----------------------------------------------------------------------------------------------
# The update step
# ----------------------------------------------------------------------------------------------


@dataclass
class UpdateResult:
    """What :meth:`SAC.update` hands back: ``td_abs [B]`` float32 for priorities (mean over heads;
    non-finite entries set to 0 when the step was skipped), metrics (empty unless asked for)."""

    td_abs: np.ndarray
    metrics: dict[str, float] = field(default_factory=dict)
    skipped: bool = False


_NOT_BUILT = ("use_rnn", "use_n_step_is", "use_prediction", "use_curiosity", "use_rnd", "use_normalization",
              "discrete_dqn_like")  # fmt: skip


def check_supported(spec: EnvSpec, sac: SacConfig) -> None:
    """Raise NotImplementedError naming the first config key or spec feature not built yet."""
    for key in _NOT_BUILT:
        if getattr(sac, key):
            raise NotImplementedError(f"sac_config.{key}=true is not implemented yet")
    if sac.burn_in_step:
        raise NotImplementedError("sac_config.burn_in_step > 0 needs use_rnn, which is not implemented yet")
    if spec.action.discrete_branches:
        raise NotImplementedError("discrete actions are not implemented yet")
    for s in spec.sensors:
        if s.is_image:
            raise NotImplementedError(f"image sensor {s.name!r} is not implemented yet")


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
    ``torch.Generator`` objects owned here, seeded from ``sac.seed`` (or, when it is None, drawn
    from torch's global RNG, so ``torch.manual_seed`` makes a run reproducible); both are in
    :meth:`state_dict`.
    """

    def __init__(
        self,
        spec: EnvSpec,
        sac: SacConfig,
        nn: NNConfig,
        replay: ReplayConfig,
        device: str | torch.device = "cpu",
        compile: bool = False,
    ) -> None:
        check_supported(spec, sac)
        self.spec = spec
        self.sac = sac
        self.device = torch.device(device)
        self.beta = float(replay.beta)
        self.beta_increment = float(replay.beta_increment_per_sampling)
        self.target_entropy = -float(spec.action.continuous_dim)

        if sac.seed is None:
            init_seed, act_seed, learn_seed = (int(s) for s in torch.randint(0, 2**62, (3,)))
        else:
            init_seed, act_seed, learn_seed = (int(s) for s in np.random.SeedSequence(sac.seed).generate_state(3))
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(init_seed)
            self.models = build_models(spec, sac, nn).to(self.device)
        self.target_representation = copy.deepcopy(self.models.representation).requires_grad_(False)
        self.target_q = copy.deepcopy(self.models.q).requires_grad_(False)
        self._act_rng = torch.Generator(device=self.device)
        self._act_rng.manual_seed(act_seed)
        self._learn_rng = torch.Generator(device=self.device)
        self._learn_rng.manual_seed(learn_seed)

        self.log_alpha = torch.nn.Parameter(
            torch.tensor(float(sac.init_log_alpha), device=self.device), requires_grad=sac.use_auto_alpha
        )
        self._critic_params: list[Tensor] = [
            *self.models.representation.parameters(),
            *self.models.q.parameters(),
        ]
        self._policy_params: list[Tensor] = list(self.models.policy.parameters())
        self.critic_optimizer = self._adam(self._critic_params)
        self.policy_optimizer = self._adam(self._policy_params)
        self.alpha_optimizer = self._adam([self.log_alpha]) if sac.use_auto_alpha else None
        self._target_params: list[Tensor] = [
            *self.target_representation.parameters(),
            *self.target_q.parameters(),
        ]
        self._acting = torch.nn.ModuleDict({"representation": self.models.representation, "policy": self.models.policy})

        # torch.compile of the loss computation (forward and, through AOTAutograd, backward);
        # its first update compiles for ~20 s on CPU. See bench/learner.py for what it gains.
        self._compute_losses = torch.compile(self._losses) if compile else self._losses
        # Hidden layers in bfloat16 (sac.compute_dtype): 2.2x faster matmuls on this project's AVX512-BF16
        # CPUs, 1.4x faster updates (bench/learner.py); output layers stay float32 (nn.layers.in_float32).
        self._low_precision = sac.compute_dtype == "bfloat16"
        self.updates = 0  # applied (not skipped) updates
        self.nonfinite_skipped = 0
        self._consecutive_nonfinite = 0

    def _adam(self, params: list[Tensor]) -> torch.optim.Adam:
        return torch.optim.Adam(params, lr=self.sac.learning_rate, fused=True)

    # -- acting ---------------------------------------------------------------------------------

    @torch.inference_mode()
    def act(self, obs: list[np.ndarray], deterministic: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Actions ``[N, A]`` float32 in ``[-1, 1]`` and their log-probability ``[N]`` under the
        current policy, for ``N`` observations given as one ``[N, *sensor_shape]`` array per sensor.
        ``deterministic`` acts with ``tanh(mean)`` (its log-prob is the density at that point)."""
        sensors = self.spec.sensors
        if len(obs) != len(sensors):
            raise ValueError(f"act: expected {len(sensors)} sensors {[s.name for s in sensors]}, got {len(obs)}")
        tensors = []
        for o, s in zip(obs, sensors, strict=True):
            if o.ndim != len(s.shape) + 1 or tuple(o.shape[1:]) != s.shape:
                raise ValueError(f"act: sensor {s.name!r} must be [N, {', '.join(map(str, s.shape))}], got {o.shape}")
            tensors.append(torch.as_tensor(o, dtype=torch.float32, device=self.device))
        state = self.models.representation(tensors)
        noise = None
        if not deterministic:
            noise = torch.randn(
                state.shape[0], self.spec.action.continuous_dim, generator=self._act_rng, device=self.device
            )
        action, log_prob = self.models.policy.sample(state, noise)
        return action.cpu().numpy(), log_prob.cpu().numpy()

    # -- learning -------------------------------------------------------------------------------

    def _subset(self) -> Tensor | None:
        """A fresh random subset of ``ensemble_q_sample`` heads; None (all heads) when it is all."""
        n, k = self.sac.ensemble_q_num, self.sac.ensemble_q_sample
        if k == n:
            return None
        return torch.randperm(n, generator=self._learn_rng, device=self.device)[:k]

    def _losses(
        self,
        obs: list[Tensor],
        actions: Tensor,
        rewards: Tensor,
        terminated: Tensor,
        truncated: Tensor,
        mask: Tensor,
        weights: Tensor | None,
        noise: Tensor,
        target_heads: Tensor | None,
        policy_heads: Tensor | None,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Metrics]:
        """The SAC losses from the current parameters: ``(q_loss, policy_loss, alpha_loss, td_abs,
        metrics)``. Batch tensors are ``[B, L(+1), ...]``; ``noise [2, B, A]`` feeds the target's
        and the policy loss's action samples. Pure tensor code, so ``compile=True`` can compile it."""
        sac, dev = self.sac, self.device
        rep, q, policy = self.models.representation, self.models.q, self.models.policy
        alpha = self.log_alpha.detach().exp()

        # 1. Target y for step 0 of each window: n-step return + gamma^m V(o_m)  (eq. 2, 3, 5).
        with torch.no_grad():
            valid = valid_steps(mask, terminated, truncated)
            next_obs = [gather_positions(o, bootstrap_index(valid)) for o in obs]
            v, v_metrics = soft_value(
                self.target_q,
                policy,
                self.target_representation(next_obs),
                rep(next_obs),
                alpha,
                noise[0],
                target_heads,
            )
            y = n_step_target(rewards, terminated, valid, v, sac.gamma)
            obs0, action0 = [o[:, 0] for o in obs], actions[:, 0]
            old_q = None
            if sac.clip_epsilon is not None:
                old_q = self.target_q(self.target_representation(obs0), action0)

        # 2. Critic, policy and alpha losses.
        state = rep(obs0)
        q_loss, td_abs, q_metrics = critic_loss(q, state, action0, y, weights, sac.clip_epsilon, old_q)
        pi_loss, log_prob, pi_metrics = policy_loss(policy, q, state, alpha, noise[1], policy_heads)
        a_loss = torch.zeros((), device=dev)
        if self.alpha_optimizer is not None:
            a_loss, _ = alpha_loss(self.log_alpha, log_prob, self.target_entropy)
        metrics = {**v_metrics, **q_metrics, **pi_metrics, "learner/alpha": alpha}
        return q_loss, pi_loss, a_loss, td_abs, metrics

    def update(self, batch: Batch, with_metrics: bool = False) -> UpdateResult:
        """One gradient step on every part from one batch (ARCHITECTURE.md 4).

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
        noise = torch.randn(2, batch.batch_size, self.spec.action.continuous_dim, generator=self._learn_rng, device=dev)
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=self._low_precision):
            q_loss, pi_loss, a_loss, td_abs, metric_tensors = self._compute_losses(
                [torch.from_numpy(o).to(dev) for o in batch.obs],
                torch.from_numpy(batch.actions).to(dev),
                torch.from_numpy(batch.rewards).to(dev),
                torch.from_numpy(batch.terminated).to(dev),
                torch.from_numpy(batch.truncated).to(dev),
                torch.from_numpy(batch.mask).to(dev),
                weights,
                noise,
                self._subset(),
                self._subset(),
            )

        # 3. One backward: the losses touch disjoint parameters (policy_loss detaches the critic,
        #    alpha_loss detaches log_prob, the target is no-grad), so each gets exactly its own grads.
        for opt in self._optimizers():
            opt.zero_grad(set_to_none=True)
        (q_loss + pi_loss + a_loss).backward()
        critic_norm, policy_norm = _grad_norm(self._critic_params), _grad_norm(self._policy_params)
        checks = torch.stack([q_loss.detach(), pi_loss.detach(), a_loss.detach(), critic_norm, policy_norm])

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

        td = torch.nan_to_num(td_abs, nan=0.0, posinf=0.0, neginf=0.0) if skipped else td_abs
        metrics: dict[str, float] = {}
        if with_metrics:
            tensors = {
                **metric_tensors,
                "learner/td_abs_mean": td_abs,
                "learner/q_loss": q_loss,
                "learner/policy_loss": pi_loss,
                "learner/alpha_loss": a_loss,
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
        return UpdateResult(td_abs=td.cpu().numpy(), metrics=metrics, skipped=skipped)

    def _optimizers(self) -> list[torch.optim.Optimizer]:
        return list(self._named_optimizers().values())

    def _skip(self, checks: Tensor) -> None:
        for opt in self._optimizers():
            opt.zero_grad(set_to_none=True)
        self.nonfinite_skipped += 1
        self._consecutive_nonfinite += 1
        if self._consecutive_nonfinite >= self.sac.max_nonfinite_steps:
            names = ("q_loss", "policy_loss", "alpha_loss", "grad_norm_critic", "grad_norm_policy")
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
        if not batch.mask[:, 0].all():
            raise ValueError("batch.mask[:, 0] must be True: every window starts at a stored step")
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
            "optimizers": {name: opt.state_dict() for name, opt in self._named_optimizers().items()},
            "beta": self.beta,
            "updates": self.updates,
            "nonfinite_skipped": self.nonfinite_skipped,
            "consecutive_nonfinite": self._consecutive_nonfinite,
            "rng": {"act": self._act_rng.get_state(), "learn": self._learn_rng.get_state()},
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
        for name, opt in optimizers.items():
            opt.load_state_dict(state["optimizers"][name])
        self.beta = float(state["beta"])
        self.updates = int(state["updates"])
        self.nonfinite_skipped = int(state["nonfinite_skipped"])
        self._consecutive_nonfinite = int(state["consecutive_nonfinite"])
        self._act_rng.set_state(state["rng"]["act"])
        self._learn_rng.set_state(state["rng"]["learn"])

    def _named_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        named: dict[str, torch.optim.Optimizer] = {
            "critic": self.critic_optimizer,
            "policy": self.policy_optimizer,
        }
        if self.alpha_optimizer is not None:
            named["alpha"] = self.alpha_optimizer
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
