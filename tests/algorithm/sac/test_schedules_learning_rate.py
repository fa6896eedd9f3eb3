"""sac_config.learning_rate_final: every optimizer's step size annealed linearly with the applied-update
count, constant after, and a resumed learner going on where it was."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from algorithm.config.random_params import apply_params, draw_for_run
from algorithm.config.schema import Config, SacConfig
from algorithm.sac.learner import SAC
from algorithm.sac.schedules import learning_rate_at, linear_anneal
from tests.algorithm.sac.test_learner import make_batch, make_sac


def step_size(sac: SAC) -> float:
    """The one step size every parameter group of every optimizer has."""
    sizes = {group["lr"] for opt in sac._optimizers() for group in opt.param_groups}
    assert len(sizes) == 1, sizes
    return sizes.pop()


def weights(sac: SAC) -> list[torch.Tensor]:
    return [p.detach().clone() for p in sac.models.parameters()]


def test_linear_anneal_moves_from_start_to_final_and_stays() -> None:
    assert [linear_anneal(1.0, 0.2, u, 4) for u in range(6)] == pytest.approx([1.0, 0.8, 0.6, 0.4, 0.2, 0.2])


def test_every_optimizer_steps_with_the_annealed_rate_and_reports_it() -> None:
    sac = make_sac(learning_rate=1e-3, learning_rate_final=2e-4, learning_rate_anneal_updates=4, use_priority=False)
    assert len(sac._optimizers()) == 3  # critic, policy and alpha all follow the schedule
    used, reported = [], []
    for i in range(6):
        result = sac.update(make_batch(seed=i), with_metrics=True)
        used.append(step_size(sac))
        reported.append(result.metrics["learner/learning_rate"])
    expected = [1e-3, 8e-4, 6e-4, 4e-4, 2e-4, 2e-4]  # the rate of update i: i updates applied before it
    assert used == pytest.approx(expected)
    assert reported == used


def test_a_rate_annealed_to_zero_stops_training() -> None:
    sac = make_sac(learning_rate=1e-3, learning_rate_final=0.0, learning_rate_anneal_updates=3, use_priority=False)
    for i in range(3):
        sac.update(make_batch(seed=i))
    before = weights(sac)
    sac.update(make_batch(seed=7))
    for a, b in zip(before, weights(sac), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # and a constant rate (the default) still moves them
    constant = make_sac(learning_rate=1e-3, use_priority=False)
    for i in range(3):
        constant.update(make_batch(seed=i))
    before = weights(constant)
    constant.update(make_batch(seed=7))
    assert any(not torch.equal(a, b) for a, b in zip(before, weights(constant), strict=True))


def test_a_resumed_learner_goes_on_with_the_rate_where_it_was() -> None:
    config = dict(learning_rate=1e-3, learning_rate_final=1e-4, learning_rate_anneal_updates=10, use_priority=False)
    sac = make_sac(**config)
    for i in range(4):
        sac.update(make_batch(seed=i))
    resumed = make_sac(**config)
    resumed.load_state_dict(copy.deepcopy(sac.state_dict()))
    a, b = sac.update(make_batch(seed=5)), resumed.update(make_batch(seed=5))
    np.testing.assert_array_equal(a.td_abs, b.td_abs)
    assert step_size(resumed) == step_size(sac) == pytest.approx(1e-3 - 9e-4 * 4 / 10)


def test_the_schedule_is_checked_at_load() -> None:
    with pytest.raises(ValueError, match="learning_rate_final"):
        SacConfig(learning_rate_final=-1e-4)
    with pytest.raises(ValueError, match="learning_rate_anneal_updates"):
        SacConfig(learning_rate_anneal_updates=0)


def test_a_schedule_left_at_null_spans_the_run_and_needs_an_end() -> None:
    """``learning_rate_anneal_updates: null`` (the default) is the run's updates, from the run's own length."""
    run = {"base_config": {"max_step": 5000}, "replay_config": {"min_size_to_sample": 1000, "batch_size": 64,
                                                                "samples_per_insert": 128}}  # fmt: skip
    config = Config.model_validate({**run, "sac_config": {"learning_rate_final": 0.0}})
    assert config.sac_config.learning_rate_anneal_updates == 2 * (5000 - 1000)
    given = Config.model_validate(
        {**run, "sac_config": {"learning_rate_final": 0.0, "learning_rate_anneal_updates": 9}}
    )
    assert given.sac_config.learning_rate_anneal_updates == 9
    endless = {"base_config": {"max_step": -1}, "sac_config": {"learning_rate_final": 0.0}}
    with pytest.raises(ValueError, match="learning_rate_anneal_updates is null.*max_step is -1"):
        Config.model_validate(endless)
    with pytest.raises(ValueError, match="learning_rate_anneal_updates is null"):
        learning_rate_at(SacConfig(learning_rate_final=0.0), 10)


def test_drawn_hyper_parameters_move_a_schedule_that_spans_the_run() -> None:
    """The evolver's and main.py's drawn values (``apply_params``) derive the run's anneal again from the drawn
    batch size or run length, and keep an anneal given as another number. Pins the gap left by the null default:
    a copy kept the count derived from the values before the draw (2000 instead of 16000 below)."""
    run = {"base_config": {"max_step": 5000}, "replay_config": {"min_size_to_sample": 1000, "samples_per_insert": 128}}
    derived = Config.model_validate({**run, "sac_config": {"learning_rate_final": 0.0}})
    assert derived.sac_config.learning_rate_anneal_updates == 4000 * 128 // 256
    assert apply_params(derived, {"replay_config.batch_size": 32}).sac_config.learning_rate_anneal_updates == 16000
    shorter = apply_params(derived, {"base_config.max_step": 3000})
    assert shorter.sac_config.learning_rate_anneal_updates == 2000 * 128 // 256
    given = Config.model_validate(
        {**run, "sac_config": {"learning_rate_final": 0.0, "learning_rate_anneal_updates": 9}}
    )
    assert apply_params(given, {"replay_config.batch_size": 32}).sac_config.learning_rate_anneal_updates == 9
    constant = Config.model_validate(run)  # no schedule: nothing derived, nothing moved
    assert apply_params(constant, {"replay_config.batch_size": 32}).sac_config.learning_rate_anneal_updates is None
    drawn = {"random_params": {"replay_config": {"batch_size": {"in": [32]}}}}
    run_config, values = draw_for_run(
        Config.model_validate({**run, **drawn, "sac_config": {"learning_rate_final": 0.0}}), seed=0
    )
    assert values == {"replay_config.batch_size": 32}
    assert run_config.sac_config.learning_rate_anneal_updates == 16000
