"""A link between two roles that goes down and comes back (a partition, a peer restarting), told once
each way in the log: :class:`Outage`.

Retries of a link run many times a second; a line per retry buries what happened, and a line every
half minute still says nothing an operator needs twice. What an operator needs is when the link went,
why, and when it came back, after how long.
"""

from __future__ import annotations

import logging
import threading
import time

BLIP_S = 3.0
"""A link down for less than this (a replay restarting, a connection replaced) is a blip: counted by the
caller, not logged."""

GRPC_DEADLINE_DETAILS = "Deadline Exceeded"
"""gRPC's status details when a call's own deadline passed without an answer from the server (a
partition, a stalled peer); a server that refuses in time (a rate limiter) sends its own words."""


def unanswered(error: BaseException) -> bool:
    """Whether ``error`` (a client's exception, whose message ends with the call's status details,
    possibly followed by the code in parentheses) is a call the peer never answered."""
    message = str(error)
    return message.endswith(f": {GRPC_DEADLINE_DETAILS}") or f": {GRPC_DEADLINE_DETAILS} (" in message


class Outage:
    """The outages of one link (``link``: what and where, e.g. ``"replay at 10.0.0.1:6000"``). Call
    :meth:`failed` on each failed call and :meth:`ok` on each answered one: the first failure that
    comes ``warn_after_s`` after the outage began logs one WARNING (the link, why, what the role does
    meanwhile), the next answer one INFO with how long it was down. A short blip shorter than
    ``warn_after_s`` logs nothing. Thread-safe (one link's calls may fail on one thread and be
    answered on another)."""

    def __init__(self, link: str, log: logging.Logger, warn_after_s: float = 0.0) -> None:
        self.link = link
        self.log = log
        self.warn_after_s = warn_after_s
        self.outages = 0  # outages that were logged
        self.down_s = 0.0  # their total length
        self._since: float | None = None
        self._warned = False
        self._lock = threading.Lock()

    @property
    def down(self) -> bool:
        return self._since is not None

    def failed(self, why: str, meanwhile: str = "retrying") -> None:
        """A call on the link failed (``why``); ``meanwhile``: what the role does until it is back."""
        now = time.monotonic()
        with self._lock:
            if self._since is None:
                self._since = now
            if self._warned or now - self._since < self.warn_after_s:
                return
            self._warned = True
            since = now - self._since
        self.log.warning("%s unreachable (%s) for %.0f s; %s. Said once: the next line on it is when it is back",
                         self.link, why, since, meanwhile)  # fmt: skip

    def ok(self) -> None:
        """A call on the link was answered."""
        if self._since is None:  # the common case, without the lock
            return
        with self._lock:
            since, warned = self._since, self._warned
            self._since, self._warned = None, False
        if since is None or not warned:
            return
        down = time.monotonic() - since
        self.outages += 1
        self.down_s += down
        self.log.info("%s is back after %.1f s", self.link, down)
