"""algorithm/spaces.py: sensor order and dtypes, flat action layout, model <-> env action scaling."""

from __future__ import annotations

from collections import OrderedDict

import gymnasium as gym
import numpy as np
import pytest

from algorithm.spaces import (
    ActionSpec,
    SensorSpec,
    action_spec,
    env_spec,
    from_env_action,
    sensor_specs,
    to_env_action,
)

Box = gym.spaces.Box


# --- sensors -----------------------------------------------------------------------------------


def test_box_is_one_float32_sensor_even_when_float64() -> None:
    (spec,) = sensor_specs(Box(-1.0, 1.0, (17,), np.float64))
    assert spec == SensorSpec("obs", (17,), np.dtype(np.float32))
    assert not spec.is_image


def test_dict_sensors_come_in_sorted_key_order_whatever_the_insertion_order() -> None:
    space = gym.spaces.Dict(
        OrderedDict(zeta=Box(0, 1, (1,)), alpha=Box(0, 1, (2,)), mid=Box(0, 255, (4, 5, 3), np.uint8))
    )
    assert list(space.spaces) == ["zeta", "alpha", "mid"]  # gymnasium keeps the OrderedDict order
    specs = sensor_specs(space)
    assert [s.name for s in specs] == ["alpha", "mid", "zeta"]
    assert [s.shape for s in specs] == [(2,), (4, 5, 3), (1,)]


def test_tuple_sensors_keep_item_order() -> None:
    specs = sensor_specs(gym.spaces.Tuple((Box(0, 1, (3,)), Box(0, 1, (1,)))))
    assert [(s.name, s.shape) for s in specs] == [("obs0", (3,)), ("obs1", (1,))]


def test_rank3_uint8_is_an_image_and_stays_uint8_but_rank3_float_is_not() -> None:
    (image,) = sensor_specs(Box(0, 255, (84, 84, 3), np.uint8))
    assert image.is_image and image.dtype == np.uint8
    (volume,) = sensor_specs(Box(0.0, 1.0, (4, 4, 3), np.float32))
    assert not volume.is_image and volume.dtype == np.float32
    (flat_bytes,) = sensor_specs(Box(0, 255, (7,), np.uint8))
    assert flat_bytes.dtype == np.float32


def test_non_box_sensor_is_rejected_by_name() -> None:
    with pytest.raises(TypeError, match="'cell'"):
        sensor_specs(gym.spaces.Dict({"position": Box(0, 1, (2,)), "cell": gym.spaces.Discrete(4)}))


# --- action layout -----------------------------------------------------------------------------


def test_box_action_spec_keeps_bounds() -> None:
    spec = action_spec(Box(np.array([-2.0, 0.0], np.float32), np.array([2.0, 5.0], np.float32)))
    assert spec == ActionSpec((), 2, (-2.0, 0.0), (2.0, 5.0))
    assert spec.size == 2 and spec.discrete_size == 0


def test_discrete_and_multidiscrete_become_branches() -> None:
    assert action_spec(gym.spaces.Discrete(4)).discrete_branches == (4,)
    spec = action_spec(gym.spaces.MultiDiscrete([2, 3]))
    assert spec.discrete_branches == (2, 3) and spec.size == 5 and spec.continuous_dim == 0


def test_mixed_tuple_puts_discrete_first() -> None:
    spec = action_spec(gym.spaces.Tuple((gym.spaces.Discrete(3), Box(-1.0, 1.0, (2,)))))
    assert spec.discrete_branches == (3,) and spec.continuous_dim == 2 and spec.size == 5


def test_box_before_discrete_in_a_tuple_is_rejected() -> None:
    with pytest.raises(TypeError, match="last item"):
        action_spec(gym.spaces.Tuple((Box(-1.0, 1.0, (2,)), gym.spaces.Discrete(3))))


def test_unbounded_continuous_action_is_rejected() -> None:
    with pytest.raises(ValueError, match="finite bounds"):
        action_spec(Box(-np.inf, np.inf, (2,)))


def test_discrete_with_nonzero_start_is_rejected() -> None:
    # argmax of a one-hot block gives 0..n-1; an env counting from ``start`` would get wrong actions
    with pytest.raises(ValueError, match="start"):
        action_spec(gym.spaces.Discrete(3, start=-1))
    with pytest.raises(ValueError, match="start"):
        action_spec(gym.spaces.MultiDiscrete([2, 3], start=[0, 1]))


def test_unsupported_action_space_is_rejected() -> None:
    with pytest.raises(TypeError, match="unsupported action space"):
        action_spec(gym.spaces.MultiBinary(3))


