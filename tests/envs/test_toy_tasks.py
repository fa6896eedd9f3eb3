"""envs/toy task envs (MaskedGrid, MixedTarget, PixelPoint) and the POMDP ids: gymnasium's checker,
seeding, the documented rewards and optima, and that algorithm/spaces and envs/make accept them."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.envs.registration import load_env_creator
from gymnasium.utils.env_checker import check_env

import envs.toy  # noqa: F401  (registers asac/*)
from algorithm.spaces import action_spec, env_spec, sensor_specs
from envs.make import make_env, make_vector_env
from envs.toy import MaskedGridEnv, MixedTargetEnv, PixelPointEnv
from envs.toy.masked_grid import INVALID_PENALTY
from envs.wrappers import HideVelocity

TASK_IDS = ["asac/MaskedGrid-v0", "asac/MixedTarget-v0", "asac/PixelPoint-v0"]
POMDP_IDS = ["asac/PendulumNoVel-v0", "asac/HalfCheetahNoVel-v0"]


def _bare(env_id: str) -> gym.Env[Any, Any]:
    """The registered entry point's env without gym.make's wrappers (what check_env wants)."""
    spec = gym.spec(env_id)
    assert isinstance(spec.entry_point, str)  # importable, not a callable object
    env = load_env_creator(spec.entry_point)(**spec.kwargs)
    assert isinstance(env, gym.Env)
    return env


def _rollout(env: gym.Env[Any, Any], seed: int, steps: int) -> list[Any]:
    """Observations and rewards of ``steps`` steps with actions from the seeded action space."""
    env.action_space.seed(seed)
    obs, _ = env.reset(seed=seed)
    out: list[Any] = [obs]
    for _ in range(steps):
        obs, reward, terminated, truncated, _ = env.step(env.action_space.sample())
        out += [obs, reward, terminated, truncated]
        if terminated or truncated:
            obs, _ = env.reset()
            out.append(obs)
    return out


def _same(a: list[Any], b: list[Any]) -> bool:
    return len(a) == len(b) and all(gym.utils.env_checker.data_equivalence(x, y) for x, y in zip(a, b, strict=True))


@pytest.mark.filterwarnings("error")  # the project's own envs: any checker warning is a failure
@pytest.mark.parametrize("env_id", TASK_IDS)
def test_gymnasium_env_checker_passes_without_a_warning(env_id: str) -> None:
    check_env(_bare(env_id), skip_render_check=True)


# The wrapped envs' own warnings only (Pendulum's [-2, 2] actions, MuJoCo's infinite observation bounds).
@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.parametrize("env_id", POMDP_IDS)
def test_gymnasium_env_checker_passes_on_the_velocity_hiding_wrappers(env_id: str) -> None:
    check_env(_bare(env_id), skip_render_check=True)


@pytest.mark.parametrize("env_id", TASK_IDS + ["asac/PendulumNoVel-v0"])
def test_same_seed_same_trajectory(env_id: str) -> None:
    first = _rollout(gym.make(env_id), seed=3, steps=25)
    assert _same(first, _rollout(gym.make(env_id), seed=3, steps=25))
    assert not _same(first, _rollout(gym.make(env_id), seed=4, steps=25))


def test_registered_time_limits() -> None:
    limits = {env_id: gym.spec(env_id).max_episode_steps for env_id in TASK_IDS + POMDP_IDS}
    assert limits == {
        "asac/MaskedGrid-v0": 20,
        "asac/MixedTarget-v0": 10,
        "asac/PixelPoint-v0": 20,
        "asac/PendulumNoVel-v0": gym.spec("Pendulum-v1").max_episode_steps,
        "asac/HalfCheetahNoVel-v0": gym.spec("HalfCheetah-v5").max_episode_steps,
    }


# --- algorithm/spaces and envs/make accept the spaces ----------------------------------------


def test_spaces_give_the_expected_sensors_and_actions() -> None:
    grid = gym.make("asac/MaskedGrid-v0")
    sensors = sensor_specs(grid.observation_space)
    assert [(s.name, s.shape, s.is_image) for s in sensors] == [("action_mask", (4,), False), ("position", (2,), False)]
    assert action_spec(grid.action_space).discrete_branches == (4,)

    mixed = action_spec(gym.make("asac/MixedTarget-v0").action_space)
    assert (mixed.discrete_branches, mixed.continuous_dim, mixed.low, mixed.high) == ((3,), 1, (-1.0,), (1.0,))

    pixel_env = gym.make("asac/PixelPoint-v0")
    pixel = env_spec(pixel_env.observation_space, pixel_env.action_space)
    assert len(pixel.sensors) == 1 and pixel.sensors[0].is_image and pixel.sensors[0].shape == (16, 16, 3)
    assert pixel.action.continuous_dim == 2 and not pixel.action.discrete_branches

    for env_id, dim in [("asac/PendulumNoVel-v0", 2), ("asac/HalfCheetahNoVel-v0", 8)]:
        (sensor,) = sensor_specs(gym.make(env_id).observation_space)
        assert sensor.shape == (dim,) and sensor.dtype == np.float32


def test_vector_env_steps_the_mixed_action_env_with_model_actions() -> None:
    venv = make_vector_env("asac/MixedTarget-v0", 2, seed=0)
    obs = venv.reset()[0]
    # the observation [one-hot option, value] is laid out like a model action [one-hot branch,
    # continuous in [-1, 1]] and the Box is [-1, 1]: it is the optimal model action
    step = venv.step(obs)
    np.testing.assert_allclose(step.rewards, 1.0, atol=1e-6)
    obs = step.obs[0]
    wrong_option = np.concatenate([np.roll(obs[:, :3], 1, axis=1), obs[:, 3:]], axis=1)
    assert venv.step(wrong_option).rewards.tolist() == [0.0, 0.0]


def test_make_env_builds_every_new_id() -> None:
    for env_id in TASK_IDS + ["asac/PendulumNoVel-v0"]:
        env = make_env(env_id, seed=0)
        obs, _ = env.reset()
        assert env.observation_space.contains(obs)


# --- MaskedGrid -------------------------------------------------------------------------------


def _optimal_grid_action(mask: np.ndarray) -> int:
    return 1 if mask[1] else 2  # right and down are the progress moves everywhere on the grid


def test_masked_grid_mask_always_allows_an_action_and_varies() -> None:
    env = gym.make("asac/MaskedGrid-v0")
    rng = np.random.default_rng(0)
    masks_at_origin: set[tuple[float, ...]] = set()
    masks: set[tuple[float, ...]] = set()
    obs, _ = env.reset(seed=0)
    for _ in range(600):
        mask = obs["action_mask"]
        assert mask.dtype == np.float32 and set(np.unique(mask)) <= {0.0, 1.0} and mask.sum() >= 1
        assert mask[1] or mask[2]  # a progress move is always allowed (start is never the goal)
        masks.add(tuple(mask))
        if not obs["position"].any():
            masks_at_origin.add(tuple(mask))
        obs, _, terminated, truncated, _ = env.step(int(rng.choice(np.flatnonzero(mask))))
        if terminated or truncated:
            obs, _ = env.reset()
    assert len(masks) >= 8  # depends on the cell and on the draw
    assert len(masks_at_origin) >= 2  # the same cell sees different masks
    assert all(m[0] == 0.0 and m[3] == 0.0 for m in masks_at_origin)  # off-grid moves are never allowed


def test_masked_grid_invalid_action_terminates_with_the_penalty() -> None:
    env = gym.make("asac/MaskedGrid-v0")
    obs, _ = env.reset(seed=1)
    invalid = int(np.flatnonzero(obs["action_mask"] == 0)[0])  # up and left are off the grid at the start
    next_obs, reward, terminated, truncated, info = env.step(invalid)
    assert (reward, terminated, truncated, info["invalid"]) == (INVALID_PENALTY, True, False, True)
    np.testing.assert_array_equal(next_obs["position"], obs["position"])


@pytest.mark.parametrize("seed", range(5))
def test_masked_grid_mask_respecting_script_reaches_the_optimum(seed: int) -> None:
    env = gym.make("asac/MaskedGrid-v0")
    obs, _ = env.reset(seed=seed)
    rewards: list[float] = []
    terminated = truncated = False
    while not (terminated or truncated):
        obs, reward, terminated, truncated, info = env.step(_optimal_grid_action(obs["action_mask"]))
        rewards.append(float(reward))
    assert terminated and not truncated and info["distance"] == 0
    assert rewards == [1.0] * 8 and sum(rewards) == env.unwrapped.optimal_return == 8.0  # type: ignore[attr-defined]
    np.testing.assert_array_equal(obs["position"], [1.0, 1.0])


def test_masked_grid_random_policies_score_well_below_the_optimum() -> None:
    env = gym.make("asac/MaskedGrid-v0")
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    respecting: list[float] = []
    ignoring: list[float] = []
    for returns, respect in [(respecting, True), (ignoring, False)]:
        for _ in range(150):
            obs, _ = env.reset()
            total, done = 0.0, False
            while not done:
                mask = obs["action_mask"]
                action = int(rng.choice(np.flatnonzero(mask))) if respect else int(rng.integers(4))
                obs, reward, terminated, truncated, _ = env.step(action)
                total += float(reward)
                done = terminated or truncated
            returns.append(total)
    assert np.mean(respecting) < 3.0  # documented: +1.30
    assert np.mean(ignoring) < -8.0  # documented: -9.67


def test_masked_grid_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="size"):
        MaskedGridEnv(size=1)
    with pytest.raises(ValueError, match="hazard_prob"):
        MaskedGridEnv(hazard_prob=1.5)
    env = MaskedGridEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="outside"):
        env.step(4)


def test_masked_grid_hazard_one_leaves_exactly_one_action() -> None:
    env = MaskedGridEnv(hazard_prob=1.0)
    obs, _ = env.reset(seed=0)
    for _ in range(8):
        assert obs["action_mask"].sum() == 1
        obs, reward, *_ = env.step(int(np.argmax(obs["action_mask"])))
        assert reward == 1.0


# --- MixedTarget ------------------------------------------------------------------------------


def test_mixed_target_scripted_optimum_earns_the_documented_maximum() -> None:
    env = gym.make("asac/MixedTarget-v0")
    obs, _ = env.reset(seed=0)
    rewards: list[float] = []
    flags = []
    for _ in range(10):
        option, value = int(np.argmax(obs[:3])), obs[3:].copy()
        obs, reward, terminated, truncated, _ = env.step((option, value))
        rewards.append(float(reward))
        flags.append((terminated, truncated))
    assert sum(rewards) == pytest.approx(10.0)
    assert flags == [(False, False)] * 9 + [(False, True)]  # time limit: truncation, never termination


def test_mixed_target_rewards_need_both_parts_right() -> None:
    env = MixedTargetEnv()
    obs, _ = env.reset(seed=0)
    for i in range(16):
        option, value = int(np.argmax(obs[:3])), float(obs[3])
        toward_zero = value - 0.5 * np.sign(value)  # off by 0.5, still inside [-1, 1]
        far = -np.sign(value) or 1.0  # off by 1 + |value| >= 1
        act, magnitude, expected = [
            ((option + 1) % 3, value, 0.0),  # wrong option, right magnitude
            (option, value, 1.0),
            (option, toward_zero, 0.5),
            (option, far, 0.0),
        ][i % 4]
        obs, reward, terminated, _, info = env.step((act, np.array([magnitude], np.float32)))
        assert reward == pytest.approx(expected, abs=1e-6) and not terminated
        assert info["correct_option"] == (act == option)


def test_mixed_target_rejects_malformed_actions() -> None:
    env = MixedTargetEnv()
    env.reset(seed=0)
    for bad in [3, (3, np.zeros(1, np.float32)), (0, np.array([1.5], np.float32)), (0.5, np.zeros(1, np.float32))]:
        with pytest.raises(ValueError):
            env.step(bad)
    with pytest.raises(ValueError, match="n_options"):
        MixedTargetEnv(n_options=1)


def test_mixed_target_random_policy_is_far_below_the_optimum() -> None:
    env = gym.make("asac/MixedTarget-v0")
    env.action_space.seed(0)
    env.reset(seed=0)
    returns = []
    for _ in range(100):
        env.reset()
        returns.append(sum(float(env.step(env.action_space.sample())[1]) for _ in range(10)))
    assert 0.8 < np.mean(returns) < 2.0  # documented: 1.40


# --- PixelPoint -------------------------------------------------------------------------------


def _greedy(env: PixelPointEnv) -> np.ndarray:
    """Full speed straight at the goal, from the env's internal state."""
    direction = (env.goal - env.point) / env.step_size
    return (direction / max(1.0, float(np.linalg.norm(direction)))).astype(np.float32)


