"""Small environments we own, registered with gymnasium on import (``envs.make`` imports this).

============================  =======================================================  ==========
id                            what                                                     time limit
============================  =======================================================  ==========
``asac/Chain-v0``             :class:`ChainEnv`, one Box ``[episode_index, t, x]``     10 steps
``asac/DictChain-v0``         ``obs_mode="dict"``, ``action_dim=3``: sensors           10 steps
                              ``counter [2]`` and ``state [3]``
``asac/TupleChain-v0``        ``obs_mode="tuple"``: sensors ``(counter [2], x [1])``   10 steps
``asac/MaskedGrid-v0``        :class:`MaskedGridEnv`: 5x5 grid walk, ``Discrete(4)``;  20 steps
                              sensors ``action_mask [4]``, ``position [2]``;
                              masked actions are fatal (-10). Optimum 8
``asac/MixedTarget-v0``       :class:`MixedTargetEnv`: match a shown target with       10 steps
                              ``Tuple(Discrete(3), Box(-1, 1, (1,)))``; Box
                              ``[4]``. Optimum 10
``asac/PixelPoint-v0``        :class:`PixelPointEnv`: move a point to a goal           20 steps
                              seen only in a ``uint8 [16, 16, 3]`` image;
                              ``Box(-1, 1, (2,))``. Optimum -4.5
``asac/PendulumNoVel-v0``     Pendulum-v1 observing ``[cos, sin]`` only (POMDP)        200 steps
``asac/HalfCheetahNoVel-v0``  HalfCheetah-v5 observing its 8 positions (POMDP)         1000 steps
============================  =======================================================  ==========

Every env class keyword (``terminate_at``, ``size``, ``n_options``, ...) can be passed as
``env_kwargs``; ``max_episode_steps`` overrides the time limit. The module docstrings of
:mod:`envs.toy.masked_grid`, :mod:`envs.toy.mixed_target` and :mod:`envs.toy.pixel_point` give
each task's optimal and random-policy returns.

The POMDP ids live here rather than in a module of their own under :mod:`envs`: every ``asac/``
id is then registered by the one import :mod:`envs.make` already does, and this table lists them
all. Their entry points are factories in :mod:`envs.toy.pomdp` that import gymnasium's env classes
only when called, so this import stays free of MuJoCo.
"""

from __future__ import annotations

import gymnasium as gym

from envs.toy.chain import ChainEnv
from envs.toy.masked_grid import MaskedGridEnv
from envs.toy.mixed_target import MixedTargetEnv
from envs.toy.pixel_point import PixelPointEnv

__all__ = ["TIME_LIMIT", "ChainEnv", "MaskedGridEnv", "MixedTargetEnv", "PixelPointEnv"]

_ENTRY_POINT = "envs.toy.chain:ChainEnv"
TIME_LIMIT = 10

gym.register("asac/Chain-v0", entry_point=_ENTRY_POINT, max_episode_steps=TIME_LIMIT)
gym.register(
    "asac/DictChain-v0",
    entry_point=_ENTRY_POINT,
    max_episode_steps=TIME_LIMIT,
    kwargs={"obs_mode": "dict", "action_dim": 3},
)
gym.register("asac/TupleChain-v0", entry_point=_ENTRY_POINT, max_episode_steps=TIME_LIMIT, kwargs={"obs_mode": "tuple"})
gym.register("asac/MaskedGrid-v0", entry_point="envs.toy.masked_grid:MaskedGridEnv", max_episode_steps=20)
gym.register("asac/MixedTarget-v0", entry_point="envs.toy.mixed_target:MixedTargetEnv", max_episode_steps=10)
gym.register("asac/PixelPoint-v0", entry_point="envs.toy.pixel_point:PixelPointEnv", max_episode_steps=20)
gym.register("asac/PendulumNoVel-v0", entry_point="envs.toy.pomdp:pendulum_no_vel", max_episode_steps=200)
gym.register("asac/HalfCheetahNoVel-v0", entry_point="envs.toy.pomdp:half_cheetah_no_vel", max_episode_steps=1000)
