"""Soft Actor-Critic, the learner's side: :class:`SAC` extends the acting :class:`~algorithm.sac.policy.Policy`
with the target networks, the optimizers and the update step, and composes what an update computes
(:class:`~algorithm.sac.losses.SacLosses`: plain SAC, with the transforms of the features the config
turns on, :mod:`algorithm.sac.features`); its checkpoint state is :mod:`algorithm.sac.checkpoint_state`'s.

The losses are pure functions in :mod:`algorithm.sac.equations`, targets over windows in
:mod:`algorithm.sac.returns`. Actions may be continuous, discrete (several branches, optional action
masks, ``discrete_dqn_like``) or both (docs/architecture.md sections 3 and 5).

Usage, in a learner loop::

    sac = SAC(spec, cfg.sac_config, cfg.nn_config, cfg.replay_config, device="cpu")
    while training:
        batch = table.sample(cfg.replay_config.batch_size)
        result = sac.update(batch, with_metrics=step % cfg.sac_config.write_summary_per_step == 0)
        if not result.skipped:
            table.update_priorities(batch.keys, result.td_abs)
        writer.write(result.metrics)

and, being a :class:`~algorithm.sac.policy.Policy`, ``actions, behaviour_logp = sac.act(obs)`` acts
(actors that do not train build the :class:`~algorithm.sac.policy.Policy` alone).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.nn.builder import build_models
from algorithm.nn.layers import uses_bfloat16
from algorithm.nn.models import SacModels
from algorithm.nn.noisy import reset_noise
from algorithm.nn.prediction import gated_gradients, observation_targets
from algorithm.sac import checkpoint_state
from algorithm.sac.batch_checks import check_batch, check_config_for_task
from algorithm.sac.equations import Metrics, importance_weights
from algorithm.sac.losses import Losses, SacLosses
from algorithm.sac.parts import LearnerParts
from algorithm.sac.policy import Policy
from algorithm.sac.schedules import discrete_target_entropy_ratio, learning_rate_at, munchausen_scale_at
from algorithm.sac.update_graph import graph_for
from algorithm.sac.window import PassInputs
from algorithm.spaces import EnvSpec
from algorithm.types import Batch


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


class SAC(Policy):
    """One learner: the :class:`~algorithm.sac.policy.Policy` (models, acting) plus target copies,
    optimizers, ``log_alpha``, PER ``beta`` and counters.

    Three Adam optimizers with separate parameters: critic (Q heads + representation), policy,
    and ``log_alpha`` (only with ``use_auto_alpha``). Adam runs ``fused``: for 256x256 models on
    CPU its three steps took 0.26 ms against 0.66 ms ``foreach`` and 0.62 ms single-tensor.
    ``compile=True`` wraps the loss computation in ``torch.compile``; on CPU it did not pay
    (5-10% slower than eager in bench/learner.py), so it is off by default.

    Randomness: as the :class:`~algorithm.sac.policy.Policy`'s, plus two ``torch.Generator`` objects
    for the noise and head subsets of :meth:`update` and for :meth:`td_errors`, seeded from the
    third seed the policy drew; all are in :meth:`state_dict`.
    """

    def __init__(
        self,
        spec: EnvSpec,
        sac_config: SacConfig,
        nn_config: NNConfig,
        replay_config: ReplayConfig,
        device: str | torch.device = "cpu",
        compile: bool = False,
        build: Callable[[EnvSpec, SacConfig, NNConfig], SacModels] = build_models,
    ) -> None:
        check_config_for_task(sac_config, spec)
        super().__init__(spec, sac_config, nn_config, device, build)
        self.beta = float(replay_config.beta)
        self.beta_increment = float(replay_config.beta_increment_per_sampling)
        act = spec.action
        self.target_entropy = -float(act.continuous_dim)
        # Discrete: a fraction of each branch's maximum entropy log|A_b| (Christodoulou 2019 used 0.98),
        # annealed from discrete_target_entropy_start when that is set (_move_loss_schedules).
        self._max_discrete_entropy = [math.log(n) for n in act.discrete_branches]
        self.discrete_target_entropy = self._discrete_target_entropy(0)
        self.munchausen_weight = torch.tensor(munchausen_scale_at(sac_config, 0), device=self.device)  # moved in place
        self._observation_targets = observation_targets(spec.sensors, nn_config.critic_only, sac_config.use_extra_data)
        self.target_representation = copy.deepcopy(self.models.representation).requires_grad_(False)
        self.target_q = copy.deepcopy(self.models.q).requires_grad_(False)
        self._learn_rng = torch.Generator(device=self.device)
        self._learn_rng.manual_seed(self._learn_seed)
        self._score_rng = torch.Generator(device=self.device)  # td_errors(): scoring new data
        self._score_rng.manual_seed(self._learn_seed + 1)

        # One temperature for the continuous part, one per discrete branch (none when greedy).
        self.log_alpha = torch.nn.Parameter(
            torch.tensor(float(sac_config.init_log_alpha), device=self.device), requires_grad=sac_config.use_auto_alpha
        )
        n_discrete_alphas = len(act.discrete_branches) if self.models.discrete_policy is not None else 0
        self.log_alpha_discrete = torch.nn.Parameter(
            torch.full((n_discrete_alphas,), float(sac_config.init_log_alpha), device=self.device),
            requires_grad=sac_config.use_auto_alpha,
        )
        self._critic_params: list[Tensor] = [
            *self.models.representation.parameters(),
            *self.models.q.parameters(),
        ]
        self._policy_params: list[Tensor] = [
            p for m in (self.models.policy, self.models.discrete_policy) if m is not None for p in m.parameters()
        ]
        alpha_params = [p for p, used in ((self.log_alpha, act.continuous_dim > 0),
                                          (self.log_alpha_discrete, n_discrete_alphas > 0)) if used]  # fmt: skip
        self.critic_optimizer = self._adam(self._critic_params)
        self.policy_optimizer = self._adam(self._policy_params) if self._policy_params else None
        self.alpha_optimizer = self._adam(alpha_params) if sac_config.use_auto_alpha and alpha_params else None
        auxiliary = [m for m in (self.models.curiosity, self.models.rnd, self.models.prediction) if m is not None]
        self._auxiliary_params: list[Tensor] = [p for m in auxiliary for p in m.parameters() if p.requires_grad]
        self.auxiliary_optimizer = self._adam(self._auxiliary_params) if self._auxiliary_params else None
        self._target_params: list[Tensor] = [
            *self.target_representation.parameters(),
            *self.target_q.parameters(),
        ]

        # torch.compile of the loss computation (forward and, through AOTAutograd, backward);
        # its first update compiles for ~20 s on CPU. See bench/learner.py for what it gains.
        self.losses = SacLosses(
            LearnerParts(
                spec=spec, sac=sac_config, device=self.device, models=self.models,
                target_representation=self.target_representation, target_q=self.target_q, policy=self._policy,
                branches=self._branches, mask_index=self._mask_index, log_alpha=self.log_alpha,
                log_alpha_discrete=self.log_alpha_discrete, target_entropy=self.target_entropy,
                discrete_target_entropy=self.discrete_target_entropy, munchausen_weight=self.munchausen_weight,
                trains_alpha=self.alpha_optimizer is not None, observation_targets=self._observation_targets,
            )
        )  # fmt: skip
        self._compute_losses = torch.compile(self.losses.__call__) if compile else self.losses
        # Hidden layers in bfloat16 (sac_config.compute_dtype): 2.2x faster matmuls on this project's AVX512-BF16
        # CPUs, 1.4x faster updates (bench/learner.py); output layers stay float32 (nn.layers.in_float32).
        self._low_precision = uses_bfloat16(sac_config.compute_dtype, self.device)
        # On a GPU the forward and backward pass is recorded once as a CUDA graph and replayed
        # (algorithm/sac/update_graph.py); None where it is not (the CPU, configs it cannot record).
        trained = [p for opt in self._optimizers() for group in opt.param_groups for p in group["params"]]
        self.update_graph = graph_for(
            sac_config, self.device, compile, bool(self.rnn_state_size), self.models.prediction is not None, trained
        )
        self.updates = 0  # applied (not skipped) updates
        self.nonfinite_skipped = 0
        self._consecutive_nonfinite = 0

    def _adam(self, params: Sequence[Tensor]) -> torch.optim.Adam:
        return torch.optim.Adam(params, lr=self.sac.learning_rate, fused=True)

    def _named_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return checkpoint_state.named_optimizers(self)

    def _optimizers(self) -> list[torch.optim.Optimizer]:
        return list(self._named_optimizers().values())

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume bit-identically (:func:`algorithm.sac.checkpoint_state.learner_state`)."""
        return checkpoint_state.learner_state(self)

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned (from an identically configured SAC)."""
        checkpoint_state.load_learner_state(self, state)

    def load_model_weights(self, weights: Mapping[str, Tensor | np.ndarray]) -> None:
        """An evolver's weights in place of this learner's
        (:func:`algorithm.sac.checkpoint_state.load_model_weights`)."""
        checkpoint_state.load_model_weights(self, weights)

    def _subset(self) -> Tensor | None:
        """A fresh random subset of ``ensemble_q_sample`` heads; None (all heads) when it is all."""
        n, k = self.sac.ensemble_q_num, self.sac.ensemble_q_sample
        if k == n:
            return None
        return torch.randperm(n, generator=self._learn_rng, device=self.device)[:k]

    def update(self, batch: Batch, with_metrics: bool = False) -> UpdateResult:
        """One gradient step on every part from one batch (docs/architecture.md section 5).

        By default all losses are computed from the same parameters (:attr:`losses`) and applied
        together (as Acme's SAC learner does; ``update_order: critic_first`` is SB3's order,
        :meth:`_critic_first_step`), which lets the whole step be skipped when anything is
        non-finite: no optimizer step, no target update, weights and optimizer state unchanged.
        After ``sac.max_nonfinite_steps`` consecutive skips this raises RuntimeError. PER ``beta``
        advances once per call, skipped or not (it counts sampled batches).
        """
        check_batch(batch, self.spec, self.sac, self.rnn_state_size)
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
        noise = self._noise(batch, self._learn_rng)
        self._move_loss_schedules()
        inputs = self._pass_inputs(batch, weights, noise, self._subset(), self._subset())
        if sac.update_order == "critic_first":
            losses, critic_norm, policy_norm, skipped = self._critic_first_step(self._on_device(inputs))
        else:
            losses, critic_norm, policy_norm, skipped = self._joint_step(inputs)
        if not skipped:
            self._consecutive_nonfinite = 0
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
            if sac.learning_rate_final is not None:  # the step size this update stepped with
                metrics["learner/learning_rate"] = float(self.critic_optimizer.param_groups[0]["lr"])
            if self._max_discrete_entropy:
                metrics["learner/discrete_target_entropy"] = float(self.discrete_target_entropy.mean())
            if sac.munchausen_scale_start is not None:
                metrics["learner/munchausen_weight"] = float(self.munchausen_weight)
        refreshed = None
        if sac.refresh_rnn_states and losses.fed_states is not None and not skipped:
            refreshed = self._window_rows(batch, losses.fed_states)
        return UpdateResult(td_abs=td.cpu().numpy(), metrics=metrics, skipped=skipped, refreshed_rnn_states=refreshed)

    def _joint_step(self, inputs: list[np.ndarray | Tensor | None]) -> tuple[Losses, Tensor, Tensor, bool]:
        """Every loss from the same weights, applied together, or the whole step skipped if anything is
        non-finite (``update_order: joint``); the pass replayed as a CUDA graph where one is recorded."""
        graph = self.update_graph
        passed = None
        if graph is not None and graph.usable:
            passed = graph.run(self._forward_backward, inputs, self.device, self._kept_modules())
        if passed is None:
            passed = self._forward_backward(self._on_device(inputs))
        losses, critic_norm, policy_norm, checks = passed
        skipped = not bool(torch.isfinite(checks).all())  # the one host sync of the step
        if skipped:
            self._skip(checks)
        else:
            self._anneal_learning_rate()
            for opt in self._optimizers():
                opt.step()
        return losses, critic_norm, policy_norm, skipped

    def _critic_first_step(self, inputs: list[Tensor | None]) -> tuple[Losses, Tensor, Tensor, bool]:
        """SB3's order (``update_order: critic_first``; its SAC.train steps the temperature, then the
        critic, then the actor): the critic, temperature and exploration models step first, then the
        policy's loss is computed again, from the same sample and temperatures, against the stepped
        critic, and the policy steps. A non-finite first pass skips everything; a non-finite policy
        loss after the critic's step skips the policy's step (the critic's stands) and counts as a
        skipped update, as in :meth:`_joint_step`."""
        losses, critic_norm, _, checks = self._forward_backward(inputs, with_policy=False)
        if not bool(torch.isfinite(checks).all()):
            self._skip(checks)
            return losses, critic_norm, torch.zeros((), device=self.device), True
        self._anneal_learning_rate()
        for name, opt in self._named_optimizers().items():
            if name != "policy":
                opt.step()
        terms = losses.policy_terms
        if self.policy_optimizer is None or terms is None:
            return losses, critic_norm, torch.zeros((), device=self.device), False
        with self._autocast():
            pi_loss, _ = self.losses.policy_loss(terms)
        pi_loss.backward()
        policy_norm = _grad_norm(self._policy_params)
        losses = dataclasses.replace(losses, policy=pi_loss)
        if not bool(torch.isfinite(torch.stack([pi_loss.detach(), policy_norm])).all()):
            checks[[1, 6]] = torch.stack([pi_loss.detach(), policy_norm]).to(checks.dtype)
            self._skip(checks)
            return losses, critic_norm, policy_norm, True
        self.policy_optimizer.step()
        return losses, critic_norm, policy_norm, False

    def _discrete_target_entropy(self, updates: int) -> Tensor:
        ratio = discrete_target_entropy_ratio(self.sac, updates)
        return torch.tensor([ratio * log_n for log_n in self._max_discrete_entropy], device=self.device)

    def _move_loss_schedules(self) -> None:
        """Move the discrete target entropy and the Munchausen weight to this update's values, in place
        (tensors the compiled loss reads, so torch.compile sees no new constant)."""
        if self.sac.discrete_target_entropy_start is not None and self._max_discrete_entropy:
            self.discrete_target_entropy.copy_(self._discrete_target_entropy(self.updates))
        if self.sac.munchausen_scale_start is not None:
            self.munchausen_weight.fill_(munchausen_scale_at(self.sac, self.updates))

    def _anneal_learning_rate(self) -> None:
        if self.sac.learning_rate_final is None:
            return
        lr = learning_rate_at(self.sac, self.updates)
        for opt in self._optimizers():
            for group in opt.param_groups:
                group["lr"] = lr

    def td_errors(self, batch: Batch) -> np.ndarray:
        """``|TD| [B]`` float32 of each window's trained step under the current weights (mean over all
        Q heads, as :meth:`update` reports it), without training: how the learner scores new data
        for ``sac_config.insert_td_priorities``. Its noise comes from a generator of its own, so
        scoring does not change the updates' random stream, and RND's running novelty mean
        (``rnd_normalize``), which the losses move, is put back: it follows trained batches only."""
        check_batch(batch, self.spec, self.sac, self.rnn_state_size)
        noise = self._noise(batch, self._score_rng)
        rnd = self.models.rnd
        mean = rnd.get_buffer("novelty_mean") if rnd is not None and self.sac.rnd_normalize else None
        kept = None if mean is None else mean.clone()
        with torch.no_grad():
            td_abs = self._batch_losses(self._on_device(self._pass_inputs(batch, None, noise, None, None))).td_abs
            if mean is not None and kept is not None:
                mean.copy_(kept)
        return torch.nan_to_num(td_abs.float(), nan=0.0, posinf=0.0, neginf=0.0).cpu().numpy()

    def _noise(self, batch: Batch, generator: torch.Generator) -> Tensor:
        """The standard normal draws one pass over ``batch`` turns into policy samples (see
        :class:`~algorithm.sac.window.PassInputs`): ``[B, samples, A]``, or ``[B, T, samples, A]`` with
        one draw per trained step (``train_every_step``: the ``T`` window steps from the first trained one)."""
        sac = self.sac
        samples = sac.n_step + 2 if sac.use_n_step_is else 2
        trained: tuple[int, ...] = ()
        if sac.train_every_step:
            trained = (batch.window - (0 if sac.burn_in_gradient else sac.burn_in_step),)
        shape = (batch.batch_size, *trained, samples, self.spec.action.continuous_dim)
        return torch.randn(shape, generator=generator, device=self.device)

    def _pass_inputs(
        self, batch: Batch, weights: Tensor | None, noise: Tensor, target_heads: Tensor | None,
        policy_heads: Tensor | None,
    ) -> list[np.ndarray | Tensor | None]:  # fmt: skip
        """What one pass over ``batch`` takes, as :meth:`PassInputs.flat` lists it (a CUDA graph records
        that list); the batch's arrays still on the host."""
        rnn_state = batch.rnn_state if self.rnn_state_size else None
        return [*batch.obs, batch.actions, batch.prev_actions, batch.rewards, batch.terminated, batch.truncated,
                batch.mask, batch.behaviour_logp, rnn_state, weights, noise, target_heads, policy_heads]  # fmt: skip

    def _on_device(self, inputs: list[np.ndarray | Tensor | None]) -> list[Tensor | None]:
        """The inputs on the device; from pinned memory (a distributed learner's batches on CUDA) the
        copies do not block: the stream orders them before the pass, and the batch outlives the update
        (whose non-finite check waits for the stream)."""
        return [torch.from_numpy(x).to(self.device, non_blocking=True) if isinstance(x, np.ndarray) else x
                for x in inputs]  # fmt: skip

    def _batch_losses(self, inputs: list[Tensor | None]) -> Losses:
        """:class:`SacLosses` of a pass's inputs on the device, observations normalized. Autocast's cache
        of cast weights is off with a CUDA graph (its recipe says so); the values are the same."""
        batch = PassInputs.from_flat(inputs, len(self.spec.sensors))
        batch.obs = self._normalize(batch.obs)
        with self._autocast():
            return self._compute_losses(batch)

    def _autocast(self) -> torch.autocast:
        cache = self.update_graph is None
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self._low_precision, cache_enabled=cache)

    def _forward_backward(
        self, inputs: list[Tensor | None], with_policy: bool = True
    ) -> tuple[Losses, Tensor, Tensor, Tensor]:
        """One pass: the losses, their gradients in every parameter's ``.grad`` (the policy's only
        ``with_policy``), the two gradient norms and what the non-finite check looks at. This is what
        a CUDA graph records (:attr:`update_graph`)."""
        losses = self._batch_losses(inputs)
        # One backward: the losses touch disjoint parameters (policy_loss detaches the critic, alpha_loss
        # detaches log_prob, the target is no-grad), so each gets exactly its own grads.
        for opt in self._optimizers():
            opt.zero_grad(set_to_none=True)
        predictions = losses.predictions
        total = losses.q + losses.alpha + losses.auxiliary + (losses.policy if with_policy else 0.0)
        total.backward(retain_graph=bool(predictions))
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
        return losses, critic_norm, policy_norm, checks

    def _kept_modules(self) -> list[torch.nn.Module]:
        return [self.models, self.target_representation, self.target_q]

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


def _grad_norm(params: list[Tensor]) -> Tensor:
    """The 2-norm of all gradients of ``params`` together (one foreach kernel)."""
    return torch.nn.utils.get_total_norm([p.grad for p in params if p.grad is not None])
