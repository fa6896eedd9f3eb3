"""The actor role: the single-process actor loop, fed with the learner's weights, feeding the replay.

Usage (``ds/actor/role.py`` composes the parts)::

    actor = DistributedActor(config, run_dir, make_env, sac, replay, learner, learner_host="10.0.0.2")
    summary = actor.run()   # until the learner says the run is done (max_step), or stop is set

What it does, in order: waits for the replay and the learner (logging what it waits for); registers
with the learner, which gives it an id, an index and a lease; derives its env seeds and its
exploration noise ``min(noise_increasing_rate * index, noise_max)`` (or ``--noise``) from the index;
takes the latest weights with ``GetParams`` and then keeps the newest broadcast version between
steps (``update_policy_mode: true``), or asks the learner for every action (``false``); and runs
:class:`~algorithm.run.actor.ActorLoop` with a :class:`~ds.actor.sink.ReplaySink`, which never drops a
chunk while the run goes on: the replay's rate limiter holding inserts back (the learner is behind)
and an unreachable replay hold the actor back (it stops stepping; its backlog stays within
``ReplaySink.max_backlog`` chunks), counted and logged. A heartbeat thread renews its lease every
few seconds (at most a third of the lease), whatever the acting thread waits for; a learner that
restarted (new id) or forgot it (lease expired: this process was stopped or cut off for longer) is
registered with again, keeping the index. The learner says when the run's budget is spent (its
heartbeat answer: it counts every actor's steps, across replay restarts); a replay that has itself
seen ``max_step`` inserts is taken as the same sign. Near the end it stops stepping once what it
holds reaches its share of what is left (``(max_step - the replay's count) / live actors``, the
learner saying how many actors are live) and waits for that to be stored, so the actors together
pass the budget by little (:meth:`DistributedActor._holds_the_rest_of_the_budget`). A replay that
does not answer (down, or stalled) is waited for; chunks stay in the sink until the replay
acknowledges them. At the end (budget spent, ``max_iter`` or a signal) the open chunks and the
sink's backlog get one last try each, without waiting in the rate limiter or retrying a replay that
is gone; what was not stored is counted (``actor/unsent_steps``) and logged in one line.

Nothing non-finite goes out or comes in: chunks with NaN/inf are dropped by the loop (counted:
``actor/nonfinite_steps``) and broadcast weights that fail :func:`~ds.net.params.decode_params` (NaN/inf
values, a wrong shape, a MAC that does not verify under the key of the learner it registered with:
another process on the learner's port, whatever version it claims) are never loaded (counted:
``actor/params_rejected``, logged once per interval).
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import grpc
import numpy as np
import torch

from algorithm.config.schema import Config
from algorithm.replay import ReplayUnavailable
from algorithm.run.actor import ActorLoop, VectorEnvLike
from algorithm.run.folder import RunDir
from algorithm.run.logging import MetricsWriter, RateMeter, Throttle
from algorithm.sac.policy import Policy
from ds.actor.sink import ReplaySink
from ds.actor.staleness import Staleness
from ds.learner import service as learner_service
from ds.learner.client import LearnerClient, LeaseExpired, Registration, RemotePolicy
from ds.net.outage import Outage
from ds.net.params import ParamsError, ParamsSubscriber, Token, decode_params, params_spec
from ds.net.rpc import peer_unresponsive, wait_until_serving
from ds.net.stream_key import StreamKey
from ds.replay import service as replay_service
from ds.replay.client import LAST_INSERTS_WAIT_S, ReplayClient

log = logging.getLogger("asac.actor")
ACTOR_SEED_STRIDE = 1000  # actor i's env j gets seed + 1000 * (i + 1) + j: never a training or eval seed
LEARNER_GONE_WARN_S = 10.0
"""How long the learner must have been unreachable before an actor warns. A learner's orderly stop closes
its server a few seconds before the actors are told to stop (a local run stops the learner first: it
saves), and a heartbeat falling in that gap is no fault; a learner gone for longer is warned about."""


def actor_noise(config: Config, index: int, override: float | None = None) -> float:
    """``min(noise_increasing_rate * index, noise_max)``, or ``override`` (``--noise``); docs/architecture.md
    section 9."""
    if override is not None:
        return float(override)
    actor = config.actor_config
    return float(min(actor.noise_increasing_rate * index, actor.noise_max))


@dataclass
class ActorSummary:
    index: int
    env_steps: int
    episodes: int
    interrupted: bool


class DistributedActor:
    """One actor process; see the module docstring. ``make_env(num_envs, seed)`` builds its envs
    once its index (hence its seed) is known; ``sac`` is a model built from the same config as the
    learner's, which receives the published weights (unused with ``update_policy_mode: false``);
    those weights must carry the HMAC of the learner it registered with (its stream key, with
    ``token`` when the run has one: ds/net/params.py), else they are dropped."""

    def __init__(
        self,
        config: Config,
        run_dir: Path,
        make_env: Callable[[int, int], VectorEnvLike],
        sac: Policy,
        replay: ReplayClient,
        learner: LearnerClient,
        learner_host: str,
        *,
        noise: float | None = None,
        stop: threading.Event | None = None,
        token: Token = None,
        heartbeat_s: float = 3.0,
        metrics_every_s: float = 10.0,
        name: str | None = None,
    ) -> None:
        self.config = config
        self.run_dir = Path(run_dir)
        self.make_env = make_env
        self.sac = sac
        self.replay = replay
        self.learner = learner
        self.learner_host = learner_host
        self.noise_override = noise
        self.token = token
        self.stop = stop or threading.Event()
        self.heartbeat_s = heartbeat_s
        self.metrics_every_s = metrics_every_s
        self.name = name or f"actor on {socket.gethostname()} (pid {os.getpid()})"
        self.update_mode = config.actor_config.update_policy_mode
        self.registration: Registration | None = None
        self.subscriber: ParamsSubscriber | None = None
        self.params_version = -1
        self.staleness = Staleness()  # updates behind the learner at each step (heartbeats tell its count)
        self.params_applied = 0
        self.params_rejected = 0
        self.loop: ActorLoop | None = None
        self.env_steps = 0
        self.episodes = 0
        self.done = False
        # The actors holding a lease, as the learner said at registration and in its latest heartbeat
        # answer (at least 1): near the budget this actor's share of what is left is 1 / this.
        self.live_actors = 1
        actor_cfg = config.actor_config
        self.sink = ReplaySink(
            replay,
            lambda: self.stop.is_set() or self.done,
            between=self._between,
            # held back by the rate limiter (the learner trains on), it keeps taking the newest weights:
            # a subscriber not read holds old versions and ZeroMQ drops the newer ones meanwhile
            waiting=self._take_new_params,
            in_flight=actor_cfg.inserts_in_flight,
            max_chunks_per_insert=actor_cfg.chunks_per_insert or config.base_config.n_agents,
            # at the run's end the learner trains until the actors leave: the last inserts may wait
            # for it; after a signal nothing is waited for (the learner may be stopping too)
            last_try_wait_s=lambda: 0.0 if self.stop.is_set() else LAST_INSERTS_WAIT_S,
        )
        self._last_check = time.monotonic()
        self._last_rejoin = -float("inf")
        self._rejoin = threading.Event()  # set by the heartbeat thread: the learner forgot us, or restarted
        self._beats_done = threading.Event()
        self._beat_error: Exception | None = None
        self._log_params = Throttle()
        self._learner_link = Outage(f"learner at {learner.address}", log, LEARNER_GONE_WARN_S)

    # -- the loop ---------------------------------------------------------------------------
    def run(self) -> ActorSummary:
        if not self._wait_for_peers():
            return ActorSummary(-1, 0, 0, True)
        try:
            reg = self._register()
            if self.update_mode:
                self._fetch_params()
        except grpc.RpcError as e:
            if not (self.stop.is_set() and peer_unresponsive(e.code())):
                raise
            # A Ctrl-C during start-up: a local run stops the learner first, so this is an orderly stop.
            log.info("stopped while starting: the learner at %s has gone (%s)", self.learner.address, e.code().name)
            return ActorSummary(-1 if self.registration is None else self.registration.index, 0, 0, True)
        index = reg.index
        noise = actor_noise(self.config, index, self.noise_override)
        seed = int(self.config.sac_config.seed or 0) + ACTOR_SEED_STRIDE * (index + 1)
        self.sac.exploration_noise = noise
        self.sac.seed_acting(seed)  # every actor's policy is built from the same config: its own noise
        policy = self.sac if self.update_mode else RemotePolicy(self.learner, noise)
        env = self.make_env(self.config.base_config.n_agents, seed)
        self.loop = loop = ActorLoop.from_config(env, policy, self.sink, self.config, seed)
        writer = MetricsWriter(RunDir(self.run_dir).role_log(f"actor_{index}"))
        writer.write({"actor/noise": noise}, 0)
        log.info("actor %s: index %d, noise %.3f, env seed %d, %d envs", reg.actor_id, index, noise, seed, env.num_envs)
        rate, last_metrics, iterations = RateMeter(), time.monotonic(), 0
        max_iter = self.config.base_config.max_iter
        beats = threading.Thread(target=self._heartbeats, name="heartbeat", daemon=True)
        beats.start()
        try:
            while not self.stop.is_set() and not self.done:
                self.staleness.acted(self.params_version)  # the step's actions come from these weights, now
                try:
                    stats = loop.step()
                except grpc.RpcError as e:  # update_policy_mode false: the learner did not answer
                    self._learner_unreachable(e)
                    self.stop.wait(1.0)
                    continue
                self.env_steps += stats.env_steps
                iterations += stats.iteration_ended
                for episode in stats.episode_metrics():
                    self.episodes += 1
                    writer.write(episode, self.env_steps)
                if max_iter >= 0 and iterations >= max_iter:
                    break
                self._take_new_params()
                self._between()
                if not self.done and self._holds_the_rest_of_the_budget():
                    # Stepping on would only add steps past max_step (up to 2 chunks per env per actor):
                    # send what is held and wait until it is stored, as at any other time (the rate
                    # limiter, a replay that restarts), then take the replay's count.
                    loop.flush()
                    self.sink.flush()
                    self._between()
                if time.monotonic() - last_metrics >= self.metrics_every_s:
                    writer.write(self._metrics(rate.mark(self.env_steps)), self.env_steps)
                    last_metrics = time.monotonic()
            loop.flush()  # the open chunks too: once stopping, one try each, stored or counted as unsent
            self.sink.flush()  # logs what was not stored, once
            self.sink.acknowledge_all()  # the replay may forget this producer
        finally:
            self._beats_done.set()
            beats.join(timeout=1.0)  # a heartbeat still on its way ends with the channel (daemon thread)
            if self.registration is not None:  # everything is sent: the learner need not wait for us
                self.learner.leave(self.registration.actor_id, self.env_steps)
            writer.write(self._metrics(rate.mark(self.env_steps)), self.env_steps)
            writer.close()
            env.close()
            if self.subscriber is not None:
                self.subscriber.close()
        return ActorSummary(index, self.env_steps, self.episodes, self.stop.is_set() and not self.done)

    def _metrics(self, steps_per_s: float) -> dict[str, float]:
        sink = self.sink
        return {
            "actor/env_steps": float(self.env_steps),
            "actor/episodes": float(self.episodes),
            "actor/inserted_steps": float(sink.inserted_steps),
            "actor/insert_waits": float(sink.insert_waits),
            "actor/insert_wait_seconds": sink.wait_seconds,
            "actor/replay_unavailable": float(sink.unavailable),
            "actor/insert_duplicates": float(sink.duplicates),
            "actor/params_version": float(self.params_version),
            "actor/params_applied": float(self.params_applied),
            "actor/params_rejected": float(self.params_rejected),
            "actor/nonfinite_steps": float(0 if self.loop is None else self.loop.nonfinite_steps),
            "actor/insert_backlog": float(sink.backlog()),
            "actor/inserts_in_flight": float(sink.in_flight),
            "actor/insert_link_ms": 1e3 * sink.link_s,
            "actor/unsent_steps": float(sink.unsent_steps),
            "time/env_steps_per_second": steps_per_s,
            **self.staleness.take(),
        }

    # -- peers ------------------------------------------------------------------------------
    def _wait_for_peers(self) -> bool:
        warn = self.config.net_config.peer_warn_s
        return wait_until_serving(
            self.replay.channel,
            replay_service.SERVICE_NAME,
            "replay",
            self.replay.address,
            self.stop,
            warn_after_s=warn,
        ) and wait_until_serving(
            self.learner.channel,
            learner_service.SERVICE_NAME,
            "learner",
            self.learner.address,
            self.stop,
            warn_after_s=warn,
        )

    def _register(self) -> Registration:
        preferred = None if self.registration is None else self.registration.index
        reg = self.learner.register(self.name, preferred)
        if self.registration is not None and reg.learner_id != self.registration.learner_id:
            log.info("learner restarted: registered again as %s (index %d)", reg.actor_id, reg.index)
        elif self.registration is not None:
            log.info("the learner dropped %s (its lease of %.1f s ran out): registered again as %s (index %d)",
                     self.registration.actor_id, reg.lease_s, reg.actor_id, reg.index)  # fmt: skip
        if self.update_mode and (self.subscriber is None or self.registration is None
                                 or reg.learner_id != self.registration.learner_id):  # fmt: skip
            if self.subscriber is not None:
                self.subscriber.close()  # a restarted learner's versions start over
            address = f"tcp://{self.learner_host}:{reg.params_port}"
            spec = params_spec(self.sac.acting_state_dict())
            self.subscriber = ParamsSubscriber(address, spec, token=self.token, stream=self._stream(reg))
            self.params_version = -1
        self.registration = reg
        self.live_actors = max(1, reg.live_actors)
        return reg

    def _stream(self, reg: Registration) -> StreamKey:
        """The key of ``reg``'s learner: only parameters it signed are taken."""
        try:
            return StreamKey(reg.learner_id, reg.params_key)
        except ValueError:
            raise ParamsError(
                f"the learner at {self.learner.address} hands out no parameter key "
                "(RegisterActorReply.params_key): it runs an older ASAC than this actor"
            ) from None

    def _fetch_params(self) -> None:
        """The latest weights over GetParams (a late joiner need not wait for the next broadcast), signed
        by the learner this actor registered with."""
        assert self.registration is not None
        version, frames = self.learner.get_params()
        spec, stream = params_spec(self.sac.acting_state_dict()), self._stream(self.registration)
        try:
            self._apply(*decode_params(frames, spec, token=self.token, stream=stream))
        except ParamsError as e:  # the same check the broadcast gets; here it is a setup error, not noise
            raise ParamsError(
                f"parameters from the learner at {self.learner.address} are not usable: {e}. Do the learner and "
                "this actor run the same task config and name the same secret (net_config.token_file)?"
            ) from None

    def _take_new_params(self) -> None:
        subscriber = self.subscriber
        if subscriber is None:
            return
        rejected = subscriber.rejected
        newer = subscriber.latest()
        if subscriber.rejected > rejected:  # never loaded: NaN/inf values, a bad MAC, a wrong layout
            self.params_rejected += subscriber.rejected - rejected
            if self._log_params():
                log.warning("rejected %d parameter broadcasts so far, acting with version %d; last: %s",
                            self.params_rejected, self.params_version, subscriber.last_error)  # fmt: skip
        if newer is not None:
            self._apply(*newer)

    def _apply(self, version: int, params: dict[str, np.ndarray]) -> None:
        if version <= self.params_version:
            return  # GetParams may have been ahead of the broadcast
        self.sac.load_acting_state_dict({k: torch.from_numpy(v) for k, v in params.items()})
        self.params_version = version
        self.params_applied += 1

    def _beat_interval(self) -> float:
        lease_s = self.registration.lease_s if self.registration is not None else self.heartbeat_s
        return min(self.heartbeat_s, lease_s / 3)

    def _heartbeats(self) -> None:
        """The heartbeat thread: renew the lease every :meth:`_beat_interval` whatever the acting
        thread is doing (stepping a slow env, waiting for a stalled replay: in the acting thread such
        waits let leases run out), and ask it to register again (:meth:`_between`) when the learner no
        longer knows this actor or has restarted (another learner id)."""
        while not self._beats_done.wait(self._beat_interval()):
            reg = self.registration
            if reg is None or self._rejoin.is_set():
                continue
            try:
                beat = self.learner.heartbeat(reg.actor_id, self.env_steps)
                self.staleness.learner_said(beat.updates)
                self._learner_link.ok()
                known = beat.learner_id == reg.learner_id
                if known:
                    self.live_actors = max(1, beat.live_actors)
                if known and beat.run_done and not self.done:
                    log.info("the learner has spent the run's budget (base_config.max_step): done")
                    self.done = True  # the acting thread stops stepping; the sink sends what it holds
            except LeaseExpired:
                known = False
            except (grpc.RpcError, ValueError) as e:
                if self._beats_done.is_set():  # the run ended: its channel closes under the heartbeat on its way
                    return
                if not isinstance(e, grpc.RpcError) or not peer_unresponsive(e.code()):
                    self._beat_error = e  # raised in the acting thread: errors surface
                    return
                self._learner_unreachable(e)
                continue
            if not known and self.registration is reg:  # (a registration made meanwhile is not stale)
                self._rejoin.set()

    def _between(self) -> None:
        """In the acting thread, between steps (and while an insert waits): register again when the
        heartbeat thread asks (at most once per heartbeat interval while the learner does not answer),
        and check whether the run's budget is spent: after every insert from its answer, and every
        ``heartbeat_s`` seconds by asking the replay."""
        if self._beat_error is not None:
            raise self._beat_error
        now = time.monotonic()
        if self._rejoin.is_set() and now - self._last_rejoin >= self._beat_interval():
            self._last_rejoin = now
            try:
                self._register()
                if self.update_mode:
                    self._fetch_params()
                self._rejoin.clear()
                self._learner_link.ok()
            except grpc.RpcError as e:
                self._learner_unreachable(e)
            except ParamsError as e:  # a learner that restarted again between RegisterActor and GetParams
                if self._log_params():
                    log.warning("%s; registering again", e)
        max_step = self.config.base_config.max_step
        if max_step < 0 or self.done:
            return
        # The replay's count never exceeds the run's (the learner's, across replay restarts), so
        # stopping on it is never early; each insert's answer carries it, so an actor stops within
        # what it holds (the learner's heartbeat says so too, but only every few seconds).
        inserted = self.sink.replay_inserted_steps
        if inserted < max_step and now - self._last_check >= self.heartbeat_s:
            self._last_check = now
            with contextlib.suppress(ReplayUnavailable):  # gone or not answering (stalled): the sink waits too
                inserted = self.replay.info()["inserted_steps"]
        if inserted >= max_step:
            log.info("the replay has %d+ env steps (base_config.max_step): done", max_step)
            self.done = True  # the loop stops stepping; the sink sends what it holds

    def _holds_the_rest_of_the_budget(self) -> bool:
        """Whether the env steps this actor holds (sent and unanswered, queued, in open chunks) reach
        its share of what is left of the budget: ``(max_step - count) / live_actors``, ``count`` the
        replay's after the latest answered insert, ``live_actors`` as the learner last said. Each
        actor stops there, so together they hold about what is left. What passes ``max_step`` is what
        an actor held beyond its share when it came near the budget (one waiting in the rate limiter
        with a full backlog does not step, and cannot shed it) and what was stored after its count:
        with four actors, 2 envs each and 16-step chunks, 28-106 steps past 600 where each one taking
        the whole rest as its share passed it by 240 (tests/test_backpressure.py). Never early: a
        count still short of ``max_step`` once this actor's steps are stored lets it step on, with a
        new share."""
        max_step = self.config.base_config.max_step
        inserted = self.sink.replay_inserted_steps
        if max_step < 0 or inserted < 0 or self.loop is None:
            return False
        # Far from the budget even the most an actor can hold is below its share: this runs every env
        # step, and the sums below cost ~2 us (2% of a one-env Pendulum step)
        most_held = (self.sink.max_backlog + self.loop.env.num_envs) * self.config.actor_config.chunk_length
        if inserted + most_held * self.live_actors < max_step:
            return False
        held = self.sink.held_steps() + self.loop.open_steps
        return inserted + held * self.live_actors >= max_step

    def _learner_unreachable(self, error: grpc.RpcError) -> None:
        if not peer_unresponsive(error.code()):
            raise error
        if self.stop.is_set():  # told to stop: the learner may be gone already (a local run stops it first)
            return
        meanwhile = f"acting with parameter version {self.params_version} meanwhile"
        self._learner_link.failed(error.code().name, meanwhile)
