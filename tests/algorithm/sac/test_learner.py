"""SAC losses (gradient isolation, alpha direction, clipping, PER weights) and the update step
(non-finite guard, bit-identical resume, target updates, a small learning check)."""

from __future__ import annotations

import copy
import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.nn.layers import uses_bfloat16
from algorithm.nn.models import QEnsemble, Representation, TanhGaussianPolicy
from algorithm.sac.equations import PolicySample, alpha_loss, critic_loss, importance_weights, policy_loss
from algorithm.sac.learner import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from algorithm.types import Batch

OBS, ACT = 3, 2
SPEC = EnvSpec((SensorSpec("obs", (OBS,)),), ActionSpec((), ACT, (-1.0,) * ACT, (1.0,) * ACT))
NN = NNConfig(hidden_units=[16, 16])


def make_batch(b: int = 8, length: int = 1, seed: int = 0, **overrides: Any) -> Batch:
    rng = np.random.default_rng(seed)
    fields: dict[str, Any] = dict(
        keys=np.arange(b, dtype=np.uint64),
        probabilities=rng.uniform(0.5, 2.0, b) / 100,
        table_size=100,
        obs=[rng.standard_normal((b, length + 1, OBS), dtype=np.float32)],
        actions=rng.uniform(-1, 1, (b, length, ACT)).astype(np.float32),
        prev_actions=np.zeros((b, length, ACT), dtype=np.float32),
        rewards=rng.standard_normal((b, length), dtype=np.float32),
        terminated=np.zeros((b, length), dtype=bool),
        truncated=np.zeros((b, length), dtype=bool),
        behaviour_logp=np.zeros((b, length), dtype=np.float32),
        mask=np.ones((b, length), dtype=bool),
    )
    fields.update(overrides)
    return Batch(**fields)


def make_sac(**sac_overrides: Any) -> SAC:
    sac_cfg = SacConfig(**{"seed": 1, **sac_overrides})
    return SAC(SPEC, sac_cfg, NN, ReplayConfig(beta=0.4, beta_increment_per_sampling=0.25))


def snapshot(sac: SAC) -> dict[str, Any]:
    return copy.deepcopy(sac.state_dict())


def assert_same_state(a: Any, b: Any) -> None:
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            assert_same_state(a[k], b[k])
    elif isinstance(a, list | tuple):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            assert_same_state(x, y)
    elif isinstance(a, Tensor):
        assert torch.equal(a, b)
    else:
        assert a == b


class LinearRepresentation(Representation):
    """A representation with parameters, to see where gradients go."""

    def __init__(self) -> None:
        super().__init__()
        self.state_dim = 4
        self.linear = nn.Linear(OBS, 4)

    def forward(self, obs: list[Tensor]) -> Tensor:
        return self.linear(obs[0])


def parts() -> tuple[LinearRepresentation, QEnsemble, TanhGaussianPolicy]:
    torch.manual_seed(0)
    return LinearRepresentation(), QEnsemble(4, ACT, [8], 3), TanhGaussianPolicy(4, ACT, [8])


def grads(module: nn.Module) -> list[Tensor | None]:
    return [p.grad for p in module.parameters()]


# -- losses -----------------------------------------------------------------------------------


def test_policy_loss_leaves_critic_and_representation_grads_untouched() -> None:
    rep, q, policy = parts()
    state = rep([torch.randn(5, OBS)])
    # composed as SAC.update does: detached state, heads run with detached parameters
    action, log_prob = policy.sample(state.detach(), torch.randn(5, ACT))
    q_min = q(state.detach(), action, torch.tensor([0, 2]), detach_params=True).min(dim=0).values
    loss, _ = policy_loss(q_min, PolicySample(action, log_prob), torch.tensor(0.2), None, None)
    loss.backward()
    assert all(g is None for g in grads(q)) and all(g is None for g in grads(rep))
    assert all(g is not None and g.abs().sum() > 0 for g in grads(policy))


