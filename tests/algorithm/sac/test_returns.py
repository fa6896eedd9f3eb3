"""Hand-computed n-step targets: termination vs truncation vs a masked tail, n = 1 and n = 3.

V-trace targets: a hand-computed batch, a literal loop reference on random windows, the on-policy
telescoping identity with the n-step target, garbage that must never leak, the logged ratios.
"""

from __future__ import annotations

import math
from typing import TypedDict

import pytest
import torch
from torch import Tensor

from algorithm.sac.returns import bootstrap_index, gather_positions, n_step_target, valid_steps, vtrace_target

GAMMA = 0.9
V = 10.0  # soft value of whatever observation the target bootstraps from


def target(
    rewards: list[float],
    mask: list[bool],
    terminated: list[bool] | None = None,
    truncated: list[bool] | None = None,
    v: float = V,
) -> float:
    n = len(rewards)
    t = lambda x: torch.tensor([x])  # noqa: E731
    term = t(terminated or [False] * n)
    valid = valid_steps(t(mask), term, t(truncated or [False] * n))
    return float(n_step_target(t(rewards).float(), term, valid, torch.tensor([v]), GAMMA)[0])


@pytest.mark.parametrize(
    ("terminated", "truncated", "expected"),
    [(False, False, 1.0 + GAMMA * V), (True, False, 1.0), (False, True, 1.0 + GAMMA * V)],
)
def test_one_step(terminated: bool, truncated: bool, expected: float) -> None:
    assert target([1.0], [True], [terminated], [truncated]) == pytest.approx(expected)


def test_three_steps_full_window_bootstraps_after_the_last_step() -> None:
    assert target([1.0, 2.0, 4.0], [True] * 3) == pytest.approx(1 + 0.9 * 2 + 0.81 * 4 + 0.729 * V)


def test_three_steps_terminated_stops_bootstrapping() -> None:
    # the episode terminates at step 1; step 2 is past the chunk's end (masked, zeros)
    y = target([1.0, 2.0, 0.0], [True, True, False], terminated=[False, True, False])
    assert y == pytest.approx(1 + 0.9 * 2)


def test_three_steps_truncated_bootstraps_from_the_real_next_obs() -> None:
    y = target([1.0, 2.0, 0.0], [True, True, False], truncated=[False, True, False])
    assert y == pytest.approx(1 + 0.9 * 2 + 0.81 * V)


def test_three_steps_masked_tail_bootstraps_like_truncation() -> None:
    # chunk cut mid-episode after step 0: no flags, the rest of the window is masked
    assert target([1.0, 0.0, 0.0], [True, False, False]) == pytest.approx(1 + 0.9 * V)


def test_masked_rewards_are_ignored_even_if_not_zero() -> None:
    assert target([1.0, 100.0, 100.0], [True, False, False]) == pytest.approx(1 + 0.9 * V)


def test_steps_after_an_episode_end_do_not_count_even_if_unmasked() -> None:
    assert target([1.0, 100.0, 100.0], [True] * 3, terminated=[True, False, False]) == pytest.approx(1.0)
    y = target([1.0, 2.0, 100.0], [True] * 3, truncated=[False, True, False])
    assert y == pytest.approx(1 + 0.9 * 2 + 0.81 * V)


def test_nonfinite_value_of_a_terminal_obs_never_leaks() -> None:
    assert target([1.0], [True], [True], v=math.nan) == pytest.approx(1.0)
    assert target([1.0], [True], [True], v=math.inf) == pytest.approx(1.0)


def test_batch_rows_are_independent() -> None:
    rewards = torch.tensor([[1.0, 2.0, 4.0], [1.0, 2.0, 0.0], [1.0, 0.0, 0.0]])
    mask = torch.tensor([[True, True, True], [True, True, False], [True, False, False]])
    terminated = torch.tensor([[False, False, False], [False, True, False], [False, False, False]])
    truncated = torch.zeros_like(terminated)
    valid = valid_steps(mask, terminated, truncated)
    y = n_step_target(rewards, terminated, valid, torch.tensor([V, 20.0, 30.0]), GAMMA)
    torch.testing.assert_close(y, torch.tensor([1 + 1.8 + 3.24 + 0.729 * V, 2.8, 1 + 0.9 * 30.0]))