def test_pixel_point_image_is_uint8_hwc_and_follows_the_state() -> None:
    env = PixelPointEnv()
    image, info = env.reset(seed=0)
    assert image.shape == (16, 16, 3) and image.dtype == np.uint8
    assert info["distance"] == pytest.approx(1.0)
    # a blob's brightest pixel is at most half a pixel off its centre in each axis: >= 255 * exp(-4/9)
    assert image[..., 2].max() == 0 and image[..., 0].max() >= 160 and image[..., 1].max() >= 160

    def pixel(xy: np.ndarray) -> tuple[int, int]:  # (row, col) of a world position
        col, row = np.clip(((xy + 1.0) / 2.0 * 16).astype(int), 0, 15)
        return int(row), int(col)

    assert np.unravel_index(np.argmax(image[..., 0]), (16, 16)) == pixel(env.point)
    assert np.unravel_index(np.argmax(image[..., 1]), (16, 16)) == pixel(env.goal)
    moved, *_ = env.step(np.array([0.3, 0.0], np.float32))  # a third of a pixel
    assert not np.array_equal(moved[..., 0], image[..., 0])
    np.testing.assert_array_equal(moved[..., 1], image[..., 1])  # the goal stays
    still, reward, *_ = env.step(np.zeros(2, np.float32))
    np.testing.assert_array_equal(still, moved)
    assert reward == -env.distance() < 0.0


