"""Crash-safe file writes and non-blocking reads shared by checkpoints and replay persistence, and
:class:`WriteFailures`: what a process that must keep running does when one of its writes fails
(a full disk, an I/O error): it logs once, keeps the previous file and tries again later."""

from __future__ import annotations

import errno
import logging
import os
import stat
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO


def _read_umask() -> int:
    mask = os.umask(0o022)  # reading the umask means setting it; done once, at import
    os.umask(mask)
    return mask


# The mode a file made by ``open()`` would get (0o666 less the umask read at import): atomic_write's
# temp files come from mkstemp, which makes them 0600 whatever the umask.
NEW_FILE_MODE = 0o666 & ~_read_umask()


class NotRegularFile(ValueError):
    """A path names something other than a regular file (a FIFO, a device, a socket, a folder, or a
    symlink where none is followed); refused before it is opened."""


def file_kind(mode: int) -> str:
    """What ``mode`` (``os.stat_result.st_mode``) is, for messages: "a regular file", "a FIFO", ..."""
    kinds = [
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISLNK, "a symlink"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
    ]
    return next((name for test, name in kinds if test(mode)), "not a regular file")


def open_regular(path: Path, *, follow_symlinks: bool = True) -> BinaryIO:
    """Open an existing regular file for reading; anything else raises :class:`NotRegularFile`
    before it is opened, so that a FIFO (whose open waits for a writer) or a device (whose open may
    act) is never opened. The open is non-blocking besides (``O_NONBLOCK``) and what was opened is
    checked again (``fstat``: the same regular file that was inspected), so a file swapped for a FIFO
    in between cannot block it either. ``follow_symlinks=False``: a symlink is refused too
    (``O_NOFOLLOW``). A missing file raises ``FileNotFoundError``."""
    st = os.stat(path, follow_symlinks=follow_symlinks)
    if not stat.S_ISREG(st.st_mode):
        raise NotRegularFile(f"{path} is {file_kind(st.st_mode)}, not a regular file")
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
    if not follow_symlinks:
        flags |= getattr(os, "O_NOFOLLOW", 0)
    f = open(path, "rb", opener=lambda name, _: os.open(name, flags))  # noqa: SIM115 - returned open
    try:
        opened = os.fstat(f.fileno())
        if not stat.S_ISREG(opened.st_mode) or (opened.st_dev, opened.st_ino) != (st.st_dev, st.st_ino):
            raise NotRegularFile(f"{path} changed while it was opened (now {file_kind(opened.st_mode)})")
        os.set_blocking(f.fileno(), True)
    except BaseException:
        f.close()
        raise
    return f


