"""envs/make.py VectorEnv: auto-reset with true final observations, termination vs truncation,
action scaling, seeding, sensor order, fresh arrays, bad input."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from algorithm.spaces import to_env_action
from envs.make import VectorEnv, make_env, make_vector_env


def chain(n: int, seed: int | None = 0, max_episode_steps: int | None = None, **kwargs: Any) -> VectorEnv:
    return make_vector_env("asac/Chain-v0", n, seed=seed, env_kwargs=kwargs, max_episode_steps=max_episode_steps)


def counters(obs: list[np.ndarray]) -> list[list[float]]:
    """``[episode_index, t]`` per env of a flat Chain observation."""
    return obs[0][:, :2].tolist()


# --- termination, truncation, final observations ----------------------------------------------


def test_time_limit_gives_truncated_with_the_true_final_obs_and_a_reset_obs() -> None:
    venv = chain(2, max_episode_steps=3)
    venv.reset()
    zeros = np.zeros((2, 1), np.float32)
    for _ in range(2):
        step = venv.step(zeros)
        assert not step.truncated.any() and not step.terminated.any()
        np.testing.assert_array_equal(step.obs[0], step.final_obs[0])
    step = venv.step(zeros)
    assert step.truncated.tolist() == [True, True] and step.terminated.tolist() == [False, False]
    assert counters(step.final_obs) == [[0.0, 3.0], [0.0, 3.0]]  # last obs of episode 0
    assert counters(step.obs) == [[1.0, 0.0], [1.0, 0.0]]  # first obs of episode 1


def test_terminal_state_gives_terminated_only() -> None:
    venv = chain(1, terminate_at=2)
    venv.reset()
    flags = []
    for _ in range(2):
        step = venv.step(np.zeros((1, 1), np.float32))
        flags.append((bool(step.terminated[0]), bool(step.truncated[0])))
    assert flags == [(False, False), (True, False)]
    assert counters(step.final_obs) == [[0.0, 2.0]] and counters(step.obs) == [[1.0, 0.0]]


def test_terminal_step_at_the_time_limit_is_terminated_not_truncated() -> None:
    venv = chain(1, terminate_at=3, max_episode_steps=3)
    venv.reset()
    for _ in range(3):
        step = venv.step(np.zeros((1, 1), np.float32))
    assert step.terminated.tolist() == [True] and step.truncated.tolist() == [False]


def test_only_finished_envs_get_a_different_final_obs_and_a_reset_info() -> None:
    venv = chain(3, max_episode_steps=2)
    venv.reset()
    venv.step(np.zeros((3, 1), np.float32))
    venv.reset_env(1)  # env 1 restarts, so envs 0 and 2 finish one step before it
    step = venv.step(np.zeros((3, 1), np.float32))
    assert step.truncated.tolist() == [True, False, True]
    np.testing.assert_array_equal(step.obs[0][1], step.final_obs[0][1])
    assert counters(step.final_obs) == [[0.0, 2.0], [1.0, 1.0], [0.0, 2.0]]
    assert counters(step.obs) == [[1.0, 0.0], [1.0, 1.0], [1.0, 0.0]]
    assert ["reset_info" in info for info in step.infos] == [True, False, True]


def test_halfcheetah_matches_envs_stepped_by_hand() -> None:
    n, limit, seed = 2, 5, 3
    venv = make_vector_env("HalfCheetah-v5", n, seed=seed, max_episode_steps=limit)
    refs = [make_env("HalfCheetah-v5", seed=seed + i, max_episode_steps=limit) for i in range(n)]
    obs = venv.reset()
    np.testing.assert_array_equal(obs[0], np.array([ref.reset()[0] for ref in refs], np.float32))
    rng = np.random.default_rng(0)
    for t in range(limit):
        actions = rng.uniform(-1.2, 1.2, (n, 6)).astype(np.float32)  # beyond [-1, 1]: clipped
        env_actions = to_env_action(venv.spec.action, actions)
        step = venv.step(actions)
        for i, ref in enumerate(refs):
            ref_obs, ref_reward, ref_term, ref_trunc, _ = ref.step(env_actions[i])
            np.testing.assert_array_equal(step.final_obs[0][i], ref_obs.astype(np.float32))
            assert step.rewards[i] == np.float32(ref_reward)
            assert (step.terminated[i], step.truncated[i]) == (ref_term, ref_trunc) == (False, t == limit - 1)
            if ref_trunc:
                np.testing.assert_array_equal(step.obs[0][i], ref.reset()[0].astype(np.float32))
                assert not np.array_equal(step.obs[0][i], step.final_obs[0][i])
            else:
                np.testing.assert_array_equal(step.obs[0][i], step.final_obs[0][i])
    (restarted,) = venv.reset_env(1)
    np.testing.assert_array_equal(restarted, refs[1].reset()[0].astype(np.float32))
    assert restarted.dtype == np.float32  # MuJoCo observations are float64
    venv.close()


def test_pendulum_steps_with_float32_outputs() -> None:
    with make_vector_env("Pendulum-v1", 4, seed=0) as venv:
        obs = venv.reset()
        assert obs[0].shape == (4, 3) and obs[0].dtype == np.float32
        step = venv.step(np.ones((4, 1), np.float32))
        assert step.rewards.dtype == np.float32 and step.rewards.shape == (4,)
        assert step.terminated.dtype == bool and step.truncated.dtype == bool
        assert np.all(np.isfinite(step.rewards)) and len(step.infos) == 4


# --- actions ------------------------------------------------------------------------------------


def test_model_actions_are_scaled_to_env_bounds_and_clipped() -> None:
    venv = chain(3, action_low=-2.0, action_high=6.0)
    x0 = venv.reset()[0][:, 2].copy()
    step = venv.step(np.array([[-1.0], [0.5], [3.0]], np.float32))
    env_actions = np.array([-2.0, 4.0, 6.0], np.float32)  # low, 3/4 of the way, clipped to high
    np.testing.assert_allclose(step.obs[0][:, 2], x0 + env_actions, rtol=1e-6)
    np.testing.assert_allclose(step.rewards, env_actions)  # t = 0 before the step


def test_discrete_actions_are_the_argmax_of_the_one_hot() -> None:
    venv = chain(2, n_actions=3)
    venv.reset()
    assert venv.spec.action.discrete_branches == (3,)
    step = venv.step(np.array([[0.1, 0.0, 0.9], [0.0, 1.0, 0.0]], np.float32))
    np.testing.assert_array_equal(step.rewards, [2.0, 1.0])


class ActionRecorder(gym.Env[np.ndarray, Any]):
    """Records what the vector env hands to ``step`` for structured action spaces."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, action_space: gym.Space[Any]) -> None:
        self.action_space = action_space
        self.actions: list[Any] = []

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        return np.zeros(1, np.float32), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        assert self.action_space.contains(action), action
        self.actions.append(action)
        return np.zeros(1, np.float32), 0.0, False, False, {}


