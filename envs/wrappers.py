"""Wrappers that :mod:`envs.make` applies; nothing else should wrap envs.

Time limits: ``make_env(max_episode_steps=N)`` hands ``N`` to :func:`gymnasium.make`, which
wraps the env in :class:`gymnasium.wrappers.TimeLimit` instead of the registered limit. That
wrapper reports the limit as ``truncated=True`` and leaves ``terminated`` to the env, which is
the distinction replay and targets rely on (ARCHITECTURE.md 3). :func:`check_max_episode_steps`
validates the override first, because gymnasium treats ``-1`` as "no limit" and does not reject
other non-positive values.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym


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
        self._pending_seed: int | None = seed

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        if seed is None:
            seed = self._pending_seed
        self._pending_seed = None
        return self.env.reset(seed=seed, options=options)
