"""The learner role: SAC trained from a replay over the network, publishing its acting weights.

Usage (``ds/learner/role.py`` composes the parts; tests pass an in-process table or a loopback client)::

    learner = Learner(config, run_dir, sac, replay, publisher, store, eval_env=env, stop=stop_event)
    summary = learner.run()     # until replay has seen base_config.max_step env steps, or stop is set

Inside, three threads keep the update loop busy without ever dropping data (ds/learner/feeds.py):

- :class:`BatchPrefetcher` samples the next batches from the replay into a bounded queue while the
  main thread trains on the current one (a full queue blocks it, counted);
- the main thread runs ``SAC.update`` and, every ``update_policy_variables_per_step`` updates,
  publishes the acting weights once over ZeroMQ and to ``GetParams`` (:class:`ParamsStore`);
- :class:`PriorityUpdater` sends the new priorities back to the replay in merged batches, from a
  bounded queue (a full queue blocks the learner, counted).

The learner counts env steps by the replay's ``inserted_steps`` (actors may come and go). Its
lifecycle is the single-process trainer's, written once in algorithm/run/learner_core.py: it evaluates
every ``eval_per_step`` env steps on its own envs (``evaluations.csv``, ``eval/*``; with ``eval_policy``,
a copy of the acting weights, on a thread of its own while training goes on), checkpoints in
the same format (``model/<env_steps>.pt``), resumes from the latest checkpoint when started again on
the same run directory, and at ``max_step`` first trains on what the replay still owes it (its rate
limiter's surplus: the data inserted before the stop is trained on as the ratio says), then makes
its final evaluation and checkpoint.

In an evolver's population (``member``, ds/member/link.py) it also posts every evaluation's return,
copies its full weights for the evolver's GetWeights between updates, loads the CEM samples the
evolver draws for it (:meth:`SAC.load_model_weights`; one waiting when it starts, a new learner's draw
of the CEM distribution, before its first update) and publishes them to its actors at once,
follows its replay to a new address, and stops, checkpointed, when the evolver retires it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from algorithm.config.schema import Config
from algorithm.replay import ReplayTable, ReplayUnavailable
from algorithm.run.actor import VectorEnvLike
from algorithm.run.evaluation import AcceptsWeights
from algorithm.run.folder import RunDir
from algorithm.run.learner_core import LearnerCore
from algorithm.run.progress import RunSummary
from algorithm.sac.learner import SAC
from algorithm.types import Batch
from ds.learner.feeds import BatchPrefetcher, PriorityUpdater, replay_link
from ds.learner.service import ActorRegistry, ParamsStore, PublishedPolicy
from ds.member.link import Membership
from ds.net.params import ParamsPublisher
from ds.replay.client import LAST_INSERTS_WAIT_S

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


class _RemoteTrainingSink:
    """Where an update's results go over the network: priorities through the :class:`PriorityUpdater`
    (merged, in the background), refreshed recurrent states straight to the replay (skipped and
    counted while it cannot be reached: a refresh only freshens stored states)."""

    def __init__(self, learner: Learner) -> None:
        self.learner = learner

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> None:
        self.learner.priorities.put(keys, priorities)

    def update_rnn_states(self, keys: np.ndarray, states: np.ndarray) -> None:
        try:
            self.learner.replay.update_rnn_states(keys, states)
        except ReplayUnavailable:
            self.learner.rnn_refreshes_skipped += 1

    def windows_after(self, key: int, limit: int) -> Batch | None:
        try:
            return self.learner.replay.windows_after(key, limit)
        except ReplayUnavailable:
            return None  # scored at a later update, when the replay is back


class Learner:
    """The learner loop; see the module docstring. ``stop`` ends it (then it checkpoints and closes).

    The replay's counters are polled every ``info_every_s``: the run's env steps, hence the stop at
    ``max_step``, are as fresh as that (a Pendulum learner with a small net takes ~300 steps/s, so a
    1 s poll ended runs ~250 steps late; a poll costs about a millisecond)."""

    def __init__(
        self,
        config: Config,
        run_dir: Path,
        sac: SAC,
        replay: ReplayTable,
        publisher: ParamsPublisher,
        store: ParamsStore,
        *,
        acting: PublishedPolicy | None = None,
        registry: ActorRegistry | None = None,
        eval_env: VectorEnvLike | None = None,
        eval_policy: AcceptsWeights | None = None,
        stop: threading.Event | None = None,
        ckpt_step: int | None = None,
        progress: bool = False,
        member: Membership | None = None,
        prefetch_depth: int = 16,
        info_every_s: float = 0.25,
        republish_every_s: float = 2.0,
    ) -> None:
        self.config = config
        self.sac, self.replay, self.publisher, self.store = sac, replay, publisher, store
        self.acting, self.registry = acting, registry
        if registry is not None:
            registry.updates = lambda: self.updates  # heartbeats say it: actors estimate their staleness
        self.member = member
        self.replay_address = "" if member is None else member.link.replay_address
        self.prefetch_depth = prefetch_depth
        self.stop = stop or threading.Event()
        self.info_every_s = info_every_s
        self.republish_every_s = republish_every_s
        self.replay_link = replay_link(replay)
        self.prefetcher = self._prefetcher(replay)
        self.priorities = PriorityUpdater(replay, link=self.replay_link)
        self.rnn_refreshes_skipped = 0
        self.publish_deferred = 0  # updates whose publish waited for the budget (the next one carries them)
        self._next_publish = 0.0  # perf_counter time before which a publish waits (publish_budget)
        self.replay_surplus = 0.0  # windows the replay's rate limiter still lets this learner draw
        self.replay_next_key = 0  # the replay's next key at the last poll: how old sampled data is
        self.sink = _RemoteTrainingSink(self)
        on_evaluation: Callable[[float, int], None] = (lambda mean, steps: None) if member is None else member.link.post
        self.core = LearnerCore(
            config, Path(run_dir), sac, log_dir=RunDir(Path(run_dir)).role_log("learner"), eval_env=eval_env,
            progress=progress, publish=self.publish, on_evaluation=on_evaluation,
            newest_key=lambda: self.replay_next_key, eval_policy=eval_policy,
        )  # fmt: skip
        self.paths = self.core.paths
        self.env_steps = EnvSteps()
        self.core.resume_then_open(self.restore, ckpt_step)

    @property
    def updates(self) -> int:
        return self.core.counters.updates

    @property
    def evaluations(self) -> int:
        return self.core.counters.evaluations

    # -- the loop ---------------------------------------------------------------------------
    def run(self) -> RunSummary:
        core, c = self.core, self.core.counters
        if core.done():  # started again on a finished run: nothing to train, nothing to change
            result = "n/a" if c.last_eval_mean is None else f"{c.last_eval_mean:.1f}"
            log.info("already finished at %d env steps; last eval return %s", c.env_steps, result)
            if self.registry is not None:
                self.registry.run_done.set()
            return RunSummary.of(c, False)
        last_info = last_publish = time.perf_counter()
        core.start()
        if self.member is not None:  # a learner that joined after a round starts from its sample
            self._load_sample(self.member)
        self.publish()
        self.prefetcher.start()
        self.priorities.start()
        self._poll_replay()
        try:
            while not self.stop.is_set() and not core.done() and not self._leaving():
                now = time.perf_counter()
                if self.member is not None:  # between two updates: a consistent copy for the evolver
                    self.member.snapshot.offer(c.updates, self.sac.models.state_dict)
                if now - last_info >= self.info_every_s:
                    self._poll_replay()
                    last_info = now
                    if self.member is not None:
                        self._follow_evolver(self.member)
                    core.tick()
                with core.timers.phase("wait"):
                    batch = self.prefetcher.get(timeout=0.5)
                if batch is None:
                    self._next_publish = 0.0  # waiting for data: the latest weights go out now
                    self.publish()
                    if now - last_publish >= self.republish_every_s:
                        self.publisher.republish()  # reaches subscribers that joined while we wait
                        last_publish = now
                    continue
                self._train_on(batch)
            if core.done() and not self.stop.is_set():
                if self.registry is not None:
                    self.registry.run_done.set()  # heartbeats tell the actors to stop stepping
                self._train_until_actors_leave()
                self._train_on_what_is_owed()
        finally:
            self.prefetcher.stop()
            self.priorities.close()
        retired = self.member is not None and self.member.link.retired
        interrupted = not core.done() and not retired
        core.finish()
        return RunSummary.of(c, interrupted, retired)

    def _prefetcher(self, replay: ReplayTable) -> BatchPrefetcher:
        batch_size, on_cuda = self.config.replay_config.batch_size, self.sac.device.type == "cuda"
        return BatchPrefetcher(replay, batch_size, self.prefetch_depth, pin_memory=on_cuda, link=self.replay_link)

    def _train_on(self, batch: Batch) -> None:
        self.core.train_on(batch, self.sink, self._metrics)

    def _train_on_what_is_owed(self) -> None:
        """At ``max_step``: the updates the data inserted so far still asks for (the replay's rate
        limiter surplus, in batches) plus the batches already fetched, so the last data is trained on."""
        batch_size = self.config.replay_config.batch_size
        self._poll_replay()
        owed = math.floor(max(self.replay_surplus, 0.0) / batch_size) + self.prefetcher.ahead
        trained = 0
        while trained < owed and not self.stop.is_set():
            batch = self.prefetcher.get(timeout=1.0)
            if batch is None:
                break  # nothing more to draw: the ratio is met
            self._train_on(batch)
            trained += 1
        if trained:
            log.info("trained %d more updates on the data inserted before max_step", trained)

    def _train_until_actors_leave(self) -> None:
        """After ``max_step``: go on training, as the replay's ratio lets batches through, until every
        live actor has heard that the run is done, sent what it held (its last inserts wait in the
        rate limiter for these updates) and left, so nothing collected is thrown away and it is all
        trained on. Actors beat at least every third of a lease and their last inserts wait at most
        :data:`LAST_INSERTS_WAIT_S` in all; one that has not left by then has gone (its lease lingers)."""
        registry = self.registry
        if registry is None:
            return
        deadline = time.monotonic() + registry.lease_s / 3 + 1.0 + LAST_INSERTS_WAIT_S + 2.0
        last_info = time.perf_counter()
        while registry.alive() and time.monotonic() < deadline and not self.stop.is_set():
            with self.core.timers.phase("wait"):
                batch = self.prefetcher.get(timeout=0.1)
            if batch is not None:
                self._train_on(batch)
            if time.perf_counter() - last_info >= self.info_every_s:
                self._poll_replay()
                last_info = time.perf_counter()

    def _leaving(self) -> bool:
        return self.member is not None and (self.member.link.retired or self.member.link.lost is not None)

    def publish(self, force: bool = False) -> None:
        """Serialise the acting weights once; send them to subscribers, GetParams and GetAction.
        The version is the update count; ``force`` publishes without a new update (new weights loaded),
        and at once. Otherwise publishing keeps to its budget (``sac_config.publish_budget``): a publish
        that took t seconds is followed by the next only once t / budget seconds have passed, so it
        costs the learner at most that share of its time; the latest weights go out at the next update
        after that (or while the learner waits for data)."""
        version, last = self.updates, self.publisher.version
        if last is not None and version <= last:
            if not force:
                return
            version = last + 1
        elif not force and time.perf_counter() < self._next_publish:
            self.publish_deferred += 1
            return
        started = time.perf_counter()
        state = self.sac.acting_state_dict()
        self.publisher.publish(version, state)
        assert self.publisher.frames is not None
        self.store.put(version, self.publisher.frames)
        if self.acting is not None:
            self.acting.load(version, state)
        ended = time.perf_counter()
        budget = self.config.sac_config.publish_budget
        self._next_publish = ended + (ended - started) / budget if budget > 0 else ended

    def _follow_evolver(self, member: Membership) -> None:
        """Between updates: load a CEM sample that arrived, and follow the replay to a new address."""
        member.link.env_steps = self.env_steps.total
        self._load_sample(member)
        address = member.link.replay_address
        if address and address != self.replay_address:
            log.info(
                "the evolver moved this learner's replay from %s to %s: reconnecting", self.replay_address, address
            )
            self.prefetcher.stop()
            self.priorities.close(timeout=1.0)
            self.replay, self.replay_address = member.connect_replay(address), address
            self.env_steps.seen = 0  # a new table counts its inserts from 0; each is an env step of this run
            self.replay_link = replay_link(self.replay)
            self.prefetcher = self._prefetcher(self.replay)
            self.priorities = PriorityUpdater(self.replay, link=self.replay_link)
            self.prefetcher.start()
            self.priorities.start()

    def _load_sample(self, member: Membership) -> None:
        """Load the CEM sample the link holds, if any, and publish it."""
        sample = member.link.take_sample()
        if sample is not None:
            self.sac.load_model_weights(sample.weights)
            self.core.counters.weights_round = sample.round
            member.link.loaded(sample.round)
            self.publish(force=True)  # actors act with the new weights from their next step
            log.info("loaded the CEM sample of round %d (targets hard-copied, optimizer moments reset); "
                     "published as version %s", sample.round, self.publisher.version)  # fmt: skip

    def _poll_replay(self) -> None:
        """Env steps from the replay's counters and, with use_normalization, its observation stats."""
        try:
            info = self.replay.info()
        except ReplayUnavailable as e:
            self.replay_link.failed(str(e), "training goes on with the batches the learner holds")
            return
        self.replay_link.ok()
        self.core.counters.env_steps = self.env_steps.observe(int(info["inserted_steps"]))
        self.core.counters.replay_inserted_seen = self.env_steps.seen
        self.replay_surplus = float(info.get("rate_limiter_surplus", 0.0))
        self.replay_next_key = int(info.get("next_key", 0))
        if self.config.sac_config.use_normalization and info.get("normalizer"):
            self.sac.load_normalizer_stats(info["normalizer"])

    def _metrics(self) -> dict[str, float]:
        metrics: dict[str, float] = {
            **self.prefetcher.metrics(),
            **self.priorities.metrics(),
            **{f"learner/{k}": float(v) for k, v in self.publisher.metrics().items()},
            "learner/rnn_refreshes_skipped": float(self.rnn_refreshes_skipped),
            "learner/publish_deferred": float(self.publish_deferred),
        }
        if self.registry is not None:
            metrics["learner/actors"] = float(len(self.registry.alive()))
            metrics["learner/actors_registered"] = float(self.registry.registered)
            metrics["learner/actors_expired"] = float(self.registry.expired)
        return metrics

    # -- checkpoints ------------------------------------------------------------------------
    def save(self) -> Path | None:
        """Checkpoint as ``model/<env_steps>.pt`` (the format of ``main.py``, so ``main.py --run`` plays it);
        None when it could not be written (logged; the earlier ones are kept)."""
        return self.core.save()

    def restore(self, step: int | None = None) -> None:
        """Resume from checkpoint ``step`` (default: the latest); a damaged or foreign file is a
        :class:`~algorithm.run.checkpoint.CheckpointError` naming it, never a fallback to an older one."""
        path, _ = self.core.restore(step)
        c = self.core.counters
        self.env_steps = EnvSteps(c.env_steps, c.replay_inserted_seen)
        # What was restored, read back from the live objects (the fault tests compare it with the file).
        log.info("resumed from %s at %d env steps, %d updates (log_alpha %r, optimizer steps %s)", path,
                 c.env_steps, c.updates, self.sac.log_alpha.item(), optimizer_steps(self.sac))  # fmt: skip
        if self.member is not None and c.weights_round:
            self.member.link.loaded(c.weights_round)


def optimizer_steps(sac: SAC) -> dict[str, int]:
    """Adam's step count per optimizer of ``sac`` (0 before its first step)."""
    out = {}
    for name, state in sac.state_dict()["optimizers"].items():
        out[name] = max((int(s["step"]) for s in state["state"].values() if "step" in s), default=0)
    return out
