"""Small environments we own, registered with gymnasium on import (``envs.make`` imports this).

=======================  ==========================================================  ==========
id                       what                                                        time limit
=======================  ==========================================================  ==========
``asac/Chain-v0``        :class:`ChainEnv`, one Box ``[episode_index, t, x]``         10 steps
``asac/DictChain-v0``    ``obs_mode="dict"``, ``action_dim=3``: sensors ``counter``   10 steps
                         ``[2]`` and ``state`` ``[3]``
``asac/TupleChain-v0``   ``obs_mode="tuple"``: sensors ``(counter [2], x [1])``      10 steps
=======================  ==========================================================  ==========

Every :class:`ChainEnv` keyword (``terminate_at``, ``n_actions``, ``image``, ...) can be passed
as ``env_kwargs``; ``max_episode_steps`` overrides the time limit.
"""

from __future__ import annotations

import gymnasium as gym

from envs.toy.chain import ChainEnv

__all__ = ["TIME_LIMIT", "ChainEnv"]

_ENTRY_POINT = "envs.toy.chain:ChainEnv"
TIME_LIMIT = 10

gym.register("asac/Chain-v0", entry_point=_ENTRY_POINT, max_episode_steps=TIME_LIMIT)
gym.register(
    "asac/DictChain-v0",
    entry_point=_ENTRY_POINT,
    max_episode_steps=TIME_LIMIT,
    kwargs={"obs_mode": "dict", "action_dim": 3},
)
gym.register(
    "asac/TupleChain-v0", entry_point=_ENTRY_POINT, max_episode_steps=TIME_LIMIT, kwargs={"obs_mode": "tuple"}
)
