"""A tiny deterministic env whose observations say where they came from.

Tests of replay, actors and vector envs need to read, from any stored row, which episode and
step produced it, and to predict rewards exactly. :class:`ChainEnv` provides that:

- ``counter = [episode_index, t]``: ``episode_index`` counts this instance's resets from 0,
  ``t`` is the number of steps taken in the current episode (0 right after reset).
- ``x`` (``action_dim`` floats): ``x_0 ~ U(-1, 1)`` drawn from the env's seeded ``np_random``
  at reset (so seeds are observable), then ``x_{t+1} = x_t + a_t`` with ``a_t`` the env-space
  action (continuous), or ``x_{t+1} = x_t + index`` in every dim (discrete).
- reward ``r_t = t + sum(a_t)`` (continuous) or ``t + index`` (discrete), with ``t`` taken
  before the step.
- ``terminated`` is True on the step that makes ``t == terminate_at``; truncation comes only
  from a time limit (``max_episode_steps`` of :func:`envs.make.make_env`).

Observation layouts (``obs_mode``): ``"flat"``: one Box ``[episode_index, t, *x]``;
``"dict"``: ``{"state": x, "counter": [episode_index, t]}`` (declared in that unsorted order, so
tests see that sensors come out sorted: ``counter``, then ``state``), plus with ``image=True``
an ``"image"`` sensor, ``uint8 [8, 8, 3]`` filled with ``t % 256``; ``"tuple"``:
``(counter, x)`` in that order.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any, Literal

import gymnasium as gym
import numpy as np

ObsMode = Literal["flat", "dict", "tuple"]

IMAGE_SHAPE = (8, 8, 3)


class ChainEnv(gym.Env[Any, Any]):
    """See the module docstring. All arguments are keyword-only ``env_kwargs``.

    Args:
        terminate_at: step count at which the episode terminates; None never terminates.
        action_dim: number of continuous action dims, also the size of ``x``.
        action_low, action_high: continuous action bounds (the same for every dim); defaults
            are not [-1, 1] so that model-to-env scaling is visible.
        n_actions: if > 0, the action space is ``Discrete(n_actions)`` instead of a Box.
        obs_mode: ``"flat"``, ``"dict"`` or ``"tuple"`` (see the module docstring).
        image: add the uint8 image sensor (``obs_mode="dict"`` only).
        render_mode: accepted for gymnasium compatibility; only None is supported.
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(
        self,
        *,
        terminate_at: int | None = None,
        action_dim: int = 1,
        action_low: float = -2.0,
        action_high: float = 2.0,
        n_actions: int = 0,
        obs_mode: ObsMode = "flat",
        image: bool = False,
        render_mode: str | None = None,
    ) -> None:
        if terminate_at is not None and terminate_at < 1:
            raise ValueError(f"ChainEnv: terminate_at must be >= 1 or None, got {terminate_at}")
        if action_dim < 1:
            raise ValueError(f"ChainEnv: action_dim must be >= 1, got {action_dim}")
        if not action_low < action_high:
            raise ValueError(f"ChainEnv: need action_low < action_high, got {action_low}, {action_high}")
        if n_actions < 0:
            raise ValueError(f"ChainEnv: n_actions must be >= 0, got {n_actions}")
        if obs_mode not in ("flat", "dict", "tuple"):
            raise ValueError(f"ChainEnv: obs_mode must be 'flat', 'dict' or 'tuple', got {obs_mode!r}")
        if image and obs_mode != "dict":
            raise ValueError("ChainEnv: image=True needs obs_mode='dict'")
        if render_mode is not None:
            raise ValueError(f"ChainEnv: render_mode {render_mode!r} is not supported")
        self.terminate_at = terminate_at
        self.obs_mode = obs_mode
        self.image = image
        self.render_mode = render_mode
        if n_actions > 0:
            self.action_space = gym.spaces.Discrete(n_actions)
        else:
            self.action_space = gym.spaces.Box(action_low, action_high, (action_dim,), np.float32)
        counter = gym.spaces.Box(0.0, np.inf, (2,), np.float32)
        x_space = gym.spaces.Box(-np.inf, np.inf, (action_dim,), np.float32)
        if obs_mode == "flat":
            self.observation_space = gym.spaces.Box(-np.inf, np.inf, (2 + action_dim,), np.float32)
        elif obs_mode == "dict":
            spaces: OrderedDict[str, gym.Space[Any]] = OrderedDict(state=x_space, counter=counter)
            if image:
                spaces["image"] = gym.spaces.Box(0, 255, IMAGE_SHAPE, np.uint8)
            self.observation_space = gym.spaces.Dict(spaces)
        else:
            self.observation_space = gym.spaces.Tuple((counter, x_space))
        self._episode = -1
        self._t = 0
        self._x = np.zeros(action_dim, np.float32)

    def _obs(self) -> Any:
        counter = np.array([self._episode, self._t], np.float32)
        x = self._x.copy()
        if self.obs_mode == "flat":
            return np.concatenate([counter, x])
        if self.obs_mode == "tuple":
            return (counter, x)
        obs: dict[str, np.ndarray] = {"state": x, "counter": counter}
        if self.image:
            obs["image"] = np.full(IMAGE_SHAPE, self._t % 256, np.uint8)
        return obs

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        super().reset(seed=seed)
        self._episode += 1
        self._t = 0
        self._x = self.np_random.uniform(-1.0, 1.0, self._x.shape).astype(np.float32)
        return self._obs(), {}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        if not self.action_space.contains(np.asarray(action, dtype=self.action_space.dtype)):
            raise ValueError(f"ChainEnv: action {action!r} is outside {self.action_space}")
        if isinstance(self.action_space, gym.spaces.Discrete):
            value = float(int(action))
            self._x = self._x + np.float32(value)
        else:
            a = np.asarray(action, np.float32)
            value = float(a.sum())
            self._x = self._x + a
        reward = float(self._t) + value
        self._t += 1
        terminated = self.terminate_at is not None and self._t >= self.terminate_at
        return self._obs(), reward, terminated, False, {}