def test_bootstrap_obs_is_the_one_after_the_last_valid_step() -> None:
    mask = torch.tensor([[True, True, True], [True, True, False], [True, False, False]])
    terminated = torch.tensor([[False, False, False], [False, False, False], [True, False, False]])
    valid = valid_steps(mask, terminated, torch.zeros_like(terminated))
    index = bootstrap_index(valid)
    assert index.tolist() == [3, 2, 1]
    # obs [B, L + 1, 2] whose value is 10 * row + position
    obs = (10 * torch.arange(3)[:, None] + torch.arange(4)[None, :]).float()[..., None].expand(3, 4, 2)
    torch.testing.assert_close(gather_positions(obs, index), torch.tensor([[3.0] * 2, [12.0] * 2, [21.0] * 2]))


# --- V-trace ---------------------------------------------------------------------------------


def test_vtrace_hand_computed() -> None:
    # gamma 0.9, lambda 0.5, rho_bar 1.5, c_bar 1; step 0's log-ratio is huge and never weighted.
    # row 0: m = 3, no end. pi/mu: step 1 -> 2, step 2 -> 0.5
    #   rho_1 = min(1.5, 2) = 1.5, c_1 = 0.5 * min(1, 2) = 0.5, rho_2 = min(1.5, 0.5) = 0.5
    #   delta_1 = 1.5 * (2 + 0.9 * 20 - 10) = 15,  delta_2 = 0.5 * (4 + 0.9 * 30 - 20) = 5.5
    #   v_1 = 10 + 15 + 0.9 * 0.5 * 5.5 = 27.475,  y = 1 + 0.9 * 27.475 = 25.7275
    # row 1: m = 2, terminates at step 1 (v(o_2) is NaN, step 2 is masked garbage). pi/mu_1 = 3
    #   rho_1 = 1.5, delta_1 = 1.5 * (2 + 0 - 10) = -12, v_1 = -2,  y = 1 + 0.9 * -2 = -0.8
    # row 2: m = 1, not terminated: y = 3 + 0.9 * 10 = 12 (the rest is garbage)
    nan, inf = math.nan, math.inf
    rewards = torch.tensor([[1.0, 2.0, 4.0], [1.0, 2.0, nan], [3.0, nan, inf]])
    mask = torch.tensor([[True, True, True], [True, True, False], [True, False, False]])
    terminated = torch.tensor([[False, False, False], [False, True, True], [False, True, False]])
    valid = valid_steps(mask, terminated, torch.zeros_like(terminated))
    values = torch.tensor([[nan, 10.0, 20.0, 30.0], [nan, 10.0, nan, -inf], [inf, 10.0, nan, nan]])
    log_ratios = torch.tensor([[100.0, math.log(2), math.log(0.5)], [100.0, math.log(3), nan], [100.0, inf, nan]])
    y, rho = vtrace_target(rewards, terminated, valid, values, log_ratios, GAMMA, 0.5, 1.5, 1.0)
    torch.testing.assert_close(y, torch.tensor([25.7275, -0.8, 12.0]))
    torch.testing.assert_close(rho, torch.tensor([[0.0, 1.5, 0.5], [0.0, 1.5, 0.0], [0.0, 0.0, 0.0]]))


class VtraceInputs(TypedDict):
    rewards: Tensor
    terminated: Tensor
    valid: Tensor
    values: Tensor
    log_ratios: Tensor


class VtraceClips(TypedDict):
    gamma: float
    lambda_: float
    rho_bar: float
    c_bar: float


