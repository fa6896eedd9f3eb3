"""A point that moves to a goal, observed only as a small rendered image.

Learning tests of image sensors need a task that is solvable from pixels alone by a small conv
net in a few tens of thousands of steps, with a known optimum. :class:`PixelPointEnv` provides
that:

- The point ``p`` and the goal ``g`` live in the square ``[-1, 1]^2``. At reset ``p`` is uniform
  in ``[-0.8, 0.8]^2`` and ``g = p + D * (cos phi, sin phi)`` with ``D = goal_distance`` (1.0)
  and ``phi`` uniform, redrawn until ``g`` also lies in ``[-0.8, 0.8]^2`` (all from the env's
  seeded ``np_random``). Every episode therefore starts exactly ``D`` from the goal.
- Action ``Box(-1, 1, (2,))``: a velocity, scaled down to unit length if it is longer, so the
  point moves ``p <- clip(p + step_size * a, -1, 1)``, at most ``step_size`` (0.1) per step in
  any direction.
- Reward: minus the distance to the goal after the move, ``-|p - g|``. Moving straight at the
  goal at full speed is optimal (it minimises every later distance at once), and an agent that
  dawdles or hovers next to the goal pays for it every step. (A progress reward, distance before
  minus after, would telescope: without a terminal bonus every policy's bootstrapped value would
  then be almost the same, leaving a learner only ``1 - gamma`` of signal.) The env never
  terminates; episodes end by the time limit (registered: 20 steps).
- Observation: ``uint8 [size, size, 3]`` (HWC, ``size`` 16 by default), black except for two
  Gaussian blobs (sigma ``0.75`` pixels, 255 at their centre) at the point (red channel) and at
  the goal (green channel). The blobs are anti-aliased, so moves smaller than a pixel change the
  image, and a conv net can locate both to better than a pixel. Rendering is numpy only.
  ``render_mode="rgb_array"`` returns the same image, scaled up 8x by pixel repetition.

Returns with the defaults over the registered 20 steps (random: mean over 20,000 seeded
episodes):

==================================================  ===============================================
policy                                              undiscounted return
==================================================  ===============================================
optimal: full speed straight at the goal            ``-4.5`` (``-(0.9 + 0.8 + ... + 0.1)``), at the
                                                    goal after 10 steps, then 0 per step
from the image only: steer from the red blob's      ``-4.50`` (300 episodes): the image holds all
intensity centroid towards the green one's          that a policy needs
zero action                                         ``-20`` (``-D`` per step)
uniform random actions                              ``-20.2`` (the point wanders about as far off)
==================================================  ===============================================

Learnable from pixels: a throwaway SAC (two stride-2 3x3 convs, 16 and 32 channels, a 50-wide
embedding, 64x64 heads, trained only for this check) went from ``-20`` to between ``-7.1`` and
``-8.2`` (deterministic evaluations every 2,500 steps) from 7,500 to 25,000 env steps, on one
seed: well clear of random, short of the optimum.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np

ARENA = 0.8  # start and goal are drawn inside [-ARENA, ARENA]^2
BLOB_SIGMA_PX = 0.75
RENDER_SCALE = 8


class PixelPointEnv(gym.Env[np.ndarray, np.ndarray]):
    """See the module docstring. All arguments are keyword-only ``env_kwargs``.

    Args:
        size: image height and width in pixels (>= 8).
        step_size: the most the point moves in one step.
        goal_distance: distance from the start to the goal, ``D``, in (0, 1.5] (longer ones
            rarely fit in the arena, and reset would redraw for long).
        render_mode: None or ``"rgb_array"``.
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        *,
        size: int = 16,
        step_size: float = 0.1,
        goal_distance: float = 1.0,
        render_mode: str | None = None,
    ) -> None:
        if size < 8:
            raise ValueError(f"PixelPointEnv: size must be >= 8, got {size}")
        if not step_size > 0.0:
            raise ValueError(f"PixelPointEnv: step_size must be > 0, got {step_size}")
        if not 0.0 < goal_distance <= 1.5:
            raise ValueError(f"PixelPointEnv: goal_distance must be in (0, 1.5], got {goal_distance}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"PixelPointEnv: render_mode {render_mode!r} is not supported")
        self.size = size
        self.step_size = step_size
        self.goal_distance = goal_distance
        self.render_mode = render_mode
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.observation_space = gym.spaces.Box(0, 255, (size, size, 3), np.uint8)
        # world coordinate of each pixel centre: x grows with the column, y with the row
        centres = (np.arange(size, dtype=np.float64) + 0.5) / size * 2.0 - 1.0
        self._centres = centres
        self._point = np.zeros(2, np.float64)
        self._goal = np.zeros(2, np.float64)

    @property
    def optimal_return(self) -> float:
        """Return of moving straight at the goal at full speed: ``-sum_k max(0, D - k * step_size)``
        over the ``ceil(D / step_size)`` steps it takes (a time limit at least that long)."""
        steps = math.ceil(self.goal_distance / self.step_size - 1e-9)
        return -sum(max(0.0, self.goal_distance - k * self.step_size) for k in range(1, steps + 1))

    @property
    def point(self) -> np.ndarray:
        """The point's position ``[x, y]`` (a copy), for scripted controllers and tests."""
        return self._point.copy()

    @property
    def goal(self) -> np.ndarray:
        """The goal's position ``[x, y]`` (a copy)."""
        return self._goal.copy()

    def distance(self) -> float:
        """Distance from the point to the goal."""
        return float(np.linalg.norm(self._goal - self._point))

    def _blob(self, xy: np.ndarray) -> np.ndarray:
        """``[size, size]`` float image of a Gaussian blob at world position ``xy``, peak 1."""
        sigma = BLOB_SIGMA_PX * 2.0 / self.size
        gx = np.exp(-0.5 * ((self._centres - xy[0]) / sigma) ** 2)
        gy = np.exp(-0.5 * ((self._centres - xy[1]) / sigma) ** 2)
        return gy[:, None] * gx[None, :]  # separable: rows follow y, columns x

    def _obs(self) -> np.ndarray:
        image = np.zeros((self.size, self.size, 3), np.uint8)
        image[..., 0] = np.rint(255.0 * self._blob(self._point))
        image[..., 1] = np.rint(255.0 * self._blob(self._goal))
        return image

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        while True:
            point = self.np_random.uniform(-ARENA, ARENA, 2)
            phi = self.np_random.uniform(0.0, 2.0 * np.pi)
            goal = point + self.goal_distance * np.array([np.cos(phi), np.sin(phi)])
            if np.all(np.abs(goal) <= ARENA):
                break
        self._point, self._goal = point, goal
        return self._obs(), {"distance": self.distance()}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        a = np.asarray(action, np.float32)
        if not self.action_space.contains(a):
            raise ValueError(f"PixelPointEnv: action {action!r} is outside {self.action_space}")
        velocity = a.astype(np.float64)
        norm = float(np.linalg.norm(velocity))
        if norm > 1.0:
            velocity /= norm
        self._point = np.clip(self._point + self.step_size * velocity, -1.0, 1.0)
        distance = self.distance()
        return self._obs(), -distance, False, False, {"distance": distance}

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        return np.repeat(np.repeat(self._obs(), RENDER_SCALE, axis=0), RENDER_SCALE, axis=1)