def test_mixed_tuple_actions_reach_each_env_in_the_space_s_structure() -> None:
    space = gym.spaces.Tuple(
        (gym.spaces.Discrete(2), gym.spaces.MultiDiscrete([2, 3]), gym.spaces.Box(0.0, 4.0, (2,), np.float32))
    )
    envs = [ActionRecorder(space), ActionRecorder(space)]
    venv = VectorEnv(envs)
    assert venv.spec.action.size == 2 + 5 + 2
    venv.reset()
    venv.step(
        np.array(
            [[0, 1, 1, 0, 0, 0, 1, -1.0, 1.0], [1, 0, 0, 1, 0, 1, 0, 0.0, 0.5]],
            np.float32,
        )
    )
    first, second = envs[0].actions[0], envs[1].actions[0]
    assert first[0] == 1 and first[1].tolist() == [0, 2] and first[2].tolist() == [0.0, 4.0]
    assert second[0] == 0 and second[1].tolist() == [1, 1] and second[2].tolist() == [2.0, 3.0]


@pytest.mark.parametrize(
    ("space", "model_action", "expected"),
    [
        (gym.spaces.MultiDiscrete([4]), [0, 0, 0, 1], [3]),
        (gym.spaces.Box(-1.0, 1.0, (2, 2), np.float32), [0.5, 0.5, -1.0, 1.0], [[0.5, 0.5], [-1.0, 1.0]]),
        (gym.spaces.Tuple((gym.spaces.Discrete(4),)), [0, 0, 1, 0], [2]),
    ],
)
def test_single_branch_and_matrix_actions_get_the_space_s_shape(
    space: gym.Space[Any], model_action: list[float], expected: list
) -> None:
    env = ActionRecorder(space)  # asserts space.contains(action)
    venv = VectorEnv([env])
    venv.reset()
    venv.step(np.array([model_action], np.float32))
    assert np.asarray(env.actions[0]).tolist() == expected


