"""The actor side: a policy steps a vector env, steps become trajectory chunks, chunks go to replay.

Usage (one process; ``ds/`` runs the same loop with a gRPC table and ZeroMQ parameters)::

    actor = ActorLoop(env, policy, sink=table.insert, chunk_length=64)
    while training:
        stats = actor.step()          # one step of every env; full chunks are handed to `sink`
        for ret, length in stats.finished: ...

The loop never needs to know where chunks go or where parameters come from: ``policy`` is anything
with :meth:`ActionSource.act`, ``sink`` any callable taking a :class:`~algorithm.types.Chunk`.

A chunk holding NaN or inf (an env that returned one as a reward or observation, or a policy that
acted with one) never reaches the sink: it is dropped whole, counted (``nonfinite_chunks``,
``nonfinite_steps``, :attr:`StepStats.nonfinite_steps`) and logged, and the loop goes on. Replay
would refuse it anyway (every inserted float must be finite); dropping it here keeps one bad step
from stopping an actor or the single-process trainer.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from algorithm.spaces import ActionSpec, EnvSpec
from algorithm.types import ActingProgress, Chunk

if TYPE_CHECKING:
    from algorithm.config.schema import Config

log = logging.getLogger("asac.actor")
_LOG_EVERY_S = 30.0  # dropped chunks: the first is logged, then at most one line (with totals) per period


def nonfinite_fields(chunk: Chunk) -> list[str]:
    """Names of ``chunk``'s float fields that hold NaN or inf (``obs[i]`` per sensor); empty if none."""
    fields = {f"obs[{i}]": o for i, o in enumerate(chunk.obs)}
    fields |= {"actions": chunk.actions, "prev_actions": chunk.prev_actions, "rewards": chunk.rewards,
               "behaviour_logp": chunk.behaviour_logp}  # fmt: skip
    if chunk.rnn_state is not None:
        fields["rnn_state"] = chunk.rnn_state
    return [name for name, a in fields.items() if a.dtype.kind == "f" and not np.isfinite(a).all()]


