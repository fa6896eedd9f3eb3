"""How the roles take part in an evolver's population (docs/architecture.md section 10, protos/evolver.proto): a
learner's folder and identity, the config a learner's group runs with, and the assignments of actors
and replays (a learner's live link with the evolver is ds/member/link.py).
ds/learner/role.py, ds/replay/role.py and ds/actor/role.py compose these with the role loops; nothing here touches envs.

Usage, a learner's (``run_learner``)::

    client = EvolverClient("evolver:61000", token=token, credentials=creds)  # creds: ds/net/security.py
    joined = join_population(client, run_dir, LearnerAddress(name, "", 61001, params_port, ""), stop)
    config = member_config(joined.registration.config_yaml, joined.learner_id, own_config, overrides)
    ...                                    # ds/member/link.py: heartbeats, returns, samples, retirement

an actor's or replay's::

    job = wait_for_assignment(lambda previous: client.assign_actor(name, previous), "actor", address, stop)
    keeper = AssignmentKeeper(client, job, lambda previous: client.assign_actor(name, previous), stop,
                              follow_gone=True)
    keeper.start()
    job, halt = keeper.tenure()  # work for job's learner until halt is set: stop, or keeper.job moved

Layout of an experiment's run directory ``models/<task>/<name>/``: ``config.yaml`` (the evolver's
config), ``evolver/`` (its state) and ``log/evolver``; learner k owns ``learner_<k>/``, a run directory
of its own (``config.yaml`` with its sampled values, ``model/``, ``log/learner``, ``evaluations.csv``,
``learner.json``) that its replay (``replay/``, ``log/replay``) and actors (``log/actor_<index>``) share;
``main.py --run -n <name>/learner_<k>`` plays its checkpoints.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import grpc

from algorithm.config.load import apply_overrides, config_from_yaml
from algorithm.config.schema import Config
from algorithm.files import WriteFailures, atomic_write
from algorithm.run.folder_lock import FolderLock, try_hold
from algorithm.run.logging import Throttle
from ds.evolver.client import EvolverClient
from ds.evolver.state import (
    Assignment,
    LearnerRegistration,
    LearnerRetired,
    NoWorkYet,
    UnknownAssignment,
    UnknownLearner,
)
from ds.net.outage import BLIP_S, Outage
from ds.net.rpc import peer_unresponsive

log = logging.getLogger("asac.population")
SLOT_FILE = "learner.json"
# Learner k runs with sac_config.seed + k * stride: its actors' (seed + 1000 * (index + 1) + env) and
# evaluation (seed + 100_000 + env) seeds stay below the next learner's.
LEARNER_SEED_STRIDE = 1_000_000
Assign = Callable[[str], Assignment]
"""``assign(previous_assignment_id) -> Assignment`` (EvolverClient.assign_actor/assign_replay bound to a
name); :class:`NoWorkYet` while no learner can take the caller."""


class SlotTaken(RuntimeError):
    """The folder of the learner id the evolver gave is held by another live learner process."""


def unreachable(error: grpc.RpcError) -> bool:
    """The evolver is down or restarting (wait and retry), rather than refusing the call."""
    return peer_unresponsive(error.code())


# ---------------------------------------------------------------------- the learner's folder and config


def learner_dir(run_dir: Path, learner_id: int) -> Path:
    return Path(run_dir) / f"learner_{learner_id}"


class LearnerSlot:
    """Learner ``learner_id``'s folder, locked (``flock`` on the folder) while its process lives.

    A learner process that starts claims the folder of a learner that ran here before and is neither
    retired nor held by a live process, and registers again as that learner (``previous_id``); the
    lock dies with its process (``kill -9`` included), so a restarted learner finds its folder free.
    ``learner.json`` says ``{"learner_id": k, "status": "active" | "retired" | "forgotten"}``
    (forgotten: the evolver's state no longer knows the id)."""

    def __init__(self, path: Path, learner_id: int, lock: FolderLock) -> None:
        self.path = path
        self.learner_id = learner_id
        self._lock = lock
        self.status_writes = WriteFailures(
            "learner status", log, retry="the folder may be claimed again, and the evolver then says what it is"
        )

    @classmethod
    def claim(cls, run_dir: Path) -> LearnerSlot | None:
        """The free folder of an active learner with the lowest id, locked; None if there is none."""
        found = []
        for file in Path(run_dir).glob(f"learner_*/{SLOT_FILE}"):
            try:
                data = json.loads(file.read_text())
                found.append((int(data["learner_id"]), str(data["status"]), file.parent))
            except (OSError, ValueError, KeyError, TypeError) as e:
                log.warning("ignoring %s: %s", file, e)
        for learner_id, status, path in sorted(found):
            if status == "active" and (slot := cls._locked(path, learner_id)) is not None:
                return slot
        return None

    @classmethod
    def create(cls, run_dir: Path, learner_id: int) -> LearnerSlot:
        """Learner ``learner_id``'s folder (made if new), locked and marked active."""
        path = learner_dir(run_dir, learner_id)
        path.mkdir(parents=True, exist_ok=True)
        slot = cls._locked(path, learner_id)
        if slot is None:
            raise SlotTaken(
                f"{path} is held by another live learner process, yet the evolver gave its id {learner_id} to this "
                "one: was the evolver's state deleted while learners ran? Stop them and start afresh"
            )
        slot.set_status("active")
        return slot

    @classmethod
    def _locked(cls, path: Path, learner_id: int) -> LearnerSlot | None:
        lock = try_hold(path)
        return None if lock is None else cls(path, learner_id, lock)

    def set_status(self, status: str) -> bool:
        """Write the status; False when it could not be (a full disk: logged, the file kept as it was)."""
        text = json.dumps({"learner_id": self.learner_id, "status": status}).encode()
        path = self.path / SLOT_FILE
        return self.status_writes.attempt(path, lambda: atomic_write(path, lambda f: f.write(text)))

    def release(self) -> None:
        self._lock.release()


def member_config(config_yaml: str, learner_id: int, own: Config, overrides: Sequence[str]) -> Config:
    """The config learner ``learner_id``, its replay and its actors run with: the evolver's (this
    learner's random_params values drawn), then this process's ``--override`` flags (flags win over
    the registry), with this process's own ``net_config`` (where it listens, whom it calls) and
    ``sac_config.seed`` moved by ``LEARNER_SEED_STRIDE * learner_id``, so that learners start from
    different weights and no two envs of the population share a seed."""
    config = config_from_yaml(config_yaml, f"the evolver's config of learner {learner_id}")
    config = apply_overrides(config, list(overrides))
    config.net_config = own.net_config.model_copy(deep=True)
    config.sac_config.seed = int(config.sac_config.seed or 0) + LEARNER_SEED_STRIDE * learner_id
    return config


# ---------------------------------------------------------------------- joining


@dataclass(frozen=True)
class LearnerAddress:
    """What a learner tells the evolver when it registers (protos/evolver.proto RegisterLearner)."""

    name: str
    host: str  # "": the address the evolver sees the call come from
    learner_port: int
    params_port: int
    replay_address: str  # "": the evolver pairs a replay with it


@dataclass
class Joined:
    registration: LearnerRegistration
    slot: LearnerSlot
    address: LearnerAddress
    fresh: bool = False  # registered as a new learner (not back with its id and folder)

    @property
    def learner_id(self) -> int:
        return self.registration.learner_id


def register(client: EvolverClient, address: LearnerAddress, previous_id: int | None) -> LearnerRegistration:
    a = address
    return client.register_learner(a.name, a.host, a.learner_port, a.params_port, a.replay_address, previous_id)


def join_population(
    client: EvolverClient, run_dir: Path, address: LearnerAddress, stop: threading.Event
) -> Joined | None:
    """Register with the evolver, as the learner of a free folder under ``run_dir`` if there is one
    (:class:`LearnerSlot`), else as a new learner; waits (logging) while the evolver is unreachable.
    None if ``stop`` was set first."""
    slot = LearnerSlot.claim(run_dir)
    waiting = Throttle(10.0)
    while not stop.is_set():
        previous = None if slot is None else slot.learner_id
        try:
            registration = register(client, address, previous)
        except (UnknownLearner, LearnerRetired) as e:
            assert slot is not None
            retired = isinstance(e, LearnerRetired)
            log.warning("not rejoining as learner %d (%s); looking for another", slot.learner_id, e)
            slot.set_status("retired" if retired else "forgotten")
            slot.release()
            slot = LearnerSlot.claim(run_dir)
            continue
        except grpc.RpcError as e:
            if not unreachable(e):
                raise
            if waiting():
                log.info("waiting for the evolver at %s to register (%s)", client.address, e.code().name)
            stop.wait(2.0)
            continue
        if slot is None:
            slot = LearnerSlot.create(run_dir, registration.learner_id)
        return Joined(registration, slot, address, fresh=previous is None)
    if slot is not None:
        slot.release()
    return None


# ---------------------------------------------------------------------- actors and replays


def wait_for_assignment(
    assign: Assign, what: str, evolver_address: str, stop: threading.Event, previous: str = ""
) -> Assignment | None:
    """``assign(previous)``, retried (logging what it waits for) while the evolver has no work or is
    unreachable; None if ``stop`` was set first."""
    waiting, backoff = Throttle(10.0), 0.2
    while not stop.is_set():
        try:
            return assign(previous)
        except NoWorkYet as e:
            reason = str(e)
        except grpc.RpcError as e:
            if not unreachable(e):
                raise
            reason = f"evolver unreachable ({e.code().name})"
        if waiting():
            log.info("%s waits for work from the evolver at %s: %s", what, evolver_address, reason)
        stop.wait(backoff)
        backoff = min(2 * backoff, 2.0)
    return None


class AssignmentKeeper:
    """Keeps an actor's or replay's assignment: renews it every ``renew_s`` seconds on a thread and
    notices when the caller must work for another learner.

    That is when the assignment ended (its learner retired, or the evolver forgot it) and Assign gave
    one for another learner; or, with ``follow_gone`` (actors), when its learner's lease has been
    expired for longer than ``lease_s`` and another learner has room. :attr:`job` is then the new
    assignment and the event of the current :meth:`tenure` is set, as it is when ``stop`` is. An
    unreachable evolver, or no room anywhere, is waited out: the work goes on meanwhile."""

    def __init__(
        self,
        client: EvolverClient,
        job: Assignment,
        assign: Assign,
        stop: threading.Event,
        *,
        follow_gone: bool,
        renew_s: float = 3.0,
    ) -> None:
        self.client = client
        self.job = job
        self.assign = assign
        self.stop = stop
        self.follow_gone = follow_gone
        self.renew_s = float(renew_s)
        self._halt = threading.Event()
        self._lock = threading.Lock()
        self._gone_since: float | None = None
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._run, name="assignment", daemon=True)
        self._log = Throttle()
        self.evolver_link = Outage(f"evolver at {client.address}", log, BLIP_S)

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._closed.set()
        if self._thread.is_alive():
            self._thread.join(5.0)

    def tenure(self) -> tuple[Assignment, threading.Event]:
        """The current assignment and an event that is set when the caller must leave it."""
        with self._lock:
            self._halt = threading.Event()
            if self.stop.is_set():
                self._halt.set()
            return self.job, self._halt

    def _run(self) -> None:
        next_renew = time.monotonic() + self.renew_s
        while not self._closed.is_set():
            if self.stop.wait(0.2):
                self._halt.set()
                if self._closed.wait(0.2):
                    return
                continue
            if time.monotonic() < next_renew:
                continue
            next_renew = time.monotonic() + self.renew_s
            try:
                self._renew()
                self.evolver_link.ok()
            except grpc.RpcError as e:
                if not unreachable(e):
                    log.error("evolver call failed: %s: %s", e.code().name, e.details())
                else:
                    self.evolver_link.failed(e.code().name, f"working on for learner {self.job.learner_id}")

    def _renew(self) -> None:
        job = self.job
        try:
            fresh = self.client.renew_assignment(job.assignment_id)
        except UnknownAssignment:
            try:
                fresh = self.assign(job.assignment_id)
            except NoWorkYet as e:
                if self._log():
                    log.info("the assignment to learner %d ended and no learner has room yet: %s", job.learner_id, e)
                return
        if fresh.learner_id == job.learner_id:
            self.job = fresh
            if fresh.learner_live or not self.follow_gone:
                self._gone_since = None
                return
            now = time.monotonic()
            self._gone_since = self._gone_since or now
            if now - self._gone_since <= fresh.lease_s:
                return
            try:
                fresh = self.assign("")
            except NoWorkYet:
                return
            if fresh.learner_id == job.learner_id:
                return
        log.info("learner %d -> learner %d (%s)", job.learner_id, fresh.learner_id, fresh.assignment_id)
        with self._lock:
            self.job = fresh
            self._gone_since = None
            self._halt.set()