def test_critic_loss_leaves_policy_grads_untouched_and_trains_the_representation() -> None:
    rep, q, policy = parts()
    obs = torch.randn(5, OBS)
    state = rep([obs])
    with torch.no_grad():
        policy.sample(state, torch.randn(5, ACT))  # a target computed from the policy, as in update()
    loss, td_abs, _ = critic_loss(q(state, torch.rand(5, ACT)), torch.randn(5), None)
    loss.backward()
    assert all(g is None for g in grads(policy))
    assert all(g is not None and g.abs().sum() > 0 for g in grads(q))
    assert all(g is not None and g.abs().sum() > 0 for g in grads(rep))
    assert td_abs.shape == (5,) and not td_abs.requires_grad


def test_every_head_trains_the_representation() -> None:
    rep, q, _ = parts()
    state = rep([torch.randn(5, OBS)])
    q_values = q(state, torch.rand(5, ACT))
    per_head = [torch.autograd.grad(q_values[i].sum(), rep.linear.weight, retain_graph=True)[0] for i in range(3)]
    assert all(g.abs().sum() > 0 for g in per_head)
    assert not torch.allclose(per_head[0], per_head[1])


def test_critic_loss_is_half_squared_error_summed_over_heads_with_td_from_the_same_pass() -> None:
    _, q, _ = parts()
    state, action, y = torch.randn(5, 4), torch.rand(5, ACT), torch.randn(5)
    loss, td_abs, _ = critic_loss(q(state, action), y, None)
    q_values = q(state, action)
    torch.testing.assert_close(loss, 0.5 * (q_values - y).pow(2).sum(0).mean())
    torch.testing.assert_close(td_abs, (q_values - y).abs().mean(0).detach())


class FixedQ(QEnsemble):
    """Q heads whose values are a parameter, independent of the input (hand-checkable losses)."""

    def __init__(self, values: list[list[float]]) -> None:
        super().__init__(1, 1, [], len(values))
        self.values = nn.Parameter(torch.tensor(values))

    def forward(
        self, state: Tensor, action: Tensor | None, heads: Tensor | None = None, detach_params: bool = False
    ) -> Tensor:
        return self.values


def test_clip_epsilon_takes_the_larger_of_clipped_and_unclipped_errors() -> None:
    # Both heads moved from the target heads' value 0 to 1. Target 2: clipped Q is 0.2 and its
    # error 1.8^2 beats the plain 1^2, a branch that is flat in Q (zero gradient). Target 0.5: the
    # plain error 0.5^2 beats the clipped (0.2 - 0.5)^2, so loss and gradient are the plain ones.
    q = FixedQ([[1.0], [1.0]])
    old_q, y = torch.tensor([[0.0], [0.0]]), torch.tensor([2.0])
    loss, _, _ = critic_loss(q(torch.zeros(1, 1), torch.zeros(1, 1)), y, None, clip_epsilon=0.2, old_q=old_q)
    assert loss.item() == pytest.approx(0.5 * (1.8**2 + 1.8**2))
    loss.backward()
    assert q.values.grad is not None and torch.all(q.values.grad == 0)

    q = FixedQ([[1.0], [1.0]])
    y = torch.tensor([0.5])
    loss, _, _ = critic_loss(q(torch.zeros(1, 1), torch.zeros(1, 1)), y, None, clip_epsilon=0.2, old_q=old_q)
    assert loss.item() == pytest.approx(0.5 * (0.5**2 + 0.5**2))
    loss.backward()
    assert q.values.grad is not None
    torch.testing.assert_close(q.values.grad, torch.tensor([[0.5], [0.5]]))

    plain, _, _ = critic_loss(FixedQ([[1.0], [1.0]])(torch.zeros(1, 1), None), torch.tensor([2.0]), None)
    assert plain.item() == pytest.approx(0.5 * (1.0 + 1.0))
    with pytest.raises(ValueError, match="old_q"):
        critic_loss(q(torch.zeros(1, 1), torch.zeros(1, 1)), y, None, clip_epsilon=0.2)


