"""The files a replay server's Save and Load rpcs may touch (ds/replay/files.py): only regular files
inside its snapshot folder, never a FIFO, device or socket, and never holding the workers the other
rpcs need. Real servers on loopback, real files, a real FIFO (``os.mkfifo``) and socket.

The test process works in the snapshot folder (``monkeypatch.chdir``), so that a server which took
relative names against its working directory, as servers before the snapshot folder did, would face
the same files."""

from __future__ import annotations

import contextlib
import os
import socket
import stat
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import pytest

from algorithm.replay import PrioritizedTable
from ds.replay.codec import chunk_to_proto
from ds.replay.service import serve_replay
from protos import replay_pb2, replay_pb2_grpc
from tests.algorithm.replay.chunks import VECTOR, make_chunk
from tests.small_disk import small_disk

pytestmark = pytest.mark.grpc

INVALID = grpc.StatusCode.INVALID_ARGUMENT


class SlowTable(PrioritizedTable):
    """A table whose ``load`` waits for ``release`` before it reads: a load from a slow disk."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.entered, self.release = threading.Event(), threading.Event()

    def load(self, path: str | Path, **kwargs: Any) -> None:
        self.entered.set()
        assert self.release.wait(60)
        super().load(path, **kwargs)


def table(cls: type[PrioritizedTable] = PrioritizedTable, chunks: int = 3) -> PrioritizedTable:
    tab = cls(100, (VECTOR,), 2, window=2, alpha=0.6, seed=0)
    for i in range(chunks):
        tab.insert(make_chunk(4, tab.info()["next_key"] + 10 * i))
    return tab


@dataclass
class Replay:
    table: PrioritizedTable
    stub: replay_pb2_grpc.ReplayServiceStub
    folder: Path  # the server's snapshot folder, <tmp>/run/replay
    outside: Path  # a folder beside the run: nothing may appear or change there

    def call(self, method: str, path: str, timeout: float = 10.0) -> tuple[grpc.StatusCode, str]:
        """One Save or Load of ``path``: its status code and details. A call the server does not answer
        ends DEADLINE_EXCEEDED at ``timeout``, so any other code says it was answered before then."""
        request = replay_pb2.SaveRequest(path=path) if method == "Save" else replay_pb2.LoadRequest(path=path)
        try:
            getattr(self.stub, method)(request, timeout=timeout)
        except grpc.RpcError as e:
            return e.code(), str(e.details())
        return grpc.StatusCode.OK, ""

    def info(self, timeout: float = 10.0) -> dict[str, int]:
        """The table's counters; raises DEADLINE_EXCEEDED when Info is not answered within ``timeout``
        (a server whose workers are all stuck never answers it)."""
        return dict(self.stub.Info(replay_pb2.InfoRequest(), timeout=timeout).counters)


def tree(root: Path, skip: Path) -> dict[str, Any]:
    """Every entry under ``root`` but ``skip``: symlinks by target, files by contents, folders by None."""
    found: dict[str, Any] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = Path(dirpath) / name
            if path == skip:
                continue
            if path.is_symlink():
                found[str(path)] = ("symlink", os.readlink(path))
            elif path.is_file():
                found[str(path)] = path.read_bytes()
            else:
                found[str(path)] = None
        dirnames[:] = [d for d in dirnames if Path(dirpath) / d != skip]
    return found


def release_fifo_readers(path: Path) -> None:
    """Open ``path`` for writing once, so that a server thread blocked opening it for reading (a
    server that opens FIFOs) gets EOF instead of waiting forever."""
    with contextlib.suppress(OSError):  # no reader waiting (ENXIO), or the FIFO was replaced
        os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))


def serve(tab: PrioritizedTable, folder: Path, **kwargs: Any) -> tuple[grpc.Server, replay_pb2_grpc.ReplayServiceStub]:
    server, port = serve_replay(tab, snapshot_dir=folder, **kwargs)
    return server, replay_pb2_grpc.ReplayServiceStub(grpc.insecure_channel(f"127.0.0.1:{port}"))


@pytest.fixture
def replay(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Replay]:
    folder, outside = tmp_path / "run" / "replay", tmp_path / "outside"
    folder.mkdir(parents=True)
    outside.mkdir()
    foreign = table(chunks=1)  # a valid snapshot that is not this table's
    for path in (outside / "x.npz", tmp_path / "run" / "x.npz"):
        foreign.save(path)
    (outside / "notes.txt").write_text("an unrelated file\n")
    monkeypatch.chdir(folder)
    tab = table()
    server, stub = serve(tab, folder)
    try:
        yield Replay(tab, stub, folder, outside)
    finally:
        for path in folder.iterdir():
            if stat.S_ISFIFO(path.lstat().st_mode):
                release_fifo_readers(path)
        server.stop(None)


# Names that lead out of the folder, each at a valid snapshot (Load would take it) or a file Save
# would replace: (name, how it is set up, what the refusal says).
OUTSIDE = {
    "absolute": ("{outside}/x.npz", None, "is absolute"),
    "dot dot": ("../x.npz", None, "holds '..'"),
    "dot dot within": ("sub/../../x.npz", None, "holds '..'"),
    "symlink out": ("link.npz", ("link.npz", "{outside}/x.npz"), "symlink"),
    "symlinked folder": ("out/x.npz", ("out", "{outside}"), "through a symlinked folder"),
}


@pytest.mark.parametrize("case", OUTSIDE)
def test_save_and_load_outside_the_folder_are_refused(replay: Replay, tmp_path: Path, case: str) -> None:
    name, link, message = OUTSIDE[case]
    name = name.format(outside=replay.outside)
    if link is not None:
        (replay.folder / link[0]).symlink_to(link[1].format(outside=replay.outside))
    before, counters = tree(tmp_path, skip=replay.folder), replay.info()
    for method in ("Save", "Load"):
        code, details = replay.call(method, name)
        assert code == INVALID, (method, code, details)
        assert details.startswith("path ") and message in details, details
        assert tree(tmp_path, skip=replay.folder) == before  # nothing created or replaced outside
        assert replay.info() == counters  # Load took nothing in
    assert sorted(p.name for p in replay.folder.iterdir()) == ([link[0]] if link else [])


def test_an_unrelated_existing_file_is_not_replaced(replay: Replay, tmp_path: Path) -> None:
    notes = replay.outside / "notes.txt"
    (replay.folder / "notes.txt").symlink_to(notes)
    (replay.folder / "inside.txt").write_text("a file of the folder\n")
    (replay.folder / "to_inside.npz").symlink_to("inside.txt")  # a symlink that stays inside
    before = tree(tmp_path, skip=Path("/nonexistent"))
    for name, message in [
        (str(notes), "is absolute"),
        (str(replay.outside / "new" / "a" / "b" / "replay.npz"), "is absolute"),  # no folders made outside
        ("notes.txt", "is a symlink: Save replaces only a regular file"),
        ("to_inside.npz", "is a symlink: Save replaces only a regular file"),  # replaced, not followed
    ]:
        code, details = replay.call("Save", name)
        assert (code, message in details) == (INVALID, True), details
    assert tree(tmp_path, skip=Path("/nonexistent")) == before
    assert notes.read_text() == "an unrelated file\n"
    assert not (replay.outside / "new").exists()


def test_an_empty_name_is_the_default_snapshot_and_relative_names_stay_inside(replay: Replay) -> None:
    assert replay.call("Save", "")[0] == grpc.StatusCode.OK
    assert replay.call("Save", "older/first.npz")[0] == grpc.StatusCode.OK  # a subfolder of the folder is made
    made = sorted(str(p.relative_to(replay.folder)) for p in replay.folder.rglob("*"))
    assert made == ["older", "older/first.npz", "replay.npz"]  # and no temp file left
    counters = replay.info()
    replay.table.insert(make_chunk(3, 500))
    assert replay.call("Load", "")[0] == grpc.StatusCode.OK
    assert replay.info() == counters
    (replay.folder / "link.npz").symlink_to("older/first.npz")  # Load follows a symlink that stays inside
    assert replay.call("Load", "link.npz")[0] == grpc.StatusCode.OK
    code, details = replay.call("Load", ".")
    assert code == INVALID and "names the snapshot folder itself" in details


def test_a_server_without_a_snapshot_folder_refuses_save_and_load(tmp_path: Path) -> None:
    server, port = serve_replay(table())
    stub = replay_pb2_grpc.ReplayServiceStub(grpc.insecure_channel(f"127.0.0.1:{port}"))
    try:
        for call, request in [(stub.Save, replay_pb2.SaveRequest(path=str(tmp_path / "x.npz"))),
                              (stub.Load, replay_pb2.LoadRequest(path=""))]:  # fmt: skip
            with pytest.raises(grpc.RpcError) as e:
                call(request, timeout=10)
            assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION
            assert "without a snapshot folder" in str(e.value.details())
    finally:
        server.stop(None)
    assert list(tmp_path.iterdir()) == []


def special_file(folder: Path, kind: str) -> tuple[str, Any]:
    """Make a FIFO or a listening Unix socket in ``folder``; its name and what keeps it alive."""
    if kind == "fifo":
        os.mkfifo(folder / "fifo.npz")
        return "fifo.npz", None
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.bind("socket.npz")  # relative: the test works in the folder (a Unix socket path is short)
    sock.listen()
    return "socket.npz", sock


@pytest.mark.parametrize(("kind", "message"), [("fifo", "is a FIFO"), ("socket", "is a socket")])
@pytest.mark.parametrize("method", ["Load", "Save"])
def test_special_files_are_refused_at_once(replay: Replay, method: str, kind: str, message: str) -> None:
    name, keep = special_file(replay.folder, kind)
    try:
        code, details = replay.call(method, name, timeout=3.0)  # a hang in open() ends DEADLINE_EXCEEDED
        assert code == INVALID and message in details, (code, details)
        kept = stat.S_IFIFO if kind == "fifo" else stat.S_IFSOCK
        assert stat.S_IFMT((replay.folder / name).lstat().st_mode) == kept
        assert sorted(p.name for p in replay.folder.iterdir()) == [name]  # not replaced, no temp file left
    finally:
        if keep is not None:
            keep.close()


def test_seventy_calls_on_a_fifo_leave_info_answering(replay: Replay) -> None:
    """The probe's attack: each Load of a FIFO used to hang a server thread in open() past its
    deadline until every worker was taken and Info timed out."""
    name, _ = special_file(replay.folder, "fifo")
    for method, request in [("Load", replay_pb2.LoadRequest(path=name)), ("Save", replay_pb2.SaveRequest(path=name))]:
        futures = [getattr(replay.stub, method).future(request, timeout=0.5) for _ in range(70)]
        codes = [f.exception().code() if f.exception() is not None else grpc.StatusCode.OK for f in futures]
        assert set(codes) == {INVALID}, (method, set(codes))
        replay.info()
    assert stat.S_ISFIFO((replay.folder / name).lstat().st_mode)


def test_a_save_racing_a_slow_load_does_not_block_info(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A Load stuck on a slow disk: Save and Load are refused at once (ABORTED) while it runs,
    Info and Insert are answered, the Load's call ends at its deadline (DEADLINE_EXCEEDED) and the
    load is abandoned, leaving the table as it was; then file work is accepted again."""
    folder = tmp_path / "replay"
    folder.mkdir()
    monkeypatch.chdir(folder)
    tab = table(SlowTable)
    tab.save(folder / "good.npz")  # 3 chunks; the table then gets a fourth, which a load would drop
    tab.insert(make_chunk(4, 900))
    server, stub = serve(tab, folder, max_workers=4)
    replay = Replay(tab, stub, folder, tmp_path / "outside")
    try:
        counters = replay.info()
        slow = stub.Load.future(replay_pb2.LoadRequest(path="good.npz"), timeout=1.5)
        assert tab.entered.wait(10)
        racing = [replay.call(m, n, timeout=2.0) for m, n in [("Save", ""), ("Load", "good.npz")] * 3]
        assert {code for code, _ in racing} == {grpc.StatusCode.ABORTED}, racing  # not queued behind the load
        assert all("Load of 'good.npz' is still running" in details for _, details in racing)
        replay.info()
        insert = replay_pb2.InsertRequest(chunks=[chunk_to_proto(make_chunk(2, 950))])
        assert len(stub.Insert(insert, timeout=1.0).keys) == 1
        counters = replay.info()
        with pytest.raises(grpc.RpcError) as late:
            slow.result()
        assert late.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
        replay.info()
    finally:
        tab.release.set()
    deadline = time.monotonic() + 10
    while (saved := replay.call("Save", "after.npz"))[0] == grpc.StatusCode.ABORTED:  # the abandoned load ends
        assert time.monotonic() < deadline, saved
        time.sleep(0.05)
    try:
        assert saved[0] == grpc.StatusCode.OK, saved
        assert replay.info() == counters  # the abandoned load installed nothing
        assert not list(folder.glob(".*.tmp"))
    finally:
        server.stop(None)


def test_a_save_to_a_full_disk_is_resource_exhausted_and_keeps_the_snapshot(tmp_path: Path) -> None:
    """gRPC's code for a file system out of space is RESOURCE_EXHAUSTED (it was FAILED_PRECONDITION,
    as for a server without a snapshot folder); the snapshot saved before stays as it was."""
    with small_disk(tmp_path / "disk", "4m") as disk:
        server, port = serve_replay(table(), snapshot_dir=disk.path)
        stub = replay_pb2_grpc.ReplayServiceStub(grpc.insecure_channel(f"127.0.0.1:{port}"))
        try:
            stub.Save(replay_pb2.SaveRequest(path="replay.npz"), timeout=10)
            before = (disk.path / "replay.npz").read_bytes()
            disk.fill()
            with pytest.raises(grpc.RpcError) as e:
                stub.Save(replay_pb2.SaveRequest(path="replay.npz"), timeout=10)
            assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED, e.value.details()
            assert "No space left" in str(e.value.details())
            assert (disk.path / "replay.npz").read_bytes() == before
            disk.free()
            stub.Save(replay_pb2.SaveRequest(path="replay.npz"), timeout=10)  # space is back: saved
        finally:
            server.stop(None)
