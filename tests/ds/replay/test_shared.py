"""Sampled batches through a file in /dev/shm (ds/replay/shared.py): the same batches as the table
draws, the late-writer fence, the files' rules, and the way back to gRPC where the replay cannot
open the file (its own /dev/shm, as in a container: a real mount namespace)."""

from __future__ import annotations

import functools
import logging
import os
import subprocess
import sys
import textwrap
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from algorithm.replay import PrioritizedTable
from ds.replay import client as client_module
from ds.replay import service as service_module
from ds.replay.client import ReplayClient
from ds.replay.service import serve_replay
from ds.replay.shared import SHARED_DIR, SharedSlot, sweep, write_shared
from tests.ds.replay.test_service import LIMIT, RNN, SENSORS, assert_same_batch, build, chunk

pytestmark = pytest.mark.grpc

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture
def twins(tmp_path: Path) -> Iterator[tuple[ReplayClient, PrioritizedTable]]:
    """A client of a served table and the table's in-process twin (same seed, same chunks)."""
    table, twin = build(), build()
    server, port = serve_replay(table, max_message_bytes=LIMIT, snapshot_dir=tmp_path)
    client = ReplayClient(f"127.0.0.1:{port}", SENSORS, 2, RNN, max_message_bytes=LIMIT)
    try:
        for t in (5, 9, 3, 7):
            first = twin.info()["next_key"]
            client.insert(chunk(t, first))
            twin.insert(chunk(t, first))
        yield client, twin
    finally:
        client.close()
        server.stop(None)


def files() -> set[str]:
    return {p.name for p in SHARED_DIR.glob("asac-batches-*")}


def test_batches_come_through_the_file_and_are_the_tables_own(
    twins: tuple[ReplayClient, PrioritizedTable], monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    client, twin = twins
    written: list[int] = []
    real = service_module.write_shared

    def counted(*args: object, **kwargs: object) -> bool:
        done = real(*args, **kwargs)  # type: ignore[arg-type]
        written.append(done)
        return done

    monkeypatch.setattr(service_module, "write_shared", counted)
    caplog.set_level(logging.INFO, "asac.replay")
    before = files()
    assert_same_batch(client.sample(16, timeout=1.0), twin.sample(16))
    assert written == []  # the first reply tells the client the table's window: it comes over gRPC
    for count in (1, 3, 5):
        got = client.sample_many(16, count, timeout=1.0)
        assert len(got) == count  # no rate limiter: all of them at once
        for batch in got:
            assert_same_batch(batch, twin.sample(16))
    assert written == [True, True, True]
    made = files() - before
    assert len(made) == 1 and any(m in r.getMessage() for m in made for r in caplog.records)
    assert (SHARED_DIR / made.pop()).stat().st_mode & 0o777 == 0o600
    client.close()
    assert files() <= before  # removed with its client


def test_a_replay_that_cannot_open_the_file_sends_the_batches(
    twins: tuple[ReplayClient, PrioritizedTable], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:  # fmt: skip
    client, twin = twins
    elsewhere = tmp_path / "shm"  # the client's file where the server does not look: another host's
    elsewhere.mkdir()
    monkeypatch.setattr(client_module, "SharedSlot", functools.partial(SharedSlot, folder=elsewhere))
    caplog.set_level(logging.INFO, "asac.replay")
    for _ in range(4):
        for batch in client.sample_many(16, 2, timeout=1.0):
            assert_same_batch(batch, twin.sample(16))
    said = [r.getMessage() for r in caplog.records if "does not write into" in r.getMessage()]
    assert len(said) == 1 and "batches come over gRPC" in said[0]  # said once, then not tried again
    assert list(elsewhere.iterdir()) == []  # the file given up is removed


def test_no_shared_memory_when_turned_off(
    twins: tuple[ReplayClient, PrioritizedTable], monkeypatch: pytest.MonkeyPatch
) -> None:
    client, _ = twins
    address = client.address
    off = ReplayClient(address, SENSORS, 2, RNN, max_message_bytes=LIMIT, shared_memory=False)
    monkeypatch.setattr(client_module, "SharedSlot", None)  # would fail if called
    try:
        for _ in range(3):
            off.sample_many(16, 2, timeout=1.0)
    finally:
        off.close()


def test_a_late_attempt_writes_nothing(tmp_path: Path) -> None:
    slot = SharedSlot(64, folder=tmp_path)
    try:
        late, current = slot.fence(), slot.fence()  # a retried or timed-out attempt, then the next one
        fill = functools.partial(np.copyto, src=np.full(64, 7, np.uint8))
        assert not write_shared(slot.name, slot.size, late, 64, fill, folder=tmp_path)
        assert bytes(slot.payload(64)) == bytes(64)
        assert write_shared(slot.name, slot.size, current, 64, fill, folder=tmp_path)
        assert bytes(slot.payload(64)) == bytes([7] * 64)
    finally:
        slot.close()
    assert not slot.path.exists()


def test_a_fence_waits_for_a_writer_holding_the_file(tmp_path: Path) -> None:
    slot = SharedSlot(8, folder=tmp_path)
    writing, release, order = threading.Event(), threading.Event(), []

    def fill(out: np.ndarray) -> None:
        writing.set()
        release.wait(5.0)
        out[:] = 1
        order.append("written")

    seq = slot.fence()
    writer = threading.Thread(target=write_shared, args=(slot.name, slot.size, seq, 8, fill, tmp_path))
    writer.start()
    assert writing.wait(5.0)
    threading.Timer(0.3, release.set).start()
    slot.fence()
    order.append("fenced")
    writer.join(5.0)
    assert order == ["written", "fenced"]
    slot.close()


@pytest.mark.parametrize("case", ["name", "size", "too much", "magic", "symlink", "missing"])
def test_the_server_writes_only_into_a_slot_it_can_check(tmp_path: Path, case: str) -> None:
    slot = SharedSlot(32, folder=tmp_path)
    seq = slot.fence()
    name, size, nbytes = slot.name, slot.size, 32
    if case == "name":
        os.link(slot.path, tmp_path / "other")
        name = "other"
    elif case == "size":
        size += 8
    elif case == "too much":
        nbytes = 40
    elif case == "magic":
        with open(slot.path, "r+b") as f:
            f.write(b"NOTASLOT")
    elif case == "symlink":
        target = SharedSlot(32, folder=tmp_path)
        name = target.name.replace(target.name[-16:], "0" * 16)
        (tmp_path / name).symlink_to(slot.path)
    elif case == "missing":
        name = slot.name[:-16] + "f" * 16
    touched: list[bool] = []
    assert not write_shared(name, size, seq, nbytes, lambda out: touched.append(True), folder=tmp_path)
    assert touched == []
    slot.close()


def test_files_of_processes_that_are_gone_are_swept(tmp_path: Path) -> None:
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead = tmp_path / f"asac-batches-{int(gone.stdout)}-{'a' * 16}"
    mine = tmp_path / f"asac-batches-{os.getpid()}-{'b' * 16}"
    other = tmp_path / "asac-batches-notes"
    for path in (dead, mine, other):
        path.write_bytes(b"x")
    assert sweep(tmp_path) == 1
    assert not dead.exists() and mine.exists() and other.exists()


@pytest.fixture
def small_tmpfs(tmp_path: Path) -> Iterator[Path]:
    """A 64 KiB tmpfs: a /dev/shm too full for a learner's file."""
    small = tmp_path / "small"
    small.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "none", str(small)], capture_output=True)
    if mounted.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        yield small
    finally:
        subprocess.run(["umount", str(small)], check=True)


