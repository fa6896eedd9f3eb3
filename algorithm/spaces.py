"""Observation and action specs derived from gymnasium spaces (docs/architecture.md section 3).

Observations are a list of sensors in a fixed order: a ``Dict`` space contributes its keys in
sorted order, a ``Tuple`` space its items in order, any other ``Box`` one sensor. Vector sensors
are float32; images (rank-3 uint8 boxes) stay uint8 HWC until they reach the device.

Actions are one flat float vector ``[one-hot of each discrete branch | continuous in [-1, 1]]``.
:func:`to_env_action` is the only place that maps it back to what the env expects.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np


@dataclass(frozen=True)
class SensorSpec:
    """One observation sensor: its name, per-step shape and storage dtype."""

    name: str
    shape: tuple[int, ...]
    dtype: np.dtype = field(default_factory=lambda: np.dtype(np.float32))

    @property
    def is_image(self) -> bool:
        return len(self.shape) == 3 and self.dtype == np.uint8


@dataclass(frozen=True)
class ActionSpec:
    """Flat action layout: discrete branches (one-hot each) followed by continuous dims.

    ``low``/``high`` are the env's bounds for the continuous part; the model always works in
    [-1, 1] and :func:`to_env_action` rescales.
    """

    discrete_branches: tuple[int, ...] = ()
    continuous_dim: int = 0
    low: tuple[float, ...] = ()
    high: tuple[float, ...] = ()

    @property
    def discrete_size(self) -> int:
        return int(sum(self.discrete_branches))

    @property
    def size(self) -> int:
        return self.discrete_size + self.continuous_dim


ACTION_MASK_SENSOR = "action_mask"


@dataclass(frozen=True)
class EnvSpec:
    """Sensors and action layout of a task.

    A sensor named ``action_mask`` (``[sum(discrete_branches)]``, 1 = allowed) masks the discrete
    actions: they get probability 0 when acting, in targets and in the policy loss (rl_games'
    action masks). It stays an ordinary sensor too, so replay stores it and the networks see it.
    """

    sensors: tuple[SensorSpec, ...]
    action: ActionSpec

    def __post_init__(self) -> None:
        index = self.action_mask_index
        if index is None:
            return
        shape, expected = self.sensors[index].shape, (self.action.discrete_size,)
        if shape != expected:
            raise ValueError(
                f"sensor {ACTION_MASK_SENSOR!r} has shape {shape}, expected {expected}: one entry per discrete "
                f"action of the branches {self.action.discrete_branches}"
            )

    @property
    def action_mask_index(self) -> int | None:
        """Index of the ``action_mask`` sensor, or None when the task has no action mask."""
        return next((i for i, s in enumerate(self.sensors) if s.name == ACTION_MASK_SENSOR), None)


def sensor_specs(space: gym.Space) -> tuple[SensorSpec, ...]:
    """Sensors of a single (not batched) observation space, in the documented order."""
    if isinstance(space, gym.spaces.Dict):
        items: list[tuple[str, gym.Space]] = sorted(space.spaces.items())
    elif isinstance(space, gym.spaces.Tuple):
        items = [(f"obs{i}", s) for i, s in enumerate(space.spaces)]
    else:
        items = [("obs", space)]
    specs = []
    for name, sub in items:
        if not isinstance(sub, gym.spaces.Box):
            raise TypeError(f"observation sensor {name!r}: only Box spaces are supported, got {sub}")
        is_image = len(sub.shape) == 3 and sub.dtype == np.uint8
        dtype = np.dtype(np.uint8) if is_image else np.dtype(np.float32)
        specs.append(SensorSpec(name=name, shape=tuple(int(d) for d in sub.shape), dtype=dtype))
    return tuple(specs)


def action_spec(space: gym.Space) -> ActionSpec:
    """Flat action spec of a single action space (Box, Discrete, MultiDiscrete or a Tuple of them)."""
    parts = list(space.spaces) if isinstance(space, gym.spaces.Tuple) else [space]
    branches: list[int] = []
    low: list[float] = []
    high: list[float] = []
    for part in parts:
        if isinstance(part, (gym.spaces.Discrete, gym.spaces.MultiDiscrete)) and np.any(part.start != 0):
            # to_env_action gives argmax indices 0..n-1, which an env counting from start would misread
            raise ValueError(f"discrete action spaces must start at 0, got start={part.start} in {part}")
        if isinstance(part, gym.spaces.Discrete):
            branches.append(int(part.n))
        elif isinstance(part, gym.spaces.MultiDiscrete):
            branches.extend(int(n) for n in np.asarray(part.nvec).ravel())
        elif isinstance(part, gym.spaces.Box):
            if not (np.all(np.isfinite(part.low)) and np.all(np.isfinite(part.high))):
                raise ValueError(f"continuous action space needs finite bounds, got {part}")
            low.extend(float(x) for x in np.asarray(part.low).ravel())
            high.extend(float(x) for x in np.asarray(part.high).ravel())
        else:
            raise TypeError(f"unsupported action space {part}")
    if any(isinstance(p, gym.spaces.Box) for p in parts[:-1]):
        raise TypeError("a continuous Box must be the last item of a Tuple action space")
    return ActionSpec(tuple(branches), len(low), tuple(low), tuple(high))


def env_spec(observation_space: gym.Space, action_space: gym.Space) -> EnvSpec:
    return EnvSpec(sensor_specs(observation_space), action_spec(action_space))


def to_env_action(spec: ActionSpec, actions: np.ndarray) -> np.ndarray | tuple[np.ndarray, ...]:
    """Model actions ``[N, size]`` -> what a batched env takes.

    Continuous dims go from [-1, 1] to [low, high] (clipped); each discrete branch becomes the
    argmax of its one-hot block. Pure continuous -> ``[N, dim]`` float array; pure discrete with
    one branch -> ``[N]`` ints; several branches -> ``[N, n_branches]``; mixed -> a tuple.
    """
    actions = np.asarray(actions)
    if actions.ndim != 2 or actions.shape[1] != spec.size:
        raise ValueError(
            f"actions must have shape [N, {spec.size}] (discrete branches {spec.discrete_branches}, "
            f"{spec.continuous_dim} continuous dims), got {actions.shape}"
        )
    discrete = []
    start = 0
    for n in spec.discrete_branches:
        discrete.append(actions[:, start : start + n].argmax(axis=1))
        start += n
    continuous = None
    if spec.continuous_dim:
        low = np.asarray(spec.low, dtype=np.float32)
        high = np.asarray(spec.high, dtype=np.float32)
        # np.minimum/np.maximum instead of np.clip: same result, half the cost on the actor's hot path.
        unit = np.minimum(np.maximum(actions[:, start:], -1.0), 1.0)
        # the final clip: float32 rounding of low + (high - low) can overshoot high (low=-3, high=0.4)
        continuous = np.minimum(np.maximum(low + (unit + 1.0) * 0.5 * (high - low), low), high)
    if continuous is not None and not discrete:
        return continuous
    disc = discrete[0] if len(discrete) == 1 else np.stack(discrete, axis=1)
    if continuous is None:
        return disc
    return (disc, continuous)


def from_env_action(spec: ActionSpec, env_actions: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_env_action` for continuous actions (used by tests and demos)."""
    if spec.discrete_branches:
        raise NotImplementedError("from_env_action handles continuous actions only")
    low = np.asarray(spec.low, dtype=np.float32)
    high = np.asarray(spec.high, dtype=np.float32)
    return (2.0 * (np.asarray(env_actions, dtype=np.float32) - low) / (high - low) - 1.0).astype(np.float32)
