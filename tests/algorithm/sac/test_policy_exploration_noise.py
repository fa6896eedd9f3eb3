"""Per-actor exploration noise (SAC.exploration_noise): the behaviour log-prob an actor stores is the
exact density of the noisier policy it acted with, for continuous and discrete actions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch.distributions import Normal, TransformedDistribution
from torch.distributions.transforms import TanhTransform

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.sac.learner import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec

OBS = SensorSpec("obs", (3,))


def make(action: ActionSpec, seed: int = 0) -> SAC:
    return SAC(EnvSpec((OBS,), action), SacConfig(seed=seed), NNConfig(hidden_units=[16]), ReplayConfig())


def policy_head(sac: SAC, obs: np.ndarray) -> tuple[torch.Tensor, ...]:
    with torch.no_grad():
        state = sac.models.representation.policy_state(sac.models.representation([torch.from_numpy(obs)]))
        if sac.models.policy is not None:
            return sac.models.policy(state)
        assert sac.models.discrete_policy is not None
        return (sac.models.discrete_policy(state, None).exp(),)


def test_zero_noise_acts_exactly_as_before() -> None:
    obs = np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32)
    plain, noiseless = (
        make(ActionSpec((), 2, (-1.0,) * 2, (1.0,) * 2)),
        make(ActionSpec((), 2, (-1.0,) * 2, (1.0,) * 2)),
    )
    noiseless.exploration_noise = 0.0
    for _ in range(3):
        a, logp = plain.act([obs])
        b, logq = noiseless.act([obs])
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(logp, logq)


@pytest.mark.parametrize("noise", [0.1, 0.5, 2.0])
def test_continuous_noise_widens_the_gaussian_and_reports_its_density(noise: float) -> None:
    sac = make(ActionSpec((), 1, (-1.0,), (1.0,)))
    sac.exploration_noise = noise
    obs = np.tile(np.array([[0.3, -0.2, 0.1]], np.float32), (4000, 1))
    actions, logp = sac.act([obs])
    mean, log_std = policy_head(sac, obs[:1])
    wide = math.sqrt(float(log_std.exp()) ** 2 + noise**2)
    dist = TransformedDistribution(Normal(mean[0], torch.tensor([wide])), [TanhTransform()])
    inner = np.abs(actions[:, 0]) < 0.999  # away from the edge, where atanh amplifies float32 rounding
    expected = dist.log_prob(torch.from_numpy(actions[inner])).sum(-1).numpy()
    np.testing.assert_allclose(logp[inner], expected, atol=2e-3, rtol=1e-3)
    pre_tanh = np.arctanh(np.clip(actions[:, 0], -0.999999, 0.999999))
    assert np.std(pre_tanh) == pytest.approx(wide, rel=0.1)
    greedy, _ = sac.act([obs[:1]], deterministic=True)  # noise never touches evaluation
    np.testing.assert_allclose(greedy[0], np.tanh(mean[0].numpy()), rtol=1e-6)


def test_discrete_noise_mixes_with_the_uniform_distribution() -> None:
    sac = make(ActionSpec((3,), 0))
    sac.exploration_noise = 0.3
    obs = np.tile(np.array([[0.5, 0.1, -0.4]], np.float32), (20000, 1))
    actions, logp = sac.act([obs])
    (probs,) = policy_head(sac, obs[:1])
    mixed = 0.7 * probs[0].numpy() + 0.3 / 3
    chosen = actions.argmax(axis=1)
    np.testing.assert_allclose(logp, np.log(mixed[chosen]), rtol=1e-5)
    np.testing.assert_allclose(np.bincount(chosen, minlength=3) / len(chosen), mixed, atol=0.015)