def test_per_weights_scale_each_samples_loss() -> None:
    q = FixedQ([[1.0, 3.0]])
    y = torch.zeros(2)
    unweighted, _, _ = critic_loss(q(torch.zeros(2, 1), None), y, None)
    assert unweighted.item() == pytest.approx(0.5 * (1 + 9) / 2)
    only_first, _, _ = critic_loss(q(torch.zeros(2, 1), None), y, torch.tensor([1.0, 0.0]))
    assert only_first.item() == pytest.approx(0.5 * 1 / 2)
    only_second, td_abs, _ = critic_loss(q(torch.zeros(2, 1), None), y, torch.tensor([0.0, 0.5]))
    assert only_second.item() == pytest.approx(0.5 * 0.5 * 9 / 2)
    torch.testing.assert_close(td_abs, torch.tensor([1.0, 3.0]))  # priorities are not weighted


def test_importance_weights_formula() -> None:
    p = torch.tensor([0.1, 0.2, 0.4], dtype=torch.float64)
    w = importance_weights(p, 10, 0.5)
    expected = np.array([1.0, 2.0, 4.0]) ** -0.5
    np.testing.assert_allclose(w.numpy(), expected / expected.max(), rtol=1e-6)
    assert w.dtype == torch.float32
    torch.testing.assert_close(importance_weights(p, 10, 0.0), torch.ones(3))


@pytest.mark.parametrize(("log_prob", "direction"), [(-5.0, -1), (-1.0, -1), (3.0, +1), (5.0, +1)])
def test_alpha_moves_toward_the_target_entropy(log_prob: float, direction: int) -> None:
    # target entropy -|A| = -2: entropy 5 or 1 is above it (alpha must fall), -3 or -5 below (alpha must rise)
    log_alpha = nn.Parameter(torch.tensor(0.0))
    opt = torch.optim.SGD([log_alpha], lr=0.1)
    loss, _ = alpha_loss(log_alpha, torch.full((4,), log_prob, requires_grad=True), target_entropy=-2.0)
    loss.backward()
    opt.step()
    assert np.sign(log_alpha.item()) == direction


def test_alpha_loss_does_not_reach_the_policy() -> None:
    _, _, policy = parts()
    _, log_prob = policy.sample(torch.randn(5, 4), torch.randn(5, ACT))
    alpha_loss(nn.Parameter(torch.tensor(0.0)), log_prob, -2.0)[0].backward()
    assert all(g is None for g in grads(policy))


# -- the update step --------------------------------------------------------------------------


def test_update_returns_priorities_and_metrics() -> None:
    sac = make_sac()
    result = sac.update(make_batch(), with_metrics=True)
    assert result.td_abs.shape == (8,) and result.td_abs.dtype == np.float32 and not result.skipped
    for key in (
        "learner/q_loss",
        "learner/policy_loss",
        "learner/alpha",
        "learner/entropy",
        "learner/q_mean",
        "learner/target_mean",
        "learner/is_weight_mean",
        "learner/beta",
        "learner/nonfinite_skipped",
    ):
        assert np.isfinite(result.metrics[key]), key
    assert result.metrics["learner/beta"] == 0.4
    assert sac.update(make_batch()).metrics == {}


def test_beta_anneals_to_one_and_weights_follow_it() -> None:
    sac = make_sac()
    betas = [sac.update(make_batch(), with_metrics=True).metrics["learner/beta"] for _ in range(4)]
    assert betas == pytest.approx([0.4, 0.65, 0.9, 1.0])
    uniform = make_batch(probabilities=np.full(8, 0.01))
    assert sac.update(uniform, with_metrics=True).metrics["learner/is_weight_mean"] == pytest.approx(1.0)
    skewed = make_batch(probabilities=np.array([0.01] * 7 + [0.5]))
    assert sac.update(skewed, with_metrics=True).metrics["learner/is_weight_mean"] < 0.9


def test_one_update_moves_every_part() -> None:
    sac = make_sac()
    before = snapshot(sac)
    sac.update(make_batch())
    after = sac.state_dict()
    for name in ("q", "policy"):
        keys = [k for k in before["models"] if k.startswith(name)]
        assert all(not torch.equal(before["models"][k], after["models"][k]) for k in keys), name
    assert not torch.equal(before["log_alpha"], after["log_alpha"])
    assert all(not torch.equal(before["target_q"][k], after["target_q"][k]) for k in before["target_q"])


