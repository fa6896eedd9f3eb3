"""Stop on SIGINT or SIGTERM by finishing cleanly, in every process that trains or serves.

Usage (``main.py``, each ``main_ds.py`` role and the ``local`` launcher)::

    stop = stop_on_signals()        # in the main thread, before the work starts
    ...                             # the work checks stop.is_set() between steps, then saves and closes
    return stop.exit_code           # 130 after SIGINT, 143 after SIGTERM (128 + the signal number)

The first signal sets the event and logs one line; the work finishes its step, saves and returns. A
second signal raises KeyboardInterrupt wherever the main thread is, to cut a stuck shutdown short.
SIGTERM is what ``kill``, ``docker stop`` and Kubernetes send: it saves exactly as Ctrl-C does.
"""

from __future__ import annotations

import logging
import signal
import threading
from types import FrameType

log = logging.getLogger("asac")


class StopRequest(threading.Event):
    """An event set by the first SIGINT or SIGTERM, remembering which one came."""

    def __init__(self) -> None:
        super().__init__()
        self.signum: int | None = None

    @property
    def exit_code(self) -> int:
        """The shell's code for death by the signal (130 SIGINT, 143 SIGTERM); 130 when none came
        (a KeyboardInterrupt raised some other way)."""
        return 128 + int(self.signum or signal.SIGINT)


def stop_on_signals(doing: str = "stopping after this step, saving") -> StopRequest:
    """Install handlers for SIGINT and SIGTERM that set the returned :class:`StopRequest`; ``doing``
    says in the log line what the process does now (``SIGINT: <doing> (again to force)``)."""
    stop = StopRequest()

    def handler(signum: int, frame: FrameType | None) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.signum = signum
        log.info("%s: %s (again to force)", signal.Signals(signum).name, doing)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop
