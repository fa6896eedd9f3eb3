"""Discrete and mixed actions: masked distributions, exact-expectation values and losses, alphas
per branch, dqn-like acting, and the SAC update on discrete batches."""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import pytest
import torch
from scipy import stats

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.nn.models import DiscretePolicy, masked_branch_log_softmax, masked_branch_one_hot_argmax
from algorithm.run.actor import uniform_random_actions
from algorithm.sac.equations import PolicySample, alpha_loss, branch_matrix, expected_log_prob, policy_loss, soft_value
from algorithm.sac.learner import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from algorithm.types import Batch

OBS = 3


def masked_spec(branches: tuple[int, ...] = (4,), continuous: int = 0) -> EnvSpec:
    sensors = (SensorSpec("action_mask", (sum(branches),)), SensorSpec("obs", (OBS,)))
    return EnvSpec(sensors, ActionSpec(branches, continuous, (-1.0,) * continuous, (1.0,) * continuous))


def make_sac(spec: EnvSpec, **sac: Any) -> SAC:
    return SAC(spec, SacConfig(**{"seed": 3, **sac}), NNConfig(hidden_units=[16]), ReplayConfig())


def random_masks(rng: np.random.Generator, n: int, branches: tuple[int, ...]) -> np.ndarray:
    """0/1 masks with at least one allowed action per branch."""
    parts = []
    for k in branches:
        m = (rng.random((n, k)) < 0.5).astype(np.float32)
        m[np.arange(n), rng.integers(k, size=n)] = 1.0
        parts.append(m)
    return np.concatenate(parts, axis=1)


def make_batch(spec: EnvSpec, b: int = 16, seed: int = 0) -> Batch:
    rng = np.random.default_rng(seed)
    act = spec.action
    masks = random_masks(rng, b * 2, act.discrete_branches).reshape(b, 2, -1)
    actions, _ = uniform_random_actions(act, b, rng, masks[:, 0])
    return Batch(
        keys=np.arange(b, dtype=np.uint64),
        probabilities=np.full(b, 1.0 / 100),
        table_size=100,
        obs=[masks, rng.standard_normal((b, 2, OBS), dtype=np.float32)],
        actions=actions[:, None],
        prev_actions=np.zeros((b, 1, act.size), dtype=np.float32),
        rewards=rng.standard_normal((b, 1), dtype=np.float32),
        terminated=rng.random((b, 1)) < 0.2,
        truncated=np.zeros((b, 1), dtype=bool),
        behaviour_logp=np.zeros((b, 1), dtype=np.float32),
        mask=np.ones((b, 1), dtype=bool),
    )


# -- distributions ------------------------------------------------------------------------------


def test_masked_actions_get_exactly_zero_probability_and_each_branch_normalises() -> None:
    logits = torch.randn(6, 5, requires_grad=True)
    mask = torch.tensor([[True, False, True, False, True]] * 6)
    log_p = masked_branch_log_softmax(logits, (2, 3), mask)
    p = log_p.exp()
    assert torch.all(p[:, 1] == 0) and torch.all(p[:, 3] == 0)
    torch.testing.assert_close(p[:, :2].sum(-1), torch.ones(6))
    torch.testing.assert_close(p[:, 2:].sum(-1), torch.ones(6))
    entropy = -(p * log_p).sum()
    entropy.backward()
    assert torch.isfinite(entropy) and torch.isfinite(logits.grad).all()
    assert torch.all(logits.grad[:, [1, 3]] == 0)  # masked logits get no gradient


def test_greedy_one_hot_never_picks_a_masked_action() -> None:
    values = torch.tensor([[5.0, 1.0, 2.0, 9.0, 0.0]])
    mask = torch.tensor([[False, True, True, False, True]])
    one_hot = masked_branch_one_hot_argmax(values, (2, 3), mask)
    torch.testing.assert_close(one_hot, torch.tensor([[0.0, 1.0, 1.0, 0.0, 0.0]]))


