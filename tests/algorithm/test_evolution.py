"""The evolver's math: CEM fit and samples, random_params sampling and validation, CemPopulation bookkeeping.

Statistical checks use fixed seeds, so they are deterministic; their tolerances are set so that a
correct implementation fails with probability well below 1e-3 over seeds.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy import stats

from algorithm.config.load import ConfigError, load_config
from algorithm.config.random_params import ParamSpecError, apply_params, parse_random_params, sample_params
from algorithm.config.schema import Config
from algorithm.evolution import (
    CemPopulation,
    cem_distribution,
    cem_due,
    elite_count,
    elite_indices,
    sample_weights,
)


def make_config(random_params: dict[str, Any] | None = None, **base: Any) -> Config:
    return Config.model_validate({"base_config": base, "random_params": random_params or {}})


def draw(random_params: dict[str, Any], n: int, seed: int = 0, counts: dict[str, list[int]] | None = None) -> list[Any]:
    """``n`` draws of the single key in ``random_params``."""
    config = make_config(random_params)
    specs = parse_random_params(config.random_params, config)
    (path,) = specs
    rng = np.random.default_rng(seed)
    return [sample_params(specs, config, counts or {}, rng)[path] for _ in range(n)]


def write_task(tmp_path: Path, text: str) -> Path:
    task = tmp_path / "task"
    task.mkdir()
    (task / "config.yaml").write_text(text)
    return task


# --- CEM: elites, fit, samples ---------------------------------------------------------------


def test_elite_mean_and_population_std_equal_hand_computed_values() -> None:
    elites: list[dict[str, np.ndarray]] = [
        {"w": np.array([[0.0, 1.0], [2.0, 3.0]], np.float32), "steps": np.array([7], np.int64)},
        {"w": np.array([[2.0, 1.0], [2.0, 5.0]], np.float32), "steps": np.array([9], np.int64)},
        {"w": np.array([[4.0, 1.0], [2.0, 4.0]], np.float32), "steps": np.array([3], np.int64)},
    ]
    mean, std = cem_distribution(elites, std_max=10.0)
    np.testing.assert_allclose(mean["w"], [[2.0, 1.0], [2.0, 4.0]], rtol=1e-7)
    # population std (ddof=0): sqrt(((0-2)^2 + 0 + (4-2)^2) / 3) and sqrt((1 + 1 + 0) / 3)
    np.testing.assert_allclose(std["w"], [[math.sqrt(8 / 3), 0.0], [0.0, math.sqrt(2 / 3)]], rtol=1e-6)
    assert mean["w"].dtype == std["w"].dtype == np.float32
    # integer tensors are not sampled: the best elite's (the first) values, std 0
    np.testing.assert_array_equal(mean["steps"], [7])
    np.testing.assert_array_equal(std["steps"], [0])


def test_std_is_capped_and_small_spreads_are_kept() -> None:
    rng = np.random.default_rng(1)
    wide = [{"w": rng.normal(0.0, 5.0, 1000).astype(np.float32)} for _ in range(4)]
    _, std = cem_distribution(wide, std_max=0.1)
    assert std["w"].max() == pytest.approx(0.1) and (std["w"] <= np.float32(0.1)).all()
    narrow = [{"w": rng.normal(0.0, 0.01, 1000).astype(np.float32)} for _ in range(4)]
    _, std = cem_distribution(narrow, std_max=0.1)
    stacked = np.stack([e["w"].astype(np.float64) for e in narrow])
    np.testing.assert_allclose(std["w"], stacked.std(axis=0), rtol=1e-5)


def test_a_single_elite_is_copied_exactly() -> None:
    elite = {"w": np.arange(6, dtype=np.float32).reshape(2, 3)}
    mean, std = cem_distribution([elite], std_max=0.1)
    np.testing.assert_array_equal(std["w"], 0.0)
    np.testing.assert_array_equal(sample_weights(mean, std, np.random.default_rng(0))["w"], elite["w"])


def test_mismatched_elites_are_rejected() -> None:
    a = {"w": np.zeros(3, np.float32)}
    with pytest.raises(ValueError, match="'w'"):
        cem_distribution([a, {"w": np.zeros(4, np.float32)}], std_max=0.1)
    with pytest.raises(ValueError, match="tensors"):
        cem_distribution([a, {"v": np.zeros(3, np.float32)}], std_max=0.1)
    with pytest.raises(ValueError, match="at least one elite"):
        cem_distribution([], std_max=0.1)


def test_samples_have_the_fitted_mean_and_std() -> None:
    rng = np.random.default_rng(2)
    mean = {"w": rng.normal(0.0, 1.0, (10, 20)).astype(np.float32), "mask": np.array([True, False])}
    std = {"w": rng.uniform(0.01, 0.1, (10, 20)).astype(np.float32), "mask": np.zeros(2, np.float32)}
    n = 2000
    draws = [sample_weights(mean, std, rng) for _ in range(n)]
    assert all(d["w"].dtype == np.float32 and d["w"].shape == (10, 20) for d in draws)
    assert all((d["mask"] == mean["mask"]).all() and d["mask"].dtype == np.bool_ for d in draws)
    w = np.stack([d["w"].astype(np.float64) for d in draws])
    z = (w - mean["w"]) / std["w"]  # standard normal per element if the draw is right
    # per element: |mean of z| < 5 / sqrt(n); pooled over 200 elements: tight mean and std
    assert np.abs(z.mean(axis=0)).max() < 5 / math.sqrt(n)
    assert abs(z.mean()) < 5 / math.sqrt(z.size)
    assert z.std() == pytest.approx(1.0, abs=0.01)
    assert stats.kstest(z[:, 0, 0], "norm").pvalue > 1e-3


def test_sample_weights_is_reproducible_from_the_seed() -> None:
    mean = {"a": np.zeros(5, np.float32), "b": np.ones((2, 2), np.float32)}
    std = {"a": np.full(5, 0.1, np.float32), "b": np.full((2, 2), 0.05, np.float32)}
    one = sample_weights(mean, std, np.random.default_rng(3))
    two = sample_weights(mean, std, np.random.default_rng(3))
    for name in mean:
        np.testing.assert_array_equal(one[name], two[name])


@pytest.mark.parametrize(
    ("n", "best", "expected"),
    [(10, 0.3, 3), (4, 0.3, 2), (1, 0.3, 1), (5, 1.0, 5), (3, 0.01, 1), (7, 0.5, 4), (20, 0.15, 3)],
)
def test_elite_count_rounds_up_to_at_least_one(n: int, best: float, expected: int) -> None:
    assert elite_count(n, best) == expected


def test_elite_indices_best_first_ties_to_lower_index_nan_last() -> None:
    assert elite_indices([1.0, 3.0, 3.0, float("nan"), 2.0], 0.6) == [1, 2, 4]
    assert elite_indices([float("nan"), 0.0], 1.0) == [1, 0]
    with pytest.raises(ValueError):
        elite_indices([], 0.3)


def test_cem_due_by_length_or_by_time_with_a_minimum() -> None:
    assert cem_due([50, 50, 60], cem_length=50, min_length=2, minutes_since_last=0.0, cem_time=3.0)
    assert not cem_due([50, 49, 60], cem_length=50, min_length=2, minutes_since_last=2.9, cem_time=3.0)
    assert cem_due([2, 49, 3], cem_length=50, min_length=2, minutes_since_last=3.0, cem_time=3.0)
    assert not cem_due([1, 49, 3], cem_length=50, min_length=2, minutes_since_last=99.0, cem_time=3.0)
    assert not cem_due([50], cem_length=50, min_length=2, minutes_since_last=99.0, cem_time=3.0)


# --- random_params: sampling -----------------------------------------------------------------


def test_elite_counts_raise_a_values_sampling_frequency() -> None:
    spec = {"sac_config": {"n_step": {"in": [1, 3, 5]}}}
    n = 3000
    flat = draw(spec, n, seed=4)
    favoured = draw(spec, n, seed=4, counts={"sac_config.n_step": [0, 40, 0]})
    # Dirichlet(1 + c) then categorical: value i comes up with probability (1 + c_i) / (K + sum c)
    for sampled, p in ((flat, 1 / 3), (favoured, 41 / 43)):
        assert stats.binomtest(sampled.count(3), n, p).pvalue > 1e-3
    assert favoured.count(3) > 2 * flat.count(3)
    assert set(flat) == {1, 3, 5}


def test_truncated_alone_is_uniform_within_bounds() -> None:
    samples = np.array(draw({"sac_config": {"learning_rate": {"truncated": [1e-4, 1e-3]}}}, 2000, seed=5))
    assert ((samples >= 1e-4) & (samples <= 1e-3)).all()
    assert stats.kstest(samples, stats.uniform(loc=1e-4, scale=9e-4).cdf).pvalue > 1e-3


def test_std_is_normal_around_the_configured_value() -> None:
    samples = np.array(draw({"sac_config": {"init_log_alpha": {"std": 0.5}}}, 2000, seed=6))
    assert samples.mean() == pytest.approx(-2.3, abs=4 * 0.5 / math.sqrt(2000))
    assert samples.std() == pytest.approx(0.5, rel=0.05)
    assert stats.kstest(samples, stats.norm(-2.3, 0.5).cdf).pvalue > 1e-3


def test_std_with_truncated_is_a_truncated_normal() -> None:
    lo, hi, centre, s = 0.004, 0.007, 0.005, 0.002  # sac_config.tau defaults to 0.005
    samples = np.array(draw({"sac_config": {"tau": {"std": s, "truncated": [lo, hi]}}}, 2000, seed=7))
    assert ((samples >= lo) & (samples <= hi)).all()
    expected = stats.truncnorm((lo - centre) / s, (hi - centre) / s, loc=centre, scale=s)
    assert stats.kstest(samples, expected.cdf).pvalue > 1e-3


def test_draws_the_schema_rejects_are_drawn_again() -> None:
    samples = draw({"sac_config": {"gamma": {"std": 0.05}}}, 500, seed=8)  # gamma <= 1, centre 0.99
    assert max(samples) <= 1.0 and min(samples) < 0.95


def test_a_centre_far_outside_the_bounds_falls_back_to_the_nearest_bound() -> None:
    samples = draw({"sac_config": {"tau": {"std": 1e-4, "truncated": [0.5, 0.6]}}}, 3, seed=9)
    assert samples == [0.5, 0.5, 0.5]


def test_integer_keys_stay_integers() -> None:
    uniform = draw({"sac_config": {"n_step": {"truncated": [1, 5]}}}, 2000, seed=10)
    assert all(type(v) is int for v in uniform)
    assert stats.chisquare(np.bincount(uniform, minlength=6)[1:]).pvalue > 1e-3
    normal = draw({"sac_config": {"n_step": {"std": 3.0, "truncated": [1.5, 8]}}}, 500, seed=11)
    assert all(type(v) is int and 2 <= v <= 8 for v in normal)
    config = make_config({"sac_config": {"n_step": {"std": 3.0, "truncated": [1.5, 8]}}})
    assert type(apply_params(config, {"sac_config.n_step": normal[0]}).sac_config.n_step) is int


def test_in_values_are_stored_as_the_schema_coerces_them() -> None:
    config = make_config({"nn_config": {"hidden_units": {"in": [[64, 64], [256, 256]]}}})
    specs = parse_random_params(config.random_params, config)
    assert specs["nn_config.hidden_units"].values == ([64, 64], [256, 256])
    lr = make_config({"sac_config": {"learning_rate": {"in": [1, 2]}}})
    values = parse_random_params(lr.random_params, lr)["sac_config.learning_rate"].values
    assert values == (1.0, 2.0) and all(type(v) is float for v in values)


def test_apply_params_returns_a_validated_copy_without_random_params() -> None:
    config = make_config({"sac_config": {"n_step": {"in": [1, 3]}}})
    applied = apply_params(config, {"sac_config.n_step": 3, "nn_config.hidden_units": [32]})
    assert (applied.sac_config.n_step, applied.nn_config.hidden_units, applied.random_params) == (3, [32], {})
    assert config.sac_config.n_step == 1  # the original is untouched
    with pytest.raises(ValueError, match="sac_config.n_step"):
        apply_params(config, {"sac_config.n_step": 0})
    with pytest.raises(ValueError, match="not a config key"):
        apply_params(config, {"sac_config.n_stepp": 2})


# --- random_params: validation at load -------------------------------------------------------


BAD_SPECS = [
    ("sac_config: {n_step: {in: []}}", "random_params.sac_config.n_step", "'in' must be a non-empty list"),
    ("sac_config: {n_step: {in: 3}}", "random_params.sac_config.n_step", "'in' must be a non-empty list"),
    ("sac_config: {n_step: {in: [3, 3]}}", "random_params.sac_config.n_step", "twice"),
    ("sac_config: {n_step: {in: [0, 1]}}", "random_params.sac_config.n_step", "'in' value 0 is not valid"),
    ("sac_config: {tau: {truncated: [0.01, 0.001]}}", "random_params.sac_config.tau", "lo < hi"),
    ("sac_config: {tau: {truncated: [0.01, 0.01]}}", "random_params.sac_config.tau", "lo < hi"),
    ("sac_config: {tau: {truncated: [0.01]}}", "random_params.sac_config.tau", "[lo, hi]"),
    ("sac_config: {gamma: {truncated: [0.9, 1.1]}}", "random_params.sac_config.gamma", "bound 1.1 is not valid"),
    ("sac_config: {n_step: {truncated: [1.2, 1.8]}}", "random_params.sac_config.n_step", "no integer"),
    ("sac_config: {tau: {std: 0}}", "random_params.sac_config.tau", "'std' must be a number > 0"),
    ("sac_config: {tau: {std: -0.1}}", "random_params.sac_config.tau", "'std' must be a number > 0"),
    ("sac_config: {clip_epsilon: {std: 0.1}}", "random_params.sac_config.clip_epsilon", "is null"),
    ("sac_config: {tau: {in: [0.1], std: 0.1}}", "random_params.sac_config.tau", "expected {in: [...]}"),
    ("sac_config: {tau: {uniform: [0.0, 1.0]}}", "random_params.sac_config.tau", "expected {in: [...]}"),
    ("sac_config: {n_stepp: {in: [1]}}", "random_params.sac_config.n_stepp", "did you mean 'n_step'"),
    ("sac_confg: {n_step: {in: [1]}}", "random_params.sac_confg", "unknown section"),
    ("reset_config: {seed: {in: [1]}}", "random_params.reset_config.seed", "reset_config has no option 'seed'"),
    ("nn_config: {activation: {std: 0.1}}", "random_params.nn_config.activation", "numeric key"),
    ("sac_config: {use_rnn: {truncated: [0, 1]}}", "random_params.sac_config.use_rnn", "numeric key"),
    ("sac_config: {n_step: 5}", "random_params.sac_config.n_step", "valid dictionary"),
]


@pytest.mark.parametrize(("spec_text", "key", "fragment"), BAD_SPECS)
def test_bad_specs_are_config_errors_naming_key_and_file(
    tmp_path: Path, spec_text: str, key: str, fragment: str
) -> None:
    task = write_task(tmp_path, "default:\n  random_params:\n    " + spec_text + "\n")
    with pytest.raises(ConfigError) as err:
        load_config(task)
    message = str(err.value)
    assert f"{key} ({task / 'config.yaml'} [default])" in message
    assert fragment in message


def test_parse_errors_carry_the_key_path() -> None:
    with pytest.raises(ParamSpecError) as err:
        parse_random_params({"sac_config": {"n_step": {"in": []}}}, Config())
    assert err.value.path == "random_params.sac_config.n_step"
    assert str(err.value) == "random_params.sac_config.n_step: 'in' must be a non-empty list"


def test_random_params_load_and_variants_add_keys(tmp_path: Path) -> None:
    task = write_task(
        tmp_path,
        """
