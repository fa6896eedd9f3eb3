"""An actor's staleness: the learner's updates at each step it takes (estimated from the heartbeats'
answers) minus the version of the weights it acts with."""

from __future__ import annotations

import pytest

from ds.actor.staleness import Staleness
from tests.ds.learner.test_service import Clock


def test_a_step_is_as_stale_as_the_updates_the_learner_made_since_its_weights() -> None:
    clock = Clock()
    meter = Staleness(clock)
    meter.acted(5)  # no answer from the learner yet: nothing to say
    assert meter.take() == {}
    meter.learner_said(100)
    clock.now = 2.0
    meter.learner_said(300)  # 100 updates/s
    meter.acted(300)  # just published: 0 behind
    clock.now = 2.5  # the learner has made ~50 more since the last answer
    meter.acted(290)
    meter.acted(-1)  # no weights yet: not a sample
    taken = meter.take()
    assert taken["actor/staleness_median"] == pytest.approx(30.0)  # samples 0 and 60
    assert taken["actor/staleness_p95"] == pytest.approx(57.0)
    assert meter.take() == {}  # each take covers the steps since the one before


def test_a_restarted_learner_counts_afresh() -> None:
    clock = Clock()
    meter = Staleness(clock)
    meter.learner_said(5000)
    clock.now = 1.0
    meter.learner_said(5100)
    clock.now = 2.0
    meter.learner_said(20)  # a new learner: its count starts over, and so does the rate
    clock.now = 3.0
    assert meter.estimate() == 20
    meter.acted(10)
    assert meter.take()["actor/staleness_median"] == 10
