"""Where the evolver sends actors and replays started without addresses (protos/evolver.proto Assign).

- An **actor** goes to the live learner with the fewest live actor assignments (the lowest id among
  equals) that has a replay and fewer than ``max_actors_each_learner`` actors: an actor of a learner
  without a replay would have nowhere to ship its chunks.
- A **replay** goes to the live learner, lowest id first, that was started with this replay's
  address or last served by it (a replay back after its lease ran out gets its learner back); else
  to the first one that was started without a replay and has no live replay assignment. The
  learner then finds the replay's address in its heartbeat replies.
- Assignments are named ``assignment-<n>``, n counting every assignment made (an actor's index is
  its learner's business, ds/learner/service.py). Every assignment has a lease renewed by
  ``AssignmentHeartbeat``; an expired one frees its place.
  Re-calling Assign with a live ``previous`` assignment (or, for a replay, from the same address)
  returns that assignment renewed, so a retry after a lost reply never takes two places. An
  assignment ends when its learner retires; it survives its learner's lease running out (the
  actor waits for the learner to come back, docs/architecture.md section 8). One whose own lease
  ran out (its caller was cut off from the evolver) is given back to its caller, same learner,
  when it calls again with it as ``previous``: after a partition every actor returns to its
  learner, however the learners' own returns are ordered, instead of to the first one back.

Usage (by :class:`ds.evolver.evolver.Evolver`, under its registry lock; not thread-safe on its own)::

    book = Assignments(lease_s=30.0, max_actors=10, clock=time.monotonic)
    assignment, changed = book.assign(Role.ACTOR, "a0", "", "", learners, live)
    book.renew(assignment.assignment_id)            # UnknownAssignment: Assign again
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from ds.evolver.state import AssignmentEntry, LearnerEntry, NoWorkYet, Role, UnknownAssignment

LAPSED_KEPT_LEASES = 10
"""How many leases an assignment that lapsed is remembered for its caller's return (:meth:`Assignments.assign`)."""