def test_targets_update_every_update_target_per_step() -> None:
    sac = make_sac(update_target_per_step=2)
    t0 = copy.deepcopy(sac.target_q.state_dict())
    sac.update(make_batch())
    assert_same_state(t0, sac.target_q.state_dict())
    sac.update(make_batch())
    online, target = sac.models.q.state_dict(), sac.target_q.state_dict()
    for k in t0:
        torch.testing.assert_close(target[k], t0[k] + 0.005 * (online[k] - t0[k]))


def test_nonfinite_reward_skips_the_step_and_too_many_stop() -> None:
    sac = make_sac(max_nonfinite_steps=3)
    sac.update(make_batch())  # a real step first, so the optimizers have state to protect
    before = snapshot(sac)
    bad = make_batch(rewards=np.array([[np.nan]] + [[0.0]] * 7, dtype=np.float32))
    result = sac.update(bad, with_metrics=True)
    assert result.skipped and sac.nonfinite_skipped == 1
    assert np.all(np.isfinite(result.td_abs))
    assert result.metrics["learner/nonfinite_skipped"] == 1.0
    after = sac.state_dict()
    for key in ("models", "target_q", "target_representation", "log_alpha", "optimizers"):
        assert_same_state(before[key], after[key])
    assert after["updates"] == before["updates"]

    sac.update(make_batch())  # a good step resets the consecutive count
    assert sac.update(bad).skipped and sac.update(bad).skipped
    with pytest.raises(RuntimeError, match="3 consecutive.*max_nonfinite_steps=3"):
        sac.update(bad)
    assert sac.nonfinite_skipped == 4


def test_nonfinite_observation_is_guarded_too() -> None:
    sac = make_sac()
    obs = np.zeros((8, 2, OBS), dtype=np.float32)
    obs[3, 0, 1] = np.inf
    assert sac.update(make_batch(obs=[obs])).skipped


def test_state_dict_resume_is_bit_identical() -> None:
    kwargs = dict(ensemble_q_num=4, ensemble_q_sample=2, n_step=2, clip_epsilon=0.5)
    batches = [make_batch(length=2, seed=s) for s in range(6)]
    original = make_sac(**kwargs)
    for b in batches[:3]:
        original.update(b)
    buffer = io.BytesIO()
    torch.save(original.state_dict(), buffer)
    tail = [original.update(b).td_abs for b in batches[3:]]
    acted = original.act([np.ones((4, OBS), dtype=np.float32)])

    resumed = make_sac(**{**kwargs, "seed": 99})
    buffer.seek(0)
    resumed.load_state_dict(torch.load(buffer, weights_only=True))
    resumed_tail = [resumed.update(b).td_abs for b in batches[3:]]
    for x, y in zip(tail, resumed_tail, strict=True):
        np.testing.assert_array_equal(x, y)
    resumed_acted = resumed.act([np.ones((4, OBS), dtype=np.float32)])
    for x, y in zip(acted, resumed_acted, strict=True):
        np.testing.assert_array_equal(x, y)
    assert_same_state(original.state_dict(), resumed.state_dict())


def test_load_state_dict_names_what_is_wrong() -> None:
    state = make_sac().state_dict()
    with pytest.raises(KeyError, match="rng"):
        make_sac().load_state_dict({k: v for k, v in state.items() if k != "rng"})
    with pytest.raises(ValueError, match="use_auto_alpha"):
        make_sac(use_auto_alpha=False).load_state_dict(state)


def test_the_same_seed_gives_the_same_run() -> None:
    a, b = make_sac(), make_sac()
    np.testing.assert_array_equal(a.update(make_batch()).td_abs, b.update(make_batch()).td_abs)
    assert not np.array_equal(make_sac(seed=2).update(make_batch()).td_abs, make_sac().update(make_batch()).td_abs)


def test_target_reads_the_obs_after_the_last_valid_step_only() -> None:
    sac = make_sac(n_step=3)
    mask = np.array([[True, True, False]] * 8)
    base = make_batch(length=3, mask=mask)

    def q_loss(batch: Batch) -> float:
        sac._learn_rng.manual_seed(0)
        return sac.update(batch, with_metrics=True).metrics["learner/target_mean"]

    reference = copy.deepcopy(sac.state_dict())
    y = q_loss(base)
    for position, changes in ((3, False), (2, True)):  # valid_len = 2
        obs = base.obs[0].copy()
        obs[:, position] += 5.0
        sac.load_state_dict(copy.deepcopy(reference))
        assert (q_loss(make_batch(length=3, mask=mask, obs=[obs])) != y) == changes, position