def vtrace_reference(
    rewards: Tensor,
    terminated: Tensor,
    valid: Tensor,
    values: Tensor,
    log_ratios: Tensor,
    gamma: float,
    lambda_: float,
    rho_bar: float,
    c_bar: float,
) -> Tensor:
    """The target formula read literally, one window and one term at a time, in Python floats."""
    ys = []
    for b in range(rewards.shape[0]):
        r, term, v, lr = rewards[b].tolist(), terminated[b].tolist(), values[b].tolist(), log_ratios[b].tolist()
        m = int(valid[b].sum())
        v_1 = v[1]
        for t in range(1, m):
            rho_t = min(rho_bar, math.exp(lr[t]))
            delta_t = rho_t * (r[t] + gamma * (0.0 if term[t] else v[t + 1]) - v[t])
            traces = math.prod(lambda_ * min(c_bar, math.exp(lr[i])) for i in range(1, t))
            v_1 += gamma ** (t - 1) * traces * delta_t
        ys.append(r[0] + gamma * (0.0 if term[0] else v_1))
    return torch.tensor(ys, dtype=torch.float64)


def random_windows(
    seed: int, batch: int = 64, window: int = 6, ratio_scale: float = 1.0
) -> tuple[VtraceInputs, Tensor, Tensor]:
    """Windows with a random ``m`` per row, termination at the last valid step with p = 0.3, and
    finite garbage wherever the target must not look. Returns the ``vtrace_target`` inputs, a
    ``[B, L]`` mask of garbage steps and a ``[B, L + 1]`` mask of garbage value positions."""
    gen = torch.Generator().manual_seed(seed)
    m = torch.randint(1, window + 1, (batch,), generator=gen)
    steps = torch.arange(window)
    mask = steps[None, :] < m[:, None]
    last = steps[None, :] == (m - 1)[:, None]
    ends = torch.rand(batch, generator=gen) < 0.3
    garbage_flags = torch.rand(batch, window, generator=gen) < 0.5  # flags past m must not matter either
    terminated = torch.where(mask, last & ends[:, None], garbage_flags)
    valid = valid_steps(mask, terminated, torch.zeros_like(terminated))
    assert torch.equal(bootstrap_index(valid), m)
    positions = torch.arange(window + 1)
    garbage_values = (positions[None, :] == 0) | (positions[None, :] > m[:, None])
    garbage_values |= (positions[None, :] == m[:, None]) & ends[:, None]  # v of a terminal obs
    noise = lambda *shape: 1e6 * torch.randn(*shape, generator=gen, dtype=torch.float64)  # noqa: E731
    rewards = torch.where(mask, torch.randn(batch, window, generator=gen, dtype=torch.float64), noise(batch, window))
    values = torch.where(
        garbage_values, noise(batch, window + 1), 5 * torch.randn(batch, window + 1, generator=gen, dtype=torch.float64)
    )
    log_ratios = ratio_scale * torch.randn(batch, window, generator=gen, dtype=torch.float64)
    log_ratios = torch.where(mask & (steps > 0), log_ratios, noise(batch, window))
    inputs = VtraceInputs(rewards=rewards, terminated=terminated, valid=valid, values=values, log_ratios=log_ratios)
    return inputs, ~valid | (steps == 0), garbage_values


@pytest.mark.parametrize(
    ("lambda_", "rho_bar", "c_bar"), [(0.9, 1.2, 0.8), (0.5, 0.7, 1.5), (1.0, 1.0, 1.0), (0.95, math.inf, math.inf)]
)
@pytest.mark.parametrize("seed", [0, 1])
def test_vtrace_matches_the_literal_formula(seed: int, lambda_: float, rho_bar: float, c_bar: float) -> None:
    inputs, _, _ = random_windows(seed)
    clips = VtraceClips(gamma=0.97, lambda_=lambda_, rho_bar=rho_bar, c_bar=c_bar)
    y, _ = vtrace_target(**inputs, **clips)
    torch.testing.assert_close(y, vtrace_reference(**inputs, **clips))


@pytest.mark.parametrize(("rho_bar", "c_bar"), [(1.0, 1.0), (2.5, 1.0), (1.0, 4.0)])
def test_vtrace_on_policy_telescopes_to_the_n_step_target(rho_bar: float, c_bar: float) -> None:
    inputs, unused, _ = random_windows(seed=2)
    inputs["log_ratios"] = torch.where(unused, inputs["log_ratios"], 0.0)  # pi = mu on every weighted step
    y, _ = vtrace_target(**inputs, gamma=0.97, lambda_=1.0, rho_bar=rho_bar, c_bar=c_bar)
    v_m = gather_positions(inputs["values"], bootstrap_index(inputs["valid"]))
    expected = n_step_target(inputs["rewards"], inputs["terminated"], inputs["valid"], v_m, 0.97)
    torch.testing.assert_close(y, expected)