class Assignments:
    """The live assignments of actors and replays to learners, with leases."""

    def __init__(self, lease_s: float, max_actors: int, clock: Callable[[], float]) -> None:
        self.lease_s = float(lease_s)
        self.max_actors = int(max_actors)
        self._clock = clock
        self.entries: dict[str, AssignmentEntry] = {}
        self.next_id = 0
        # Assignments whose lease ran out (a partition, a pause), kept for LAPSED_KEPT_LEASES leases: a caller
        # back with one as ``previous`` returns to the same learner rather than to whichever is live first.
        self._lapsed: dict[str, AssignmentEntry] = {}

    def assign(
        self,
        role: Role,
        name: str,
        address: str,
        previous: str,
        learners: Mapping[int, LearnerEntry],
        live: Callable[[LearnerEntry], bool],
    ) -> tuple[AssignmentEntry, bool]:
        """The assignment for this caller and whether the state changed (a new one, or a replay that
        moved). A replay's learner gets ``replay_address = address``. :class:`NoWorkYet` if none fits."""
        self.expire()
        same = [a for a in self.entries.values() if a.role is role and a.assignment_id == previous]
        if role is Role.REPLAY:
            same += [a for a in self.entries.values() if a.role is role and a.address == address]
        if same:
            assignment, changed = same[0], False
            assignment.expires = self._clock() + self.lease_s
            if role is Role.REPLAY and assignment.address != address:  # restarted elsewhere
                assignment.address = learners[assignment.learner_id].replay_address = address
                changed = True
            return assignment, changed
        if (back := self._back(role, previous, learners)) is not None:
            back.name, back.expires = name, self._clock() + self.lease_s
            if role is Role.REPLAY:
                back.address = learners[back.learner_id].replay_address = address
            self.entries[back.assignment_id] = back
            return back, True
        candidates = sorted((e for e in learners.values() if live(e)), key=lambda e: e.learner_id)
        entry = self._replay_learner(address, candidates) if role is Role.REPLAY else self._actor_learner(candidates)
        if role is Role.REPLAY:
            entry.replay_address = address
        assignment = AssignmentEntry(
            f"assignment-{self.next_id}",  # not "actor-<n>": n counts assignments, not the actor's index
            role,
            name,
            entry.learner_id,
            address if role is Role.REPLAY else "",
            self._clock() + self.lease_s,
        )
        self.next_id += 1
        self.entries[assignment.assignment_id] = assignment
        return assignment, True

    def _back(self, role: Role, previous: str, learners: Mapping[int, LearnerEntry]) -> AssignmentEntry | None:
        """``previous``'s lapsed assignment, if its learner is still known and not retired and has room for
        it again (an actor: fewer than ``max_actors``; a replay: no other replay took its place meanwhile)."""
        lapsed = self._lapsed.pop(previous, None) if previous else None
        if lapsed is None or lapsed.role is not role:
            return None
        learner = learners.get(lapsed.learner_id)
        if learner is None or learner.retired:
            return None
        if role is Role.ACTOR and self.actor_counts().get(lapsed.learner_id, 0) >= self.max_actors:
            return None
        taken = any(a.role is Role.REPLAY and a.learner_id == lapsed.learner_id for a in self.entries.values())
        return None if role is Role.REPLAY and taken else lapsed

    def renew(self, assignment_id: str) -> AssignmentEntry:
        self.expire()
        assignment = self.entries.get(assignment_id)
        if assignment is None:
            raise UnknownAssignment(
                f"assignment {assignment_id!r} is unknown, expired, or its learner retired: Assign again"
            )
        assignment.expires = self._clock() + self.lease_s
        return assignment

    def expire(self) -> list[AssignmentEntry]:
        """Drop the assignments whose lease ran out; returns them."""
        now = self._clock()
        expired = [a for a in self.entries.values() if a.expires < now]
        for a in expired:
            del self.entries[a.assignment_id]
            self._lapsed[a.assignment_id] = a
        for key in [k for k, a in self._lapsed.items() if a.expires < now - LAPSED_KEPT_LEASES * self.lease_s]:
            del self._lapsed[key]
        return expired

    def end_learner(self, learner_id: int) -> None:
        """Drop every assignment to a retired learner (their next heartbeat answers NOT_FOUND)."""
        for book in (self.entries, self._lapsed):
            for key in [k for k, a in book.items() if a.learner_id == learner_id]:
                del book[key]

    def actor_counts(self) -> dict[int, int]:
        counts: dict[int, int] = {}
        for a in self.entries.values():
            if a.role is Role.ACTOR:
                counts[a.learner_id] = counts.get(a.learner_id, 0) + 1
        return counts

    def _actor_learner(self, live: list[LearnerEntry]) -> LearnerEntry:
        counts = self.actor_counts()
        fits = [e for e in live if e.replay_address and counts.get(e.learner_id, 0) < self.max_actors]
        if not fits:
            replayless = sum(1 for e in live if not e.replay_address)
            raise NoWorkYet(
                f"no learner has room for an actor: {len(live)} live learners, {replayless} of them without a "
                f"replay yet, the others at max_actors_each_learner={self.max_actors}"
            )
        return min(fits, key=lambda e: (counts.get(e.learner_id, 0), e.learner_id))

    def _replay_learner(self, address: str, live: list[LearnerEntry]) -> LearnerEntry:
        served = {a.learner_id for a in self.entries.values() if a.role is Role.REPLAY}
        for entry in live:
            if entry.replay_address == address:
                return entry
        for entry in live:
            if not entry.replay_static and entry.learner_id not in served:
                return entry
        raise NoWorkYet(f"no learner without a replay: {len(live)} live learners, each has one (or none registered)")

    def to_state(self) -> dict[str, Any]:
        return {"next_id": self.next_id, "entries": [a.to_json() for a in self.entries.values()]}

    def load_state(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`to_state`; every assignment gets a fresh lease."""
        self.next_id = int(state["next_id"])
        now = self._clock()
        for data in state["entries"]:
            assignment = AssignmentEntry.from_json(data)
            assignment.expires = now + self.lease_s
            self.entries[assignment.assignment_id] = assignment
