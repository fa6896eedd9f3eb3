"""evaluate(): each sub-env's episode quota, and acting by the policy's mode or by sampling it, on a
real CartPole-v1 with a real (untrained, seeded) discrete policy."""

from __future__ import annotations

import numpy as np

from algorithm.config.schema import NNConfig, SacConfig
from algorithm.run.evaluation import evaluate
from algorithm.sac.policy import Policy
from envs.make import make_vector_env

NN = NNConfig(hidden_units=[16, 16])


def cartpole_policy(num_envs: int) -> tuple:
    env = make_vector_env("CartPole-v1", num_envs, seed=3)
    return env, Policy(env.spec, SacConfig(seed=5), NN)


def test_the_episodes_are_spread_over_the_sub_envs_and_all_counted() -> None:
    env, policy = cartpole_policy(3)
    result = evaluate(env, policy, 7, seed=11)
    assert len(result.returns) == len(result.lengths) == 7
    np.testing.assert_array_equal(result.returns, result.lengths)  # CartPole pays 1 a step


def test_the_mode_is_scored_the_same_on_the_same_starts_and_sampling_is_not() -> None:
    env, policy = cartpole_policy(2)
    first, again = (evaluate(env, policy, 6, seed=11) for _ in range(2))
    np.testing.assert_array_equal(first.returns, again.returns)
    # Sampling draws from the policy's generator, which advances: the same start states give other
    # episodes (a flag that did not reach the policy would score the mode twice and tie).
    sampled = [evaluate(env, policy, 6, seed=11, deterministic=False).returns for _ in range(2)]
    assert not np.array_equal(sampled[0], sampled[1])
    assert not np.array_equal(sampled[0], first.returns)
