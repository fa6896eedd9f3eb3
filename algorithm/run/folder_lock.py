"""One live process per folder: ``flock`` on the folder itself, held while the process lives.

A run trained by two processes at once (the same ``main.py ... -n NAME`` in two terminals, or a
``main_ds.py ... local`` started again while the first still runs) interleaves two runs' rows in
``evaluations.csv`` and overwrites each other's checkpoints, silently. The process that drives a run
holds its folder's lock; a second one stops before it touches anything, naming the holder.

Usage::

    lock = hold_folder(run_dir, "run")     # FolderInUse if another live process holds it
    ...                                    # train
    lock.release()                         # or let the process end: the kernel drops the lock

The lock is taken on the folder's own descriptor, so no file is added to the folder (a damaged run
that is refused stays byte for byte as it was), and it dies with its process (``kill -9``
included), so a run whose process was killed is free to resume. The holder is named from
``/proc/locks`` where there is one. A population's learners hold the same lock on their own folders
(ds/member/population.py).
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path


class FolderInUse(Exception):
    """Another live process holds the folder's lock; the message names it and what to do."""


class FolderLock:
    """A held lock on ``folder``: :meth:`release` (or the process's end) frees it."""

    def __init__(self, folder: Path, fd: int) -> None:
        self.folder = folder
        self._fd: int | None = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the flock
            self._fd = None


def try_hold(folder: Path) -> FolderLock | None:
    """The lock on ``folder`` (made if missing), or None when another live process holds it."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)  # not inherited by child processes
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return FolderLock(folder, fd)


def holder(folder: Path) -> str:
    """``process PID`` holding the flock on ``folder``, from Linux's ``/proc/locks`` (lines such as
    ``1: FLOCK  ADVISORY  WRITE 4242 00:2f:1234 0 EOF``); ``another process`` where that says nothing."""
    try:
        st = os.stat(folder)
        inode = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
        with open("/proc/locks") as locks:
            for line in locks:
                fields = line.split()
                if len(fields) > 5 and fields[1] == "FLOCK" and fields[5] == inode:
                    return f"process {int(fields[4])}"
    except (OSError, ValueError):
        pass
    return "another process"


def hold_folder(folder: Path, what: str) -> FolderLock:
    """:func:`try_hold`, or :class:`FolderInUse` naming ``what`` the folder is (e.g. "run"), the
    process that holds it and what to do."""
    lock = try_hold(folder)
    if lock is not None:
        return lock
    raise FolderInUse(
        f"{what} {folder} is in use by {holder(folder)}, which is training it now: wait for it to finish or stop it "
        "(Ctrl-C saves, and the same command resumes), or give this one another name with -n"
    )


__all__ = ["FolderInUse", "FolderLock", "hold_folder", "try_hold"]
