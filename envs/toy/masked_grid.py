"""A grid walk whose invalid actions are fatal, with the valid-action mask in the observation.

Learning tests of discrete SAC with action masks need a task where ignoring the mask is
punished at once and reading it is enough to act well. :class:`MaskedGridEnv` provides that:

- The agent walks on a ``size x size`` grid from the top-left cell ``(0, 0)`` to the goal, the
  bottom-right cell ``(size - 1, size - 1)``. Actions ``Discrete(4)``: 0 up (row - 1),
  1 right (col + 1), 2 down (row + 1), 3 left (col - 1).
- Before every decision the env draws the mask from its seeded ``np_random``: moves off the grid
  are invalid, and every on-grid move is invalid with probability ``hazard_prob``, independently;
  if that left no *progress* move (one that brings the agent closer to the goal, Manhattan
  distance), one of them, chosen uniformly, is made valid again. So a progress move is always
  allowed (before the goal), the mask changes from step to step and cell to cell, and it cannot
  be memorised from the position: an agent has to read it.
- Taking an invalid action: reward ``-10``, ``terminated=True``, the agent does not move.
- A valid move: reward ``+1`` if it brings the agent closer to the goal, ``-2`` if it takes it
  farther away (on a grid every move does one or the other; the asymmetry makes a detour a net
  loss, so wandering scores clearly below the optimum). Reaching the goal terminates.

Observation: ``Dict(action_mask=Box(0, 1, (4,)), position=Box(0, 1, (2,)))``, float32, with
``action_mask[a] = 1`` where action ``a`` is allowed and ``position = [row, col] / (size - 1)``.
Sensors in sorted order: ``action_mask``, then ``position``. ``info["distance"]`` is the
Manhattan distance to the goal; a step's ``info["invalid"]`` says whether it was fatal.

Returns with the defaults (``size=5``, ``hazard_prob=0.5``) and the registered time limit of 20
steps, means over 20,000 seeded episodes:

==========================================  ========================================================
policy                                      undiscounted return
==========================================  ========================================================
optimal: any allowed progress move          ``+8`` (``2 * (size - 1)``), goal in 8 steps, every time
uniform over the allowed actions            ``+1.30``; reaches the goal in 56% of episodes
uniform over all 4 actions (mask ignored)   ``-9.67``; an invalid action after 1.6 steps on average
==========================================  ========================================================

An optimal policy needs only the mask: take action 1 (right) or 2 (down) when allowed (they are
the progress moves from anywhere on the grid, and one of them is always allowed before the goal).
Learnable: a throwaway double DQN with a 64x64 MLP on ``[action_mask, position]`` (trained only
for this check, epsilon-greedy over all four actions, so it learned the mask from the penalty)
scored the optimum at its first evaluation, after 2,500 env steps, and kept it to 15,000.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

N_ACTIONS = 4
# (d_row, d_col) of actions 0 up, 1 right, 2 down, 3 left
MOVES = np.array([[-1, 0], [0, 1], [1, 0], [0, -1]], dtype=np.int64)
INVALID_PENALTY = -10.0
CLOSER_REWARD = 1.0
AWAY_PENALTY = -2.0


class MaskedGridEnv(gym.Env[Any, Any]):
    """See the module docstring. All arguments are keyword-only ``env_kwargs``.

    Args:
        size: side of the square grid (>= 2); the optimal return is ``2 * (size - 1)``.
        hazard_prob: probability that an on-grid move is masked at a step, in [0, 1]. 0 masks
            only moves off the grid; 1 leaves exactly one allowed action per step (a progress
            move).
        render_mode: accepted for gymnasium compatibility; only None is supported.
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, *, size: int = 5, hazard_prob: float = 0.5, render_mode: str | None = None) -> None:
        if size < 2:
            raise ValueError(f"MaskedGridEnv: size must be >= 2, got {size}")
        if not 0.0 <= hazard_prob <= 1.0:
            raise ValueError(f"MaskedGridEnv: hazard_prob must be in [0, 1], got {hazard_prob}")
        if render_mode is not None:
            raise ValueError(f"MaskedGridEnv: render_mode {render_mode!r} is not supported")
        self.size = size
        self.hazard_prob = hazard_prob
        self.render_mode = render_mode
        self.action_space = gym.spaces.Discrete(N_ACTIONS)
        self.observation_space = gym.spaces.Dict(
            {
                "action_mask": gym.spaces.Box(0.0, 1.0, (N_ACTIONS,), np.float32),
                "position": gym.spaces.Box(0.0, 1.0, (2,), np.float32),
            }
        )
        self._goal = np.array([size - 1, size - 1], np.int64)
        self._pos = np.zeros(2, np.int64)
        self._mask = np.ones(N_ACTIONS, bool)

    @property
    def optimal_return(self) -> float:
        """Return of any policy that always takes a valid progress move."""
        return float(2 * (self.size - 1))

    def _distance(self, pos: np.ndarray) -> int:
        return int(np.abs(self._goal - pos).sum())

    def _draw_mask(self) -> np.ndarray:
        """Valid-action mask for the current cell; see the module docstring."""
        targets = self._pos + MOVES
        on_grid = np.all((targets >= 0) & (targets < self.size), axis=1)
        progress = np.flatnonzero(on_grid & (np.abs(self._goal - targets).sum(axis=1) < self._distance(self._pos)))
        mask = on_grid & (self.np_random.random(N_ACTIONS) >= self.hazard_prob)
        if len(progress) and not mask[progress].any():
            mask[progress[int(self.np_random.integers(len(progress)))]] = True
        elif not mask.any():  # at the goal: terminal, never acted on, but the mask must not be empty
            mask = on_grid
        return mask

    def _obs(self) -> dict[str, np.ndarray]:
        return {
            "action_mask": self._mask.astype(np.float32),
            "position": (self._pos / (self.size - 1)).astype(np.float32),
        }

    def action_masks(self) -> np.ndarray:
        """Current valid-action mask as bools (the same as the observation's ``action_mask``)."""
        return self._mask.copy()

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict]:
        super().reset(seed=seed)
        self._pos = np.zeros(2, np.int64)
        self._mask = self._draw_mask()
        return self._obs(), {"distance": self._distance(self._pos)}

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict]:
        if not self.action_space.contains(np.asarray(action, dtype=np.int64)):
            raise ValueError(f"MaskedGridEnv: action {action!r} is outside {self.action_space}")
        a = int(action)
        if not self._mask[a]:
            return self._obs(), INVALID_PENALTY, True, False, {"distance": self._distance(self._pos), "invalid": True}
        before = self._distance(self._pos)
        self._pos = self._pos + MOVES[a]
        after = self._distance(self._pos)
        reward = CLOSER_REWARD if after < before else AWAY_PENALTY
        terminated = after == 0
        self._mask = self._draw_mask()
        return self._obs(), reward, terminated, False, {"distance": after, "invalid": False}
