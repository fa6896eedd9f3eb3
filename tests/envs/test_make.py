"""envs/make.py make_env: ids, time limits, seeding, bad input; real Pendulum and MuJoCo envs."""

from __future__ import annotations

import numpy as np
import pytest

from envs.make import make_env, make_vector_env


def test_unknown_id_names_the_id_and_suggests_close_matches() -> None:
    with pytest.raises(ValueError, match=r"unknown environment id 'HalfCheeta-v5'.*'HalfCheetah-v5'"):
        make_env("HalfCheeta-v5", seed=0)
    with pytest.raises(ValueError, match=r"'asac/Chian-v0'.*'asac/Chain-v0'"):
        make_vector_env("asac/Chian-v0", 2, seed=0)
    with pytest.raises(ValueError, match=r"unknown environment id 'NoSuchThing-v9'$"):
        make_env("NoSuchThing-v9", seed=0)


def test_module_prefixed_id_imports_the_module_first() -> None:
    env = make_env("envs.toy:asac/Chain-v0", seed=0)
    assert env.observation_space.shape == (3,)
    # a module that cannot be imported is named, with where to put it (the launchers show it as one line)
    with pytest.raises(ValueError, match="cannot import 'no_such_module' for 'no_such_module:Thing-v0'.*task's folder"):
        make_env("no_such_module:Thing-v0", seed=0)


def test_time_limit_override_truncates_and_does_not_terminate() -> None:
    env = make_env("Pendulum-v1", seed=0, max_episode_steps=5)  # registered limit is 200
    env.reset()
    flags = [env.step(np.zeros(1, np.float32))[2:4] for _ in range(5)]
    assert flags == [(False, False)] * 4 + [(False, True)]


def test_terminal_state_terminates_and_does_not_truncate() -> None:
    env = make_env("asac/Chain-v0", seed=0, env_kwargs={"terminate_at": 2}, max_episode_steps=50)
    env.reset()
    flags = [env.step(np.zeros(1, np.float32))[2:4] for _ in range(2)]
    assert flags == [(False, False), (True, False)]


@pytest.mark.parametrize("bad", [0, -1, 2.5, True])
def test_bad_max_episode_steps_is_rejected(bad: object) -> None:
    with pytest.raises(ValueError, match="max_episode_steps"):
        make_env("asac/Chain-v0", seed=0, max_episode_steps=bad)  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", [-1, 1.5, "0"])
def test_bad_seed_is_rejected(bad: object) -> None:
    with pytest.raises(ValueError, match="seed"):
        make_env("asac/Chain-v0", seed=bad)  # type: ignore[arg-type]


def test_reserved_keys_in_env_kwargs_are_rejected() -> None:
    with pytest.raises(ValueError, match="max_episode_steps"):
        make_env("asac/Chain-v0", seed=0, env_kwargs={"max_episode_steps": 3})


def test_unknown_env_kwarg_error_names_the_env() -> None:
    with pytest.raises(TypeError, match="bogus") as info:
        make_env("asac/Chain-v0", seed=0, env_kwargs={"bogus": 1})
    assert any("asac/Chain-v0" in note for note in info.value.__notes__)


def test_seed_is_applied_on_the_first_reset_and_to_the_spaces() -> None:
    a = make_env("Pendulum-v1", seed=7)
    b = make_env("Pendulum-v1", seed=7)
    reference = make_env("Pendulum-v1", seed=None)
    first = a.reset()[0]
    np.testing.assert_array_equal(first, b.reset()[0])
    np.testing.assert_array_equal(first, reference.reset(seed=7)[0])
    np.testing.assert_array_equal(a.reset(seed=7)[0], first)  # an explicit seed reseeds
    np.testing.assert_array_equal(a.action_space.sample(), b.action_space.sample())
    np.testing.assert_array_equal(a.observation_space.sample(), b.observation_space.sample())
    assert not np.array_equal(make_env("Pendulum-v1", seed=8).reset()[0], b.reset(seed=7)[0])


def test_numpy_integer_seeds_are_accepted() -> None:
    np.testing.assert_array_equal(
        make_env("Pendulum-v1", seed=np.int64(3)).reset()[0],  # type: ignore[arg-type]
        make_env("Pendulum-v1", seed=3).reset()[0],
    )


def test_later_unseeded_resets_continue_the_seeded_rng() -> None:
    a = make_env("asac/Chain-v0", seed=3)
    b = make_env("asac/Chain-v0", seed=3)
    starts_a = [a.reset()[0][2] for _ in range(3)]
    starts_b = [b.reset()[0][2] for _ in range(3)]
    assert starts_a == starts_b and len(set(starts_a)) == 3


def test_render_mode_is_passed_through() -> None:
    env = make_env("Pendulum-v1", seed=0, render_mode="rgb_array")
    assert env.render_mode == "rgb_array"


@pytest.mark.parametrize(("env_id", "obs_dim", "act_dim"), [("Pendulum-v1", 3, 1), ("HalfCheetah-v5", 17, 6)])
def test_real_envs_step(env_id: str, obs_dim: int, act_dim: int) -> None:
    env = make_env(env_id, seed=0)
    obs, _ = env.reset()
    assert obs.shape == (obs_dim,)
    for _ in range(20):
        obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        assert np.all(np.isfinite(obs)) and np.isfinite(float(reward)) and not terminated and not truncated
    assert env.action_space.shape == (act_dim,)
    env.close()
