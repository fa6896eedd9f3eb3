"""Large messages without page faults: glibc's malloc told to keep freed memory for reuse.

A learner receives a few hundred KB of batches per call, a replay as much in chunks, and each reply
passes through several buffers of that size (gRPC's, Python's bytes, numpy's). glibc serves an
allocation of 128 KB or more with a fresh ``mmap`` and unmaps it when freed (raising that threshold
only as larger blocks are freed), so every message page-faulted its buffers in again: ~380 faults
and ~0.9 ms of CPU per call of eight HalfCheetah batches, half of the learner's receiving cost
(bench/transport.py). Served from the heap and kept there, the same buffers are reused.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger("asac.net")

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
MMAP_THRESHOLD_BYTES = 64 * 1024 * 1024  # allocations below this come from the heap
TRIM_THRESHOLD_BYTES = 256 * 1024 * 1024  # free memory at the heap's top kept up to this much


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds for this process (a role's first act); False where the
    C library is not glibc or refuses (nothing changes then, only speed)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    done = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
    if not done:
        log.debug("mallopt refused the thresholds; large messages keep page-faulting their buffers in")
    return done