def test_uniform_random_actions_respect_the_mask_with_exact_log_probability() -> None:
    rng = np.random.default_rng(0)
    mask = np.array([[1, 0, 1, 0, 0, 1, 1]] * 3000, dtype=np.float32)
    actions, logp = uniform_random_actions(ActionSpec((4, 3), 0), 3000, rng, mask)
    first, second = actions[:, :4].argmax(1), actions[:, 4:].argmax(1)
    assert set(first) == {0, 2} and set(second) == {1, 2}
    np.testing.assert_allclose(logp, np.log(1 / 2) + np.log(1 / 2), rtol=1e-6)
    assert stats.chisquare(np.bincount(first)[[0, 2]]).pvalue > 1e-3  # uniform among the allowed


# -- values and losses --------------------------------------------------------------------------


def test_soft_value_is_the_exact_expectation_averaged_over_branches() -> None:
    # branch 0: pi = (0.25, 0.75), Q = (1, 3), alpha 0.5; branch 1: pi = (1, 0, 0), Q = (2, 7, 7), alpha 2
    probs = torch.tensor([[0.25, 0.75, 1.0, 0.0, 0.0]])
    log_probs = torch.tensor([[math.log(0.25), math.log(0.75), 0.0, -1e9, -1e9]])
    q = torch.tensor([[1.0, 3.0, 2.0, 7.0, 7.0]])
    pi = PolicySample(probs=probs, log_probs=log_probs)
    v = soft_value(q, pi, torch.tensor(0.0), torch.tensor([0.5, 2.0]), branch_matrix((2, 3)))
    v0 = 0.25 * (1 - 0.5 * math.log(0.25)) + 0.75 * (3 - 0.5 * math.log(0.75))
    v1 = 1.0 * (2 - 2.0 * 0.0)
    assert v.item() == pytest.approx((v0 + v1) / 2)
    # dqn-like: greedy one-hot, no entropy -> the Q of the greedy action (double-DQN target)
    greedy = PolicySample(probs=torch.tensor([[0.0, 1.0, 0.0, 1.0, 0.0]]))
    v = soft_value(q, greedy, torch.tensor(0.0), None, branch_matrix((2, 3)))
    assert v.item() == pytest.approx((3.0 + 7.0) / 2)
    # mixed: minus alpha_c log pi_c of the continuous sample
    mixed = PolicySample(torch.zeros(1, 1), torch.tensor([-1.5]), probs, log_probs)
    v = soft_value(q, mixed, torch.tensor(0.1), torch.tensor([0.5, 2.0]), branch_matrix((2, 3)))
    assert v.item() == pytest.approx((v0 + v1) / 2 + 0.15)


def test_discrete_policy_loss_moves_only_the_policy_toward_high_q() -> None:
    torch.manual_seed(0)
    policy = DiscretePolicy(OBS, (3,), [8])
    opt = torch.optim.SGD(policy.parameters(), lr=0.5)
    state = torch.randn(32, OBS)
    q = torch.tensor([0.0, 0.0, 5.0]).expand(32, 3).clone().requires_grad_(True)
    before = policy(state).exp()[:, 2].mean().item()
    for _ in range(20):
        log_probs = policy(state)
        loss, metrics = policy_loss(q, PolicySample(probs=log_probs.exp(), log_probs=log_probs),
                                    torch.tensor(0.0), torch.tensor([0.1]), branch_matrix((3,)))  # fmt: skip
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert q.grad is None  # the discrete loss holds Q fixed
    assert policy(state).exp()[:, 2].mean().item() > max(0.9, before)
    assert metrics["learner/entropy_discrete"].shape == (32, 1)


def test_discrete_alpha_moves_each_branch_toward_its_own_target() -> None:
    # branch 0 is uniform over 4 actions: entropy log 4 > target 0.98 log 4, so its alpha must fall;
    # branch 1 is near-deterministic: entropy far below 0.98 log 3, so its alpha must rise
    probs = torch.tensor([[0.25, 0.25, 0.25, 0.25, 0.98, 0.01, 0.01]])
    pi = PolicySample(probs=probs, log_probs=probs.log())
    target = torch.tensor([0.98 * math.log(4), 0.98 * math.log(3)])
    log_alpha = torch.nn.Parameter(torch.zeros(2))
    alpha_loss(log_alpha, expected_log_prob(pi, branch_matrix((4, 3))), target)[0].backward()
    assert log_alpha.grad is not None
    assert log_alpha.grad[0] > 0 and log_alpha.grad[1] < 0  # gradient descent: alpha_0 falls, alpha_1 rises


