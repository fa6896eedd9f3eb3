"""A link's outage is told once when noticed and once when it ends (ds/net/outage.py); a blip is not."""

from __future__ import annotations

import logging
import time

import pytest

from ds.net.outage import Outage, unanswered
from ds.replay.client import ReplayUnreachable

log = logging.getLogger("asac.test_outage")


def lines(caplog: pytest.LogCaptureFixture) -> list[tuple[int, str]]:
    return [(r.levelno, r.getMessage()) for r in caplog.records if r.name == log.name]


def test_an_outage_is_told_once_when_noticed_and_once_when_it_ends(caplog: pytest.LogCaptureFixture) -> None:
    link = Outage("replay at 10.0.0.1:6000", log, warn_after_s=0.2)
    with caplog.at_level(logging.INFO, logger=log.name):
        link.ok()  # answered, never down: nothing
        for _ in range(50):  # many retries inside and past the grace
            link.failed("UNAVAILABLE", "keeping the chunks")
            time.sleep(0.01)
        assert link.down
        link.ok()
        link.ok()
    told = lines(caplog)
    assert len(told) == 2, told
    assert told[0][0] == logging.WARNING
    assert told[0][1].startswith("replay at 10.0.0.1:6000 unreachable (UNAVAILABLE) for 0 s; keeping the chunks")
    assert told[1][0] == logging.INFO and told[1][1].startswith("replay at 10.0.0.1:6000 is back after 0.")
    assert (link.outages, link.down) == (1, False) and 0.4 < link.down_s < 2.0


def test_a_blip_shorter_than_the_grace_is_not_logged(caplog: pytest.LogCaptureFixture) -> None:
    link = Outage("learner at 10.0.0.2:6001", log, warn_after_s=5.0)
    with caplog.at_level(logging.INFO, logger=log.name):
        for _ in range(3):
            link.failed("UNAVAILABLE")
        link.ok()
        link.failed("UNAVAILABLE")  # a new outage starts its own clock
    assert lines(caplog) == [] and link.outages == 0 and link.down


def test_a_call_the_peer_never_answered_is_told_from_a_refusal_in_time() -> None:
    assert unanswered(ReplayUnreachable(None, "replay Insert at 10.0.0.1:6000: Deadline Exceeded"))  # type: ignore[arg-type]
    assert unanswered(TimeoutError("replay Sample at 10.0.0.1:6000: Deadline Exceeded (DEADLINE_EXCEEDED)"))
    refused = (
        "replay Insert at 10.0.0.1:6000: insert of 64 steps held back 2.0 s by the rate limiter (DEADLINE_EXCEEDED)"
    )
    assert not unanswered(TimeoutError(refused))
