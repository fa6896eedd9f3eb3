"""sac_config.update_order: joint (every loss from the same weights, applied together) against
critic_first (SB3's order: the critic steps, then the policy's loss is taken against the stepped critic)."""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import pytest
import torch

from algorithm.config.schema import SacConfig
from algorithm.sac.update_graph import why_not_graphed
from tests.algorithm.sac.test_discrete import make_batch as discrete_batch
from tests.algorithm.sac.test_discrete import make_sac as make_discrete_sac
from tests.algorithm.sac.test_discrete import masked_spec
from tests.algorithm.sac.test_learner import make_batch, make_sac


def grads(params: list[torch.Tensor]) -> list[torch.Tensor]:
    return [p.grad.clone() if p.grad is not None else torch.zeros_like(p) for p in params]


def params(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


def test_critic_first_takes_the_policy_loss_against_the_stepped_critic() -> None:
    config: dict[str, Any] = dict(use_priority=False, learning_rate=1e-2)
    first = make_sac(update_order="critic_first", **config)
    joint = make_sac(**config)
    for i in range(3):
        first.update(make_batch(seed=10 + i))
        joint.update(make_batch(seed=10 + i))
    # the reference: a joint learner in the same state whose Q heads already are the ones critic_first
    # steps to on this batch; its policy gradient is the one against the stepped critic
    reference = make_sac(**config)
    before = copy.deepcopy(first.state_dict())
    first.update(make_batch(seed=0))
    stepped_q = copy.deepcopy(first.models.q.state_dict())
    reference.load_state_dict(copy.deepcopy(before))
    reference.models.q.load_state_dict(stepped_q)
    reference.update(make_batch(seed=0))
    joint.load_state_dict(copy.deepcopy(before))
    joint.update(make_batch(seed=0))

    policy = first._policy_params
    for a, b in zip(grads(policy), grads(reference._policy_params), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
    # the same critic step in both orders, a different policy gradient
    for a, b in zip(params(first.models.q), params(joint.models.q), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    gaps = [float((a - b).abs().max()) for a, b in zip(grads(policy), grads(joint._policy_params), strict=True)]
    assert max(gaps) > 1e-4, gaps


def test_critic_first_trains_every_part_and_its_metrics_report_the_second_policy_pass() -> None:
    sac = make_sac(update_order="critic_first", use_priority=False)
    before = {name: params(m) for name, m in (("q", sac.models.q), ("policy", sac.models.policy))}
    alpha = float(sac.log_alpha.detach())
    result = sac.update(make_batch(), with_metrics=True)
    assert not result.skipped and sac.updates == 1
    for name, module in (("q", sac.models.q), ("policy", sac.models.policy)):
        assert any(not torch.equal(a, b) for a, b in zip(before[name], params(module), strict=True)), name
    assert float(sac.log_alpha.detach()) != alpha
    assert result.metrics["learner/grad_norm_policy"] > 0
    assert np.isfinite(result.metrics["learner/policy_loss"])


def test_critic_first_skips_a_nonfinite_step_whole() -> None:
    sac = make_sac(update_order="critic_first", use_priority=False)
    before = params(sac.models)
    rewards = np.full((8, 1), np.nan, dtype=np.float32)
    result = sac.update(make_batch(rewards=rewards))
    assert result.skipped and sac.updates == 0 and sac.nonfinite_skipped == 1
    for a, b in zip(before, params(sac.models), strict=True):
        assert torch.equal(a, b)


def test_critic_first_on_discrete_actions() -> None:
    spec = masked_spec((4, 3), continuous=2)
    sac = make_discrete_sac(spec, update_order="critic_first")
    before = params(sac.models)
    for i in range(3):
        assert not sac.update(discrete_batch(spec, seed=i)).skipped
    assert any(not torch.equal(a, b) for a, b in zip(before, params(sac.models), strict=True))


def test_critic_first_is_not_recorded_as_a_cuda_graph_and_bad_values_are_named() -> None:
    why = why_not_graphed(SacConfig(update_order="critic_first"), torch.device("cuda"), False, False, False)
    assert why is not None and "critic_first" in why
    assert why_not_graphed(SacConfig(), torch.device("cuda"), False, False, False) is None
    with pytest.raises(ValueError, match="update_order"):
        SacConfig(update_order="policy_first")


def poison_after_critic_step(sac: Any) -> None:
    """The critic's optimizer steps, then one Q weight becomes NaN: the first pass was finite, the
    policy's loss against the stepped critic is not (how a critic that diverges in one step looks)."""
    step = sac.critic_optimizer.step

    def step_then_poison(*args: Any, **kwargs: Any) -> Any:
        out = step(*args, **kwargs)
        with torch.no_grad():
            next(sac.models.q.parameters()).view(-1)[0] = float("nan")
        return out

    sac.critic_optimizer.step = step_then_poison


def test_critic_first_skips_the_policy_step_when_the_stepped_critic_makes_its_loss_nonfinite() -> None:
    sac = make_sac(update_order="critic_first", use_priority=False)
    sac.update(make_batch(seed=1))
    policy_before, q_before, target_before = params(sac.models.policy), params(sac.models.q), params(sac.target_q)
    poison_after_critic_step(sac)
    result = sac.update(make_batch(seed=2), with_metrics=True)
    assert result.skipped and sac.updates == 1 and sac.nonfinite_skipped == 1
    assert not np.isfinite(result.metrics["learner/policy_loss"])
    assert all(torch.equal(a, b) for a, b in zip(policy_before, params(sac.models.policy), strict=True))
    assert all(torch.equal(a, b) for a, b in zip(target_before, params(sac.target_q), strict=True))
    assert any(not torch.equal(a, b) for a, b in zip(q_before, params(sac.models.q), strict=True))  # it stands
    assert np.isfinite(result.td_abs).all()


def test_critic_first_names_the_policy_loss_when_nonfinite_steps_run_out() -> None:
    sac = make_sac(update_order="critic_first", use_priority=False, max_nonfinite_steps=1)
    poison_after_critic_step(sac)
    with pytest.raises(RuntimeError, match=r"policy_loss=nan"):
        sac.update(make_batch(seed=2))