# -- the learner --------------------------------------------------------------------------------


@pytest.mark.parametrize("dqn_like", [False, True])
def test_act_never_takes_a_masked_action_and_reports_its_probability(dqn_like: bool) -> None:
    spec = masked_spec((4, 3))
    sac = make_sac(spec, discrete_dqn_like=dqn_like, discrete_dqn_epsilon=0.5)
    rng = np.random.default_rng(1)
    masks = random_masks(rng, 2000, (4, 3))
    obs = [masks, rng.standard_normal((2000, OBS), dtype=np.float32)]
    for deterministic in (False, True):
        actions, logp = sac.act(obs, deterministic=deterministic)
        chosen = actions[:, :7] > 0.5
        assert np.all(chosen.sum(1) == 2) and not np.any(chosen & (masks < 0.5))
        assert np.all(np.isfinite(logp)) and np.all(logp <= 0)


def test_dqn_like_explores_epsilon_greedily_with_the_true_behaviour_probability() -> None:
    spec = masked_spec((4,))
    sac = make_sac(spec, discrete_dqn_like=True, discrete_dqn_epsilon=0.3)
    mask = np.tile(np.array([[1, 1, 0, 1]], dtype=np.float32), (20000, 1))
    state = np.tile(np.array([[0.3, -0.2, 0.5]], dtype=np.float32), (20000, 1))
    greedy, _ = sac.act([mask[:1], state[:1]], deterministic=True)
    g = int(greedy[0].argmax())
    actions, logp = sac.act([mask, state])
    counts = np.bincount(actions.argmax(1), minlength=4)
    expected = np.array([0.1, 0.1, 0.0, 0.1])
    expected[g] += 0.7
    assert counts[2] == 0
    allowed = [0, 1, 3]
    assert stats.chisquare(counts[allowed], expected[allowed] * 20000).pvalue > 1e-3
    np.testing.assert_allclose(np.exp(logp), expected[actions.argmax(1)], rtol=1e-5)


@pytest.mark.parametrize(
    ("branches", "continuous", "dqn_like"), [((4,), 0, False), ((4,), 0, True), ((2, 3), 2, False), ((3,), 1, True)]
)
def test_update_trains_every_part_and_resumes_bit_identically(
    branches: tuple[int, ...], continuous: int, dqn_like: bool
) -> None:
    spec = masked_spec(branches, continuous)
    a, b = make_sac(spec, discrete_dqn_like=dqn_like), make_sac(spec, discrete_dqn_like=dqn_like)
    before = {k: v.clone() for k, v in a.models.state_dict().items()}
    result = a.update(make_batch(spec), with_metrics=True)
    assert not result.skipped and result.td_abs.shape == (16,)
    assert all(not torch.equal(before[k], v) for k, v in a.models.state_dict().items()), "a part did not train"
    if not dqn_like:
        assert a.log_alpha_discrete.shape == (len(branches),)
        assert not torch.equal(a.log_alpha_discrete, b.log_alpha_discrete)
        assert "learner/alpha_discrete" in result.metrics and "learner/entropy_discrete" in result.metrics
    else:
        assert a.log_alpha_discrete.numel() == 0 and a.models.discrete_policy is None
    b.load_state_dict(copy.deepcopy(a.state_dict()))  # a copy, as from a checkpoint file
    ra, rb = a.update(make_batch(spec, seed=1)), b.update(make_batch(spec, seed=1))
    np.testing.assert_array_equal(ra.td_abs, rb.td_abs)
    for (k, va), vb in zip(a.models.state_dict().items(), b.models.state_dict().values(), strict=True):
        assert torch.equal(va, vb), k


