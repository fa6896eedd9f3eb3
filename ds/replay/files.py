"""The files the replay server's Save and Load rpcs may touch, and how long they may take.

A replay server owns one folder, its snapshot folder (the replay role's ``<run>/replay/``, where it
keeps ``replay.npz``). :class:`SnapshotFolder` turns the name a client sends into a path in it, or
refuses it (a :class:`~ds.net.wire.WireError`, INVALID_ARGUMENT, naming the problem):

- an empty name is the default snapshot, ``replay.npz`` (the file the replay role loads when it
  starts and saves when it stops);
- otherwise a relative name: absolute paths, any ``..`` part and NUL characters are refused, and
  the name is resolved (symlinks followed) and must stay inside the folder, so a symlinked folder
  or file pointing out of it is refused too;
- what it names must be a regular file or not exist yet: a FIFO, device, socket or folder is
  refused at once, before anything opens it (Load opens the file only with ``O_NOFOLLOW |
  O_NONBLOCK`` and checks it again, :func:`algorithm.files.open_regular`). Save also refuses a
  symlink in the file's place (it replaces only regular files, and never one outside the folder);
  Load follows a symlink that stays inside.

:class:`FileWork` runs that file work, one Save or Load at a time, on a thread of its own, so that
a slow disk holds no gRPC worker past the call's deadline: at the deadline the call is answered
DEADLINE_EXCEEDED and the work is abandoned (a Save keeps the old file, a Load leaves the table
as it was); a Save or Load arriving while one runs is refused with ABORTED. Info, Insert, Sample and
the other rpcs are answered meanwhile.
"""

from __future__ import annotations

import logging
import os
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path, PurePosixPath

from algorithm.files import file_kind
from algorithm.run.folder import RunDir
from ds.net.wire import WireError

__all__ = ["DEFAULT_SNAPSHOT", "FileWork", "FileWorkAbandoned", "FileWorkBusy", "SnapshotFolder"]

log = logging.getLogger(__name__)

DEFAULT_SNAPSHOT = RunDir(Path()).replay.name  # "replay.npz": the replay role's own snapshot


class SnapshotFolder:
    """The folder ``root`` whose files a client may name (created by the first Save)."""

    def __init__(self, root: str | Path, default: str = DEFAULT_SNAPSHOT) -> None:
        self.root = Path(root)
        self.default = default

    def for_save(self, name: str) -> Path:
        """Where Save of ``name`` writes: a path inside the folder that does not exist yet or is a
        regular file (the temp file goes beside it, the rename replaces it)."""
        path = self._named(name)
        try:
            st = os.lstat(path)
        except FileNotFoundError:
            return path
        if not stat.S_ISREG(st.st_mode):
            raise WireError("path", f"{name!r} is {file_kind(st.st_mode)}: Save replaces only a regular file")
        return path

    def for_load(self, name: str) -> Path:
        """What Load of ``name`` reads: a path inside the folder, symlinks resolved; a missing file
        is left to the reader (which names it), anything but a regular file is refused here."""
        path = self._named(name)
        resolved = _resolve(path, name)
        if not resolved.is_relative_to(self.root.resolve()):
            raise WireError("path", f"{name!r} is a symlink pointing out of the replay's snapshot folder")
        try:
            st = os.lstat(resolved)
        except (FileNotFoundError, NotADirectoryError):
            return resolved
        if not stat.S_ISREG(st.st_mode):
            raise WireError("path", f"{name!r} is {file_kind(st.st_mode)}: Load reads only a regular file")
        return resolved

    def _named(self, name: str) -> Path:
        """``name`` (empty: the default) as a path in the folder whose parent folders are resolved
        and inside it; the last part is not resolved (the callers decide about a symlink there)."""
        if "\0" in name:  # the OS would refuse it with a message that does not say which field
            raise WireError("path", f"holds a NUL character: {name!r}")
        name = name or self.default
        rule = "name a file inside the replay's snapshot folder, relative to it"
        relative = PurePosixPath(name)
        if relative.is_absolute():
            raise WireError("path", f"{name!r} is absolute: {rule} (e.g. {self.default!r})")
        if ".." in relative.parts:
            raise WireError("path", f"{name!r} holds '..': {rule}, without '..'")
        if not relative.parts:
            raise WireError("path", f"{name!r} names the snapshot folder itself: {rule}")
        root = self.root.resolve()
        parent = _resolve((root / relative).parent, name)
        if not parent.is_relative_to(root):
            raise WireError("path", f"{name!r} leads out of the replay's snapshot folder through a symlinked folder")
        return parent / relative.name


