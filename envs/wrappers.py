"""Wrappers that :mod:`envs.make` applies; nothing else should wrap envs.

Time limits: ``make_env(max_episode_steps=N)`` hands ``N`` to :func:`gymnasium.make`, which
wraps the env in :class:`gymnasium.wrappers.TimeLimit` instead of the registered limit. That
wrapper reports the limit as ``truncated=True`` and leaves ``terminated`` to the env, which is
the distinction replay and targets rely on (docs/architecture.md section 3). :func:`check_max_episode_steps`
validates the override first, because gymnasium treats ``-1`` as "no limit" and does not reject
other non-positive values.

Partial observability: :class:`HideVelocity` keeps chosen entries of a flat Box observation. The
POMDP ids built on it (``asac/PendulumNoVel-v0``, ``asac/HalfCheetahNoVel-v0``) are registered
in :mod:`envs.toy`, and their factories in :mod:`envs.toy.pomdp` are the only callers.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np


def check_max_episode_steps(max_episode_steps: int | None) -> None:
    """Raise ``ValueError`` unless ``max_episode_steps`` is None or a positive int."""
    if max_episode_steps is None:
        return
    if isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, int) or max_episode_steps < 1:
        raise ValueError(f"max_episode_steps must be a positive int or None, got {max_episode_steps!r}")


class SeedOnFirstReset(gym.Wrapper[Any, Any, Any, Any]):
    """Seeds the env's RNG on its first ``reset()`` when the caller passes no seed.

    gymnasium seeds an env only through ``reset(seed=...)``; this lets :func:`envs.make.make_env`
    take the seed up front so that callers reset without knowing it. An explicit ``seed`` passed
    to ``reset`` always wins; later unseeded resets continue the seeded RNG (reproducible).
    """

    def __init__(self, env: gym.Env[Any, Any], seed: int) -> None:
        super().__init__(env)
        self.pending_seed: int | None = seed  # the next unseeded reset's; None once reset

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        if seed is None:
            seed = self.pending_seed
        self.pending_seed = None
        return self.env.reset(seed=seed, options=options)


class HideVelocity(gym.ObservationWrapper[np.ndarray, Any, Any], gym.utils.RecordConstructorArgs):
    """Keeps only the observation entries at ``keep`` (in that order), as float32.

    Dropping the velocity entries of a fully observed control task makes it partially observed:
    a memoryless policy sees positions only and must infer motion from history (frame stacking
    or recurrence), which is what the POMDP learning tests measure. The new space is a float32
    Box with the kept entries' bounds; values are cast to float32 (MuJoCo observations are
    float64) so every sensor matches :func:`algorithm.spaces.sensor_specs`' storage dtype.

    Args:
        env: an env with a one-dimensional Box observation space.
        keep: indices to keep, distinct and within the observation, at least one; negative
            indices count from the end as in numpy.
    """

    def __init__(self, env: gym.Env[np.ndarray, Any], keep: Sequence[int]) -> None:
        space = env.observation_space
        if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
            raise TypeError(f"HideVelocity needs a one-dimensional Box observation space, got {space}")
        n = space.shape[0]
        indices = [int(i) for i in keep]
        if not indices:
            raise ValueError("HideVelocity: keep must name at least one observation entry")
        if any(not -n <= i < n for i in indices):
            raise ValueError(f"HideVelocity: keep {indices} has an index outside the {n} observation entries")
        normalised = [i % n for i in indices]
        if len(set(normalised)) != len(normalised):
            raise ValueError(f"HideVelocity: keep {indices} names an entry twice")
        gym.utils.RecordConstructorArgs.__init__(self, keep=tuple(indices))
        gym.ObservationWrapper.__init__(self, env)
        self.keep = np.array(normalised, np.int64)
        self.observation_space = gym.spaces.Box(
            np.asarray(space.low[self.keep], np.float32),
            np.asarray(space.high[self.keep], np.float32),
            (len(normalised),),
            np.float32,
        )

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return np.asarray(observation)[self.keep].astype(np.float32, copy=False)
