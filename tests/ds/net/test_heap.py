"""Every role keeps freed memory on glibc's heap (ds/net/heap.py): a learner's buffers for the batches
it receives are reused rather than page-faulted in again. Run in fresh processes (the setting is
process-wide), each a replay server and its client on loopback, the batches over the socket (as between
hosts: on one host they come through a file in /dev/shm, ds/replay/shared.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
SAMPLING = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from ds.net.heap import keep_freed_memory
    assert keep_freed_memory()
from algorithm.replay import PrioritizedTable
from algorithm.spaces import SensorSpec
from bench.replay import random_chunk
from ds.replay.client import ReplayClient
from ds.replay.codec import message_limit_bytes
from ds.replay.service import serve_replay
sensors, rng = (SensorSpec("obs", (17,)),), np.random.default_rng(0)
table = PrioritizedTable(20_000, sensors, 6, 1, alpha=0.0, seed=0)
for _ in range(100):
    table.insert(random_chunk(sensors, 6, 64, rng))
limit = message_limit_bytes(sensors, 6, 256, 1)
server, port = serve_replay(table, "127.0.0.1:0", max_message_bytes=limit)
client = ReplayClient(f"127.0.0.1:{port}", sensors, 6, max_message_bytes=limit, shared_memory=False)  # as across hosts
for _ in range(5):
    client.sample_many(256, 16, 5.0)
start = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(30):
    client.sample_many(256, 16, 5.0)
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - start) / 30)
server.stop(None)
"""


def faults_per_call(mode: str) -> float:
    out = subprocess.run([sys.executable, "-c", SAMPLING, mode], cwd=ROOT, capture_output=True, text=True,
                         check=True, timeout=120)  # fmt: skip
    return float(out.stdout.strip().splitlines()[-1])


def test_a_learners_sampled_batches_reuse_their_buffers_instead_of_faulting_them_in() -> None:
    """16 HalfCheetah-size batches a call (~870 KB); the process holds server and client, both kept."""
    plain, kept = faults_per_call("plain"), faults_per_call("keep")
    assert kept <= plain / 4, (plain, kept)
