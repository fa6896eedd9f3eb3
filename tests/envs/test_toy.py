"""envs/toy: the Chain env's observations, rewards, termination and layouts are what its docs say."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import envs.toy  # noqa: F401  (registers asac/*)
from envs.toy import ChainEnv
from envs.toy.chain import IMAGE_SHAPE


def test_counter_and_x_follow_the_documented_rules() -> None:
    env = ChainEnv(action_dim=2)
    obs, _ = env.reset(seed=0)
    x0 = obs[2:].copy()
    assert obs[:2].tolist() == [0.0, 0.0] and np.all(np.abs(x0) <= 1.0)
    a = np.array([0.5, -1.5], np.float32)
    obs, reward, terminated, truncated, _ = env.step(a)
    assert obs[:2].tolist() == [0.0, 1.0]
    np.testing.assert_allclose(obs[2:], x0 + a, rtol=1e-6)
    assert reward == pytest.approx(0.0 - 1.0) and not terminated and not truncated
    _, reward, _, _, _ = env.step(np.array([2.0, 2.0], np.float32))
    assert reward == pytest.approx(1.0 + 4.0)  # t before the step + sum(action)
    obs, _ = env.reset()
    assert obs[:2].tolist() == [1.0, 0.0]  # second episode of this instance


def test_terminates_exactly_at_terminate_at() -> None:
    env = ChainEnv(terminate_at=3)
    env.reset(seed=0)
    flags = [env.step(np.zeros(1, np.float32))[2] for _ in range(3)]
    assert flags == [False, False, True]


def test_discrete_variant_uses_the_index() -> None:
    env = ChainEnv(n_actions=3, action_dim=2)
    obs, _ = env.reset(seed=0)
    obs2, reward, *_ = env.step(2)
    assert reward == 2.0
    np.testing.assert_allclose(obs2[2:], obs[2:] + 2.0)


def test_same_seed_same_start_and_different_seed_different_start() -> None:
    a, b, c = ChainEnv(), ChainEnv(), ChainEnv()
    assert a.reset(seed=4)[0][2] == b.reset(seed=4)[0][2] != c.reset(seed=5)[0][2]


def test_out_of_bounds_action_is_an_error() -> None:
    env = ChainEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="outside"):
        env.step(np.array([2.5], np.float32))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"terminate_at": 0}, "terminate_at"),
        ({"action_dim": 0}, "action_dim"),
        ({"action_low": 1.0, "action_high": 1.0}, "action_low < action_high"),
        ({"obs_mode": "list"}, "obs_mode"),
        ({"image": True}, "image"),
        ({"n_actions": -1}, "n_actions"),
    ],
)
def test_bad_kwargs_name_the_problem(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ChainEnv(**kwargs)


def test_registered_layouts() -> None:
    flat = gym.make("asac/Chain-v0")
    assert flat.observation_space.shape == (3,)
    dict_env = gym.make("asac/DictChain-v0", image=True)
    obs, _ = dict_env.reset(seed=0)
    assert list(obs) == ["state", "counter", "image"]
    assert obs["state"].shape == (3,) and obs["counter"].tolist() == [0.0, 0.0]
    obs, *_ = dict_env.step(np.zeros(3, np.float32))
    assert obs["image"].shape == IMAGE_SHAPE and obs["image"].dtype == np.uint8 and np.all(obs["image"] == 1)
    tuple_env = gym.make("asac/TupleChain-v0")
    counter, x = tuple_env.reset(seed=0)[0]
    assert counter.shape == (2,) and x.shape == (1,)


def test_registered_time_limit_truncates() -> None:
    env = gym.make("asac/Chain-v0")
    env.reset(seed=0)
    results = [env.step(np.zeros(1, np.float32))[2:4] for _ in range(envs.toy.TIME_LIMIT)]
    assert results[-1] == (False, True)
    assert all(r == (False, False) for r in results[:-1])
