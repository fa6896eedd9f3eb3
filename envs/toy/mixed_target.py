"""A one-step-at-a-time target task with a mixed discrete + continuous action.

Learning tests of hybrid action spaces need a task where both parts of a
``Tuple(Discrete(k), Box(-1, 1, (1,)))`` action matter and the best action is known exactly.
:class:`MixedTargetEnv` provides that:

- Each step the observation shows a target: ``[one_hot(choice) (k floats), value]`` with
  ``choice`` uniform in ``0..k-1`` and ``value`` uniform in ``[-1, 1]``, both drawn from the env's
  seeded ``np_random`` at reset and again after every step (each step is a fresh target, so the
  task is a contextual bandit stretched over an episode).
- Acting with ``(option, magnitude)`` earns ``r = 1[option == choice] * max(0, 1 - |magnitude -
  value|)``: up to 1 when both parts are right, 0 for a wrong option whatever the magnitude, and
  a right option with a magnitude off by ``e`` earns ``1 - e`` (0 once ``e >= 1``).
- The env never terminates; episodes end by the time limit (registered: 10 steps), as truncation.

The observation is laid out like the flat model action of :mod:`algorithm.spaces` (one-hot
branch, then the continuous dim in [-1, 1]), so the optimal model action is the observation itself.

Returns over the registered 10 steps with ``k = 3`` (means over 20,000 seeded episodes for the
random policies; the optimum is exact):

=====================================================  ====================================
policy                                                 undiscounted return
=====================================================  ====================================
optimal: ``(choice, value)``                           ``10`` (1 per step)
right option, magnitude 0                              ``5.0`` (``1 - E|value|`` per step)
uniform random (``action_space.sample()``)             ``1.40`` (``(1/k) * 5/12`` per step)
=====================================================  ====================================
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np


class MixedTargetEnv(gym.Env[Any, Any]):
    """See the module docstring. All arguments are keyword-only ``env_kwargs``.

    Args:
        n_options: ``k``, the size of the discrete part (>= 2).
        render_mode: accepted for gymnasium compatibility; only None is supported.
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, *, n_options: int = 3, render_mode: str | None = None) -> None:
        if n_options < 2:
            raise ValueError(f"MixedTargetEnv: n_options must be >= 2, got {n_options}")
        if render_mode is not None:
            raise ValueError(f"MixedTargetEnv: render_mode {render_mode!r} is not supported")
        self.n_options = n_options
        self.render_mode = render_mode
        self.action_space = gym.spaces.Tuple(
            (gym.spaces.Discrete(n_options), gym.spaces.Box(-1.0, 1.0, (1,), np.float32))
        )
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (n_options + 1,), np.float32)
        self._choice = 0
        self._value = 0.0

    def _draw_target(self) -> None:
        self._choice = int(self.np_random.integers(self.n_options))
        self._value = float(np.float32(self.np_random.uniform(-1.0, 1.0)))

    def _obs(self) -> np.ndarray:
        obs = np.zeros(self.n_options + 1, np.float32)
        obs[self._choice] = 1.0
        obs[-1] = self._value
        return obs

    def optimal_action(self) -> tuple[int, np.ndarray]:
        """The action that earns reward 1 for the target now shown."""
        return self._choice, np.array([self._value], np.float32)

    def _parse(self, action: Any) -> tuple[int, float]:
        """``(option, magnitude)`` of an action in the action space; anything else is a ``ValueError``."""
        try:
            option, magnitude = action
            mag = np.asarray(magnitude, np.float32)
        except (TypeError, ValueError) as err:
            raise ValueError(f"MixedTargetEnv: action {action!r} is not an (option, magnitude) pair") from err
        integral = np.ndim(option) == 0 and np.issubdtype(np.asarray(option).dtype, np.integer)
        if not integral or not self.action_space.contains((np.int64(option), mag)):
            raise ValueError(f"MixedTargetEnv: action {action!r} is outside {self.action_space}")
        return int(option), float(mag[0])

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self._draw_target()
        return self._obs(), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        option, mag = self._parse(action)
        correct = option == self._choice
        error = abs(mag - self._value)
        reward = max(0.0, 1.0 - error) if correct else 0.0
        info = {"correct_option": correct, "magnitude_error": error}
        self._draw_target()
        return self._obs(), reward, False, False, info
