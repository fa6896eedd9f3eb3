"""Crash-safe file writes and non-blocking reads shared by checkpoints and replay persistence."""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


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
    if it raises, the temp file is removed and ``path`` is left as it was."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
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
