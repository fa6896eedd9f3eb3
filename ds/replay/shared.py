"""Sampled batches through a file in shared memory when a learner and its replay share a host.

A learner's replay client creates one file under ``/dev/shm`` (:class:`SharedSlot`: mode 0600, its
pages reserved when it is made, so a full ``/dev/shm`` is an error then and never a SIGBUS later),
maps it and names it in every Sample request. A replay server that can open it
(:func:`write_shared`) packs the batches there and answers with their length alone; one that cannot
(another host, a container with its own ``/dev/shm``, a server without this) answers with the data
as before, and the client stops naming the file. The reply's ~0.9 MB (HalfCheetah default, 16
batches) then never crosses the socket: gRPC reading it and the kernel copying it were most of the
learner's CPU per sampled step (bench/transport.py), and the replay skips two copies and the send.

Late writers: an attempt that timed out or was retried may still run on the server. Before each
attempt the client writes a new sequence number into the file's header (:meth:`SharedSlot.fence`,
under an ``flock``); the server writes only while it holds that lock and only when the header holds
its attempt's number. So once an attempt's reply is in, nothing but the client's next attempt writes
into the file, and the client reads what the answering attempt wrote. The client copies the batches
out before its next call (ds/replay/packed.py ``unpack_batches``), so one file per client suffices.

Files left by a process that was killed are removed by the next slot made on the host by the same
user (:func:`sweep`): their names carry the creator's process id.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import mmap
import os
import re
import secrets
import stat
import struct
import weakref
from collections.abc import Callable
from pathlib import Path

import numpy as np

log = logging.getLogger("asac.replay")

SHARED_DIR = Path("/dev/shm")
MAGIC = b"ASACBAT1"
_HEADER = struct.Struct("<8sQ")  # magic, the sequence number of the attempt that may write
HEADER_BYTES = 64  # the batches start here (a multiple of ALIGN in ds/replay/packed.py)
_NAME = re.compile(r"asac-batches-(\d+)-[0-9a-f]{16}")
_MAP_FLAGS = mmap.MAP_SHARED | getattr(mmap, "MAP_POPULATE", 0)  # Linux: the pages mapped in one go


class SharedSlot:
    """A ``HEADER_BYTES + capacity``-byte file in ``folder``, mapped, for one client's sampled
    batches. Raises ``OSError`` where it cannot be made (no ``/dev/shm``, full, read-only)."""

    def __init__(self, capacity: int, folder: Path | None = None) -> None:
        folder = SHARED_DIR if folder is None else folder
        sweep(folder)
        self.name = f"asac-batches-{os.getpid()}-{secrets.token_hex(8)}"
        self.path = Path(folder) / self.name
        self.size = HEADER_BYTES + int(capacity)
        self.seq = 0
        flags = os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
        self._fd = os.open(self.path, flags, 0o600)
        try:
            os.posix_fallocate(self._fd, 0, self.size)  # tmpfs pages reserved now: ENOSPC here, not SIGBUS later
            self._map = mmap.mmap(self._fd, self.size)
        except BaseException:
            os.close(self._fd)
            self.path.unlink(missing_ok=True)
            raise
        _HEADER.pack_into(self._map, 0, MAGIC, 0)
        # removed when closed, collected or at the interpreter's exit, whichever comes first
        self._finalizer = weakref.finalize(self, _remove, self.path, self._fd, self._map)

    @property
    def capacity(self) -> int:
        """Bytes of batches the file holds."""
        return self.size - HEADER_BYTES

    def fence(self) -> int:
        """A new attempt's sequence number, written into the header once no server writes (see the
        module docstring); the attempt's request carries it."""
        self.seq += 1
        fcntl.flock(self._fd, fcntl.LOCK_EX)
        try:
            _HEADER.pack_into(self._map, 0, MAGIC, self.seq)
        finally:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
        return self.seq

    def payload(self, nbytes: int) -> memoryview:
        """The first ``nbytes`` bytes of batches, as the server wrote them (not a copy)."""
        if not 0 < nbytes <= self.capacity:
            raise ValueError(f"shared_bytes is {nbytes}, but the shared file {self.path} holds 1 to {self.capacity}")
        return memoryview(self._map)[HEADER_BYTES : HEADER_BYTES + nbytes]

    def close(self) -> None:
        """Unmap, close and remove the file (a server still holding it open finishes harmlessly)."""
        self._finalizer()


def _remove(path: Path, fd: int, mapped: mmap.mmap) -> None:
    with contextlib.suppress(BufferError):  # a view of it is still alive: the mapping goes with the last one
        mapped.close()
    os.close(fd)
    path.unlink(missing_ok=True)


def write_shared(name: str, size: int, seq: int, nbytes: int, fill: Callable[[np.ndarray], None],
                 folder: Path | None = None) -> bool:  # fmt: skip
    """Server side: ``fill`` the first ``nbytes`` batch bytes of the caller's file ``name`` (a
    writable uint8 array of them), if it is a slot of this user of exactly ``size`` bytes whose
    header holds ``seq``, holding its lock meanwhile. False, and nothing written, otherwise: the
    caller then sends the batches in the reply."""
    if not _NAME.fullmatch(name) or not 0 < nbytes <= size - HEADER_BYTES:
        return False
    try:
        fd = os.open((SHARED_DIR if folder is None else folder) / name, os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:  # another host's file, another /dev/shm, removed since
        return False
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_size != size or st.st_uid != os.getuid():
            return False
        mapped = mmap.mmap(fd, size, flags=_MAP_FLAGS)  # pages mapped at once: no fault per page
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            try:
                magic, current = _HEADER.unpack_from(mapped, 0)
                if magic != MAGIC or current != seq:  # a late attempt: the client has moved on
                    return False
                view = np.frombuffer(mapped, np.uint8, nbytes, HEADER_BYTES)
                fill(view)
                del view
            finally:
                fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            with contextlib.suppress(BufferError):  # fill failed, its traceback holds a view: unmapped with it
                mapped.close()
        return True
    finally:
        os.close(fd)


def sweep(folder: Path) -> int:
    """Remove this user's slot files in ``folder`` whose creating process is gone; returns how many."""
    removed = 0
    try:
        names = os.listdir(folder)
    except OSError:
        return 0
    for name in names:
        match = _NAME.fullmatch(name)
        if match is None or _alive(int(match.group(1))):
            continue
        path = Path(folder) / name
        try:
            if path.lstat().st_uid == os.getuid():
                path.unlink()
                removed += 1
        except OSError:
            continue
    if removed:
        log.info("removed %d shared batch file(s) of processes that are gone from %s", removed, folder)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, another user's
        return True
    return True
