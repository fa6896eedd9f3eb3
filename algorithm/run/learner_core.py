"""The learner's lifecycle, written once for both modes: the update step, evaluation cadence,
summaries, checkpoints, resume, the update-to-data budget and the stop at ``max_step`` (the run's
counters and its summary: algorithm/run/progress.py).

Usage (``algorithm/run/trainer.py`` and ``ds/learner/learner.py`` are the two drivers)::

    core = LearnerCore(config, run_dir, sac, eval_env=env, log_dir=run_dir / "log")
    state = core.restore()                      # None on a new run; else the checkpoint (extras inside)
    while not core.done() and not stop.is_set():
        ...                                     # the mode's data: actor steps in-process, or batches over gRPC
        result = core.train_on(batch, sink)     # update, priorities/recurrent states to the sink, summaries
        core.tick()                             # evaluation and checkpoint when due, the progress line
    core.finish()                               # final evaluation when done, checkpoint, close

The two modes differ only in where batches come from and where priorities and weights go (as
Acme's learner takes a data iterator): :class:`~algorithm.run.trainer.EmbeddedTrainer` steps its actor
loop and trains on its in-process table as :class:`UpdateBudget` says; the distributed
:class:`~ds.learner.learner.Learner` trains on what a prefetcher brings from the replay server, whose rate
limiter applies the same ratio to actors it cannot otherwise slow down.

Checkpoints have one format for both (``model/<env_steps>.pt``: ``sac``, ``counters``, ``rng``,
``eval_env_rng`` and the mode's extras), so ``main.py --run`` plays either and a finished run knows
its last evaluation.

A checkpoint, an ``evaluations.csv`` row or the run's ``config.yaml`` that cannot be written (a full
disk, an I/O error) never stops training: it is logged once (:class:`~algorithm.files.WriteFailures`),
the files before it stay as they were, and it is tried again at the next checkpoint (the rows at
the next evaluation, all of them, in order); a final checkpoint that fails is logged as such.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from algorithm.config.load import config_to_yaml
from algorithm.config.schema import Config
from algorithm.files import WriteFailures, atomic_write
from algorithm.run.actor import VectorEnvLike
from algorithm.run.checkpoint import (
    capture_rng,
    list_checkpoints,
    load_for_resume,
    restore_rng,
    restoring,
    save_checkpoint,
)
from algorithm.run.evaluation import (
    AcceptsWeights,
    BackgroundEvaluation,
    EvalResult,
    Scored,
    append_evaluations,
    evaluate,
    evaluation_row,
    read_evaluations,
)
from algorithm.run.folder import EVAL_SEED_OFFSET, RunDir
from algorithm.run.logging import MetricsWriter, ProgressLine, RateMeter, Throttle, Timers
from algorithm.run.progress import RunCounters, budget_spent
from algorithm.sac.learner import SAC, UpdateResult
from algorithm.types import Batch

log = logging.getLogger("asac.learner")


class UpdateBudget:
    """The update-to-data ratio of the in-process loop: once the replay holds ``min_size_to_sample``
    steps, every env step earns ``updates_per_step`` updates (``samples_per_insert / batch_size``),
    paid right after the step that earned them, however many envs run in parallel.

    Only data that is there earns updates: a replay below ``min_size_to_sample`` (a fresh run, or a
    resumed one whose replay was not saved) earns none, and a balance carried over from a checkpoint
    is dropped when its replay did not come back (:meth:`forgive`), so a resumed run never waits for
    updates that no data can pay (the hang of a resume with an empty replay)."""

    def __init__(self, updates_per_step: float, min_size_to_sample: int, owed: float = 0.0) -> None:
        self.updates_per_step = float(updates_per_step)
        self.min_size_to_sample = int(min_size_to_sample)
        self.owed = float(owed)

    def can_sample(self, replay_size: int) -> bool:
        return replay_size >= self.min_size_to_sample

    def earn(self, env_steps: int, replay_size: int) -> None:
        if self.can_sample(replay_size):
            self.owed += env_steps * self.updates_per_step

    def take(self, replay_size: int) -> bool:
        """Whether one update is owed and can be drawn now (then it is counted as paid)."""
        if self.owed >= 1.0 and self.can_sample(replay_size):
            self.owed -= 1.0
            return True
        return False

    def forgive(self, replay_size: int) -> None:
        """A replay smaller than ``min_size_to_sample`` cannot pay what is owed: start from zero."""
        if not self.can_sample(replay_size):
            self.owed = 0.0


def sample_age(keys: np.ndarray, newest_key: int, chunk_length: int) -> dict[str, float]:
    """How old sampled data is, in env steps since it was stored (median and 95th percentile of a
    batch's windows): keys count stored rows, one of every ``chunk_length + 1`` a chunk's bootstrap
    row, so ``rows * T / (T + 1)`` steps. Distributed, ``newest_key`` is as of the learner's last
    replay poll (at most ``info_every_s`` old), so ages there read low by that much."""
    rows = np.maximum(newest_key - keys.astype(np.int64), 0) * (chunk_length / (chunk_length + 1))
    median, p95 = np.percentile(rows, [50, 95])
    return {"replay/sample_age_steps_median": float(median), "replay/sample_age_steps_p95": float(p95)}


class TrainingSink(Protocol):
    """Where the results of an update go: the table's priorities and refreshed recurrent states; and
    where new data to score comes from (``sac_config.insert_td_priorities``)."""

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> None: ...

    def update_rnn_states(self, keys: np.ndarray, states: np.ndarray) -> None: ...

    def windows_after(self, key: int, limit: int) -> Batch | None: ...


class LearnerCore:
    """See the module docstring. ``on_evaluation(mean, env_steps)`` is called after every evaluation
    (the evolver link posts it); ``publish`` after every ``update_policy_variables_per_step``
    updates (where weights go: an acting copy in-process, ZeroMQ subscribers distributed);
    ``extra_state()`` is what the mode adds to each checkpoint (and reads back from :meth:`restore`'s
    state); ``newest_key()`` the replay's next key, for the age of sampled data (:func:`sample_age`)."""

    def __init__(
        self,
        config: Config,
        run_dir: Path,
        sac: SAC,
        *,
        log_dir: Path,
        eval_env: VectorEnvLike | None = None,
        progress: bool = False,
        publish: Callable[[], None] = lambda: None,
        on_evaluation: Callable[[float, int], None] = lambda mean, steps: None,
        extra_state: Callable[[], dict[str, Any]] = dict,
        newest_key: Callable[[], int] | None = None,
        eval_policy: AcceptsWeights | None = None,
    ) -> None:
        self.config = config
        self.paths = RunDir(Path(run_dir))
        self.sac = sac
        self.log_dir = log_dir
        evaluating = eval_env is not None and config.eval_config.eval_per_step > 0
        self.eval_env = eval_env if evaluating else None
        # With eval_policy (a copy to act with), evaluations run beside training (the distributed learner);
        # without, between updates (main.py: the same cadence and rows, in line)
        self.background = (
            BackgroundEvaluation(self.eval_env, eval_policy, config.eval_config.eval_episodes)
            if self.eval_env is not None and eval_policy is not None
            else None
        )
        self.evaluations_skipped = 0  # due while the one before was still running (background only)
        self.eval_seed = int(config.sac_config.seed or 0) + EVAL_SEED_OFFSET
        self.progress = progress
        self.publish = publish
        self.on_evaluation = on_evaluation
        self.extra_state = extra_state
        self.newest_key = newest_key
        self.counters = RunCounters(
            next_eval=config.eval_config.eval_per_step, next_save=config.sac_config.save_model_per_step
        )
        self._chunk_length = config.actor_config.chunk_length
        self.timers = Timers()
        self._log_skipped = Throttle()
        self.update_rate = RateMeter()
        self.writer: MetricsWriter | None = None
        self.bar: ProgressLine | None = None
        self._started = time.perf_counter()
        self._last_save = time.perf_counter()
        self.finishing = False  # in finish(): the saves now are the last ones
        self.checkpoint_writes = WriteFailures("checkpoint", log, retry="trying again at the next checkpoint",
                                               kept=self._checkpoints_kept)  # fmt: skip
        self.evaluation_writes = WriteFailures(
            "evaluations", log, retry="its row is held and written with the next evaluation's",
            kept=lambda path: f"{path} keeps its rows" if path.exists() else f"{path} was not created",
        )  # fmt: skip
        self.config_writes = WriteFailures("run config", log, retry="trying again at the next checkpoint")
        self._eval_rows: list[list[str]] = []  # evaluations.csv rows not written yet
        self._config_written = False

    # -- lifecycle --------------------------------------------------------------------------
    def resume_then_open(self, restore: Callable[[int | None], object], ckpt_step: int | None) -> None:
        """A run's start in either mode: the mode's ``restore`` from the latest checkpoint (``ckpt_step``:
        that one, also on a new run, where it says there is none), then :meth:`open`. Restored before
        anything is written: a run whose checkpoint cannot be read keeps its files."""
        if list_checkpoints(self.paths.model) or ckpt_step is not None:
            restore(ckpt_step)
        self.open()

    def open(self) -> None:
        """Write the run's config and open its TensorBoard folder (after a restore that worked:
        a run whose checkpoint cannot be read keeps its files)."""
        self.paths.root.mkdir(parents=True, exist_ok=True)
        self._write_config()
        self.writer = MetricsWriter(self.log_dir)
        self.writer.text("config", config_to_yaml(self.config), self.counters.env_steps)

    def start(self) -> None:
        """Start the clocks (wall seconds go on from the checkpoint's) and the progress line."""
        self._started = time.perf_counter() - self.counters.wall_seconds
        self._last_save = time.perf_counter()
        if self.progress and self.bar is None:
            self.bar = ProgressLine(self.config.base_config.max_step)

    def done(self) -> bool:
        return budget_spent(self.config.base_config, self.counters)

    def tick(self, recent_return: float | None = None) -> None:
        """Between updates: wall clock, evaluation and checkpoint when due, the progress line."""
        c = self.counters
        c.wall_seconds = time.perf_counter() - self._started
        self.evaluate_if_due()
        minutes = (time.perf_counter() - self._last_save) / 60
        if c.env_steps >= c.next_save or minutes >= self.config.sac_config.save_model_per_minute:
            self.save()
        if self.bar is not None:
            shown = recent_return if recent_return is not None else c.last_eval_mean
            self.bar.update(c.env_steps, c.updates, self.update_rate.mark(c.updates), shown)

    def finish(self) -> Path | None:
        """End of a run (budget spent, stop asked or interrupted): the final evaluation when the budget
        is spent and none was made at this step, a checkpoint, the writers closed."""
        c = self.counters
        c.wall_seconds = time.perf_counter() - self._started
        if self.bar is not None:
            self.bar.close()
            self.bar = None
        self.finishing = True
        if self.background is not None and (scored := self.background.wait()) is not None:
            self._record(scored)  # the one in flight is kept, whatever stops the run
        if self.done() and self.eval_env is not None and c.last_eval_step != c.env_steps:
            self.evaluate()
        elif self._eval_rows:
            self._write_evaluations()
        path = self.save()
        if self.writer is not None:
            self.writer.close()
        return path

    # -- the update -------------------------------------------------------------------------
    def train_on(
        self, batch: Batch, sink: TrainingSink, extra_metrics: Callable[[], dict[str, float]] = dict
    ) -> UpdateResult:
        """One SAC update on ``batch``; its priorities (when they matter and the step was not skipped)
        and refreshed recurrent states go to ``sink``; weights are published every
        ``update_policy_variables_per_step`` updates; every ``write_summary_per_step`` the metrics
        (the update's, ``extra_metrics()``, phase times, rates) are written."""
        cfg = self.config
        c = self.counters
        with_metrics = c.updates % cfg.sac_config.write_summary_per_step == 0
        with self.timers.phase("update"):
            result = self.sac.update(batch, with_metrics=with_metrics)
        if result.skipped and self._log_skipped():
            log.warning("update skipped: non-finite loss or gradient (%d skipped so far; %d in a row stop the run)",
                        self.sac.nonfinite_skipped, cfg.sac_config.max_nonfinite_steps)  # fmt: skip
        if cfg.replay_config.alpha > 0 and not result.skipped:
            with self.timers.phase("priorities"):
                sink.update_priorities(batch.keys, result.td_abs)
        if cfg.sac_config.insert_td_priorities:
            with self.timers.phase("score_new"):
                self._score_new_data(sink)
        if result.refreshed_rnn_states is not None:
            with self.timers.phase("rnn_refresh"):
                sink.update_rnn_states(*result.refreshed_rnn_states)
        c.updates += 1
        if c.updates % cfg.sac_config.update_policy_variables_per_step == 0:
            with self.timers.phase("publish"):
                self.publish()
        if with_metrics:
            age = {} if self.newest_key is None else sample_age(batch.keys, self.newest_key(), self._chunk_length)
            self.write_summary({**result.metrics, **age, **extra_metrics()})
        return result

    def _score_new_data(self, sink: TrainingSink) -> None:
        """``insert_td_priorities``: the steps stored since the last call (a batch at a time) get their
        |TD| under the current networks as priority, in place of the maximum priority the table gave
        them on insert (the original's ``use_add_with_td`` scored an episode before adding
        it; here a step may be sampled once at the maximum before it is scored)."""
        c, limit = self.counters, self.config.replay_config.batch_size
        while (new := sink.windows_after(c.scored_below, limit)) is not None:  # each stored step once
            sink.update_priorities(new.keys, self.sac.td_errors(new))
            c.scored_below = int(new.keys.max()) + 1
            if new.batch_size < limit:
                break

    def write_summary(self, metrics: dict[str, float]) -> None:
        c = self.counters
        if self.writer is None:
            return
        self.writer.write(
            {
                **metrics,
                **self.timers.fractions(),
                "learner/updates": float(c.updates),
                "time/updates_per_second": self.update_rate.mark(c.updates),
                "time/wall_seconds": c.wall_seconds,
            },
            c.env_steps,
        )

    def write(self, metrics: dict[str, float]) -> None:
        """Scalars at the current env step (episode returns, staleness)."""
        if self.writer is not None:
            self.writer.write(metrics, self.counters.env_steps)

    # -- evaluation -------------------------------------------------------------------------
    def evaluate_if_due(self) -> None:
        """Evaluate when ``next_eval`` is reached, unless the budget is spent: then :meth:`finish`'s
        final evaluation, after the last updates, is the one (a distributed learner trains on what
        the replay still owes it first, so a due one here would be a second row a few steps before).
        In the background, a finished evaluation is recorded here, and one due while another still
        runs is skipped (counted, ``eval/skipped``)."""
        c = self.counters
        if self.background is not None and (scored := self.background.collect()) is not None:
            self._record(scored)
        if self.eval_env is None or self.done() or c.env_steps < c.next_eval:
            return
        if self.background is None:
            self.evaluate()
            return
        if self.background.busy():
            self.evaluations_skipped += 1
        else:
            seed = self.eval_seed if not c.evaluations else None  # one seeded stream a run (in its checkpoints)
            self.background.start(self.sac.acting_state_dict(), c.env_steps, c.updates, c.wall_seconds, seed)
        self._advance_next_eval()

    def _advance_next_eval(self) -> None:
        """The next evaluation: at the next multiple of ``eval_per_step`` past the current env step
        (a jump over several multiples evaluates once)."""
        c, every = self.counters, self.config.eval_config.eval_per_step
        if c.env_steps >= c.next_eval:
            c.next_eval += every * math.ceil((c.env_steps - c.next_eval + 1) / every)

    def evaluate(self) -> EvalResult:
        """Evaluate the policy on the eval envs now, in this thread (after the one in the background, if
        any, is recorded)."""
        assert self.eval_env is not None
        c = self.counters
        if self.background is not None and (scored := self.background.wait()) is not None:
            self._record(scored)
        with self.timers.phase("eval"):
            seed = self.eval_seed if not c.evaluations else None  # one seeded stream a run (in its checkpoints)
            result = evaluate(self.eval_env, self.sac, self.config.eval_config.eval_episodes, seed)
        self._record(Scored(c.env_steps, c.updates, c.wall_seconds, result))
        self._advance_next_eval()
        return result

    def _record(self, scored: Scored) -> None:
        """An evaluation's row, scalars, log line and callback, at the counters of the weights it scored."""
        c, result = self.counters, scored.result
        c.evaluations += 1
        c.last_eval_mean, c.last_eval_step = result.mean, scored.env_steps
        self._eval_rows.append(evaluation_row(scored.env_steps, scored.updates, scored.wall_seconds, result))
        self._write_evaluations()
        if self.writer is not None:
            self.writer.write(
                {
                    "eval/return_mean": result.mean,
                    "eval/return_std": result.std,
                    "eval/episode_length": float(result.lengths.mean()),
                    **({} if self.background is None else {"eval/skipped": float(self.evaluations_skipped)}),
                },
                scored.env_steps,
            )
        log.info("eval at %d env steps, %d updates: return %.1f +- %.1f", scored.env_steps, scored.updates,
                 result.mean, result.std)  # fmt: skip
        self.on_evaluation(result.mean, scored.env_steps)

    def _write_evaluations(self) -> None:
        """The rows not written yet, all or none (the next evaluation tries again)."""
        path, rows = self.paths.evaluations, self._eval_rows
        if self.evaluation_writes.attempt(path, lambda: append_evaluations(path, rows), final=self.finishing):
            self._eval_rows = []
        elif self.finishing:
            log.error("%d evaluation rows are not in %s (each is in an \"eval at\" line of the log above)",
                      len(rows), path)  # fmt: skip

    # -- checkpoints ------------------------------------------------------------------------
    def save(self) -> Path | None:
        """Checkpoint the SAC state, counters, global RNGs and the mode's ``extra_state()`` as
        ``model/<env_steps>.pt``; None when it could not be written (logged; the checkpoints before
        it are kept and the next one is due at the next interval, as if this one had been written)."""
        c, cfg = self.counters, self.config.sac_config
        while c.next_save <= c.env_steps:
            c.next_save += cfg.save_model_per_step
        if not self._config_written:
            self._write_config()
        extra = self.extra_state()  # first: it may bring counters up to date (the budget's balance)
        state = {"sac": self.sac.state_dict(), "counters": asdict(c), "rng": capture_rng(), **extra}
        if self.eval_env is not None:  # the evaluations after a resume go on with the stream's next starts
            state["eval_env_rng"] = self.eval_env.rng_states()
        path = self.paths.model / f"{c.env_steps}.pt"
        written = self.checkpoint_writes.attempt(
            path,
            lambda: save_checkpoint(self.paths.model, c.env_steps, state, keep=cfg.keep_checkpoints),
            final=self.finishing,
        )
        self._last_save = time.perf_counter()
        if not written:
            return None
        log.info("checkpoint %s (%d updates)", path, c.updates)
        return path

    def _checkpoints_kept(self, path: Path) -> str:
        try:
            steps = list_checkpoints(self.paths.model)
        except OSError:
            steps = []
        if not steps:
            return "no checkpoint of this run is on disk yet"
        return f"the checkpoints before it are kept (the latest: {self.paths.model / f'{steps[-1]}.pt'})"

    def _write_config(self) -> None:
        """``config.yaml``, atomically: a resumed run whose disk is full keeps the file it has."""
        path, text = self.paths.config, config_to_yaml(self.config).encode()
        self._config_written = self.config_writes.attempt(path, lambda: atomic_write(path, lambda f: f.write(text)))

    def restore(self, step: int | None = None) -> tuple[Path, dict[str, Any]]:
        """Resume from checkpoint ``step`` (default: the latest): SAC state, counters, global RNGs.
        Returns the path and the whole state for the mode's extras. A damaged or foreign file is a
        :class:`~algorithm.run.checkpoint.CheckpointError` naming it, never a fallback to an older one."""
        path, state = load_for_resume(self.paths.model, step)
        with restoring(path):
            self.sac.load_state_dict(state["sac"])
            self.counters = RunCounters.from_checkpoint(state["counters"], self.counters)
            restore_rng(state["rng"])
            if self.eval_env is not None:
                restore_env_rngs(self.eval_env, state.get("eval_env_rng"), "evaluation", path)
        return path, state


def restore_env_rngs(env: VectorEnvLike, states: list[dict[str, Any]] | None, which: str, path: Path) -> bool:
    """Put a checkpoint's env RNGs (``VectorEnv.rng_states``) back into ``env``; whether it did. None (a
    checkpoint written without them) leaves the envs as made: their streams start again from their seeds.
    States that do not fit (a run resumed with another env count) are logged, and the envs draw their
    starts anew."""
    if states is None:
        return False
    try:
        env.set_rng_states(states)
    except ValueError as err:
        log.info("%s envs' RNGs in %s not used (%s): their episodes start anew", which, path, err)
        return False
    return True


def last_evaluation(path: Path) -> tuple[int, float] | None:
    """The last row of an ``evaluations.csv`` as ``(env_steps, return_mean)``; None without one
    (or when it cannot be read: this is for messages, never for decisions)."""
    try:
        rows = read_evaluations(path)
    except (OSError, ValueError, TypeError):
        return None
    return (int(rows[-1]["env_steps"]), rows[-1]["return_mean"]) if rows else None