def test_env_spec_combines_both() -> None:
    spec = env_spec(Box(-1.0, 1.0, (3,)), gym.spaces.Discrete(2))
    assert spec.sensors[0].shape == (3,) and spec.action.discrete_branches == (2,)


# --- model <-> env actions ---------------------------------------------------------------------


def test_continuous_scaling_maps_unit_interval_onto_bounds() -> None:
    spec = ActionSpec((), 2, (-2.0, 0.0), (2.0, 10.0))
    out = to_env_action(spec, np.array([[-1.0, -1.0], [0.0, 0.0], [1.0, 1.0], [0.5, -0.5]], np.float32))
    assert isinstance(out, np.ndarray)
    np.testing.assert_allclose(out, [[-2.0, 0.0], [0.0, 5.0], [2.0, 10.0], [1.0, 2.5]], atol=1e-6)


def test_out_of_range_model_actions_are_clipped_to_bounds() -> None:
    spec = ActionSpec((), 1, (-3.0,), (0.5,))
    out = to_env_action(spec, np.array([[7.0], [-7.0]], np.float32))
    np.testing.assert_array_equal(out, np.array([[0.5], [-3.0]], np.float32))


def test_scaled_actions_never_leave_float32_bounds() -> None:
    # float32 rounding of low + (high - low) overshoots high for e.g. low=-3, high=0.4; envs that
    # check ``action_space.contains`` would reject such an action.
    rng = np.random.default_rng(0)
    low = np.float32(rng.uniform(-5.0, 0.0, 64))
    high = np.float32(rng.uniform(0.05, 5.0, 64))
    space = Box(low, high, dtype=np.float32)
    spec = action_spec(space)
    for unit in (-1.0, 1.0, 5.0, -5.0):
        out = to_env_action(spec, np.full((1, 64), unit, np.float32))
        assert isinstance(out, np.ndarray)
        assert space.contains(out[0]), f"unit action {unit} left the bounds"
    out = to_env_action(spec, rng.uniform(-1.0, 1.0, (100, 64)).astype(np.float32))
    assert isinstance(out, np.ndarray)
    assert all(space.contains(row) for row in out)


def test_round_trip_through_env_space() -> None:
    rng = np.random.default_rng(1)
    low = rng.uniform(-10.0, 0.0, 5).astype(np.float32)
    high = low + rng.uniform(0.1, 20.0, 5).astype(np.float32)
    spec = action_spec(Box(low, high, dtype=np.float32))
    model = rng.uniform(-1.0, 1.0, (50, 5)).astype(np.float32)
    env = to_env_action(spec, model)
    assert isinstance(env, np.ndarray)
    np.testing.assert_allclose(from_env_action(spec, env), model, atol=1e-5)
    np.testing.assert_allclose(to_env_action(spec, from_env_action(spec, env)), env, rtol=1e-5, atol=1e-5)


def test_from_env_action_refuses_discrete_specs() -> None:
    with pytest.raises(NotImplementedError):
        from_env_action(ActionSpec((2,), 0), np.zeros((1, 2)))


def test_discrete_branches_are_argmax_of_their_one_hot_block() -> None:
    single = to_env_action(ActionSpec((3,), 0), np.array([[0, 0, 1], [1, 0, 0]], np.float32))
    np.testing.assert_array_equal(single, [2, 0])
    several = to_env_action(ActionSpec((2, 3), 0), np.array([[0, 1, 0, 1, 0], [1, 0, 0, 0, 1]], np.float32))
    np.testing.assert_array_equal(several, [[1, 1], [0, 2]])


def test_mixed_actions_give_discrete_and_scaled_continuous() -> None:
    spec = ActionSpec((2,), 1, (0.0,), (4.0,))
    out = to_env_action(spec, np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 1.0]], np.float32))
    assert isinstance(out, tuple)
    discrete, continuous = out
    np.testing.assert_array_equal(discrete, [1, 0])
    np.testing.assert_allclose(continuous, [[2.0], [4.0]])


@pytest.mark.parametrize("shape", [(4, 1), (4, 3), (2,), (1, 2, 1)])
def test_actions_of_the_wrong_shape_are_rejected(shape: tuple[int, ...]) -> None:
    # a [N, 1] array would otherwise broadcast silently against two continuous dims
    with pytest.raises(ValueError, match="shape"):
        to_env_action(ActionSpec((), 2, (-1.0, -1.0), (1.0, 1.0)), np.zeros(shape, np.float32))
