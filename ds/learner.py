"""The learner role: SAC trained from a replay over the network, publishing its acting weights.

Usage (``ds/roles.py`` composes the parts; tests pass an in-process table or a loopback client)::

    learner = Learner(config, run_dir, sac, replay, publisher, store, eval_env=env, stop=stop_event)
    summary = learner.run()     # until replay has seen base_config.max_step env steps, or stop is set

Inside, three threads keep the update loop busy without ever dropping data (ds/replay_feeds.py):

- :class:`BatchPrefetcher` samples the next batches from the replay into a bounded queue while the
  main thread trains on the current one (a full queue blocks it, counted);
- the main thread runs ``SAC.update`` and, every ``update_policy_variables_per_step`` updates,
  publishes the acting weights once over ZeroMQ and to ``GetParams`` (:class:`ParamsStore`);
- :class:`PriorityUpdater` sends the new priorities back to the replay in merged batches, from a
  bounded queue (a full queue blocks the learner, counted).

The learner counts env steps by the replay's ``inserted_steps`` (actors may come and go), evaluates
its own policy every ``eval_per_step`` of them on its own envs (``evaluations.csv``, ``eval/*``),
checkpoints like the single-process trainer (``model/<env_steps>.pt``) and resumes from the latest
checkpoint when started again on the same run directory.

In an evolver's population (``member``, ds/evolver_link.py) it also posts every evaluation's return,
copies its full weights for the evolver's GetWeights between updates, loads the CEM samples the
evolver draws for it (:meth:`SAC.load_model_weights`) and publishes them to its actors at once,
follows its replay to a new address, and stops, checkpointed, when the evolver retires it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from algorithm.actor import VectorEnvLike
from algorithm.checkpoint import (
    capture_rng,
    list_checkpoints,
    load_for_resume,
    restore_rng,
    restoring,
    save_checkpoint,
)
from algorithm.config import config_to_yaml
from algorithm.config_schema import Config
from algorithm.evaluation import append_evaluation, evaluate
from algorithm.logging import MetricsWriter, ProgressLine, RateMeter, Timers
from algorithm.replay import ReplayTable
from algorithm.sac import SAC
from algorithm.trainer import EVAL_SEED_OFFSET, RunDir
from ds.evolver_link import Membership
from ds.learner_service import ActingPolicy, ActorRegistry, ParamsStore
from ds.params import ParamsPublisher
from ds.replay_feeds import BatchPrefetcher, PriorityUpdater, Throttle, unavailable
from ds.replay_service import ReplayRpcError

log = logging.getLogger("asac.learner")


class EnvSteps:
    """Env steps of the whole run, counted from the replay's ``inserted_steps``. A replay restarted
    without its saved contents counts from 0 again: what it inserts then is added, never lost."""

    def __init__(self, total: int = 0, seen: int = 0) -> None:
        self.total = int(total)
        self.seen = int(seen)

    def observe(self, inserted: int) -> int:
        if inserted < self.seen:
            log.warning("replay reports %d inserted steps after %d: it restarted; counting on", inserted, self.seen)
            self.seen = 0
        self.total += inserted - self.seen
        self.seen = inserted
        return self.total


@dataclass
class LearnerSummary:
    env_steps: int
    updates: int
    wall_seconds: float
    last_eval_mean: float | None
    interrupted: bool
    retired: bool = False


class Learner:
    """The learner loop; see the module docstring. ``stop`` ends it (then it checkpoints and closes)."""

    def __init__(
        self,
        config: Config,
        run_dir: Path,
        sac: SAC,
        replay: ReplayTable,
        publisher: ParamsPublisher,
        store: ParamsStore,
        *,
        acting: ActingPolicy | None = None,
        registry: ActorRegistry | None = None,
        eval_env: VectorEnvLike | None = None,
        stop: threading.Event | None = None,
        ckpt_step: int | None = None,
        progress: bool = False,
        member: Membership | None = None,
        prefetch_depth: int = 4,
        info_every_s: float = 1.0,
        republish_every_s: float = 2.0,
    ) -> None:
        self.config = config
        self.paths = RunDir(Path(run_dir))
        self.sac, self.replay, self.publisher, self.store = sac, replay, publisher, store
        self.acting, self.registry, self.eval_env = acting, registry, eval_env
        self.member = member
        self.replay_address = "" if member is None else member.link.replay_address
        self.prefetch_depth = prefetch_depth
        self.stop = stop or threading.Event()
        self.progress = progress
        self.info_every_s = info_every_s
        self.republish_every_s = republish_every_s
        self.prefetcher = BatchPrefetcher(replay, config.replay_config.batch_size, prefetch_depth)
        self.priorities = PriorityUpdater(replay)
        self.updates = 0
        self.rnn_refreshes_skipped = 0
        self.env_steps = EnvSteps()
        self.wall_seconds = 0.0
        self.next_eval = config.eval_config.eval_per_step
        self.next_save = config.sac_config.save_model_per_step
        self.evaluations = 0
        self.last_eval_mean: float | None = None
        self.weights_round = 0  # the CEM round whose sample these weights descend from (0: none)
        self.timers = Timers()
        self.eval_seed = int(config.sac_config.seed or 0) + EVAL_SEED_OFFSET
        self._log_replay = Throttle(30.0)
        self._log_skipped = Throttle(30.0)
        if list_checkpoints(self.paths.model) or ckpt_step is not None:  # --ckpt on a new run: say so
            self.restore(ckpt_step)
        if member is not None and self.weights_round:
            member.link.loaded(self.weights_round)
        self.writer = MetricsWriter(self.paths.log / "learner")
        self.writer.text("config", config_to_yaml(config), self.env_steps.total)

    # -- the loop ---------------------------------------------------------------------------
    def run(self) -> LearnerSummary:
        cfg = self.config
        summary_every = cfg.sac_config.write_summary_per_step
        publish_every = cfg.sac_config.update_policy_variables_per_step
        priorities_matter = cfg.replay_config.alpha > 0
        bar = ProgressLine(cfg.base_config.max_step) if self.progress else None
        rate = RateMeter()
        started = time.perf_counter() - self.wall_seconds
        last_save = last_info = last_publish = time.perf_counter()
        self.publish()
        self.prefetcher.start()
        self.priorities.start()
        self._poll_replay()
        try:
            while not self.stop.is_set() and not self._done() and not self._leaving():
                now = time.perf_counter()
                self.wall_seconds = now - started
                if self.member is not None:  # between two updates: a consistent copy for the evolver
                    self.member.snapshot.offer(self.updates, self.sac.models.state_dict)
                if now - last_info >= self.info_every_s:
                    self._poll_replay()
                    last_info = now
                    if self.member is not None:
                        self._follow_evolver(self.member)
                    self._maybe_evaluate()
                    if (now - last_save) / 60 >= cfg.sac_config.save_model_per_minute or (
                        self.env_steps.total >= self.next_save
                    ):
                        self.save()
                        last_save = time.perf_counter()
                    if bar is not None:
                        bar.update(self.env_steps.total, self.updates, rate.mark(self.updates), self.last_eval_mean)
                with self.timers.phase("wait"):
                    batch = self.prefetcher.get(timeout=0.5)
                if batch is None:
                    if now - last_publish >= self.republish_every_s:
                        self.publisher.republish()  # reaches subscribers that joined while we wait
                        last_publish = now
                    continue
                with_metrics = self.updates % summary_every == 0
                with self.timers.phase("update"):
                    result = self.sac.update(batch, with_metrics=with_metrics)
                if result.skipped and self._log_skipped():
                    skipped, limit = self.sac.nonfinite_skipped, self.config.sac_config.max_nonfinite_steps
                    log.warning("update skipped: non-finite loss or gradient (%d skipped so far; %d in a row stop "
                                "the learner)", skipped, limit)  # fmt: skip
                if priorities_matter and not result.skipped:
                    with self.timers.phase("priorities"):
                        self.priorities.put(batch.keys, result.td_abs)
                if result.refreshed_rnn_states is not None:
                    with self.timers.phase("rnn_refresh"):
                        self._refresh_rnn_states(*result.refreshed_rnn_states)
                self.updates += 1
                if self.updates % publish_every == 0:
                    with self.timers.phase("publish"):
                        self.publish()
                    last_publish = time.perf_counter()
                if with_metrics:
                    self._write_summary(result.metrics, rate.mark(self.updates))
        finally:
            self.prefetcher.stop()
            self.priorities.close()
            if bar is not None:
                bar.close()
        retired = self.member is not None and self.member.link.retired
        interrupted = not self._done() and not retired
        if self._done():
            self._maybe_evaluate(final=True)
        self.save()
        self.writer.close()
        summary = (self.env_steps.total, self.updates, self.wall_seconds, self.last_eval_mean, interrupted, retired)
        return LearnerSummary(*summary)

    def _refresh_rnn_states(self, keys: np.ndarray, states: np.ndarray) -> None:
        """sac_config.refresh_rnn_states: write the recomputed states back. A refresh only freshens
        stored states, so one the replay cannot take now (unreachable) is skipped and counted."""
        try:
            self.replay.update_rnn_states(keys, states)
        except ReplayRpcError as e:
            if not unavailable(e):
                raise
            self.rnn_refreshes_skipped += 1

    def _done(self) -> bool:
        max_step = self.config.base_config.max_step
        return max_step >= 0 and self.env_steps.total >= max_step

    def _leaving(self) -> bool:
        return self.member is not None and (self.member.link.retired or self.member.link.lost is not None)

    def publish(self, force: bool = False) -> None:
        """Serialise the acting weights once; send them to subscribers, GetParams and GetAction.
        The version is the update count; ``force`` publishes without a new update (new weights loaded)."""
        version, last = self.updates, self.publisher.version
        if last is not None and version <= last:
            if not force:
                return
            version = last + 1
        state = self.sac.acting_state_dict()
        self.publisher.publish(version, state)
        assert self.publisher.frames is not None
        self.store.put(version, self.publisher.frames)
        if self.acting is not None:
            self.acting.load(version, state)

    def _follow_evolver(self, member: Membership) -> None:
        """Between updates: load a CEM sample that arrived, and follow the replay to a new address."""
        member.link.env_steps = self.env_steps.total
        sample = member.link.take_sample()
        if sample is not None:
            self.sac.load_model_weights(sample.weights)
            self.weights_round = sample.round
            member.link.loaded(sample.round)
            self.publish(force=True)  # actors act with the new weights from their next step
            log.info("loaded the CEM sample of round %d (targets hard-copied, optimizer moments reset); "
                     "published as version %s", sample.round, self.publisher.version)  # fmt: skip
        address = member.link.replay_address
        if address and address != self.replay_address:
            log.info(
                "the evolver moved this learner's replay from %s to %s: reconnecting", self.replay_address, address
            )
            self.prefetcher.stop()
            self.priorities.close(timeout=1.0)
            self.replay, self.replay_address = member.connect_replay(address), address
            self.env_steps.seen = 0  # a new table counts its inserts from 0; each is an env step of this run
            self.prefetcher = BatchPrefetcher(self.replay, self.config.replay_config.batch_size, self.prefetch_depth)
            self.priorities = PriorityUpdater(self.replay)
            self.prefetcher.start()
            self.priorities.start()

    def _poll_replay(self) -> None:
        """Env steps from the replay's counters and, with use_normalization, its observation stats."""
        try:
            info = self.replay.info()
        except ReplayRpcError as e:
            if not unavailable(e):
                raise
            if self._log_replay():
                log.warning("replay unreachable, waiting for it: %s", e)
            return
        self.env_steps.observe(int(info["inserted_steps"]))
        if self.config.sac_config.use_normalization and info.get("normalizer"):
            self.sac.load_normalizer_stats(info["normalizer"])

    def _maybe_evaluate(self, final: bool = False) -> None:
        every = self.config.eval_config.eval_per_step
        if self.eval_env is None or every <= 0:
            return
        steps = self.env_steps.total
        if steps < self.next_eval and not (final and self.evaluations == 0):
            return
        with self.timers.phase("eval"):
            seed = self.eval_seed if not self.evaluations else None  # one seeded stream per process
            result = evaluate(self.eval_env, self.sac, self.config.eval_config.eval_episodes, seed)
        self.evaluations += 1
        self.last_eval_mean = result.mean
        append_evaluation(self.paths.evaluations, steps, self.updates, self.wall_seconds, result)
        if self.member is not None:
            self.member.link.post(result.mean, steps)
        self.writer.write(
            {
                "eval/return_mean": result.mean,
                "eval/return_std": result.std,
                "eval/episode_length": result.lengths.mean(),
            },
            steps,
        )
        log.info("eval at %d env steps, %d updates: return %.1f +- %.1f", steps, self.updates, result.mean, result.std)
        self.next_eval += every * max(1, math.ceil((steps - self.next_eval + 1) / every))

    def _write_summary(self, learner_metrics: dict[str, float], updates_per_s: float) -> None:
        metrics: dict[str, float] = {
            **learner_metrics,
            **self.prefetcher.metrics(),
            **self.priorities.metrics(),
            **{f"learner/{k}": float(v) for k, v in self.publisher.metrics().items()},
            **self.timers.fractions(),
            "learner/updates": float(self.updates),
            "learner/rnn_refreshes_skipped": float(self.rnn_refreshes_skipped),
            "time/updates_per_second": updates_per_s,
            "time/wall_seconds": self.wall_seconds,
        }
        if self.registry is not None:
            metrics["learner/actors"] = float(len(self.registry.alive()))
            metrics["learner/actors_registered"] = float(self.registry.registered)
            metrics["learner/actors_expired"] = float(self.registry.expired)
        self.writer.write(metrics, self.env_steps.total)

    # -- checkpoints ------------------------------------------------------------------------
    def counters(self) -> dict[str, Any]:
        return {
            "env_steps": self.env_steps.total,
            "replay_inserted_seen": self.env_steps.seen,
            "updates": self.updates,
            "wall_seconds": self.wall_seconds,
            "next_eval": self.next_eval,
            "next_save": self.next_save,
            "evaluations": self.evaluations,
            "weights_round": self.weights_round,
        }

    def save(self) -> Path:
        """Checkpoint the SAC state, counters and RNGs as ``model/<env_steps>.pt`` (the format of
        ``main.py``, so ``main.py --run`` plays it)."""
        while self.next_save <= self.env_steps.total:
            self.next_save += self.config.sac_config.save_model_per_step
        state = {"sac": self.sac.state_dict(), "counters": self.counters(), "rng": capture_rng()}
        keep = self.config.sac_config.keep_checkpoints
        path = save_checkpoint(self.paths.model, self.env_steps.total, state, keep=keep)
        log.info("checkpoint %s (%d updates)", path, self.updates)
        return path

    def restore(self, step: int | None = None) -> None:
        """Resume from checkpoint ``step`` (default: the latest); a damaged or foreign file is a
        :class:`~algorithm.checkpoint.CheckpointError` naming it, never a fallback to an older one."""
        path, state = load_for_resume(self.paths.model, step)
        with restoring(path):
            self.sac.load_state_dict(state["sac"])
            counters = state["counters"]
            self.env_steps = EnvSteps(int(counters["env_steps"]), int(counters["replay_inserted_seen"]))
            self.updates = int(counters["updates"])
            self.wall_seconds = float(counters["wall_seconds"])
            self.next_eval, self.next_save = int(counters["next_eval"]), int(counters["next_save"])
            self.evaluations = int(counters["evaluations"])
            self.weights_round = int(counters.get("weights_round", 0))  # checkpoints from before the evolver lack it
            restore_rng(state["rng"])
        # What was restored, read back from the live objects (the fault tests compare it with the file).
        log.info("resumed from %s at %d env steps, %d updates (log_alpha %r, optimizer steps %s)", path,
                 self.env_steps.total, self.updates, self.sac.log_alpha.item(), optimizer_steps(self.sac))  # fmt: skip


def optimizer_steps(sac: SAC) -> dict[str, int]:
    """Adam's step count per optimizer of ``sac`` (0 before its first step)."""
    out = {}
    for name, state in sac.state_dict()["optimizers"].items():
        out[name] = max((int(s["step"]) for s in state["state"].values() if "step" in s), default=0)
    return out