@pytest.mark.parametrize("junk", [math.nan, math.inf, -math.inf])
def test_vtrace_garbage_never_leaks(junk: float) -> None:
    inputs, unused, garbage_values = random_windows(seed=3, ratio_scale=2.0)
    clips = VtraceClips(gamma=0.97, lambda_=0.9, rho_bar=1.2, c_bar=0.8)
    y, rho = vtrace_target(**inputs, **clips)
    assert torch.isfinite(y).all()
    invalid = ~inputs["valid"]
    inputs["rewards"] = torch.where(invalid, junk, inputs["rewards"])
    inputs["values"] = torch.where(garbage_values, junk, inputs["values"])
    inputs["log_ratios"] = torch.where(unused, junk, inputs["log_ratios"])
    y_junk, rho_junk = vtrace_target(**inputs, **clips)
    torch.testing.assert_close(y_junk, y, rtol=0, atol=0)
    torch.testing.assert_close(rho_junk, rho, rtol=0, atol=0)


def test_vtrace_rho_is_clipped_on_weighted_steps_and_zero_elsewhere() -> None:
    inputs, unused, _ = random_windows(seed=4, ratio_scale=2.0)
    rho_bar = 1.3
    _, rho = vtrace_target(**inputs, gamma=0.97, lambda_=0.9, rho_bar=rho_bar, c_bar=0.8)
    assert (rho[:, 0] == 0).all() and (rho[unused] == 0).all()
    weighted = ~unused
    torch.testing.assert_close(rho[weighted], inputs["log_ratios"][weighted].exp().clamp(max=rho_bar))
    assert (rho[weighted] > 0).all() and (rho[weighted] <= rho_bar).all()
    assert (rho[weighted] == rho_bar).any() and (rho[weighted] < rho_bar).any()  # both sides of the clip occur


def test_vtrace_runs_under_autograd() -> None:
    inputs, _, garbage_values = random_windows(seed=5, batch=8)
    values = inputs["values"] = torch.where(garbage_values, 0.0, inputs["values"]).requires_grad_()
    y, _ = vtrace_target(**inputs, gamma=0.97, lambda_=0.9, rho_bar=1.2, c_bar=0.8)
    y.sum().backward()
    assert values.grad is not None and torch.isfinite(values.grad).all()


def test_vtrace_uses_only_the_valid_prefix_up_to_a_termination() -> None:
    # a ``valid`` that runs on past a termination or past a gap counts as its clean prefix
    rewards = torch.tensor([[1.0, 2.0, 4.0, 8.0]] * 2)
    terminated = torch.tensor([[False, True, False, False], [False, False, False, False]])
    values = torch.tensor([[0.0, 10.0, 20.0, 30.0, 40.0]] * 2)
    log_ratios = torch.full((2, 4), math.log(0.5))
    sloppy = torch.tensor([[True, True, True, True], [True, True, False, True]])
    clean = torch.tensor([[True, True, False, False], [True, True, False, False]])
    y_sloppy, rho_sloppy = vtrace_target(rewards, terminated, sloppy, values, log_ratios, GAMMA, 0.9, 1.0, 1.0)
    y_clean, rho_clean = vtrace_target(rewards, terminated, clean, values, log_ratios, GAMMA, 0.9, 1.0, 1.0)
    torch.testing.assert_close(y_sloppy, y_clean)
    torch.testing.assert_close(rho_sloppy, rho_clean)
    # row 0: v_1 = 10 + 0.5 * (2 - 10) = 6; row 1: v_1 = 10 + 0.5 * (2 + 0.9 * 20 - 10) = 15
    torch.testing.assert_close(y_clean, torch.tensor([1 + 0.9 * 6.0, 1 + 0.9 * 15.0]))