class ActionSource(Protocol):
    """What acts: :class:`algorithm.sac.learner.SAC` or anything shaped like it. A recurrent policy
    (``rnn_state_size > 0``) acts through ``act_recurrent`` and the loop carries its state."""

    rnn_state_size: int
    progress: ActingProgress  # the loop's, which it updates (exploration schedules read it)

    def act(self, obs: list[np.ndarray], deterministic: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Batched actions ``[N, A]`` in model space and their behaviour log-probabilities ``[N]``."""
        ...

    def act_recurrent(
        self, obs: list[np.ndarray], prev_actions: np.ndarray, rnn_state: np.ndarray, deterministic: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`act` plus the previous actions and states in, and the next states out."""
        ...


class VectorEnvLike(Protocol):
    """What :mod:`envs.make` provides; declared here so ``algorithm`` imports nothing from ``envs``."""

    num_envs: int
    spec: EnvSpec

    def reset(self, seed: int | None = None) -> list[np.ndarray]: ...

    def step(self, actions: np.ndarray) -> Any: ...

    def reset_env(self, index: int) -> list[np.ndarray]: ...

    def rng_states(self) -> list[dict[str, Any]]: ...

    def set_rng_states(self, states: Sequence[dict[str, Any]]) -> None: ...

    def close(self) -> None: ...


class ChunkBuilder:
    """Accumulates per-env steps and cuts :class:`Chunk` s at episode end or ``chunk_length`` steps.

    Buffers are ``[N, chunk_length + 1, ...]`` and every env writes its own row with one fancy-index
    assignment per field (a plain slice while all envs are at the same step), so a step costs about
    the same for 1 or 64 envs; only emitting a chunk copies.
    """

    def __init__(self, num_envs: int, spec: EnvSpec, chunk_length: int, rnn_state_size: int = 0) -> None:
        self.num_envs = num_envs
        self.chunk_length = chunk_length
        n, t, a = num_envs, chunk_length, spec.action.size
        self._rnn = np.zeros((n, t, rnn_state_size), dtype=np.float32) if rnn_state_size else None
        self._obs = [np.zeros((n, t + 1, *s.shape), dtype=s.dtype) for s in spec.sensors]
        self._actions = np.zeros((n, t, a), dtype=np.float32)
        self._prev_actions = np.zeros((n, t, a), dtype=np.float32)
        self._rewards = np.zeros((n, t), dtype=np.float32)
        self._terminated = np.zeros((n, t), dtype=bool)
        self._truncated = np.zeros((n, t), dtype=bool)
        self._logp = np.zeros((n, t), dtype=np.float32)
        self._t = np.zeros(n, dtype=np.int64)
        self._envs = np.arange(n)

    @property
    def open_steps(self) -> int:
        """Steps recorded in chunks not yet completed, over every env."""
        return int(self._t.sum())

    def add(
        self,
        obs: list[np.ndarray],
        actions: np.ndarray,
        prev_actions: np.ndarray,
        behaviour_logp: np.ndarray,
        rewards: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        final_obs: list[np.ndarray],
        rnn_state: np.ndarray | None = None,
    ) -> list[Chunk]:
        """Record one step of every env; returns the chunks completed by it (possibly none).

        ``obs`` is what the policy saw, ``final_obs`` the observation after the step (the true final
        one where an episode ended), ``rnn_state`` the recurrent state fed in with ``obs``."""
        e: np.ndarray | slice = self._envs
        t: np.ndarray | int = self._t
        if (self._t == self._t[0]).all():  # every env at the same step (the usual case): a strided copy
            e, t = slice(None), int(self._t[0])
        if self._rnn is not None:
            self._rnn[e, t] = rnn_state
        for buf, o in zip(self._obs, obs, strict=True):
            buf[e, t] = o
        self._actions[e, t] = actions
        self._prev_actions[e, t] = prev_actions
        self._logp[e, t] = behaviour_logp
        self._rewards[e, t] = rewards
        self._terminated[e, t] = terminated
        self._truncated[e, t] = truncated
        self._t += 1
        done = terminated | truncated
        cut = np.flatnonzero(done | (self._t == self.chunk_length))
        chunks = []
        for i in cut:
            length = int(self._t[i])
            for buf, o in zip(self._obs, final_obs, strict=True):
                buf[i, length] = o[i]
            chunks.append(self._emit(int(i), length))
        return chunks

    def flush(self, index: int, final_obs: list[np.ndarray], truncate: bool) -> Chunk | None:
        """Cut env ``index``'s open chunk now; ``final_obs`` is its next observation, per sensor.

        ``truncate=True`` marks the episode as ended by the caller (a forced reset); False just
        cuts the chunk (e.g. before a final checkpoint) and the episode continues elsewhere."""
        length = int(self._t[index])
        if length == 0:
            return None
        self._truncated[index, length - 1] = truncate
        for buf, o in zip(self._obs, final_obs, strict=True):
            buf[index, length] = o
        return self._emit(index, length)

    def _emit(self, i: int, length: int) -> Chunk:
        self._t[i] = 0
        return Chunk(
            obs=[buf[i, : length + 1].copy() for buf in self._obs],
            actions=self._actions[i, :length].copy(),
            prev_actions=self._prev_actions[i, :length].copy(),
            rewards=self._rewards[i, :length].copy(),
            terminated=self._terminated[i, :length].copy(),
            truncated=self._truncated[i, :length].copy(),
            behaviour_logp=self._logp[i, :length].copy(),
            rnn_state=None if self._rnn is None else self._rnn[i, :length].copy(),
        )


def uniform_random_actions(
    spec: ActionSpec, n: int, rng: np.random.Generator, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Uniform exploration actions in model space with their exact behaviour log-density.

    ``mask [n, sum(branches)]`` (the ``action_mask`` sensor, nonzero = allowed) restricts each
    discrete branch to its allowed actions, uniformly."""
    parts = []
    logp = np.zeros(n, dtype=np.float64)
    start = 0
    for branch in spec.discrete_branches:
        if mask is None:
            choice = rng.integers(branch, size=n)
            logp -= np.log(branch)
        else:
            allowed = mask[:, start : start + branch] > 0.5
            counts = allowed.sum(axis=1)
            # the k-th allowed action, k uniform in [0, count): first index whose running count exceeds k
            k = (rng.random(n) * counts).astype(np.int64)
            choice = (allowed.cumsum(axis=1) > k[:, None]).argmax(axis=1)
            logp -= np.log(counts)
        parts.append(np.eye(branch, dtype=np.float32)[choice])
        start += branch
    if spec.continuous_dim:
        parts.append(rng.uniform(-1.0, 1.0, size=(n, spec.continuous_dim)).astype(np.float32))
        logp -= spec.continuous_dim * np.log(2.0)  # density of U[-1, 1]^d
    return np.concatenate(parts, axis=1), logp.astype(np.float32)


@dataclass
class StepStats:
    env_steps: int
    finished: list[tuple[float, int]] = field(default_factory=list)  # (return, length) of ended episodes
    chunks: int = 0  # handed to the sink
    iteration_ended: bool = False
    nonfinite_steps: int = 0  # steps of the chunks dropped for NaN/inf values

    def episode_metrics(self) -> list[dict[str, float]]:
        """What each episode that ended writes to TensorBoard, the same in both modes."""
        return [{"actor/episode_return": ret, "actor/episode_length": length} for ret, length in self.finished]


class ActorLoop:
    """Steps ``env`` with ``policy`` and hands completed chunks to ``sink``.

    ``random_steps``: the first that many env steps (over all envs) use uniform random actions.
    ``reset_on_iteration``: when env 0's episode ends, every other env is cut (truncated, real final
    observation kept) and reset too, so all envs start the next iteration together.
    Chunks with NaN/inf values are dropped, counted and logged (see the module docstring).
    """

    def __init__(
        self,
        env: VectorEnvLike,
        policy: ActionSource,
        sink: Callable[[Chunk], Any],
        chunk_length: int,
        random_steps: int = 0,
        reset_on_iteration: bool = False,
        seed: int | None = None,
    ) -> None:
        self.env = env
        self.policy = policy
        self.sink = sink
        self.random_steps = random_steps
        self.reset_on_iteration = reset_on_iteration
        self.rng = np.random.default_rng(seed)
        self.spec = env.spec
        n = env.num_envs
        rnn_size = getattr(policy, "rnn_state_size", 0)
        self.builder = ChunkBuilder(n, self.spec, chunk_length, rnn_size)
        self.obs = env.reset(seed=seed)
        self.prev_actions = np.zeros((n, self.spec.action.size), dtype=np.float32)
        self.rnn_state = np.zeros((n, rnn_size), dtype=np.float32) if rnn_size else None
        self.episode_return = np.zeros(n, dtype=np.float64)
        self.episode_length = np.zeros(n, dtype=np.int64)
        self.total_steps = 0
        self.progress = ActingProgress()
        self.nonfinite_chunks = 0
        self.nonfinite_steps = 0
        self._last_log = -float("inf")

    @classmethod
    def from_config(
        cls, env: VectorEnvLike, policy: ActionSource, sink: Callable[[Chunk], Any], config: Config, seed: int | None
    ) -> ActorLoop:
        """The loop a run's config asks for (``actor_config`` and ``base_config.reset_on_iteration``),
        the same in ``main.py`` and in a distributed actor."""
        return cls(
            env,
            policy,
            sink,
            chunk_length=config.actor_config.chunk_length,
            random_steps=config.actor_config.random_steps,
            reset_on_iteration=config.base_config.reset_on_iteration,
            seed=seed,
        )

    def step(self) -> StepStats:
        n = self.env.num_envs
        next_rnn_state = None
        self.progress.env_steps = self.total_steps  # (set from outside on a resume)
        self.policy.progress = self.progress  # each step: a policy may serve more than one loop
        if self.rnn_state is not None:  # the state advances during random warm-up too
            actions, logp, next_rnn_state = self.policy.act_recurrent(self.obs, self.prev_actions, self.rnn_state)
        if self.total_steps < self.random_steps:
            mask_index = self.spec.action_mask_index
            mask = None if mask_index is None else self.obs[mask_index]
            actions, logp = uniform_random_actions(self.spec.action, n, self.rng, mask)
        elif self.rnn_state is None:
            actions, logp = self.policy.act(self.obs, deterministic=False)
        result = self.env.step(actions)
        chunks = self.builder.add(
            self.obs,
            actions,
            self.prev_actions,
            logp,
            result.rewards,
            result.terminated,
            result.truncated,
            result.final_obs,
            self.rnn_state,
        )
        self.total_steps += n
        self.episode_return += result.rewards
        self.episode_length += 1
        done = result.terminated | result.truncated
        stats = StepStats(env_steps=n)
        self.prev_actions = np.where(done[:, None], 0.0, actions).astype(np.float32)
        if next_rnn_state is not None:
            self.rnn_state = np.where(done[:, None], 0.0, next_rnn_state).astype(np.float32)
        self.obs = result.obs
        for i in np.flatnonzero(done):
            stats.finished.append((float(self.episode_return[i]), int(self.episode_length[i])))
            self.progress.best_episode_return = max(self.progress.best_episode_return, float(self.episode_return[i]))
            self.episode_return[i] = 0.0
            self.episode_length[i] = 0
        if done[0]:
            stats.iteration_ended = True
            if self.reset_on_iteration:
                chunks.extend(self._reset_others())
        dropped = self.nonfinite_steps
        stats.chunks = sum(self._emit(chunk) for chunk in chunks)
        stats.nonfinite_steps = self.nonfinite_steps - dropped
        return stats

    @property
    def open_steps(self) -> int:
        """Steps taken and not yet handed to the sink (the open chunks)."""
        return self.builder.open_steps

    def flush(self) -> int:
        """Hand every open chunk to the sink now (before a final checkpoint, or before a pause);
        returns how many. Stepping may go on after it: each env's episode continues in a new chunk."""
        count = 0
        for i in range(self.env.num_envs):
            chunk = self.builder.flush(i, [o[i] for o in self.obs], truncate=False)
            if chunk is not None:
                count += self._emit(chunk)
        return count

    def _emit(self, chunk: Chunk) -> bool:
        """Hand ``chunk`` to the sink, unless it holds NaN/inf: then count it, log it, and drop it."""
        bad = nonfinite_fields(chunk)
        if not bad:
            self.sink(chunk)
            return True
        self.nonfinite_chunks += 1
        self.nonfinite_steps += len(chunk)
        if time.monotonic() - self._last_log >= _LOG_EVERY_S:
            self._last_log = time.monotonic()
            log.warning("dropped a chunk of %d steps with non-finite values in %s; %d chunks (%d steps) dropped so "
                        "far", len(chunk), ", ".join(bad), self.nonfinite_chunks, self.nonfinite_steps)  # fmt: skip
        return False

    def _reset_others(self) -> list[Chunk]:
        chunks = []
        for i in range(1, self.env.num_envs):
            chunk = self.builder.flush(i, [o[i] for o in self.obs], truncate=True)
            if chunk is not None:
                chunks.append(chunk)
            fresh = self.env.reset_env(i)
            for o, f in zip(self.obs, fresh, strict=True):
                o[i] = f
            self.prev_actions[i] = 0.0
            if self.rnn_state is not None:
                self.rnn_state[i] = 0.0
            self.episode_return[i] = 0.0
            self.episode_length[i] = 0
        return chunks