def atomic_write(
    path: Path, write: Callable[[BinaryIO], object], before_replace: Callable[[], object] | None = None
) -> None:
    """Call ``write(f)`` on a temp file beside ``path``, fsync it, rename it over ``path`` and fsync
    the folder, so a crash leaves either the old file or the new one, never half of one.

    ``path`` itself is never opened: the rename replaces its directory entry (a symlink there is
    replaced, not followed). ``before_replace`` is called after the fsync, right before the rename;
    if it raises, the temp file is removed and ``path`` is left as it was.

    A write that fails (a full disk, an I/O error) removes the temp file, leaves ``path`` as it was
    and raises the ``OSError``, also when ``write`` turned it into another exception (``torch.save``
    raises a RuntimeError from its zip writer with the cause lost in its message).

    The file gets the mode a plain ``open()`` would give it under the process's umask
    (:data:`NEW_FILE_MODE`, e.g. 0644), so another user or a container with another uid can read a
    run's checkpoints and evaluations where the umask allows it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), NEW_FILE_MODE)
            sink = _Recorded(f)
            try:
                write(sink)  # type: ignore[arg-type]  # a file in all but name
            except Exception as e:
                if sink.error is None or isinstance(e, OSError):
                    raise
                raise sink.error from e
            f.flush()
            os.fsync(f.fileno())
        if before_replace is not None:
            before_replace()
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)  # make the rename itself durable
    finally:
        os.close(dir_fd)


class _Recorded:
    """The temp file as ``atomic_write``'s writer sees it: the file itself, remembering the first
    ``OSError`` its writes raised."""

    def __init__(self, f: BinaryIO) -> None:
        self._f = f
        self.error: OSError | None = None

    def write(self, data: Any) -> int:
        try:
            return self._f.write(data)
        except OSError as e:
            self.error = self.error or e
            raise

    def flush(self) -> None:
        try:
            self._f.flush()
        except OSError as e:
            self.error = self.error or e
            raise

    def __getattr__(self, name: str) -> Any:
        return getattr(self._f, name)


def describe_os_error(error: OSError) -> str:
    """``No space left on device [ENOSPC]``: the cause of a failed write, for one log line."""
    if error.errno is None:
        return f"{type(error).__name__}: {error}"
    return f"{error.strerror or os.strerror(error.errno)} [{errno.errorcode.get(error.errno, error.errno)}]"


def previous_file_kept(path: Path) -> str:
    """What a failed atomic write of ``path`` leaves: the previous file, or nothing."""
    return f"{path} keeps its previous contents" if path.exists() else f"{path} was not created"


class WriteFailures:
    """The writes of one kind of file (checkpoints, a replay snapshot, the evolver's state,
    ``evaluations.csv``, TensorBoard summaries) in a process that must go on when they fail.

    :meth:`attempt` runs a write; an ``OSError`` (a full disk, an I/O error, a folder made read-only)
    becomes False and one ERROR line naming the file, the cause and what is kept (``kept(path)``;
    written with :func:`atomic_write`, the previous file, whole). Later failures are logged again only
    for another cause (errno), until a write succeeds, which is logged once too (``... written again``).
    The caller tries again at its next interval; nothing else changes. ``final=True`` (the save at
    shutdown, after which there is no next interval) logs its failure in any case.

    Usage::

        checkpoints = WriteFailures("checkpoint", log, retry="trying again at the next checkpoint")
        if checkpoints.attempt(path, lambda: save_checkpoint(...)):
            log.info("checkpoint %s", path)
    """

    def __init__(
        self,
        what: str,
        logger: logging.Logger,
        *,
        retry: str = "trying again at the next save",
        kept: Callable[[Path], str] = previous_file_kept,
    ) -> None:
        self.what = what
        self.log = logger
        self.retry = retry
        self.kept = kept
        self.failures = 0  # failed attempts since the last write that worked
        self.total_failures = 0
        self._causes: set[int | None] = set()  # errnos logged since the last write that worked
        self._lock = threading.Lock()

    @property
    def failing(self) -> bool:
        """Whether the last attempt failed."""
        return self.failures > 0

    def attempt(self, path: Path, write: Callable[[], object], *, final: bool = False) -> bool:
        """Run ``write()`` (which writes ``path``): True when it worked, False (logged) on an OSError."""
        try:
            write()
        except OSError as e:
            self.failed(path, e, final=final)
            return False
        self.succeeded(path)
        return True

    def failed(self, path: Path, error: OSError, *, final: bool = False) -> None:
        """Count and log (see the class) a write of ``path`` that raised ``error``."""
        with self._lock:
            self.failures += 1
            self.total_failures += 1
            new_cause = error.errno not in self._causes
            self._causes.add(error.errno)
        cause = describe_os_error(error)
        if final:
            self.log.error("could not write the final %s %s at shutdown: %s; %s", self.what, path, cause,
                           self.kept(path))  # fmt: skip
        elif new_cause:
            self.log.error("could not write the %s %s: %s; %s; %s (logged once until it works again)", self.what,
                           path, cause, self.kept(path), self.retry)  # fmt: skip
        else:
            self.log.debug("could not write the %s %s again: %s", self.what, path, cause)

    def succeeded(self, path: Path) -> None:
        """A write of ``path`` worked: after failures, say so once."""
        with self._lock:
            failures, self.failures = self.failures, 0
            self._causes.clear()
        if failures:
            self.log.info("writing the %s works again (%s), after %d failed attempt%s", self.what, path, failures,
                          "s" * (failures != 1))  # fmt: skip
