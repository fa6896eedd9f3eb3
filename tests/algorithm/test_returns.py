"""Hand-computed n-step targets: termination vs truncation vs a masked tail, n = 1 and n = 3."""

from __future__ import annotations

import math

import pytest
import torch

from algorithm.returns import bootstrap_index, gather_positions, n_step_target, valid_steps

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
    torch.testing.assert_close(
        gather_positions(obs, index), torch.tensor([[3.0] * 2, [12.0] * 2, [21.0] * 2])
    )
