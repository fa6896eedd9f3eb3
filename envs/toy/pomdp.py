"""Partially observed versions of standard control tasks: the velocities are hidden.

Factories for the ids registered in :mod:`envs.toy` (``asac/PendulumNoVel-v0``,
``asac/HalfCheetahNoVel-v0``). Each builds the underlying env class directly, without its own
registered time limit, and wraps it in :class:`envs.wrappers.HideVelocity`; gymnasium then adds
the ``asac/`` id's time limit around the result (the same as the original's, so episodes match
the fully observed task step for step). The gymnasium env classes are imported inside the
factories, so importing :mod:`envs.toy` does not load MuJoCo.

- ``PendulumNoVel``: Pendulum-v1 observes ``[cos(theta), sin(theta), theta_dot]``; keep the
  first two.
- ``HalfCheetahNoVel``: HalfCheetah-v5 observes ``qpos`` (without ``rootx`` by default: 8
  entries, ``rootz``, ``rooty`` and six joint angles) then ``qvel`` (9 entries); keep the
  ``qpos`` part, whose length the env reports in ``observation_structure["qpos"]`` (so it stays
  right with ``exclude_current_positions_from_observation=False``, which makes it 9).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from envs.wrappers import HideVelocity

PENDULUM_KEEP = (0, 1)  # cos(theta), sin(theta); index 2 is the angular velocity


def pendulum_no_vel(**kwargs: Any) -> gym.Env[Any, Any]:
    """Pendulum-v1's env, observing ``[cos(theta), sin(theta)]`` only; ``kwargs`` go to it."""
    from gymnasium.envs.classic_control.pendulum import PendulumEnv

    return HideVelocity(PendulumEnv(**kwargs), keep=PENDULUM_KEEP)


def half_cheetah_no_vel(**kwargs: Any) -> gym.Env[Any, Any]:
    """HalfCheetah-v5's env, observing its joint positions only; ``kwargs`` go to it."""
    from gymnasium.envs.mujoco.half_cheetah_v5 import HalfCheetahEnv

    env = HalfCheetahEnv(**kwargs)
    return HideVelocity(env, keep=range(env.observation_structure["qpos"]))
