"""A learner's live link with the evolver of its population: heartbeats, posted returns, CEM samples
to load, retirement (:class:`EvolverLink`); the snapshot of its full weights the evolver fetches for a
round (:class:`WeightsSnapshot`); and what ds/learner/learner.py gets of both (:class:`Membership`).

Usage (ds/learner/role.py; the learner joined with :func:`ds.member.population.join_population`)::

    link = EvolverLink(client, joined, params_spec(sac.models.state_dict()))
    link.start()                               # a new learner after a round: its first sample; then
                                               # heartbeats every 3 s on a thread of its own
    address = wait_for_replay(link, stop)      # the replay the evolver pairs with this learner
    member = Membership(link, WeightsSnapshot(token), connect_replay)
    LearnerServicer(..., weights=member.snapshot)
    summary = Learner(..., member=member).run()  # posts returns, loads samples, stops when retired
    code = exit_code(link, joined)             # 0 retired, 1 forgotten by the evolver
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import grpc
import torch

from algorithm.replay import ReplayTable
from algorithm.run.logging import Throttle
from ds.evolver.client import EvolverClient, Sample
from ds.evolver.state import Instruction, LearnerRetired, UnknownLearner
from ds.member.population import Joined, register, unreachable
from ds.net.outage import BLIP_S, Outage
from ds.net.params import ParamsError, ParamsSpec, Token, encode_params
from ds.net.rpc import PEER_WARN_AFTER_S

log = logging.getLogger("asac.population")


class EvolverLink:
    """A learner's side of the population, on a thread of its own so that the update loop never
    waits for the evolver.

    Every ``heartbeat_s`` seconds the thread renews the lease (with :attr:`loaded_round`, which
    acknowledges a loaded sample) and follows the orders: LOAD_WEIGHTS fetches the sample, checked
    against ``weights_spec`` (the learner's own full weights), for :meth:`take_sample`; RETIRE sets
    :attr:`retired`; a new replay address lands in :attr:`replay_address`. Returns queued by
    :meth:`post` go out at once, tagged with the round of the weights they describe, and wait while
    the evolver is unreachable (it is waited out: training goes on). A learner that joined as new
    after a CEM round fetches the sample the evolver drew for it in :meth:`start`, before the
    thread starts, so the learner loads it before its first update. A lease that ran out
    (NOT_FOUND) is renewed by registering again with ``previous_id``; if the evolver no longer knows
    the id at all, :attr:`lost` says so and the learner should exit (and start again as a new one).
    """

    def __init__(
        self, client: EvolverClient, joined: Joined, weights_spec: ParamsSpec, heartbeat_s: float = 3.0
    ) -> None:
        self.client = client
        self.joined = joined
        self.learner_id = joined.learner_id
        self.weights_spec = weights_spec
        self.heartbeat_s = float(heartbeat_s)
        self.replay_address = joined.registration.replay_address
        self.loaded_round = 0
        self.env_steps = 0
        self.rounds = joined.registration.rounds
        self.retired = False
        self.lost: str | None = None
        self.posted = 0
        self.dropped = 0
        self._sample: Sample | None = None
        self._posts: deque[tuple[float, int, int]] = deque()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._run, name="evolver-link", daemon=True)
        self._log = Throttle()
        self.evolver_link = Outage(f"evolver at {client.address}", log, BLIP_S)

    def start(self) -> None:
        if self.joined.fresh and self.rounds > 0:
            self._guarded(self._take_join_sample)
        self._thread.start()

    def _take_join_sample(self) -> None:
        sample = self.client.get_sample(self.learner_id, self.weights_spec)
        if sample is not None:
            with self._lock:
                self._sample = sample
            log.info("learner %d joined after round %d: starting from a sample of the CEM distribution",
                     self.learner_id, sample.round)  # fmt: skip

    def close(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    # -- the update loop's side ---------------------------------------------------------------
    def post(self, mean_return: float, env_steps: int) -> None:
        """Queue one evaluation's mean return (of the weights loaded last: :attr:`loaded_round`)."""
        with self._lock:
            self._posts.append((float(mean_return), int(env_steps), self.loaded_round))
        self._wake.set()

    def take_sample(self) -> Sample | None:
        """The sample fetched for this learner, once; load it, then call :meth:`loaded`."""
        with self._lock:
            sample, self._sample = self._sample, None
        return sample

    def loaded(self, round_: int) -> None:
        self.loaded_round = int(round_)
        self._wake.set()  # acknowledge it now: the evolver stops announcing it

    # -- the thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        next_beat = 0.0
        while not self._stop.is_set() and not self.retired:
            if time.monotonic() >= next_beat or self._wake.is_set():
                self._wake.clear()
                self._guarded(self._beat)
                next_beat = time.monotonic() + self.heartbeat_s
            self._guarded(self._send_posts)
            self._wake.wait(max(0.0, next_beat - time.monotonic()))

    def _guarded(self, call: Callable[[], None]) -> None:
        try:
            call()
            self.evolver_link.ok()
        except UnknownLearner:
            self.evolver_link.ok()  # it answered: the lease ran out meanwhile
            self._guarded(self._rejoin)
        except LearnerRetired as e:
            self._retire(str(e))
        except grpc.RpcError as e:
            if not unreachable(e):
                log.error("evolver call failed: %s: %s", e.code().name, e.details())
            else:
                self.evolver_link.failed(e.code().name, "training on; returns wait to be posted")
            self._stop.wait(1.0)
        except ParamsError as e:
            if self._log():
                log.error("learner %d: the evolver's sample does not fit this learner's models: %s", self.learner_id, e)

    def _beat(self) -> None:
        orders = self.client.heartbeat(self.learner_id, self.env_steps, self.loaded_round or None)
        self.rounds = orders.rounds
        if orders.replay_address:
            self.replay_address = orders.replay_address
        if orders.instruction is Instruction.RETIRE:
            self._retire("the heartbeat answered RETIRE")
        elif orders.instruction is Instruction.LOAD_WEIGHTS and orders.sample_round > self.loaded_round:
            with self._lock:
                held = self._sample
            if held is None or held.round < orders.sample_round:
                sample = self.client.get_sample(self.learner_id, self.weights_spec)
                if sample is not None:
                    with self._lock:
                        self._sample = sample
                    log.info("learner %d: the CEM sample of round %d arrived", self.learner_id, sample.round)

    def _send_posts(self) -> None:
        while True:
            with self._lock:
                if not self._posts:
                    return
                mean_return, env_steps, weights_round = self._posts[0]
            accepted = self.client.post_reward(self.learner_id, mean_return, env_steps, weights_round)
            with self._lock:
                self._posts.popleft()
            self.posted += 1
            if not accepted:
                self.dropped += 1
                log.info("return %.1f at %d env steps not counted: a CEM sample replaces these weights",
                         mean_return, env_steps)  # fmt: skip

    def _rejoin(self) -> None:
        try:
            registration = register(self.client, self.joined.address, self.learner_id)
        except UnknownLearner as e:
            self.lost = f"the evolver no longer knows learner {self.learner_id} ({e}); start again to join afresh"
            self._stop.set()
            return
        if registration.replay_address:
            self.replay_address = registration.replay_address
        log.info("learner %d registered again with the evolver (its lease had run out)", self.learner_id)

    def _retire(self, why: str) -> None:
        if not self.retired:
            log.info("learner %d retired by the evolver (%s)", self.learner_id, why)
        self.retired = True


class WeightsSnapshot:
    """What serves a learner's GetWeights (the evolver's CEM round): the full model weights, copied
    between two updates (never halfway through an optimizer step) and encoded with the run's token.

    GetWeights runs on an RPC thread: :meth:`__call__` asks for a copy and waits up to ``timeout_s``
    for the update loop to make one in :meth:`offer` (called between updates; it does nothing unless
    asked); if none comes it serves the last copy, or None (the evolver then leaves the learner out
    of the round)."""

    def __init__(self, token: Token = None, timeout_s: float = 20.0) -> None:
        self.token = token
        self.timeout_s = float(timeout_s)
        self._cond = threading.Condition()
        self._asked = 0
        self._taken = 0
        self._latest: tuple[int, dict[str, torch.Tensor]] | None = None

    def __call__(self) -> tuple[int, list[bytes]] | None:
        with self._cond:
            self._asked += 1
            wanted = self._asked
            self._cond.wait_for(lambda: self._taken >= wanted, timeout=self.timeout_s)
            latest = self._latest
        if latest is None:
            return None
        version, weights = latest
        return version, encode_params(version, weights, self.token)

    def offer(self, version: int, weights: Callable[[], dict[str, torch.Tensor]]) -> None:
        """Copy ``weights()`` if a GetWeights waits for it (cheap otherwise)."""
        if self._taken >= self._asked:
            return
        copied = {name: t.detach().to("cpu", copy=True) for name, t in weights().items()}
        with self._cond:
            self._latest = (int(version), copied)
            self._taken = self._asked
            self._cond.notify_all()


@dataclass
class Membership:
    """What a learner of a population needs besides its own parts (ds/learner/learner.py): its link to the
    evolver, the snapshot that serves its GetWeights, and how to connect to a replay address the
    evolver names (a replay assigned to it, or moved)."""

    link: EvolverLink
    snapshot: WeightsSnapshot
    connect_replay: Callable[[str], ReplayTable]


def wait_for_replay(link: EvolverLink, stop: threading.Event, warn_after_s: float = PEER_WARN_AFTER_S) -> str | None:
    """The replay address the evolver names for this learner, once it does (logging while it waits);
    None if the learner was stopped, retired or forgotten first."""
    waiting, started, warned = Throttle(), time.monotonic(), False
    while not link.replay_address:
        if link.retired or link.lost or stop.wait(0.5):
            return None
        waited = time.monotonic() - started
        if waited > 5.0 and waiting():
            log.info("learner %d waits for the evolver to pair a replay with it (start one with --evolver_host)",
                     link.learner_id)  # fmt: skip
        if not warned and waited >= warn_after_s:
            log.warning("learner %d: no replay free for it has registered with the evolver for %.0f s; still "
                        "waiting. Start one more replay (main_ds.py TASK replay -n NAME --evolver_host=HOST_E): "
                        "each learner of a population needs its own", link.learner_id, waited)  # fmt: skip
            warned = True
    return link.replay_address


def exit_code(link: EvolverLink, joined: Joined, updates: int | None = None) -> int:
    """The exit code of a learner that stopped: 1 forgotten by the evolver, 0 retired (its folder is
    marked retired, so no learner process claims it again), else 130 (stopped by a signal)."""
    if link.lost:
        log.error("learner %d: %s", link.learner_id, link.lost)
        return 1
    if link.retired:
        joined.slot.set_status("retired")
        log.info("learner %d retired by the evolver%s: exiting", link.learner_id,
                 "" if updates is None else f" after {updates} updates, checkpoint saved")  # fmt: skip
        return 0
    return 130