def test_act_returns_bounded_actions_and_log_probs() -> None:
    sac = make_sac()
    obs = [np.random.default_rng(0).standard_normal((5, OBS)).astype(np.float32)]
    actions, logp = sac.act(obs)
    assert actions.shape == (5, ACT) and actions.dtype == np.float32 and np.all(np.abs(actions) <= 1)
    assert logp.shape == (5,) and logp.dtype == np.float32 and np.all(np.isfinite(logp))
    assert not np.array_equal(actions, sac.act(obs)[0])  # fresh noise each call
    np.testing.assert_array_equal(sac.act(obs, deterministic=True)[0], sac.act(obs, deterministic=True)[0])
    with pytest.raises(ValueError, match="sensor 'obs'"):
        sac.act([np.zeros((5, OBS + 1), dtype=np.float32)])


def test_acting_state_dict_carries_the_policy_to_another_instance() -> None:
    learner, actor = make_sac(), make_sac(seed=7)
    learner.update(make_batch())
    actor.load_acting_state_dict(learner.acting_state_dict())
    obs = [np.ones((3, OBS), dtype=np.float32)]
    np.testing.assert_array_equal(learner.act(obs, deterministic=True)[0], actor.act(obs, deterministic=True)[0])
    with pytest.raises(RuntimeError, match="critic.w"):
        actor.load_acting_state_dict({"critic.w": torch.zeros(1)})


def test_load_model_weights_hard_copies_targets_and_restarts_the_moments() -> None:
    """An evolver's sample (ds/member/population.py): online weights replaced, targets equal to them at once,
    Adam's moments of the replaced weights gone (the alpha optimizer's kept), log_alpha untouched."""
    elite, learner = make_sac(seed=3), make_sac()
    for s in range(3):
        elite.update(make_batch(seed=s))
        learner.update(make_batch(seed=s))
    sample = {k: v.numpy().copy() for k, v in elite.models.state_dict().items()}  # as the network delivers it
    log_alpha = learner.log_alpha.detach().clone()
    learner.load_model_weights(sample)
    assert_same_state(elite.models.state_dict(), learner.models.state_dict())
    assert_same_state(learner.models.q.state_dict(), learner.target_q.state_dict())
    rep, target_rep = learner.models.representation.state_dict(), learner.target_representation.state_dict()
    assert_same_state(rep, target_rep)
    assert not learner.critic_optimizer.state and learner.policy_optimizer is not None
    assert not learner.policy_optimizer.state
    assert learner.alpha_optimizer is not None and learner.alpha_optimizer.state
    assert torch.equal(learner.log_alpha.detach(), log_alpha)
    assert not learner.update(make_batch(seed=9)).skipped  # trains on from the new point
    before = snapshot(learner)
    with pytest.raises(ValueError, match=r"tensors \['q\."):
        learner.load_model_weights({k: v for k, v in sample.items() if not k.startswith("q.")})
    assert_same_state(before, learner.state_dict())  # nothing half-loaded


def test_head_subsets_are_fresh_and_of_the_configured_size() -> None:
    sac = make_sac(ensemble_q_num=5, ensemble_q_sample=2)
    subsets = [sac._subset() for _ in range(20)]
    assert all(s is not None and len(set(s.tolist())) == 2 for s in subsets)
    assert len({tuple(sorted(s.tolist())) for s in subsets if s is not None}) > 1
    assert make_sac()._subset() is None  # 2 of 2: the minimum is over all heads


def test_bad_batches_get_clear_errors() -> None:
    sac = make_sac()
    with pytest.raises(ValueError, match="window is 2 steps"):
        sac.update(make_batch(length=2))
    with pytest.raises(ValueError, match="sensor 'obs'"):
        sac.update(make_batch(obs=[np.zeros((8, 2, OBS), dtype=np.float64)]))
    with pytest.raises(ValueError, match="batch.rewards"):
        sac.update(make_batch(rewards=np.zeros((8, 2), dtype=np.float32)))
    with pytest.raises(ValueError, match=r"mask\[:, 0\]"):
        sac.update(make_batch(mask=np.zeros((8, 1), dtype=bool)))


