"""A small tmpfs to fill up, for the full-disk tests (mounting one needs root; without it they skip).

Usage::

    with small_disk(tmp_path / "disk", "4m") as disk:   # skips the test, saying why, without root
        ...                                            # write under disk.path
        disk.fill()                                    # a filler file takes every free byte
        disk.fill(leave=65536)                         # ... or all but 64 kB
        ...                                            # writes now fail with ENOSPC
        disk.free()                                    # the filler is gone: space is back
        with disk.kept_full():                         # the filler takes any space freed meanwhile
            ...                                        # (a process's failed temp file, deleted)
"""

from __future__ import annotations

import contextlib
import errno
import os
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest


class SmallDisk:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.filler = path / "filler"

    def available(self) -> int:
        st = os.statvfs(self.path)
        return st.f_bavail * st.f_frsize

    def fill(self, leave: int = 0) -> int:
        """Take every free byte but ``leave`` with the filler file (unbuffered: each write that fits
        is kept); returns the bytes it holds."""
        block = b"\0" * 4096
        fd = os.open(self.filler, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        try:
            if leave:
                while self.available() > leave:
                    os.write(fd, block)
                return self.filler.stat().st_size
            while True:
                try:
                    os.write(fd, block)
                except OSError as e:
                    if e.errno != errno.ENOSPC:
                        raise
                    break
            for size in (512, 64, 1):  # what is left of the last block
                with contextlib.suppress(OSError):
                    while True:
                        os.write(fd, block[:size])
        finally:
            os.close(fd)
        return self.filler.stat().st_size

    def free(self) -> None:
        self.filler.unlink(missing_ok=True)

    @contextlib.contextmanager
    def kept_full(self, every_s: float = 0.05) -> Iterator[None]:
        """Full for the duration: a thread fills again whatever is freed (a writer that failed deletes
        its temp file, which would let the next writes through); the filler stays afterwards."""
        done = threading.Event()

        def keep() -> None:
            while not done.wait(every_s):
                if self.available() > 0:
                    self.fill()

        self.fill()
        thread = threading.Thread(target=keep, name="keep-full", daemon=True)
        thread.start()
        try:
            yield
        finally:
            done.set()
            thread.join()


@contextlib.contextmanager
def small_disk(path: Path, size: str = "4m") -> Iterator[SmallDisk]:
    """A tmpfs of ``size`` mounted at ``path`` for the duration; unmounted afterwards in any case."""
    if os.geteuid() != 0:
        pytest.skip("needs root to mount a tmpfs (the full-disk tests fill a small one)")
    path.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", str(path)],
                             capture_output=True, text=True)  # fmt: skip
    if mounted.returncode != 0:
        pytest.skip(f"needs root to mount a tmpfs: mount failed ({mounted.stderr.strip()})")
    try:
        yield SmallDisk(path)
    finally:
        for _ in range(50):  # a process of the test may still be closing its files
            if subprocess.run(["umount", str(path)], capture_output=True).returncode == 0:
                break
            time.sleep(0.1)
        else:
            subprocess.run(["umount", "-l", str(path)], capture_output=True)
