"""The evolver's registry: learners' addresses and leases, samples waiting to be loaded, returns in
flight, and the assignments of actors and replays. It is what the rpcs of protos/evolver.proto
touch; the population and its CEM rounds live in :class:`ds.evolver.evolver.Evolver`.

Every method takes the registry's own lock, held for a few dictionary operations: nothing here waits
for the population, the disk or the network, so heartbeats, PostReward, GetSample and Assign answer
at once even while a round runs (the original system ran CEM inside an rpc under a global lock).

- **Leases.** A learner that sent nothing for ``lease_s`` seconds is *gone*: it keeps its id, config,
  returns and pending sample, but its calls answer :class:`UnknownLearner` until it registers again
  with ``previous_id`` (which may bring a new address). The evolver leaves gone learners out of
  rounds (:meth:`gone`).
- **Stale returns.** Returns describe the weights a learner holds. Once a round drew a sample for a
  learner, what it posts with ``weights_round`` below that round is dropped (``PostReward`` answers
  ``accepted: false``) until it loads the sample and says so (``loaded_round`` in a heartbeat or
  ``weights_round`` in a post); returns still queued when the round ran are dropped the same way.
- **Announced only once saved.** A pending sample is offered (LOAD_WEIGHTS, GetSample) only after its
  file and the state naming it are on disk, so a round the evolver loses in a crash was never
  announced and round numbers stay unique.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from algorithm.config.load import config_to_yaml
from algorithm.config.random_params import apply_params
from algorithm.config.schema import Config
from algorithm.evolution import CemPopulation, RoundResult
from ds.evolver.assign import Assignments
from ds.evolver.state import (
    Assignment,
    AssignmentEntry,
    EvolverInfo,
    Instruction,
    LearnerEntry,
    LearnerInfo,
    LearnerOrders,
    LearnerRegistration,
    LearnerRetired,
    PendingSample,
    Role,
    UnknownLearner,
)
from ds.net.params import Token, encode_params

log = logging.getLogger("asac.evolver")


@dataclass(frozen=True)
class Return:
    """One posted evaluation return, queued until the evolver adds it to the population."""

    learner_id: int
    value: float
    env_steps: int
    weights_round: int


class LearnerRegistry:
    """Learners, pending samples, queued returns and assignments, behind one short lock. Thread-safe."""

    def __init__(
        self, config: Config, experiment: str, lease_s: float, clock: Callable[[], float], token: Token = None
    ) -> None:
        self.config = config
        self.experiment = experiment
        self.lease_s = float(lease_s)
        self._said_gone: set[int] = set()
        self.token = token
        self._clock = clock
        self._lock = threading.Lock()
        self.learners: dict[int, LearnerEntry] = {}
        self.pending: dict[int, PendingSample] = {}
        self.assignments = Assignments(lease_s, config.base_config.max_actors_each_learner, clock)
        self.rounds = 0
        self.last_elites: list[int] = []
        self.dirty = False  # something to save
        self._inbox: list[Return] = []
        self._obsolete: set[str] = set()  # sample files to delete once a state without them is saved

    # ------------------------------------------------------------------ learners

    def add(
        self,
        learner_id: int,
        params: dict[str, Any],
        name: str,
        host: str,
        learner_port: int,
        params_port: int,
        replay_address: str,
    ) -> LearnerEntry:
        """A learner the population just added."""
        with self._lock:
            entry = LearnerEntry(learner_id, name, host, learner_port, params_port, params)
            self.learners[learner_id] = entry
            self._attach(entry, replay_address)
            return entry

    def reattach(
        self, learner_id: int, name: str, host: str, learner_port: int, params_port: int, replay_address: str
    ) -> LearnerEntry:
        """A known learner back (restart, lease expired), maybe at a new address."""
        with self._lock:
            entry = self.learners.get(learner_id)
            if entry is None:
                raise UnknownLearner(
                    f"learner {learner_id} is not known to this evolver (never registered here, or the evolver's "
                    "state was lost): register without previous_id"
                )
            if entry.retired:
                raise LearnerRetired(f"learner {learner_id} was retired in round {entry.retired_round}")
            entry.name, entry.host, entry.learner_port, entry.params_port = name, host, learner_port, params_port
            self._attach(entry, replay_address)
            return entry

    def _attach(self, entry: LearnerEntry, replay_address: str) -> None:
        if replay_address:
            entry.replay_address, entry.replay_static = replay_address, True
        entry.expires = self._clock() + self.lease_s
        self.dirty = True

    def registration(self, entry: LearnerEntry) -> LearnerRegistration:
        return LearnerRegistration(
            entry.learner_id,
            self.experiment,
            self.config_yaml(entry),
            dict(entry.params),
            self.lease_s,
            entry.replay_address,
            self.rounds,
        )

    def heartbeat(self, learner_id: int, env_steps: int, loaded_round: int | None) -> LearnerOrders:
        _check_count("env_steps", env_steps)
        if loaded_round is not None:
            _check_count("loaded_round", loaded_round)
        with self._lock:
            entry = self._entry(learner_id, retired_ok=True)
            if entry.retired:
                return LearnerOrders(Instruction.RETIRE, 0, "", self.lease_s, self.rounds)
            entry.expires = self._clock() + self.lease_s
            entry.env_steps = int(env_steps)
            if loaded_round is not None:
                self._acknowledge(entry, loaded_round)
            pending = self.pending.get(learner_id)
            if pending is not None and pending.saved:
                return LearnerOrders(
                    Instruction.LOAD_WEIGHTS, pending.round, entry.replay_address, self.lease_s, self.rounds
                )
            return LearnerOrders(Instruction.CONTINUE, 0, entry.replay_address, self.lease_s, self.rounds)

    def post(self, learner_id: int, value: float, env_steps: int, weights_round: int) -> bool:
        """Queue a return; False when it is stale (see the module docstring)."""
        if not math.isfinite(value):
            raise ValueError(f"mean_return: must be finite, got {value!r}")
        _check_count("env_steps", env_steps)
        _check_count("weights_round", weights_round)
        with self._lock:
            entry = self._entry(learner_id)
            entry.expires = self._clock() + self.lease_s
            entry.env_steps = max(entry.env_steps, int(env_steps))
            if weights_round:
                self._acknowledge(entry, weights_round)
            pending = self.pending.get(learner_id)
            if pending is not None and weights_round < pending.round:
                return False
            self._inbox.append(Return(learner_id, float(value), int(env_steps), int(weights_round)))
            self.dirty = True
            return True

    def sample(self, learner_id: int) -> tuple[int, list[bytes]] | None:
        """``(round, frames)`` of the sample waiting for this learner, or None."""
        with self._lock:
            self._entry(learner_id)
            pending = self.pending.get(learner_id)
            if pending is None or not pending.saved:
                return None
        if pending.frames is None:  # encoded outside the lock; two first calls at once encode the same bytes
            pending.frames = encode_params(pending.round, pending.weights, self.token)
        return pending.round, pending.frames

    # ------------------------------------------------------------------ actors and replays

    def assign(self, role: Role, name: str, address: str, previous: str) -> tuple[Assignment, bool]:
        """An assignment (ds/evolver/assign.py) and whether it is new or moved (then save)."""
        if not isinstance(role, Role):
            raise ValueError(f"role: must be ACTOR or REPLAY, got {role!r}")
        if role is Role.REPLAY:
            if not address:
                raise ValueError("address: a replay must say where it serves")
            check_address("address", address)
        with self._lock:
            self.dirty |= bool(self.assignments.expire())
            assignment, changed = self.assignments.assign(role, name, address, previous, self.learners, self._live)
            self.dirty |= changed
            return self._view(assignment), changed

    def renew(self, assignment_id: str) -> Assignment:
        with self._lock:
            self.dirty |= bool(self.assignments.expire())
            return self._view(self.assignments.renew(assignment_id))

    def _view(self, a: AssignmentEntry, with_config: bool = True) -> Assignment:
        e = self.learners[a.learner_id]
        config_yaml = self.config_yaml(e) if with_config else ""
        return Assignment(
            a.assignment_id,
            a.role,
            e.learner_id,
            e.host,
            e.learner_port,
            e.params_port,
            e.replay_address,
            config_yaml,
            self.experiment,
            self.lease_s,
            self._live(e),
        )

    # ------------------------------------------------------------------ for the evolver's rounds

    def take_returns(self) -> list[Return]:
        """The queued returns that still describe their learner's weights; the queue empties."""
        with self._lock:
            inbox, self._inbox = self._inbox, []
            fresh = []
            for item in inbox:
                entry, pending = self.learners[item.learner_id], self.pending.get(item.learner_id)
                if not entry.retired and (pending is None or item.weights_round >= pending.round):
                    fresh.append(item)
            return fresh

    def live(self) -> list[int]:
        with self._lock:
            return [i for i, e in self.learners.items() if self._live(e)]

    def gone(self) -> set[int]:
        """Learners whose lease ran out (not retired): they sit rounds out. Each is logged once when
        first found gone (and once when back: :meth:`reattach`'s caller)."""
        with self._lock:
            gone = {i for i, e in self.learners.items() if not e.retired and not self._live(e)}
            for i in sorted(gone - self._said_gone):
                log.warning("learner %d at %s: not heard from for over %.0f s (its lease); it sits CEM rounds out "
                            "until it is back. Said once", i, self.learners[i].address, self.lease_s)  # fmt: skip
            self._said_gone = gone
            return gone

    def address(self, learner_id: int) -> str:
        with self._lock:
            return self.learners[learner_id].address

    def apply_round(self, result: RoundResult, population: CemPopulation) -> None:
        """Record a round the population ran: samples to announce once saved, retirements (their
        assignments end), the mirrors of rounds and elite counts."""
        with self._lock:
            for i in result.mean_returns:
                entry, record = self.learners[i], population.learners.get(i)
                entry.rounds = record.rounds if record else entry.rounds + 1
                entry.times_elite = record.times_elite if record else entry.times_elite
            for i, weights in result.samples_for.items():
                if (old := self.pending.get(i)) is not None:
                    self._obsolete.add(old.file_name)
                self.pending[i] = PendingSample(i, result.round, weights)
            for i in result.retired:
                self.learners[i].retired_round = result.round
                if (old := self.pending.pop(i, None)) is not None:
                    self._obsolete.add(old.file_name)
                self.assignments.end_learner(i)
            self.rounds, self.last_elites = result.round, list(result.elites)
            self.dirty = True

    def add_sample(self, learner_id: int, round_: int, weights: dict[str, np.ndarray]) -> None:
        """A sample for a learner outside a round (one that registered after round ``round_``), offered
        like a round's once saved."""
        with self._lock:
            self.pending[learner_id] = PendingSample(learner_id, round_, weights)
            self.dirty = True

    # ------------------------------------------------------------------ state

    def snapshot(self) -> tuple[dict[str, Any], list[PendingSample], set[str]]:
        """The registry's part of the saved state, the samples to write first, and the files that
        may go once it is saved; clears ``dirty``."""
        with self._lock:
            state = {
                "rounds": self.rounds,
                "last_elites": list(self.last_elites),
                "learners": [e.to_json() for e in self.learners.values()],
                "assignments": self.assignments.to_state(),
                "pending": [{"learner_id": p.learner_id, "round": p.round} for p in self.pending.values()],
                "inbox": [[r.learner_id, r.value, r.env_steps, r.weights_round] for r in self._inbox],
            }
            obsolete, self._obsolete = self._obsolete, set()
            self.dirty = False
            return state, [p for p in self.pending.values() if not p.saved], obsolete

    def mark_saved(self, samples: list[PendingSample]) -> None:
        with self._lock:
            for sample in samples:
                sample.saved = True

    def save_failed(self, obsolete: set[str]) -> None:
        """The state of the last :meth:`snapshot` was not written: save again at the next chance, and
        its obsolete files go only once a later state without them is."""
        with self._lock:
            self._obsolete |= obsolete
            self.dirty = True

    def load(self, state: Mapping[str, Any], read: Callable[[int, int], PendingSample]) -> None:
        """Restore :meth:`snapshot`'s state (``read(learner_id, round)`` loads a sample file); every
        learner and assignment gets a fresh lease."""
        now = self._clock()
        self.rounds = int(state["rounds"])
        self.last_elites = [int(i) for i in state["last_elites"]]
        for data in state["learners"]:
            entry = LearnerEntry.from_json(data)
            entry.expires = now + self.lease_s
            self.learners[entry.learner_id] = entry
        self.assignments.load_state(state["assignments"])
        self._inbox = [Return(int(i), float(v), int(s), int(r)) for i, v, s, r in state["inbox"]]
        unknown = {a.learner_id for a in self.assignments.entries.values()} | {r.learner_id for r in self._inbox}
        if unknown - set(self.learners):
            raise ValueError(f"assignments or returns name learners {sorted(unknown - set(self.learners))}")
        self.pending = {int(p["learner_id"]): read(int(p["learner_id"]), int(p["round"])) for p in state["pending"]}

    def info(self, means: Mapping[int, float], window: Mapping[int, int]) -> EvolverInfo:
        """Every learner (``means``/``window``: mean return and returns held, from the population)."""
        with self._lock:
            self.dirty |= bool(self.assignments.expire())
            actors = self.assignments.actor_counts()
            learners = [
                LearnerInfo(
                    i,
                    e.name,
                    e.host,
                    e.learner_port,
                    e.params_port,
                    e.replay_address,
                    means.get(i),
                    window.get(i, 0),
                    e.rounds,
                    e.times_elite,
                    e.retired,
                    self._live(e),
                    dict(e.params),
                    actors.get(i, 0),
                    e.env_steps,
                    self.pending[i].round if i in self.pending else 0,
                )
                for i, e in sorted(self.learners.items())
            ]
            assignments = [self._view(a, with_config=False) for a in self.assignments.entries.values()]
            return EvolverInfo(self.experiment, self.rounds, list(self.last_elites), learners, assignments)

    # ------------------------------------------------------------------ helpers (lock held)

    def _entry(self, learner_id: int, retired_ok: bool = False) -> LearnerEntry:
        entry = self.learners.get(learner_id)
        if entry is None:
            raise UnknownLearner(f"learner {learner_id} is not registered: RegisterLearner")
        if entry.retired:
            if retired_ok:
                return entry
            raise LearnerRetired(f"learner {learner_id} was retired in round {entry.retired_round}")
        if entry.expires < self._clock():
            raise UnknownLearner(f"learner {learner_id}'s lease expired: RegisterLearner with previous_id")
        return entry

    def _live(self, entry: LearnerEntry) -> bool:
        return not entry.retired and entry.expires >= self._clock()

    def _acknowledge(self, entry: LearnerEntry, loaded_round: int) -> None:
        entry.loaded_round = max(entry.loaded_round, int(loaded_round))
        pending = self.pending.get(entry.learner_id)
        if pending is not None and pending.saved and pending.round <= loaded_round:
            del self.pending[entry.learner_id]
            self._obsolete.add(pending.file_name)
            self.dirty = True

    def config_yaml(self, entry: LearnerEntry) -> str:
        """The learner's config as YAML, computed once per learner (its params never change)."""
        if entry.config_yaml is None:
            entry.config_yaml = config_to_yaml(apply_params(self.config, entry.params))
        return entry.config_yaml


def check_port(name: str, port: int, lowest: int) -> None:
    if not lowest <= port <= 65535:
        raise ValueError(f"{name}: must be in {lowest}..65535, got {port}")


def check_host(name: str, host: str) -> None:
    """A host name or address others can dial: non-empty, no spaces or control characters."""
    if not host or not host.isprintable() or any(c.isspace() for c in host):
        raise ValueError(f"{name}: {host!r} is not a host name or address")


def check_address(name: str, address: str) -> None:
    """``host:port`` (``[v6]:port`` too), as actors and learners dial it; a bad one would be handed
    on to every peer assigned to it."""
    host, _, port = address.rpartition(":")
    if not (port.isascii() and port.isdigit()) or not 1 <= int(port) <= 65535:
        raise ValueError(f"{name}: {address!r} is not host:port with a port in 1..65535")
    check_host(name, host)


def _check_count(name: str, value: int) -> None:
    if value < 0:
        raise ValueError(f"{name}: must be >= 0, got {value}")