def test_a_full_shared_memory_is_an_error_when_made_not_later(small_tmpfs: Path) -> None:
    with pytest.raises(OSError):
        SharedSlot(1 << 20, folder=small_tmpfs)
    assert list(small_tmpfs.iterdir()) == []


def test_a_client_without_room_in_shared_memory_samples_over_grpc(
    twins: tuple[ReplayClient, PrioritizedTable], small_tmpfs: Path, monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:  # fmt: skip
    client, twin = twins
    monkeypatch.setattr(client_module, "SharedSlot", functools.partial(SharedSlot, folder=small_tmpfs))
    caplog.set_level(logging.INFO, "asac.replay")
    count = 64 * 1024 // client.specs.layout(16, twin.window).batch_bytes + 1  # their file: over 64 KiB
    for _ in range(3):
        for batch in client.sample_many(16, count, timeout=1.0):
            assert_same_batch(batch, twin.sample(16))
    said = [r.getMessage() for r in caplog.records if "no file for batches" in r.getMessage()]
    assert len(said) == 1 and "batches come over gRPC" in said[0], said
    assert list(small_tmpfs.iterdir()) == []


SERVE = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {root!r})
    from ds.replay.service import serve_replay
    from tests.ds.replay.test_service import LIMIT, build
    server, port = serve_replay(build(), max_message_bytes=LIMIT)
    print(port, flush=True)
    time.sleep(120)
""")


def test_a_replay_with_its_own_dev_shm_serves_over_grpc(caplog: pytest.LogCaptureFixture) -> None:
    """The replay in a mount namespace with a /dev/shm of its own (what a container has): the
    client's file is out of its reach, so the batches come in the replies."""
    own_shm = ["unshare", "-m", "sh", "-c", 'mount -t tmpfs none /dev/shm && exec "$0" "$@"']
    probe = subprocess.run([*own_shm, "true"], capture_output=True, text=True)
    if probe.returncode:
        pytest.skip(f"no mount namespace here: {probe.stderr.strip()}")
    server = subprocess.Popen([*own_shm, sys.executable, "-c", SERVE.format(root=str(ROOT))], stdout=subprocess.PIPE,
                              text=True)  # fmt: skip
    try:
        assert server.stdout is not None
        port = int(server.stdout.readline())
        caplog.set_level(logging.INFO, "asac.replay")
        client = ReplayClient(f"127.0.0.1:{port}", SENSORS, 2, RNN, max_message_bytes=LIMIT)
        twin = build()
        for t in (5, 9, 3):
            first = twin.info()["next_key"]
            client.insert(chunk(t, first))
            twin.insert(chunk(t, first))
        before = files()
        for _ in range(3):
            for batch in client.sample_many(16, 2, timeout=5.0):
                assert_same_batch(batch, twin.sample(16))
        assert sum("does not write into" in r.getMessage() for r in caplog.records) == 1
        assert files() <= before
        client.close()
    finally:
        server.kill()
        server.wait(10)
