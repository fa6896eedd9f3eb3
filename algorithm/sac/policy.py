"""The acting side of Soft Actor-Critic: :class:`Policy` holds the models and the acting randomness,
and acts; it builds no optimizer and no target network. Actors, evaluation, ``--run`` and the
learner's GetAction copy use it; :class:`algorithm.sac.learner.SAC` extends it with the learner's side.

Usage, in an actor::

    policy = Policy(spec, cfg.sac_config, cfg.nn_config)
    policy.load_acting_state_dict(published)          # weights from the learner
    actions, behaviour_logp = policy.act(obs)         # or act_recurrent(obs, prev, state) with use_rnn
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor

from algorithm.config.schema import NNConfig, SacConfig
from algorithm.nn.builder import build_models
from algorithm.nn.colored_noise import ColoredNoise, inverse_cdf_choice
from algorithm.nn.models import masked_branch_one_hot_argmax, stored_action_log_prob
from algorithm.nn.noisy import NoisyLayer, reset_noise, set_noise
from algorithm.nn.numpy_acting import numpy_actor_for
from algorithm.nn.recurrent import RecurrentRepresentation
from algorithm.nn.user import ModelBuilder
from algorithm.sac.equations import PolicySample, branch_matrix
from algorithm.spaces import EnvSpec
from algorithm.types import ActingProgress

log = logging.getLogger("asac.policy")


class Policy:
    """The models of one agent and what acting needs: the acting generators, the NumPy actor, the
    exploration noise. Acting reads ``representation``, the policies, the normalizer, the Q heads
    (dqn-like discrete branches only) and the RND model (novelty-picked candidates); the other
    models are built too (so a policy and a learner of the same seed start from the same weights)
    but acting never runs them.

    Randomness: model initialisation uses torch's global RNG, forked and seeded with ``sac.seed``
    when it is set (the global state is left as it was). Action noise comes from a
    ``torch.Generator`` (acting in NumPy: a ``numpy.random.Generator``) seeded from ``sac.seed``
    (or, when it is None, drawn from torch's global RNG, so ``torch.manual_seed`` makes a run
    reproducible); both are in :meth:`state_dict`. A third seed is drawn for the learner's side.
    """

    def __init__(
        self,
        spec: EnvSpec,
        sac_config: SacConfig,
        nn_config: NNConfig,
        device: str | torch.device = "cpu",
        build: ModelBuilder = build_models,
    ) -> None:
        self.spec = spec
        self.sac = sac_config
        self.device = torch.device(device)
        act = spec.action
        self._branches = branch_matrix(act.discrete_branches, self.device) if act.discrete_branches else None
        self._mask_index = spec.action_mask_index

        if sac_config.seed is None:
            init_seed, act_seed, learn_seed = (int(s) for s in torch.randint(0, 2**62, (3,)))
        else:
            init_seed, act_seed, learn_seed = (
                int(s) for s in np.random.SeedSequence(sac_config.seed).generate_state(3)
            )
        self._learn_seed = learn_seed
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(init_seed)
            self.models = build(spec, sac_config, nn_config).to(self.device)
        self._act_rng = torch.Generator(device=self.device)
        self._colored: ColoredNoise | None = None
        self._seed_acting_generators(act_seed)

        acting: dict[str, torch.nn.Module] = {"representation": self.models.representation}
        if self.models.normalizer is not None:
            acting["normalizer"] = self.models.normalizer
        for name in ("policy", "discrete_policy"):
            module = getattr(self.models, name)
            if module is not None:
                acting[name] = module
        if self._branches is not None and self.models.discrete_policy is None:
            acting["q"] = self.models.q  # dqn_like: the Q heads pick the discrete actions
        if self.models.rnd is not None:
            acting["rnd"] = self.models.rnd  # actors choose by novelty
        self._acting = torch.nn.ModuleDict(acting)
        # Noisy layers (nn_config.noisy_q / noisy_policy) draw fresh noise for every update and every
        # stochastic act() call, from this object's generators; deterministic acting uses the mean weights.
        self._noisy = any(isinstance(m, NoisyLayer) for m in self.models.modules())
        rep = self.models.representation
        self.rnn_state_size = rep.rnn_state_size if isinstance(rep, RecurrentRepresentation) else 0
        # act() in NumPy where that computes what torch would (nn/numpy_acting.py), else None.
        self._numpy_actor = None
        if sac_config.numpy_acting:
            discrete = bool(act.discrete_branches)
            self._numpy_actor = numpy_actor_for(self.models, self.device.type, bool(self.rnn_state_size), discrete)
        # Extra exploration of one distributed actor, min(noise_increasing_rate * i, noise_max)
        # (docs/architecture.md section 9): stochastic acting widens the pre-tanh Gaussian to
        # std' = sqrt(std^2 + noise^2) and mixes each discrete branch with the uniform distribution
        # over allowed actions (weight min(noise, 1)).
        # The log-prob returned is the widened policy's, so the stored behaviour mu stays exact.
        self.exploration_noise = 0.0
        # What the acting loop has done (ActorLoop hands its own in): RND's action choice ends by it.
        self.progress = ActingProgress()
        self._novelty_choice_ended = False

    # -- acting ---------------------------------------------------------------------------------

    def _seed_acting_generators(self, act_seed: int) -> None:
        self._act_rng.manual_seed(act_seed)
        # numpy_acting's noise: drawing it with torch cost as much as the NumPy forward itself
        # (13 vs 2 us per call inside an actor loop, and the env step after it 8 us more).
        self._act_np_rng = np.random.default_rng(act_seed)
        # sac_config.action_noise_color > 0: the acting noise of each env is correlated across its steps
        # (nn/colored_noise.py); its own generator, so that white acting draws the same as before.
        if self.sac.action_noise_color > 0:
            self._colored = ColoredNoise(self.sac.action_noise_color, np.random.default_rng([act_seed, 1]))

    def seed_acting(self, seed: int) -> None:
        """Reseed the acting noise (white and colored) from ``seed``: each distributed actor calls it
        with its own seed, so that actors built from one config do not all draw the same noise."""
        self._seed_acting_generators(int(np.random.SeedSequence([seed, 7]).generate_state(1)[0]))

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
            shape = (obs[0].shape[0], self.spec.action.continuous_dim)
            colored = self._colored
            noise = self._act_np_rng.standard_normal(shape, np.float32) if colored is None else colored.draw(*shape)
        return self._numpy_actor.act(obs, noise, 0.0 if deterministic else self.exploration_noise)

    @torch.inference_mode()
    def _act_torch(self, obs: list[np.ndarray], deterministic: bool) -> tuple[np.ndarray, np.ndarray]:
        return self._act_with_noise(self.obs_tensors(obs), deterministic, None)

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
        tensors = self.obs_tensors(obs)
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

    def obs_tensors(self, obs: list[np.ndarray]) -> list[Tensor]:
        """``obs`` as the models take it: each sensor checked against the spec, float32 on the policy's
        device, normalized when the run normalizes observations (what :meth:`act` feeds the networks)."""
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
            if self.models.rnd is None or deterministic or not self.chooses_by_novelty():
                action, log_prob = self._act(full_state, tensors, deterministic)
            else:  # the most novel of rnd_n_sample policy actions per env
                n, k = full_state.shape[0], self.sac.rnd_n_sample
                repeated = full_state.repeat_interleave(k, dim=0)
                candidates, log_probs = self._act(
                    repeated, [t.repeat_interleave(k, dim=0) for t in tensors], False, colored=False
                )
                novelty = self.models.rnd.novelty(repeated, candidates).view(n, k)
                pick = novelty.argmax(dim=1) + torch.arange(n, device=self.device) * k
                # log-prob under the policy alone: the selection's own probability has no closed form
                action, log_prob = candidates[pick], log_probs[pick]
            return action.cpu().numpy(), log_prob.cpu().numpy()
        finally:
            if self._noisy and deterministic:
                set_noise(self._acting, True)

    def chooses_by_novelty(self) -> bool:
        """Whether stochastic acting takes the most novel of RND's candidates: until the loop's env
        steps reach ``rnd_choice_steps`` (0: no limit) and until one of its episodes has returned
        ``rnd_choice_until_return`` (None: no limit). The choice leaves a path once its pairs are
        familiar, also after it found the goal (bench/results/mountain_car/README.md); ending it
        hands acting back to the policy. A chance fading from 1 to 0, drawn per step, was tried
        first: mixing the two actions step by step lost the sustained push that finds the goal (4 of
        5 development seeds never found it)."""
        sac, progress = self.sac, self.progress
        if 0 < sac.rnd_choice_steps <= progress.env_steps:
            reason = f"rnd_choice_steps {sac.rnd_choice_steps} reached"
        elif sac.rnd_choice_until_return is not None and progress.best_episode_return >= sac.rnd_choice_until_return:
            reason = f"an episode returned {progress.best_episode_return:.1f} (rnd_choice_until_return)"
        else:
            return True
        if not self._novelty_choice_ended:  # once per policy: the schedules only move forward
            self._novelty_choice_ended = True
            log.info("RND's action choice ends at %d env steps: %s; the policy acts alone", progress.env_steps, reason)
        return False

    def _act(
        self, full_state: Tensor, tensors: list[Tensor], deterministic: bool, colored: bool = True
    ) -> tuple[Tensor, Tensor]:
        """Actions and behaviour log-probs of ``n`` states. With colored noise (``colored`` and
        ``action_noise_color > 0``) one correlated standard normal per continuous dimension and per
        discrete branch, per env (RND's candidates, ``colored=False``, stay white)."""
        state = self.models.representation.policy_state(full_state)
        n, spec = state.shape[0], self.spec.action
        log_prob = torch.zeros(n, device=self.device)
        continuous = None
        extra = 0.0 if deterministic else self.exploration_noise
        draws = None
        if colored and self._colored is not None and not deterministic:
            z = self._colored.draw(n, spec.continuous_dim + len(spec.discrete_branches))
            draws = torch.as_tensor(z, device=self.device)
        if self.models.policy is not None:
            if deterministic:
                continuous, log_prob = self.models.policy.sample(state, None)
            else:
                if draws is None:
                    noise = torch.randn(n, spec.continuous_dim, generator=self._act_rng, device=self.device)
                else:
                    noise = draws[:, : spec.continuous_dim]
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
            for b, branch_probs in enumerate(probs.split(list(spec.discrete_branches), dim=-1)):
                if deterministic:
                    choice = branch_probs.argmax(dim=-1)
                elif draws is not None:
                    choice = inverse_cdf_choice(branch_probs, draws[:, spec.continuous_dim + b])
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
            pi.continuous, pi.continuous_log_prob = self.models.policy.sample(
                policy_state, noise, self.sac.tanh_log_det_epsilon
            )
        if self.models.discrete_policy is not None:
            pi.log_probs = self.models.discrete_policy(policy_state, mask)
            pi.probs = pi.log_probs.exp()
        elif self._branches is not None:
            pi.probs = self._greedy(state, pi.continuous, mask)
        return pi

    # -- weights --------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """The models and the acting generators' states."""
        return {"models": self.models.state_dict(), "rng": self._acting_rng_state()}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore the models and the acting generators from :meth:`state_dict` or from a learner's
        :meth:`algorithm.sac.learner.SAC.state_dict` (a checkpoint's ``"sac"``: its learner parts are not read)."""
        if "models" not in state:
            raise KeyError("policy state dict lacks 'models'")
        self.models.load_state_dict(state["models"])
        self._load_acting_rng_state(state.get("rng", {}))

    def _acting_rng_state(self) -> dict[str, Any]:
        """The acting generators' states (torch, NumPy, and the colored noise's stream)."""
        rng: dict[str, Any] = {"act": self._act_rng.get_state(), "act_numpy": self._act_np_rng.bit_generator.state}
        if self._colored is not None:
            colored = self._colored.state()
            rng["act_colored"] = {
                "generator": self._colored.rng.bit_generator.state,
                "sequences": torch.from_numpy(colored["sequences"]),
                "position": colored["position"],
            }
        return rng

    def _load_acting_rng_state(self, rng: Mapping[str, Any]) -> None:
        if "act" in rng:
            self._act_rng.set_state(rng["act"])
        if "act_numpy" in rng:  # checkpoints from before numpy_acting have none
            self._act_np_rng.bit_generator.state = rng["act_numpy"]
        if self._colored is not None and "act_colored" in rng:
            colored = rng["act_colored"]
            self._colored.rng.bit_generator.state = colored["generator"]
            self._colored.load_state({"sequences": np.asarray(colored["sequences"]), "position": colored["position"]})

    def acting_state_dict(self) -> dict[str, Tensor]:
        """The parameters :meth:`act` uses (``representation.*`` and ``policy.*``), flat name ->
        tensor: what a learner publishes to actors."""
        return self._acting.state_dict()

    def load_acting_state_dict(self, state: dict[str, Tensor]) -> None:
        """Load what :meth:`acting_state_dict` returned (an actor receiving published weights);
        missing or unexpected names raise, naming them."""
        self._acting.load_state_dict(state)