@pytest.mark.parametrize("seed", range(4))
def test_pixel_point_greedy_controller_reaches_the_goal(seed: int) -> None:
    env = gym.make("asac/PixelPoint-v0")
    inner = env.unwrapped
    assert isinstance(inner, PixelPointEnv)
    env.reset(seed=seed)
    total, steps = 0.0, 0
    while inner.distance() > 1e-6:
        _, reward, terminated, truncated, info = env.step(_greedy(inner))
        total, steps = total + float(reward), steps + 1
        assert not terminated and not truncated
    assert steps == 10 and total == pytest.approx(inner.optimal_return) and inner.optimal_return == pytest.approx(-4.5)
    image, reward, *_ = env.step(_greedy(inner))  # at the goal: stays there, at no cost
    assert reward == pytest.approx(0.0, abs=1e-6)
    assert np.unravel_index(np.argmax(image[..., 0]), (16, 16)) == np.unravel_index(np.argmax(image[..., 1]), (16, 16))


def test_pixel_point_optimal_return_formula_matches_the_greedy_controller() -> None:
    env = PixelPointEnv(goal_distance=0.25)  # not a multiple of the step: distances 0.15, 0.05, 0
    env.reset(seed=0)
    total = sum(float(env.step(_greedy(env))[1]) for _ in range(5))
    assert total == pytest.approx(env.optimal_return) and env.optimal_return == pytest.approx(-0.2)


