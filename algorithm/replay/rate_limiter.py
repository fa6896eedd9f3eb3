"""Keeps sampled windows per inserted step near ``samples_per_insert`` (the update-to-data ratio).

The idea is Reverb's ``SampleToInsertRatio`` limiter
(https://github.com/google-deepmind/reverb/blob/master/reverb/rate_limiters.py), restated here:
count inserted steps ``I``, evicted steps ``E`` and sampled windows ``S``; once ``min_size_to_sample``
steps are stored, every inserted step entitles the learner to ``samples_per_insert`` windows. The
surplus ``D = (I - min_size_to_sample) * samples_per_insert - S`` is the number of windows the
learner may still draw; the limiter keeps it within ``[-tolerance, +tolerance]``.

Unlike Reverb (which rejects an error buffer narrower than one request), a request is also let
through whenever the *other* side is the one behind (an insert when ``D <= 0``, a sample when
``D > 0``), so the band may be overshot by one request but the two sides can never both be blocked,
whatever the tolerance, batch size and chunk length.

Usage (the table does this; holding ``limiter.condition``, a re-entrant lock, around the whole
operation makes admission and action atomic)::

    with limiter.condition:
        limiter.await_sample(batch_size, timeout)   # raises SampleTimeout
        ...draw the batch...
        limiter.record_sample(batch_size)

With ``enforce_ratio=False`` (the single-process loop, which inserts and samples from one thread
and decides itself how many updates to run per env step) inserts never block and sampling only
waits for ``min_size_to_sample`` stored steps.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from algorithm.replay.base import SampleTimeout


class InsertTimeout(TimeoutError):
    """An insert stayed blocked by the rate limiter (learner behind) for longer than its timeout."""


class RateLimiter:
    """Sample-to-insert ratio with tolerance and a minimum size; one limiter per table."""

    def __init__(
        self,
        samples_per_insert: float,
        min_size_to_sample: int,
        tolerance: float = 0.0,
        enforce_ratio: bool = True,
    ) -> None:
        if not samples_per_insert > 0:
            raise ValueError(f"samples_per_insert must be > 0, got {samples_per_insert}")
        if int(min_size_to_sample) < 1:
            raise ValueError(f"min_size_to_sample must be >= 1, got {min_size_to_sample}")
        if not tolerance >= 0:
            raise ValueError(f"samples_per_insert_tolerance must be >= 0, got {tolerance}")
        self.samples_per_insert = float(samples_per_insert)
        self.min_size_to_sample = int(min_size_to_sample)
        self.tolerance = float(tolerance)
        self.enforce_ratio = bool(enforce_ratio)
        self.condition = threading.Condition(threading.RLock())
        self.inserted = 0
        self.evicted = 0
        self.sampled = 0
        self.insert_waits = 0
        self.sample_waits = 0
        self.insert_wait_seconds = 0.0
        self.sample_wait_seconds = 0.0

    @property
    def size(self) -> int:
        """Steps currently stored (inserted minus evicted)."""
        return self.inserted - self.evicted

    @property
    def surplus(self) -> float:
        """Windows the learner may still draw before it is ahead of the target ratio (``D``)."""
        return (self.inserted - self.min_size_to_sample) * self.samples_per_insert - self.sampled

    def can_insert(self, n: int) -> bool:
        """Whether inserting ``n`` steps now keeps the learner within tolerance (or it is behind)."""
        if not self.enforce_ratio or self.size < self.min_size_to_sample:
            return True
        d = self.surplus
        return d <= 0 or d + n * self.samples_per_insert <= self.tolerance

    def can_sample(self, n: int) -> bool:
        """Whether ``n`` windows may be drawn now: enough steps stored and, when the ratio is
        enforced, the learner not ahead of the inserters by more than the tolerance."""
        if self.size < self.min_size_to_sample:
            return False
        if not self.enforce_ratio:
            return True
        d = self.surplus
        return d > 0 or d - n >= -self.tolerance

    def await_insert(self, n: int, timeout: float | None) -> None:
        """Block until :meth:`can_insert`; raise :class:`InsertTimeout` after ``timeout`` seconds
        (None: forever, 0: check once)."""
        with self.condition:
            if self.can_insert(n):
                return
            self.insert_waits += 1
            start = time.monotonic()
            ok = self.condition.wait_for(lambda: self.can_insert(n), timeout)
            self.insert_wait_seconds += time.monotonic() - start
        if not ok:
            owed = self.surplus
            raise InsertTimeout(
                f"insert of {n} steps held back {timeout} s by the rate limiter, as it should be while the learner "
                f"is behind: it has {owed:.0f} windows to sample first ({owed / self.samples_per_insert:.0f} env "
                f"steps' worth at samples_per_insert {self.samples_per_insert:g})"
            )

    def await_sample(self, n: int, timeout: float | None) -> None:
        """Block until :meth:`can_sample`; raise :class:`~algorithm.replay.base.SampleTimeout`
        after ``timeout`` seconds (None: forever, 0: check once)."""
        with self.condition:
            if self.can_sample(n):
                return
            self.sample_waits += 1
            start = time.monotonic()
            ok = self.condition.wait_for(lambda: self.can_sample(n), timeout)
            self.sample_wait_seconds += time.monotonic() - start
        if not ok:
            if self.size < self.min_size_to_sample:
                why = f"{self.size} steps stored < min_size_to_sample {self.min_size_to_sample}"
            else:
                why = (
                    f"rate-limited: the learner has sampled the {self.sampled} windows its "
                    f"{self.inserted - self.min_size_to_sample} steps past min_size_to_sample allow at "
                    f"samples_per_insert {self.samples_per_insert:g}, and waits for more data"
                )
            raise SampleTimeout(f"could not sample {n} windows within {timeout} s ({why})")

    def record_insert(self, n: int, evicted: int = 0) -> None:
        """Count ``n`` inserted and ``evicted`` dropped steps and wake waiters."""
        with self.condition:
            self.inserted += int(n)
            self.evicted += int(evicted)
            self.condition.notify_all()

    def record_sample(self, n: int) -> None:
        """Count ``n`` sampled windows and wake waiters."""
        with self.condition:
            self.sampled += int(n)
            self.condition.notify_all()

    def info(self) -> dict[str, float]:
        """Counters for ``replay/*`` metrics."""
        return {
            "rate_limiter_surplus": float(self.surplus),
            "insert_waits": float(self.insert_waits),
            "sample_waits": float(self.sample_waits),
            "insert_wait_seconds": self.insert_wait_seconds,
            "sample_wait_seconds": self.sample_wait_seconds,
        }

    def state_dict(self) -> dict[str, Any]:
        """The counters that decide future admissions (saved with the table)."""
        return {"inserted": self.inserted, "evicted": self.evicted, "sampled": self.sampled}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore counters written by :meth:`state_dict`."""
        counts = {k: int(state[k]) for k in ("inserted", "evicted", "sampled")}
        if min(counts.values()) < 0 or counts["evicted"] > counts["inserted"]:
            raise ValueError(f"invalid rate limiter state {counts}")
        with self.condition:
            self.inserted, self.evicted, self.sampled = (
                counts["inserted"],
                counts["evicted"],
                counts["sampled"],
            )
            self.condition.notify_all()
