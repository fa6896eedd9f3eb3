"""gRPC's client I/O for role processes, chosen before grpc is imported (grpc reads it once).

grpcio's default client stack (EventEngine) reads a reply on its own threads and then wakes the
calling thread. A learner takes a Sample reply of 16 batches (~0.9 MB at the HalfCheetah default)
every ~0.2 s; between calls those threads go idle, and each call then costs ~20 context switches
and 2.25 ms of CPU on this project's 2-core machine. With the ``event_engine_client`` experiment
off, the calling thread polls and reads the socket itself: ~9 switches and 1.58 ms per call, the
same ~0.85 ms when calls come back to back, and inserts as fast as with it on
(bench/results/transport/README.md). The setting is the environment variable grpc documents for
its experiments, so a user's own ``GRPC_EXPERIMENTS`` wins, and child processes inherit it.
"""

from __future__ import annotations

import os
import sys

GRPC_EXPERIMENTS_ENV = "GRPC_EXPERIMENTS"
ROLE_GRPC_EXPERIMENTS = "-event_engine_client"


def read_replies_on_calling_thread() -> None:
    """Turn grpc's EventEngine client off for this process and its children, unless
    ``GRPC_EXPERIMENTS`` is already set. Raises RuntimeError once grpc is imported (too late: the
    setting would silently do nothing)."""
    if "grpc" in sys.modules:
        raise RuntimeError(
            "read_replies_on_calling_thread() must run before grpc is imported: call it first thing in the "
            "process's entry point, as main_ds.py does"
        )
    os.environ.setdefault(GRPC_EXPERIMENTS_ENV, ROLE_GRPC_EXPERIMENTS)
