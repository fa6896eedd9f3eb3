"""V-trace in the learner (``sac_config.use_n_step_is``): ratios from the stored behaviour
log-probability, the on-policy case equal to the plain n-step target, and the ratios logged."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.nn.models import TanhGaussianPolicy
from algorithm.sac.features import Temperatures, VTraceTarget
from algorithm.sac.learner import SAC
from algorithm.sac.window import PassInputs, cut_window
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from algorithm.types import Batch

OBS, N_STEP, B = 3, 4, 32


def make_sac(spec: EnvSpec, **sac: Any) -> SAC:
    cfg = SacConfig(**{"seed": 5, "n_step": N_STEP, "use_priority": False, **sac})
    return SAC(spec, cfg, NNConfig(hidden_units=[16]), ReplayConfig())


def make_batch(spec: EnvSpec, behaviour_logp: np.ndarray | None = None, seed: int = 0) -> Batch:
    rng = np.random.default_rng(seed)
    act = spec.action
    parts = [np.eye(n, dtype=np.float32)[rng.integers(n, size=(B, N_STEP))] for n in act.discrete_branches]
    if act.continuous_dim:
        parts.append(rng.uniform(-0.9, 0.9, (B, N_STEP, act.continuous_dim)).astype(np.float32))
    mask = np.ones((B, N_STEP), dtype=bool)
    mask[: B // 2, 2:] = False  # short windows (chunk ends)
    terminated = np.zeros((B, N_STEP), dtype=bool)
    terminated[B // 2 : B // 2 + 4, 1] = True
    mask[B // 2 : B // 2 + 4, 2:] = False
    return Batch(
        keys=np.arange(B, dtype=np.uint64),
        probabilities=np.full(B, 0.01),
        table_size=100,
        obs=[rng.standard_normal((B, N_STEP + 1, OBS), dtype=np.float32)],
        actions=np.concatenate(parts, axis=-1),
        prev_actions=np.zeros((B, N_STEP, act.size), dtype=np.float32),
        rewards=rng.standard_normal((B, N_STEP), dtype=np.float32),
        terminated=terminated,
        truncated=np.zeros((B, N_STEP), dtype=bool),
        behaviour_logp=np.zeros((B, N_STEP), dtype=np.float32) if behaviour_logp is None else behaviour_logp,
        mask=mask,
    )


def current_log_pi(sac: SAC, batch: Batch) -> np.ndarray:
    noise = torch.zeros(B, N_STEP + 2, sac.spec.action.continuous_dim)
    inputs = PassInputs.from_flat([torch.from_numpy(x) if isinstance(x, np.ndarray) else x
                                   for x in sac._pass_inputs(batch, None, noise, None, None)], 1)  # fmt: skip
    parts = sac.losses.parts
    with torch.no_grad():
        window = cut_window(inputs, sac.sac, sac.models, sac.target_representation, None)
        temperatures = Temperatures(torch.tensor(0.1), sac.log_alpha_discrete.exp())
        _, log_pi = VTraceTarget(parts).window_values(window, temperatures, None)
    return log_pi.numpy()


DISCRETE = EnvSpec((SensorSpec("obs", (OBS,)),), ActionSpec((3,), 0))


def test_on_policy_vtrace_equals_the_n_step_target() -> None:
    # Discrete SAC values are exact expectations (no sampling), and with mu = pi every ratio is 1:
    # the V-trace sum telescopes to the n-step return, so both learners see the same targets.
    plain, traced = make_sac(DISCRETE), make_sac(DISCRETE, use_n_step_is=True)
    batch = make_batch(DISCRETE)
    batch.behaviour_logp = current_log_pi(traced, batch)
    a = plain.update(batch, with_metrics=True).metrics
    b = traced.update(batch, with_metrics=True).metrics
    assert b["learner/target_mean"] == pytest.approx(a["learner/target_mean"], rel=1e-5)
    assert b["learner/q_loss"] == pytest.approx(a["learner/q_loss"], rel=1e-5)
    assert b["learner/vtrace_rho"] == pytest.approx(1.0)


def test_off_policy_data_changes_the_target_and_the_logged_ratios() -> None:
    traced = make_sac(DISCRETE, use_n_step_is=True)
    batch = make_batch(DISCRETE)
    on_policy = current_log_pi(traced, batch)
    batch.behaviour_logp = on_policy + np.log(4.0)  # behaviour 4x likelier than pi: rho = 1/4
    off = traced.update(batch, with_metrics=True).metrics
    assert off["learner/vtrace_rho"] == pytest.approx(0.25, rel=1e-4)
    batch.behaviour_logp = on_policy
    reference = make_sac(DISCRETE, use_n_step_is=True).update(batch, with_metrics=True).metrics
    assert off["learner/target_mean"] != pytest.approx(reference["learner/target_mean"], rel=1e-4)


@pytest.mark.parametrize("spec", [
    EnvSpec((SensorSpec("obs", (OBS,)),), ActionSpec((), 2, (-1.0, -1.0), (1.0, 1.0))),
    EnvSpec((SensorSpec("obs", (OBS,)),), ActionSpec((2, 3), 1, (-1.0,), (1.0,))),
])  # fmt: skip
def test_vtrace_updates_continuous_and_mixed_actions(spec: EnvSpec) -> None:
    sac = make_sac(spec, use_n_step_is=True)
    for seed in range(3):
        result = sac.update(make_batch(spec, seed=seed), with_metrics=True)
        assert not result.skipped and np.isfinite(result.metrics["learner/vtrace_rho"])
    # behaviour far likelier than the current policy (log mu = +20): the ratios fall well below 1,
    # so the continuous log pi of stored actions really enters the trace
    unlikely = make_batch(spec, behaviour_logp=np.full((B, N_STEP), 20.0, np.float32))
    assert sac.update(unlikely, with_metrics=True).metrics["learner/vtrace_rho"] < 0.01


def test_policy_log_prob_of_its_own_sample_matches_the_sampling_log_prob() -> None:
    torch.manual_seed(0)
    policy = TanhGaussianPolicy(OBS, 2, [16])
    state = torch.randn(64, OBS)
    action, log_prob = policy.sample(state, torch.randn(64, 2))
    torch.testing.assert_close(policy.log_prob(state, action), log_prob, rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize("mean", [0.0, 5.0, 8.0, 10.0, 30.0])
def test_on_policy_ratios_stay_one_when_the_policy_saturates(mean: float) -> None:
    # Issue 15, defect 2: the learner recomputed log pi by atanh of the stored float32 action
    # clamped below 1, so a saturated policy (pre-tanh mean 8: median ratio 0.03; 10: ~1e-14) cut
    # its own on-policy traces. Both sides now use the stored action's measure (models.py).
    spec = EnvSpec((SensorSpec("obs", (OBS,)),), ActionSpec((), 2, (-1.0, -1.0), (1.0, 1.0)))
    sac = make_sac(spec)
    policy = sac.models.policy
    assert policy is not None and sac._numpy_actor is not None
    with torch.no_grad():
        policy.head.weight.zero_()
        policy.head.bias.copy_(torch.tensor([mean, -mean, -0.5, 0.0]))  # means +-mean, std 0.61 and 1
    obs = np.random.default_rng(0).standard_normal((2000, OBS), dtype=np.float32)
    numpy_actor = sac._numpy_actor
    for acting in (numpy_actor, None):  # an actor acts with NumPy where it can, else with torch
        sac._numpy_actor = acting
        actions, behaviour_logp = sac.act([obs])
        with torch.no_grad():
            state = sac.models.representation.policy_state(sac.models.representation([torch.from_numpy(obs)]))
            log_pi = policy.log_prob(state, torch.from_numpy(actions)).numpy()
        ratios = np.exp(log_pi - behaviour_logp)
        assert np.all(np.isfinite(ratios))
        np.testing.assert_allclose(ratios, 1.0, atol=1e-3)
