"""Deterministic evaluation on envs separate from training, appended to ``evaluations.csv``.

The CSV (``env_steps,updates,wall_seconds,return_mean,return_std``) is the interface scripts and
our own learning checks read; TensorBoard gets the same numbers as ``eval/*``. Rows are appended
by writing the whole file again atomically (:func:`algorithm.files.atomic_write`): a write that
fails (a full disk) leaves the file as it was, never with half a row.
"""

from __future__ import annotations

import csv
import io
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from algorithm.files import atomic_write, open_regular
from algorithm.run.actor import ActionSource, VectorEnvLike

CSV_FIELDS = ("env_steps", "updates", "wall_seconds", "return_mean", "return_std")


class AcceptsWeights(ActionSource, Protocol):
    """A policy that takes a learner's acting weights (``algorithm.sac.policy.Policy``)."""

    def load_acting_state_dict(self, state: dict[str, Any]) -> None: ...


@dataclass
class EvalResult:
    returns: np.ndarray
    lengths: np.ndarray

    @property
    def mean(self) -> float:
        return float(self.returns.mean())

    @property
    def std(self) -> float:
        return float(self.returns.std())


def evaluate(
    env: VectorEnvLike, policy: ActionSource, episodes: int, seed: int | None, deterministic: bool = True
) -> EvalResult:
    """Run ``episodes`` episodes, spread evenly over ``env``'s sub-envs.

    ``deterministic`` (the default, what every reported evaluation uses) acts with the policy's mode;
    ``deterministic=False`` acts as an actor does (sampling, with the policy's acting noise, colored
    when the config asks for it) -- a diagnostic of how much of a return the mode alone earns.

    Each sub-env runs a fixed quota of episodes (not "the first N to finish"), so short episodes
    are not over-represented. ``seed`` reseeds the envs; callers pass it on the first evaluation
    only and None afterwards, so each evaluation draws fresh start states from one seeded stream
    (as SB3's EvalCallback does). Reseeding every time would score every evaluation on the same
    few start states: on Pendulum-v1 one such set of 10 averaged -249 for a policy whose mean over
    100 episodes was -133.
    """
    n = env.num_envs
    quota = np.full(n, episodes // n) + (np.arange(n) < episodes % n)
    obs = env.reset(seed=seed)
    returns: list[float] = []
    lengths: list[int] = []
    ep_ret = np.zeros(n)
    ep_len = np.zeros(n, dtype=np.int64)
    done_count = np.zeros(n, dtype=np.int64)
    rnn_size = getattr(policy, "rnn_state_size", 0)
    rnn_state = np.zeros((n, rnn_size), dtype=np.float32)
    prev_actions = np.zeros((n, env.spec.action.size), dtype=np.float32)
    while (done_count < quota).any():
        if rnn_size:
            actions, _, rnn_state = policy.act_recurrent(obs, prev_actions, rnn_state, deterministic=deterministic)
        else:
            actions, _ = policy.act(obs, deterministic=deterministic)
        result = env.step(actions)
        done = result.terminated | result.truncated
        if rnn_size:  # a recurrent policy starts each episode from zeros
            rnn_state = np.where(done[:, None], 0.0, rnn_state).astype(np.float32)
            prev_actions = np.where(done[:, None], 0.0, actions).astype(np.float32)
        ep_ret += result.rewards
        ep_len += 1
        for i in np.flatnonzero(result.terminated | result.truncated):
            if done_count[i] < quota[i]:
                returns.append(float(ep_ret[i]))
                lengths.append(int(ep_len[i]))
                done_count[i] += 1
            ep_ret[i] = 0.0
            ep_len[i] = 0
        obs = result.obs
    return EvalResult(np.asarray(returns), np.asarray(lengths))


def evaluation_row(env_steps: int, updates: int, wall_seconds: float, result: EvalResult) -> list[str]:
    """One row of ``evaluations.csv`` (:data:`CSV_FIELDS`)."""
    return [str(env_steps), str(updates), f"{wall_seconds:.2f}", f"{result.mean:.4f}", f"{result.std:.4f}"]


def append_evaluations(path: Path, rows: Sequence[Sequence[str]]) -> None:
    """Append ``rows`` to the CSV at ``path`` (with the header when it is new), all or none: the file
    is written again beside itself and renamed over (a few kB even for thousands of evaluations); an
    ``OSError`` leaves it as it was."""
    try:
        with open_regular(path) as f:
            old = f.read()
    except FileNotFoundError:
        old = b""
    text = io.StringIO(newline="")
    writer = csv.writer(text)
    if not old:
        writer.writerow(CSV_FIELDS)
    elif not old.endswith(b"\n"):  # a row cut short by a crash of an older version: start a new line
        text.write("\r\n")
    writer.writerows(rows)
    new = text.getvalue().encode()
    atomic_write(path, lambda f: f.write(old + new))


def append_evaluation(path: Path, env_steps: int, updates: int, wall_seconds: float, result: EvalResult) -> None:
    append_evaluations(path, [evaluation_row(env_steps, updates, wall_seconds, result)])


def read_evaluations(path: Path) -> list[dict[str, float]]:
    with path.open(newline="") as f:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]


@dataclass
class Scored:
    """An evaluation made beside training: the counters of the weights it scored, and its result."""

    env_steps: int
    updates: int
    wall_seconds: float
    result: EvalResult


class BackgroundEvaluation:
    """Evaluations on a thread of their own, with a copy of the acting weights, so that training goes
    on meanwhile (the distributed learner's; ``main.py`` evaluates in line, between updates).

    Usage::

        evals = BackgroundEvaluation(eval_env, policy_copy, episodes=10)
        evals.start(sac.acting_state_dict(), env_steps, updates, wall_seconds, seed)   # when one is due
        scored = evals.collect()        # between updates: the finished one (or None); errors raise here
        scored = evals.wait()           # at the end: waits for the one in flight

    One runs at a time: :meth:`busy` says whether one is in flight. ``policy`` is only ever used by the
    evaluation thread (weights are copied in before it starts)."""

    def __init__(self, env: VectorEnvLike, policy: AcceptsWeights, episodes: int) -> None:
        self.env, self.policy, self.episodes = env, policy, episodes
        self._thread: threading.Thread | None = None
        self._scored: Scored | None = None
        self._error: BaseException | None = None

    def busy(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, weights: dict[str, Any], env_steps: int, updates: int, wall_seconds: float,
              seed: int | None) -> None:  # fmt: skip
        """Score ``weights`` (the acting state of ``updates`` updates at ``env_steps``) beside training."""
        if self._thread is not None:
            raise RuntimeError("BackgroundEvaluation.start: one is in flight or not collected")
        self.policy.load_acting_state_dict(weights)

        def run() -> None:
            try:
                result = evaluate(self.env, self.policy, self.episodes, seed)
                self._scored = Scored(env_steps, updates, wall_seconds, result)
            except BaseException as e:  # surfaces in the training thread, at collect()
                self._error = e

        self._thread = threading.Thread(target=run, name="evaluation", daemon=True)
        self._thread.start()

    def collect(self) -> Scored | None:
        """The evaluation that has finished since the last call, or None (none, or still running)."""
        if self._thread is None or self._thread.is_alive():
            return None
        self._thread.join()
        self._thread = None
        error, scored, self._error, self._scored = self._error, self._scored, None, None
        if error is not None:
            raise error
        return scored

    def wait(self) -> Scored | None:
        """The one in flight, once it has finished (None when there is none)."""
        if self._thread is not None:
            self._thread.join()
        return self.collect()