def _resolve(path: Path, name: str) -> Path:
    try:
        return path.resolve()
    except (RuntimeError, OSError) as e:  # a symlink loop (RuntimeError before Python 3.13)
        raise WireError("path", f"{name!r} cannot be resolved ({e})") from None


class FileWorkBusy(Exception):
    """Another Save or Load is still running (ABORTED): the server does one at a time."""


class FileWorkAbandoned(Exception):
    """The file work did not finish within the call's deadline and was abandoned (DEADLINE_EXCEEDED)."""


class _Job:
    """One Save or Load: ``gate`` is what the work calls right before it changes anything."""

    def __init__(self, what: str) -> None:
        self.what = what
        self.started = time.monotonic()
        self.done = threading.Event()
        self.error: BaseException | None = None
        self._lock = threading.Lock()
        self._state = "working"  # -> "committing" (the work passed its gate) or "abandoned" (it never will)

    def gate(self) -> None:
        with self._lock:
            if self._state == "abandoned":
                raise FileWorkAbandoned(f"{self.what} was abandoned at its call's deadline")
            self._state = "committing"

    def abandon(self) -> bool:
        """Abandon the work unless it already passed its gate (then it finishes in moments)."""
        with self._lock:
            if self._state == "committing":
                return False
            self._state = "abandoned"
            return True


class FileWork:
    """Runs one Save or Load at a time on a thread of its own, each bounded by its call's deadline."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._running: _Job | None = None

    def run(self, what: str, work: Callable[[Callable[[], None]], object], timeout: float | None) -> None:
        """Run ``work(gate)`` (it calls ``gate()`` right before it changes a file or the table) and
        wait for it at most ``timeout`` seconds (None: until it ends). Raises what ``work`` raised,
        :class:`FileWorkBusy` at once if another job runs, or :class:`FileWorkAbandoned` at the
        timeout: the work then stops at its gate, having changed nothing, and its thread ends when
        its current read or write does (until then further jobs are refused as busy)."""
        job = _Job(what)
        with self._lock:
            running = self._running
            if running is None:
                self._running = job
        if running is not None:
            raise FileWorkBusy(
                f"{what} refused: {running.what} is still running ({time.monotonic() - running.started:.1f} s so "
                "far) and this replay does one Save or Load at a time; try again once it has finished"
            )
        threading.Thread(target=self._work, args=(job, work), name=f"replay {what}", daemon=True).start()
        if not job.done.wait(timeout) and job.abandon():
            raise FileWorkAbandoned(
                f"{what} did not finish within the call's deadline ({timeout:.1f} s) and was abandoned: nothing "
                "was changed; give it a longer deadline"
            )
        job.done.wait()  # done, or past its gate: only the rename or the table swap is left
        if job.error is not None:
            raise job.error

    def _work(self, job: _Job, work: Callable[[Callable[[], None]], object]) -> None:
        try:
            work(job.gate)
        except FileWorkAbandoned:
            log.warning("replay %s was abandoned at its call's deadline after %.1f s", job.what,
                        time.monotonic() - job.started)  # fmt: skip
        except BaseException as e:  # handed to the waiting call
            job.error = e
        finally:
            with self._lock:
                self._running = None
            job.done.set()
