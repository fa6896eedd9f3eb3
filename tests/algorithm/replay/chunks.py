"""Chunks whose contents name their own keys, so a test can tell where every sampled value came from.

With ``first_key`` the key the table will give the chunk's first step, observation row ``i`` holds
``first_key + i`` in every element and step ``i`` has reward ``first_key + i + 0.5``: a sampled value
identifies the row it was read from.
"""

from __future__ import annotations

import numpy as np

from algorithm.spaces import SensorSpec
from algorithm.types import Chunk

VECTOR = SensorSpec("state", (3,))
IMAGE = SensorSpec("pixels", (4, 4, 3), np.dtype(np.uint8))


def make_chunk(
    t: int,
    first_key: int = 0,
    sensors: tuple[SensorSpec, ...] = (VECTOR,),
    action_size: int = 2,
    terminated: bool = False,
    truncated: bool = False,
    rnn_state_size: int = 0,
) -> Chunk:
    """A valid ``t``-step chunk; only the last step carries the termination/truncation flags."""
    ids = np.arange(first_key, first_key + t + 1, dtype=np.float64)
    obs = []
    for s in sensors:
        values = ids % 256 if s.is_image else ids  # images hold the key modulo 256
        obs.append(np.broadcast_to(values.reshape(-1, *[1] * len(s.shape)), (t + 1, *s.shape)).astype(s.dtype))
    term = np.zeros(t, dtype=bool)
    trunc = np.zeros(t, dtype=bool)
    term[-1], trunc[-1] = terminated, truncated
    return Chunk(
        obs=obs,
        actions=np.repeat(ids[:t, None], action_size, axis=1).astype(np.float32),
        prev_actions=np.repeat(ids[:t, None] - 1, action_size, axis=1).astype(np.float32),
        rewards=(ids[:t] + 0.5).astype(np.float32),
        terminated=term,
        truncated=trunc,
        behaviour_logp=-(ids[:t] + 1).astype(np.float32),
        rnn_state=np.repeat(ids[:t, None], rnn_state_size, axis=1).astype(np.float32) if rnn_state_size else None,
    )
