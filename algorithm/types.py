"""Data that crosses part boundaries: trajectory chunks going into replay, batches coming out, and
what an acting loop tells its policy about its progress.

Layouts are batch-major everywhere: ``[B, L, ...]`` for windows, ``[T, ...]`` for a chunk.
See docs/architecture.md section 3 for the contract these types implement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Chunk:
    """``T`` consecutive steps of one env plus the observation after the last step.

    ``obs[i]`` has shape ``[T + 1, *sensor_shape]``: row ``t`` is the observation the policy saw
    before acting at step ``t``; row ``T`` is the observation after the last step — on
    termination or time-limit truncation the real final observation, never the auto-reset one.
    Only the last step of a chunk may be ``terminated`` or ``truncated``: actors cut chunks at
    episode end or after ``chunk_length`` steps. A chunk cut mid-episode has both flags False at
    its last step, and its windows bootstrap from ``obs[T]`` exactly as on truncation.
    """

    obs: list[np.ndarray]
    actions: np.ndarray  # [T, A] float32, model space ([one-hot | [-1, 1]])
    prev_actions: np.ndarray  # [T, A] float32, zeros at episode start
    rewards: np.ndarray  # [T] float32
    terminated: np.ndarray  # [T] bool: no bootstrapping past this step
    truncated: np.ndarray  # [T] bool: episode ended by a time limit; bootstrap from the next obs
    behaviour_logp: np.ndarray  # [T] float32: log mu(a_t|o_t) of the policy that acted, noise included
    rnn_state: np.ndarray | None = None  # [T, H] recurrent state fed in with o_t (recurrent models)

    def __len__(self) -> int:
        return int(self.rewards.shape[0])


@dataclass
class Batch:
    """``B`` windows of ``L = burn_in_step + n_step`` consecutive steps from replay.

    Window ``b`` starts at row ``keys[b]``. ``mask[b, t]`` is True where step ``t`` exists in the
    same chunk; a window that runs past its chunk's end is masked there and never reads another
    chunk. ``obs[i]`` has shape ``[B, L + 1, ...]``: position ``t`` is the observation before step
    ``t`` and position ``t + 1`` the one after it; past the chunk's end every position repeats the
    chunk's final observation, so the last valid next observation is always at ``valid_len``.
    Masked positions of the other per-step arrays are zeros/False.

    ``probabilities[b]`` is the probability with which ``keys[b]`` was drawn and ``table_size``
    the number of sampleable rows then: the learner derives importance weights from them
    (``(table_size * p) ** -beta``), so replay never needs beta.
    """

    keys: np.ndarray  # [B] uint64
    probabilities: np.ndarray  # [B] float64
    table_size: int
    obs: list[np.ndarray]  # each [B, L + 1, *sensor_shape]
    actions: np.ndarray  # [B, L, A] float32
    prev_actions: np.ndarray  # [B, L, A] float32
    rewards: np.ndarray  # [B, L] float32
    terminated: np.ndarray  # [B, L] bool
    truncated: np.ndarray  # [B, L] bool
    behaviour_logp: np.ndarray  # [B, L] float32
    mask: np.ndarray  # [B, L] bool
    rnn_state: np.ndarray | None = None  # [B, H] stored state at the window start

    @property
    def batch_size(self) -> int:
        return int(self.keys.shape[0])

    @property
    def window(self) -> int:
        return int(self.mask.shape[1])


@dataclass
class ActingProgress:
    """What one acting loop has done so far, for exploration that depends on it (RND's action choice
    ends per ``sac_config.rnd_choice_steps`` and ``rnd_choice_until_return``). The loop owns it and
    updates it before each step (:class:`~algorithm.run.actor.ActorLoop`); the policy reads it."""

    env_steps: int = 0  # over all envs of this loop, random warm-up included
    best_episode_return: float = -math.inf  # the highest return of an episode this loop finished