@pytest.mark.parametrize("shape", [(2,), (3, 1), (2, 2), (2, 1, 1)])
def test_actions_of_the_wrong_shape_name_the_expected_shape(shape: tuple[int, ...]) -> None:
    venv = chain(2)
    venv.reset()
    with pytest.raises(ValueError, match=r"\(2, 1\)"):
        venv.step(np.zeros(shape, np.float32))


def test_non_finite_actions_name_the_env() -> None:
    venv = chain(3)
    venv.reset()
    with pytest.raises(ValueError, match=r"envs \[1\]"):
        venv.step(np.array([[0.0], [np.nan], [0.0]], np.float32))


def test_step_before_reset_is_an_error() -> None:
    with pytest.raises(RuntimeError, match="before reset"):
        chain(1).step(np.zeros((1, 1), np.float32))


def test_envs_with_different_spaces_are_rejected() -> None:
    with pytest.raises(ValueError, match="env 1's action space"):
        VectorEnv(
            [
                make_env("asac/Chain-v0", seed=0),
                make_env("asac/Chain-v0", seed=0, env_kwargs={"n_actions": 2}),
            ]
        )
    with pytest.raises(ValueError, match="at least one"):
        VectorEnv([])


@pytest.mark.parametrize("bad", [0, -2, 1.0])
def test_bad_num_envs_is_rejected(bad: object) -> None:
    with pytest.raises(ValueError, match="num_envs"):
        make_vector_env("asac/Chain-v0", bad, seed=0)  # type: ignore[arg-type]


# --- seeds --------------------------------------------------------------------------------------


def rollout(venv: VectorEnv, steps: int) -> list[np.ndarray]:
    rng = np.random.default_rng(1)
    seen = [venv.reset()[0]]
    for _ in range(steps):
        step = venv.step(rng.uniform(-1.0, 1.0, (venv.num_envs, venv.spec.action.size)).astype(np.float32))
        seen += [step.final_obs[0], step.obs[0]]
    return seen


def test_same_seed_gives_identical_observation_sequences() -> None:
    for env_id in ("asac/Chain-v0", "Pendulum-v1"):
        a = rollout(make_vector_env(env_id, 2, seed=11, max_episode_steps=4), 9)
        b = rollout(make_vector_env(env_id, 2, seed=11, max_episode_steps=4), 9)
        c = rollout(make_vector_env(env_id, 2, seed=12, max_episode_steps=4), 9)
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
        assert not np.array_equal(a[0], c[0])


def test_env_i_is_seeded_with_seed_plus_i() -> None:
    obs = make_vector_env("Pendulum-v1", 3, seed=20).reset()[0]
    for i in range(3):
        np.testing.assert_array_equal(obs[i], make_vector_env("Pendulum-v1", 1, seed=20 + i).reset()[0][0])
    assert len({tuple(row) for row in obs.tolist()}) == 3


def test_reset_with_a_seed_reseeds_every_env() -> None:
    venv = make_vector_env("Pendulum-v1", 2, seed=None)
    first = venv.reset(seed=5)[0]
    venv.step(np.zeros((2, 1), np.float32))
    np.testing.assert_array_equal(venv.reset(seed=5)[0], first)
    np.testing.assert_array_equal(first, make_vector_env("Pendulum-v1", 2, seed=5).reset()[0])


def test_unseeded_envs_differ() -> None:
    a = make_vector_env("asac/Chain-v0", 2, seed=None).reset()[0]
    b = make_vector_env("asac/Chain-v0", 2, seed=None).reset()[0]
    assert not np.array_equal(a, b) and a[0, 2] != a[1, 2]


# --- sensors and arrays -------------------------------------------------------------------------


def test_dict_sensors_come_sorted_with_their_dtypes() -> None:
    venv = make_vector_env("asac/DictChain-v0", 2, seed=0, env_kwargs={"image": True})
    assert [s.name for s in venv.spec.sensors] == ["counter", "image", "state"]
    counter, image, state = venv.reset()
    assert counter.shape == (2, 2) and counter.dtype == np.float32
    assert image.shape == (2, 8, 8, 3) and image.dtype == np.uint8
    assert state.shape == (2, 3) and state.dtype == np.float32
    step = venv.step(np.zeros((2, 3), np.float32))
    assert step.obs[0].tolist() == [[0.0, 1.0], [0.0, 1.0]] and np.all(step.obs[1] == 1)
    assert [a.shape for a in step.final_obs] == [(2, 2), (2, 8, 8, 3), (2, 3)]