default:
  random_params:
    sac_config:
      n_step: {in: [1, 3, 5]}
      learning_rate: {truncated: [0.0001, 0.001]}
      tau: {std: 0.002, truncated: [0.001, 0.01]}
      gamma: {std: 0.005}
wide:
  random_params:
    sac_config:
      gamma: {std: 0.01}
    nn_config:
      hidden_units: {in: [[64, 64], [256, 256]]}
""",
    )
    resolved = load_config(task, "wide")
    sac = resolved.config.random_params["sac_config"]
    assert sac["n_step"] == {"in": [1, 3, 5]} and sac["gamma"] == {"std": 0.01}
    assert resolved.config.random_params["nn_config"]["hidden_units"] == {"in": [[64, 64], [256, 256]]}
    assert resolved.sources["random_params.sac_config.gamma"].endswith("[wide]")
    assert resolved.sources["random_params.sac_config.tau"].endswith("[default]")
    population = CemPopulation(resolved.config)
    learner_id, params = population.add_learner(np.random.default_rng(0))
    learner = population.learner_config(learner_id)
    assert learner.sac_config.n_step == params["sac_config.n_step"] in (1, 3, 5)
    assert learner.nn_config.hidden_units in ([64, 64], [256, 256])


@pytest.mark.parametrize(
    ("base_text", "fragment"),
    [
        ("{evolver_cem_length: 5, evolver_cem_min_length: 6}", "evolver_cem_min_length must be <="),
        ("{evolver_remove_worst: 0}", "-1 (off) or >= 1"),
        ("{evolver_cem_best: 0.0}", "greater than 0"),
        ("{evolver_cem_std_max: 0}", "greater than 0"),
    ],
)
def test_evolver_keys_are_validated(tmp_path: Path, base_text: str, fragment: str) -> None:
    task = write_task(tmp_path, "default:\n  base_config: " + base_text + "\n")
    with pytest.raises(ConfigError, match="base_config") as err:
        load_config(task)
    assert fragment in str(err.value)


# --- CemPopulation ------------------------------------------------------------------------------


def weights_of(learner_id: int) -> dict[str, np.ndarray]:
    return {"w": np.full((3, 2), float(learner_id), np.float32), "step": np.array([learner_id], np.int64)}


def population_with(n: int, rng: np.random.Generator, **base: Any) -> CemPopulation:
    population = CemPopulation(make_config({"sac_config": {"n_step": {"in": [1, 3, 5]}}}, **base))
    for _ in range(n):
        population.add_learner(rng)
    return population


def post(population: CemPopulation, returns: dict[int, list[float]]) -> None:
    for learner_id, values in returns.items():
        for value in values:
            population.post_return(learner_id, value)


def test_a_round_keeps_elites_and_samples_the_rest() -> None:
    rng = np.random.default_rng(12)
    population = population_with(5, rng, evolver_cem_best=0.4, evolver_cem_length=3, evolver_cem_min_length=2)
    post(population, {0: [1.0, 2.0], 1: [5.0, 6.0, 7.0], 2: [0.0], 3: [9.0, 9.0, 9.0], 4: [3.0]})
    assert not population.round_due(minutes_since_last=0.0)
    assert not population.round_due(minutes_since_last=5.0)  # learners 2 and 4 have 1 < min_length
    post(population, {0: [3.0], 2: [0.0, 0.0], 4: [3.0, 3.0]})
    assert population.round_due(minutes_since_last=0.0)
    assert population.elites() == [3, 1]

    result = population.run_round({i: weights_of(i) for i in population.elites()}, rng)
    assert (result.round, result.elites, result.retired) == (1, [3, 1], [])
    assert result.mean_returns == {0: 2.0, 1: 6.0, 2: 0.0, 3: 9.0, 4: 3.0}
    assert sorted(result.samples_for) == [0, 2, 4]
    np.testing.assert_allclose(result.mean["w"], 2.0)  # mean of the elites' weights 3 and 1
    np.testing.assert_allclose(result.std["w"], 0.1)  # their std 1.0, capped at the default 0.1
    np.testing.assert_array_equal(result.mean["step"], [3])  # the best elite's counter
    for sample in result.samples_for.values():
        assert sample["w"].dtype == np.float32 and sample["w"].shape == (3, 2)
        assert np.abs(sample["w"] - 2.0).max() < 0.6
    assert all(not r.returns and r.rounds == 1 for r in population.learners.values())
    assert [population.learners[i].times_elite for i in range(5)] == [0, 1, 0, 1, 0]


def test_elite_values_are_counted() -> None:
    rng = np.random.default_rng(13)
    population = population_with(4, rng, evolver_cem_best=0.5, evolver_cem_length=1, evolver_cem_min_length=1)
    post(population, {0: [4.0], 1: [3.0], 2: [2.0], 3: [1.0]})
    population.run_round({i: weights_of(i) for i in population.elites()}, rng)
    expected = [0, 0, 0]
    for i in (0, 1):
        expected[[1, 3, 5].index(population.learners[i].params["sac_config.n_step"])] += 1
    assert population.counts == {"sac_config.n_step": expected}


def test_learners_without_returns_sit_the_round_out() -> None:
    rng = np.random.default_rng(14)
    population = population_with(3, rng, evolver_cem_best=0.5)
    post(population, {0: [1.0], 1: [2.0]})
    result = population.run_round({1: weights_of(1)}, rng)
    assert (result.elites, sorted(result.samples_for)) == ([1], [0])
    assert population.learners[2].rounds == 0
    post(population, {0: [5.0]})
    with pytest.raises(ValueError, match="weights of every elite"):
        population.run_round({}, rng)


def test_never_elite_learners_retire_after_remove_worst_rounds() -> None:
    rng = np.random.default_rng(15)
    population = population_with(4, rng, evolver_cem_best=0.25, evolver_remove_worst=2)
    returns = {0: [10.0], 1: [5.0], 2: [3.0], 3: [1.0]}
    post(population, returns)
    first = population.run_round({0: weights_of(0)}, rng)
    assert first.retired == []
    post(population, returns)
    second = population.run_round({0: weights_of(0)}, rng)
    # 1, 2 and 3 were never elite in 2 rounds; retiring all would leave fewer than elites + 1 = 2
    assert second.retired == [3, 2]
    assert sorted(second.samples_for) == [1]
    assert sorted(population.learners) == [0, 1] and population.retired == [3, 2]
    with pytest.raises(KeyError, match="retired"):
        population.post_return(3, 1.0)
    with pytest.raises(KeyError, match="not registered"):
        population.post_return(99, 1.0)


def test_remove_worst_off_never_retires() -> None:
    rng = np.random.default_rng(16)
    population = population_with(4, rng, evolver_cem_best=0.25, evolver_remove_worst=-1)
    for _ in range(6):
        post(population, {0: [10.0], 1: [5.0], 2: [3.0], 3: [1.0]})
        assert population.run_round({0: weights_of(0)}, rng).retired == []
    assert sorted(population.learners) == [0, 1, 2, 3]


def test_returns_window_keeps_the_last_cem_length_finite_values() -> None:
    population = population_with(1, np.random.default_rng(17), evolver_cem_length=3, evolver_cem_min_length=1)
    post(population, {0: [1.0, 2.0, 3.0, 4.0]})
    assert population.learners[0].returns == [2.0, 3.0, 4.0]
    with pytest.raises(ValueError, match="non-finite"):
        population.post_return(0, float("nan"))


def test_state_round_trips_and_the_copy_continues_identically() -> None:
    rng = np.random.default_rng(18)
    population = population_with(5, rng, evolver_cem_best=0.4, evolver_remove_worst=1)
    post(population, {0: [1.0, 0.5], 1: [2.25], 2: [3.0], 3: [0.1], 4: [1e-300]})
    population.run_round({i: weights_of(i) for i in population.elites()}, rng)
    population.add_learner(rng)
    post(population, {0: [0.3], 5: [7.0 / 3.0]})

    state = population.to_state()
    restored = CemPopulation.from_state(population.config, json.loads(json.dumps(state)))
    assert restored.to_state() == state
    assert json.loads(json.dumps(state)) == state

    rng_copy = np.random.Generator(type(rng.bit_generator)())
    rng_copy.bit_generator.state = copy.deepcopy(rng.bit_generator.state)
    outcomes = []
    for pop, generator in ((population, rng), (restored, rng_copy)):
        learner = pop.add_learner(generator)
        post(pop, {i: [float(i)] for i in pop.learners})
        result = pop.run_round({i: weights_of(i) for i in pop.elites()}, generator)
        outcomes.append((learner, result, pop.to_state()))
    (learner_a, result_a, state_a), (learner_b, result_b, state_b) = outcomes
    assert learner_a == learner_b and state_a == state_b
    assert (result_a.elites, result_a.retired) == (result_b.elites, result_b.retired)
    assert result_a.samples_for.keys() == result_b.samples_for.keys()
    for i, sample in result_a.samples_for.items():
        np.testing.assert_array_equal(sample["w"], result_b.samples_for[i]["w"])


def test_restored_counts_follow_values_when_the_choices_change() -> None:
    population = population_with(0, np.random.default_rng(19))
    population.counts["sac_config.n_step"] = [4, 5, 6]
    state = population.to_state()
    changed = make_config({"sac_config": {"n_step": {"in": [5, 2, 1]}}})
    assert CemPopulation.from_state(changed, state).counts == {"sac_config.n_step": [6, 0, 4]}
    with pytest.raises(ValueError, match="version"):
        CemPopulation.from_state(changed, {**state, "version": 0})


def test_reset_config_options_are_drawn_like_any_key_and_must_be_configured_first() -> None:
    # Issue 15, defect 4: reset_config (the env's reset options, a free mapping) could not be
    # randomized: random_params knew only the schema's sections.
    config = Config.model_validate({
        "reset_config": {"low": -0.05, "high": 0.05, "mode": "a"},
        "random_params": {"reset_config": {"high": {"truncated": [0.1, 0.3]}, "mode": {"in": ["a", "b"]}}},
    })  # fmt: skip
    specs = parse_random_params(config.random_params, config)
    rng = np.random.default_rng(0)
    draws = [sample_params(specs, config, {}, rng) for _ in range(200)]
    assert all(0.1 <= d["reset_config.high"] <= 0.3 for d in draws)
    assert {d["reset_config.mode"] for d in draws} == {"a", "b"}
    applied = apply_params(config, draws[0])
    assert applied.reset_config == {"low": -0.05, **{k.split(".")[1]: v for k, v in draws[0].items()}}
    with pytest.raises(ParamSpecError, match=r"random_params.reset_config.lo: reset_config has no option 'lo'"):
        parse_random_params({"reset_config": {"lo": {"truncated": [0.0, 1.0]}}}, config)
    with pytest.raises(ParamSpecError, match="'truncated' and 'std' need a numeric key"):
        parse_random_params({"reset_config": {"mode": {"truncated": [0.0, 1.0]}}}, config)
    overridden = load_config(None, None, ["reset_config.high=0.2"]).config  # null by default: a key sets it
    assert overridden.reset_config == {"high": 0.2}