def test_pixel_point_long_actions_are_cut_to_unit_speed_and_walls_hold() -> None:
    env = PixelPointEnv()
    env.reset(seed=0)
    start = env.point
    env.step(np.array([1.0, 1.0], np.float32))
    assert np.linalg.norm(env.point - start) == pytest.approx(0.1)
    for _ in range(30):
        env.step(np.array([-1.0, 0.0], np.float32))
    assert env.point[0] == -1.0
    with pytest.raises(ValueError, match="outside"):
        env.step(np.array([2.0, 0.0], np.float32))


def test_pixel_point_renders_rgb_array_and_other_sizes() -> None:
    env = PixelPointEnv(size=24, render_mode="rgb_array")
    image, _ = env.reset(seed=0)
    assert image.shape == (24, 24, 3)
    frame = env.render()
    assert frame is not None and frame.shape == (24 * 8, 24 * 8, 3) and frame.dtype == np.uint8
    with pytest.raises(ValueError, match="size"):
        PixelPointEnv(size=4)


# --- HideVelocity and the POMDP ids -------------------------------------------------------------


@pytest.mark.parametrize(
    ("env_id", "base_id", "keep"),
    [("asac/PendulumNoVel-v0", "Pendulum-v1", [0, 1]), ("asac/HalfCheetahNoVel-v0", "HalfCheetah-v5", range(8))],
)
def test_pomdp_ids_observe_the_kept_entries_of_the_original(env_id: str, base_id: str, keep: Any) -> None:
    hidden, full = gym.make(env_id), gym.make(base_id)
    assert hidden.observation_space.shape == (len(keep),) and hidden.observation_space.dtype == np.float32
    assert hidden.action_space == full.action_space
    hidden.action_space.seed(0)
    obs_h, _ = hidden.reset(seed=5)
    obs_f, _ = full.reset(seed=5)
    for _ in range(5):
        assert obs_h.dtype == np.float32
        np.testing.assert_array_equal(obs_h, obs_f[list(keep)].astype(np.float32))
        action = hidden.action_space.sample()
        obs_h, r_h, *_ = hidden.step(action)
        obs_f, r_f, *_ = full.step(action)
        assert r_h == r_f


