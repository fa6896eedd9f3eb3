"""How many learner updates behind the weights an actor acts with are, at the steps it takes.

Usage (the actor's heartbeat thread and acting thread)::

    meter = Staleness()
    meter.learner_said(beat.updates)          # each heartbeat answer: the learner's updates so far
    meter.acted(params_version)               # each step: the version (an update count) acted with
    meter.take()                              # {"actor/staleness_median": ..., "_p95": ...} since last take

The learner's update count at a step is estimated from the last two heartbeat answers (its count then,
plus its rate between them times the time since), so a step's staleness is that estimate minus the
version acted with (never below 0). Measured where the actor acts, not at heartbeats: an actor held
back by the replay's rate limiter does not act meanwhile, and takes the newest weights before its
next step.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

SAMPLES = 4096  # the latest steps kept between two takes


class Staleness:
    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._said: list[tuple[float, int]] = []  # the last two (time, updates) answers
        self._samples: deque[float] = deque(maxlen=SAMPLES)

    def learner_said(self, updates: int) -> None:
        """A heartbeat answer: the learner has made ``updates`` updates (a smaller count: it restarted)."""
        with self._lock:
            if self._said and updates < self._said[-1][1]:
                self._said.clear()
            self._said = [*self._said[-1:], (self._clock(), int(updates))]

    def estimate(self) -> float | None:
        """The learner's updates now, as the last answers tell; None before the first."""
        with self._lock:
            said = list(self._said)
        if not said:
            return None
        (t1, u1), now = said[-1], self._clock()
        if len(said) < 2 or said[1][0] <= said[0][0]:
            return float(u1)
        t0, u0 = said[0]
        return u1 + (u1 - u0) / (t1 - t0) * max(now - t1, 0.0)

    def acted(self, version: int) -> None:
        """A step taken with the weights of ``version`` (nothing noted before weights or answers)."""
        learner = self.estimate()
        if learner is None or version < 0:
            return
        self._samples.append(max(learner - version, 0.0))

    def take(self) -> dict[str, float]:
        """Median and p95 of the steps since the last take (empty when there were none)."""
        samples = list(self._samples)
        self._samples.clear()
        if not samples:
            return {}
        return {
            "actor/staleness_median": float(np.median(samples)),
            "actor/staleness_p95": float(np.percentile(samples, 95)),
        }