def test_acting_weights_include_the_q_heads_only_when_they_choose_actions() -> None:
    assert any(k.startswith("q.") for k in make_sac(masked_spec(), discrete_dqn_like=True).acting_state_dict())
    names = make_sac(masked_spec()).acting_state_dict()
    assert any(k.startswith("discrete_policy.") for k in names) and not any(k.startswith("q.") for k in names)


def test_a_mask_sensor_of_the_wrong_size_is_refused() -> None:
    with pytest.raises(ValueError, match="action_mask"):
        EnvSpec((SensorSpec("action_mask", (3,)),), ActionSpec((4,), 0))


# -- noisy layers in the learner ------------------------------------------------------------------


def test_noisy_heads_explore_stochastically_act_deterministically_and_resume_exactly() -> None:
    spec = masked_spec((3,), 2)
    nn_cfg = NNConfig(hidden_units=[16], noisy_q=True, noisy_policy=True)

    def make() -> SAC:
        return SAC(spec, SacConfig(seed=4), nn_cfg, ReplayConfig())

    sac = make()
    obs = [np.ones((1, 3), dtype=np.float32), np.full((1, OBS), 0.5, dtype=np.float32)]
    first, second = sac.act(obs, deterministic=True), sac.act(obs, deterministic=True)
    np.testing.assert_array_equal(first[0], second[0])  # mean weights: no noise
    assert sac.models.policy is not None
    head = sac.models.policy.head
    with torch.no_grad():  # tanh of the mean from the noise-free weights mu
        state = sac.models.representation.policy_state(sac.models.representation([torch.from_numpy(o) for o in obs]))
        mean = torch.nn.functional.linear(sac.models.policy.trunk(state), head.weight_mu, head.bias_mu).chunk(2, -1)[0]
    np.testing.assert_allclose(first[0][:, 3:], torch.tanh(mean).numpy(), rtol=1e-5, atol=1e-6)
    noisy_means = {tuple(np.round(sac._acting["policy"].head.effective_params()[1][:2].tolist(), 6))
                   for _ in range(3) if sac.act(obs) is not None}  # fmt: skip
    assert len(noisy_means) == 3  # every stochastic act draws fresh noise

    other = make()
    for seed in range(2):
        sac.update(make_batch(spec, seed=seed))
    other.load_state_dict(copy.deepcopy(sac.state_dict()))
    a, b = sac.update(make_batch(spec, seed=5)), other.update(make_batch(spec, seed=5))
    np.testing.assert_array_equal(a.td_abs, b.td_abs)


def test_the_discrete_target_entropy_anneals_linearly_from_its_start_and_resumes_where_it_was() -> None:
    spec = masked_spec((4, 3))
    log_n = np.log([4.0, 3.0])
    sac = make_sac(spec, discrete_target_entropy_start=0.9, discrete_target_entropy_ratio=0.3,
                   discrete_target_entropy_anneal_updates=4)  # fmt: skip
    seen = []
    for i in range(6):
        result = sac.update(make_batch(spec, seed=i), with_metrics=True)
        seen.append(result.metrics["learner/discrete_target_entropy"])
    ratios = [0.9, 0.75, 0.6, 0.45, 0.3, 0.3]  # read before each update: 0, 1, ... updates done
    np.testing.assert_allclose(seen, [r * log_n.mean() for r in ratios], rtol=1e-6)

    resumed = make_sac(spec, discrete_target_entropy_start=0.9, discrete_target_entropy_ratio=0.3,
                       discrete_target_entropy_anneal_updates=8)  # fmt: skip
    state = sac.state_dict()
    state["updates"] = 2
    resumed.load_state_dict(state)
    resumed.update(make_batch(spec, seed=9))
    np.testing.assert_allclose(resumed.discrete_target_entropy.numpy(), (0.9 - 0.6 * 2 / 8) * log_n, rtol=1e-6)

    constant = make_sac(spec, discrete_target_entropy_ratio=0.3)
    for i in range(3):
        constant.update(make_batch(spec, seed=i))
    np.testing.assert_allclose(constant.discrete_target_entropy.numpy(), 0.3 * log_n, rtol=1e-6)