@pytest.mark.parametrize(
    ("terminated", "expected", "mean_tol", "max_tol"), [(True, 1.0, 0.02, 0.1), (False, 2.0, 0.2, 0.3)]
)
def test_q_learns_a_constant_reward(terminated: bool, expected: float, mean_tol: float, max_tol: float) -> None:
    # reward 1 at every step, alpha ~ 0. Terminal steps: Q = 1 exactly. Otherwise Q bootstraps to
    # 1 / (1 - gamma) = 2, a little above it because the policy picks actions where Q is high.
    sac = SAC(
        SPEC,
        SacConfig(seed=0, gamma=0.5, tau=0.5, learning_rate=3e-3, use_auto_alpha=False, init_log_alpha=-20.0),
        NNConfig(hidden_units=[32, 32]),
        ReplayConfig(),
    )
    batch = make_batch(b=64, rewards=np.ones((64, 1), dtype=np.float32), terminated=np.full((64, 1), terminated))
    for _ in range(300):
        sac.update(batch)
    with torch.no_grad():
        q = sac.models.q(torch.from_numpy(batch.obs[0][:, 0]), torch.from_numpy(batch.actions[:, 0]))
    assert q.shape == (2, 64)
    assert torch.all((q.mean(1) - expected).abs() < mean_tol), q.mean(1)
    assert torch.all((q - expected).abs() < max_tol), q


def test_bfloat16_compute_keeps_outputs_parameters_and_losses_float32() -> None:
    full, low = make_sac(), make_sac(compute_dtype="bfloat16")
    batch = make_batch(b=64)
    a = full.update(batch, with_metrics=True).metrics
    b = low.update(batch, with_metrics=True).metrics
    # Same seed, same batch: the losses agree to bfloat16's rounding but not exactly (it really ran in bf16).
    for key in ("learner/q_loss", "learner/policy_loss", "learner/q_mean"):
        assert b[key] == pytest.approx(a[key], rel=0.05, abs=0.02), key
    assert a["learner/q_loss"] != b["learner/q_loss"]
    assert all(p.dtype == torch.float32 for p in low.models.parameters())
    state = torch.randn(5, OBS)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        q = low.models.q(state, torch.zeros(5, ACT))
        mean, log_std = low.models.policy(state)
        hidden = low.models.q.layers[0](torch.cat([state, torch.zeros(5, ACT)], -1))
    assert hidden.dtype == torch.bfloat16  # hidden layers do run in bf16 under autocast
    assert q.dtype == mean.dtype == log_std.dtype == torch.float32  # output layers do not


def test_bfloat16_updates_still_fit_a_regression_target() -> None:
    """With gamma 0 the target is the reward: 100 bf16 updates fit it as float32 updates do."""
    losses = {}
    for dtype in ("float32", "bfloat16"):
        sac = make_sac(compute_dtype=dtype, learning_rate=3e-3, gamma=0.0)
        batch = make_batch(b=64, rewards=np.full((64, 1), 2.0, np.float32))
        first = sac.update(batch, with_metrics=True).metrics["learner/q_loss"]
        for _ in range(100):
            last = sac.update(batch, with_metrics=True).metrics["learner/q_loss"]
        losses[dtype] = (first, last)
    for dtype, (first, last) in losses.items():
        assert last < 0.05 * first, (dtype, first, last)


def test_auto_compute_dtype_follows_the_cpu_flags(tmp_path: Path) -> None:
    cpu = torch.device("cpu")
    with_bf16, without = tmp_path / "a", tmp_path / "b"
    with_bf16.write_text("processor : 0\nflags\t\t: fpu sse2 avx512f avx512_bf16 avx512vl\n")
    without.write_text("processor : 0\nflags\t\t: fpu sse2 avx2\n")
    assert uses_bfloat16("auto", cpu, with_bf16) and not uses_bfloat16("auto", cpu, without)
    assert not uses_bfloat16("auto", cpu, tmp_path / "missing")
    assert uses_bfloat16("bfloat16", cpu, without) and not uses_bfloat16("float32", cpu, with_bf16)