def test_tuple_sensors_keep_item_order() -> None:
    venv = make_vector_env("asac/TupleChain-v0", 2, seed=0)
    counter, x = venv.reset()
    assert counter.shape == (2, 2) and x.shape == (2, 1)
    assert counter.tolist() == [[0.0, 0.0], [0.0, 0.0]]


def test_returned_arrays_are_fresh() -> None:
    venv = chain(2, max_episode_steps=2)
    obs = venv.reset()
    first = venv.step(np.zeros((2, 1), np.float32))
    kept = [a.copy() for a in first.obs + first.final_obs]
    assert first.obs[0] is not first.final_obs[0] and first.obs[0] is not obs[0]
    first.obs[0][:] = -99.0  # a caller scribbling on what it got changes nothing later
    second = venv.step(np.zeros((2, 1), np.float32))
    np.testing.assert_array_equal(first.final_obs[0], kept[1])
    assert counters(second.final_obs) == [[0.0, 2.0], [0.0, 2.0]]
    assert not np.shares_memory(second.obs[0], first.obs[0])


def test_reset_env_restarts_one_env_and_returns_unbatched_sensors() -> None:
    venv = make_vector_env("asac/DictChain-v0", 2, seed=0)
    venv.reset()
    venv.step(np.zeros((2, 3), np.float32))
    counter, state = venv.reset_env(0)
    assert counter.tolist() == [1.0, 0.0] and state.shape == (3,) and state.dtype == np.float32
    step = venv.step(np.zeros((2, 3), np.float32))
    assert step.obs[0].tolist() == [[1.0, 1.0], [0.0, 2.0]]
    with pytest.raises(IndexError, match="env index 2"):
        venv.reset_env(2)


def test_every_reset_passes_the_configured_reset_options() -> None:
    # reset_config reaches env.reset(options=...) at the first reset, a forced one and every
    # auto-reset (CartPole draws its start state from [low, high]).
    from envs.make import make_vector_env

    env = make_vector_env("CartPole-v1", 2, seed=0, reset_options={"low": 0.2, "high": 0.25})
    starts = [np.stack(env.reset(seed=0)[0])]
    starts.append(np.stack(env.reset_env(1)[0])[None])
    for _ in range(100):
        result = env.step(np.tile(np.array([[1.0, 0.0]], np.float32), (2, 1)))
        ended = result.terminated | result.truncated
        if ended.any():
            starts.append(result.obs[0][ended])
    assert len(starts) > 3  # auto-resets happened
    assert all(((s >= 0.2) & (s <= 0.25)).all() for s in starts), starts


def test_rng_states_put_into_a_new_vector_env_continue_the_stream_and_bad_ones_change_nothing() -> None:
    # What a checkpoint keeps of its envs (algorithm/run/learner_core.py, algorithm/run/trainer.py): a new
    # vector env given them resets as the first would have next, not as a fresh one does.
    first = make_vector_env("Pendulum-v1", 3, seed=5)
    never_reset = first.rng_states()
    assert never_reset == [{"seed": 5}, {"seed": 6}, {"seed": 7}]
    first.reset()
    first.reset()
    states = first.rng_states()
    expected = first.reset()
    second = make_vector_env("Pendulum-v1", 3, seed=5)
    fresh = make_vector_env("Pendulum-v1", 3, seed=5).reset()
    second.set_rng_states(states)
    got = second.reset()
    assert all(np.array_equal(a, b) for a, b in zip(got, expected, strict=True))
    assert not all(np.array_equal(a, b) for a, b in zip(got, fresh, strict=True))

    pending = make_vector_env("Pendulum-v1", 3, seed=9)
    pending.set_rng_states(never_reset)  # not reset yet: the first reset takes the saved seeds
    assert all(np.array_equal(a, b) for a, b in zip(pending.reset(), fresh, strict=True))

    third = make_vector_env("Pendulum-v1", 3, seed=5)
    with pytest.raises(ValueError, match="2 env RNG states for 3 envs"):
        third.set_rng_states(states[:2])
    with pytest.raises(ValueError, match="env 1's RNG state names no numpy bit generator: 'Nope'"):
        third.set_rng_states([states[0], {**states[1], "bit_generator": "Nope"}, states[2]])
    with pytest.raises(ValueError, match="env 2's RNG state does not fit a PCG64"):
        third.set_rng_states([states[0], states[1], {"bit_generator": "PCG64", "state": "x"}])
    assert all(np.array_equal(a, b) for a, b in zip(third.reset(), fresh, strict=True))  # unchanged