def test_half_cheetah_positions_are_the_first_eight_entries() -> None:
    env = _bare("asac/HalfCheetahNoVel-v0")
    assert isinstance(env, HideVelocity)
    assert env.unwrapped.observation_structure == {"skipped_qpos": 1, "qpos": 8, "qvel": 9}  # type: ignore[attr-defined]
    assert env.keep.tolist() == list(range(8))


def test_hide_velocity_keeps_bounds_order_and_rejects_bad_indices() -> None:
    base = gym.make("Pendulum-v1")
    wrapped = HideVelocity(base, keep=[2, 0])
    assert isinstance(wrapped.observation_space, gym.spaces.Box)
    np.testing.assert_array_equal(wrapped.observation_space.low, [-8.0, -1.0])
    obs, _ = wrapped.reset(seed=0)
    raw = wrapped.unwrapped._get_obs()  # type: ignore[attr-defined]
    np.testing.assert_array_equal(obs, raw[[2, 0]])
    assert HideVelocity(base, keep=[-1]).keep.tolist() == [2]
    for bad, match in [([], "at least one"), ([3], "outside"), ([0, -3], "twice")]:
        with pytest.raises(ValueError, match=match):
            HideVelocity(base, keep=bad)
    with pytest.raises(TypeError, match="one-dimensional Box"):
        HideVelocity(gym.make("asac/PixelPoint-v0"), keep=[0])
