"""Pendulum-v1 with bad numbers at fixed steps, for the non-finite fault tests. Importing this module
registers ``asac_test/FaultyPendulum-v0`` (the build path ``tests.fault_envs:asac_test/FaultyPendulum-v0``
imports it in every role process); episodes are 200 steps, as Pendulum-v1's.

Each env counts its episodes ``e = 0, 1, 2, ...`` and the steps ``t = 1..200`` of each:

- ``e % 3 == 1``: the reward of step ``NAN_REWARD_STEP`` is NaN;
- ``e % 3 == 2``: the observation after step 200 (the episode's final observation, which no policy
  acts on: the next one is a reset's) is NaN;
- ``e % 3 == 0`` and ``e > 0``: the reward of step ``HUGE_REWARD_STEP`` is ``HUGE_REWARD``: finite, so it
  is stored, and so large that a learner's squared TD error overflows to inf.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

EPISODE_STEPS = 200
NAN_REWARD_STEP = 60
HUGE_REWARD_STEP = 120
HUGE_REWARD = 1e30
ENV_ID = "asac_test/FaultyPendulum-v0"
BUILD_PATH = f"tests.fault_envs:{ENV_ID}"


class FaultyPendulum(gym.Wrapper[np.ndarray, np.ndarray, np.ndarray, np.ndarray]):
    """See the module docstring."""

    def __init__(self, env: gym.Env[np.ndarray, np.ndarray]) -> None:
        super().__init__(env)
        self.episode, self.t = -1, 0

    def reset(self, **kwargs: Any) -> tuple[np.ndarray, dict[str, Any]]:
        self.episode, self.t = self.episode + 1, 0
        return self.env.reset(**kwargs)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.t += 1
        kind = self.episode % 3
        if kind == 1 and self.t == NAN_REWARD_STEP:
            reward = float("nan")
        elif kind == 2 and self.t == EPISODE_STEPS:
            obs = np.full_like(obs, np.nan)
        elif kind == 0 and self.episode > 0 and self.t == HUGE_REWARD_STEP:
            reward = HUGE_REWARD
        return obs, float(reward), terminated, truncated, info


def faulty_pendulum(**kwargs: Any) -> gym.Env[np.ndarray, np.ndarray]:
    from gymnasium.envs.classic_control.pendulum import PendulumEnv

    return FaultyPendulum(PendulumEnv(**kwargs))


def dropped_steps(env_steps: int, chunk_length: int, flushed: bool) -> int:
    """Steps a one-env actor drops after ``env_steps`` steps with chunks of ``chunk_length`` steps (a
    divisor of 200): per completed episode with a NaN, the one chunk that holds it; in the episode
    under way, the chunk with the NaN reward once completed, or, when the actor stopped and handed in
    its open chunk (``flushed``), that open chunk if it holds the NaN reward already."""
    episodes, t = divmod(env_steps, EPISODE_STEPS)
    bad = sum(1 for e in range(episodes) if e % 3 in (1, 2))
    start = (NAN_REWARD_STEP - 1) // chunk_length * chunk_length  # first step of the NaN reward's chunk
    end = start + chunk_length
    extra = 0
    if episodes % 3 == 1:
        if t >= end:
            extra = chunk_length
        elif flushed and t >= NAN_REWARD_STEP:
            extra = t - start
    return bad * chunk_length + extra


gym.register(ENV_ID, entry_point=faulty_pendulum, max_episode_steps=EPISODE_STEPS)
