"""Stop on SIGINT, SIGTERM or SIGHUP by finishing cleanly, in every process that trains or serves.

Usage (``main.py``, each ``main_ds.py`` role and the ``local`` launcher)::

    stop = stop_on_signals()        # in the main thread, before the work starts
    ...                             # the work checks stop.is_set() between steps, then saves and closes
    return stop.exit_code           # 130 after SIGINT, 143 after SIGTERM, 129 after SIGHUP (128 + the number)

The first signal sets the event and logs one line; the work finishes its step, saves and returns. A
second signal raises KeyboardInterrupt wherever the main thread is, to cut a stuck shutdown short.
SIGTERM is what ``kill``, ``docker stop`` and Kubernetes send: it saves exactly as Ctrl-C does.
SIGHUP is what a process started from a terminal gets when the terminal closes (an SSH session
dropped): it saves too, rather than ending the process where it stands and losing the work since the
last checkpoint; where stdout or stderr is a terminal it is pointed at ``/dev/null`` (writes to a
hung-up terminal fail). A process started under ``nohup`` ignores SIGHUP, and still does.

A role started by ``main_ds.py ... local`` also stops, as on SIGTERM, when its launcher dies without
stopping it (``kill -9``): :func:`stop_with_launcher`.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import stat
import sys
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
        """The shell's code for death by the signal (130 SIGINT, 143 SIGTERM, 129 SIGHUP); 130 when none came
        (a KeyboardInterrupt raised some other way)."""
        return 128 + int(self.signum or signal.SIGINT)


def exit_quietly_on_sigint() -> None:
    """Until :func:`stop_on_signals` installs a run's handlers, make SIGINT end the process with 130 and no
    traceback. The entry points call it first: their imports (torch, a role's code) and set-up take a second
    or two, and a Ctrl-C then, which every role of a local run gets at once, printed a KeyboardInterrupt
    traceback per process from wherever its import stood. SystemExit unwinds as that did (context managers
    that remove a run folder not yet started still run)."""
    signal.signal(signal.SIGINT, _exit_by_signal)


def _exit_by_signal(signum: int, frame: FrameType | None) -> None:
    raise SystemExit(128 + signum)


def stop_on_signals(doing: str = "stopping after this step, saving") -> StopRequest:
    """Install handlers for SIGINT, SIGTERM and SIGHUP that set the returned :class:`StopRequest`; ``doing``
    says in the log line what the process does now (``SIGINT: <doing> (again to force)``)."""
    stop = StopRequest()

    def handler(signum: int, frame: FrameType | None) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        if signum == signal.SIGHUP:
            _leave_hung_up_terminal()
        stop.signum = signum
        log.info("%s: %s (again to force)", signal.Signals(signum).name, doing)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    if signal.getsignal(signal.SIGHUP) is not signal.SIG_IGN:  # nohup's choice stands
        signal.signal(signal.SIGHUP, handler)
    return stop


def _leave_hung_up_terminal() -> None:
    """Point stdout and stderr, where they are a terminal, at /dev/null: after SIGHUP every write to
    it fails (``local`` stopped its roles in order, then failed on printing its summary there: exit
    1; tests/test_local_journeys.py). Files and pipes are left as they are."""
    for stream in (sys.stdout, sys.stderr):
        try:
            fd = stream.fileno()
            if not stat.S_ISCHR(os.fstat(fd).st_mode):  # a terminal, even hung up (isatty is not:
                continue  # its ioctl answers EIO on a hung-up terminal)
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, fd)
            os.close(null)
        except (OSError, ValueError, AttributeError):  # no file descriptor (a test's capture), or closed
            continue


LAUNCHER_PID_ENV = "ASAC_LAUNCHER_PID"
"""Set by the ``local`` launcher in its children's environment: its own pid."""
_PR_SET_PDEATHSIG = 1  # linux/prctl.h
# The launcher's death comes as its own signal, not SIGTERM: Linux sends the parent-death signal
# each time the thread that is the child's parent dies, and the launcher's children are handed from
# its dying main thread to its other threads first, so it comes several times; as SIGTERM the second
# one was "again to force" and cut the save short.
LAUNCHER_DIED = signal.SIGUSR2


def stop_with_launcher(stop: StopRequest) -> None:
    """In a role started by ``local`` (``ASAC_LAUNCHER_PID`` set), after :func:`stop_on_signals`: ask
    Linux for :data:`LAUNCHER_DIED` when the launcher dies (``prctl(PR_SET_PDEATHSIG)``), so a
    launcher killed with -9 does not leave its roles running, unseen, with nobody reading their
    output: each saves and exits as on SIGTERM (143); repeats of the signal change nothing. If the
    launcher is already gone, stop now. Elsewhere (no such variable, or no prctl: not Linux)
    nothing is done."""
    launcher = os.environ.get(LAUNCHER_PID_ENV, "")
    if not launcher.isdigit() or not sys.platform.startswith("linux"):
        return

    def launcher_died(signum: int = LAUNCHER_DIED, frame: FrameType | None = None) -> None:
        if not stop.is_set():  # a repeat, or a stop already under way, is not a second signal
            log.info("the launcher (pid %s) died: stopping", launcher)
            stop.signum = signal.SIGTERM
            stop.set()

    signal.signal(LAUNCHER_DIED, launcher_died)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, int(LAUNCHER_DIED), 0, 0, 0) != 0:
            return
    except (OSError, AttributeError):
        return
    if os.getppid() != int(launcher):  # died before the request was in place: no signal will come
        launcher_died()
