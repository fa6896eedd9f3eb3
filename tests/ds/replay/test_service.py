"""The replay server against hostile and concurrent peers: malformed payloads, oversize messages,
timeouts, an unreachable server, many clients at once, and the health service."""

from __future__ import annotations

import dataclasses
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

from algorithm.replay import InsertTimeout, PrioritizedTable, RateLimiter, ReplayUnavailable, SampleTimeout
from algorithm.types import Batch
from ds.net.rpc import RetryPolicy, set_serving
from ds.net.wire import WireError, to_tensor
from ds.replay.client import ReplayClient, ReplayRequestRejected, ReplayRpcError
from ds.replay.codec import chunk_to_proto, message_limit_bytes
from ds.replay.service import SERVICE_NAME, serve_replay
from protos import replay_pb2, replay_pb2_grpc
from tests.algorithm.replay.chunks import IMAGE, VECTOR, make_chunk
from tests.ds.conftest import ServeOverGrpc

pytestmark = pytest.mark.grpc

SENSORS = (VECTOR, IMAGE)
RNN = 2
LIMIT = 1 << 20  # 1 MiB: small enough that a test can exceed it cheaply


def build(seed: int = 0) -> PrioritizedTable:
    return PrioritizedTable(200, SENSORS, 2, window=3, alpha=0.6, rnn_state_size=RNN, seed=seed)


def chunk(t: int, first_key: int) -> Any:
    return make_chunk(t, first_key, SENSORS, rnn_state_size=RNN)


@dataclass
class Served:
    """A served table, its in-process twin (same seed, same valid operations), and two ways in."""

    table: PrioritizedTable
    twin: PrioritizedTable
    client: ReplayClient
    stub: replay_pb2_grpc.ReplayServiceStub

    def insert(self, t: int) -> np.ndarray:
        first = self.twin.info()["next_key"]
        keys = self.client.insert(chunk(t, first))
        np.testing.assert_array_equal(keys, self.twin.insert(chunk(t, first)))
        return keys


@pytest.fixture
def served(tmp_path: Path) -> Iterator[Served]:
    table = build()
    server, port = serve_replay(table, max_message_bytes=LIMIT, snapshot_dir=tmp_path)
    address = f"127.0.0.1:{port}"
    # A raw channel that may send more than the server accepts, to test the server's own limit.
    channel = grpc.insecure_channel(address, options=[("grpc.max_send_message_length", 64 << 20)])
    client = ReplayClient(address, SENSORS, 2, RNN, max_message_bytes=LIMIT)
    try:
        s = Served(table, build(), client, replay_pb2_grpc.ReplayServiceStub(channel))
        for t in (5, 9, 3):
            s.insert(t)
        yield s
    finally:
        client.close()
        channel.close()
        server.stop(None)


def assert_same_batch(a: Batch, b: Batch) -> None:
    for field in dataclasses.fields(Batch):
        x, y = getattr(a, field.name), getattr(b, field.name)
        for u, v in zip(x, y, strict=True) if field.name == "obs" else [(x, y)]:
            np.testing.assert_array_equal(u, v)
            assert np.asarray(u).dtype == np.asarray(v).dtype


COUNTS = ("size", "next_key", "inserted_steps", "inserted_chunks", "sampled_windows", "priority_updates")


def assert_unchanged(s: Served) -> None:
    """The served table still holds exactly what its twin holds: same counts, same next batch."""
    info, twin = s.client.info(), s.twin.info()
    assert {k: info[k] for k in COUNTS} == {k: twin[k] for k in COUNTS}
    assert info["total_priority"] == twin["total_priority"]
    assert_same_batch(s.client.sample(16, timeout=1.0), s.twin.sample(16))


def valid_insert(s: Served, t: int = 4) -> replay_pb2.InsertRequest:
    return replay_pb2.InsertRequest(chunks=[chunk_to_proto(chunk(t, s.twin.info()["next_key"]))])


# Each case corrupts a valid one-chunk InsertRequest of T = 4 steps; the message names the field.
BAD_INSERTS: dict[str, tuple[Callable[[replay_pb2.InsertRequest], None], str]] = {
    "wrong dtype": (
        lambda r: r.chunks[0].obs[1].CopyFrom(to_tensor(np.zeros((5, 4, 4, 3), np.float32))),
        "chunks[0].obs[1] (pixels) is float32 of shape [5, 4, 4, 3], expected uint8 of shape [T+1, 4, 4, 3] with T = 4",
    ),
    "wrong shape": (
        lambda r: r.chunks[0].actions.CopyFrom(to_tensor(np.zeros((4, 3), np.float32))),
        "chunks[0].actions is float32 of shape [4, 3], expected float32 of shape [T, 2] with T = 4",
    ),
    "obs rows != T + 1": (
        lambda r: r.chunks[0].obs[0].CopyFrom(to_tensor(np.zeros((4, 3), np.float32))),
        "chunks[0].obs[0] (state) is float32 of shape [4, 3], expected float32 of shape [T+1, 3] with T = 4",
    ),
    "NaN observation": (
        lambda r: r.chunks[0].obs[0].CopyFrom(to_tensor(np.full((5, 3), np.nan, np.float32))),
        "chunks[0].obs[0] (state) has non-finite values",
    ),
    "inf action": (
        lambda r: r.chunks[0].prev_actions.CopyFrom(to_tensor(np.full((4, 2), np.inf, np.float32))),
        "chunks[0].prev_actions has non-finite values",
    ),
    "length mismatch": (
        lambda r: setattr(r.chunks[0].rewards, "data", b"\x00" * 15),
        "chunks[0].rewards has 15 bytes of data, but float32 of shape [4] needs 16",
    ),
    "garbage bytes for a bool": (
        lambda r: setattr(r.chunks[0].terminated, "data", b"\x00\x03\x00\xff"),
        "chunks[0].terminated is bool but holds bytes other than 0 and 1",
    ),
    "unknown dtype": (
        lambda r: setattr(r.chunks[0].behaviour_logp, "dtype", "object"),
        "chunks[0].behaviour_logp has unsupported dtype 'object'",
    ),
    "missing field": (
        lambda r: r.chunks[0].ClearField("truncated"),
        "chunks[0].truncated is missing",
    ),
    "missing rnn state": (
        lambda r: r.chunks[0].ClearField("rnn_state"),
        "chunks[0].rnn_state is missing",
    ),
    "negative priority": (
        lambda r: r.chunks[0].priorities.CopyFrom(to_tensor(np.array([1.0, -0.5, 1.0, 1.0]))),
        "chunks[0].priorities must be >= 0",
    ),
    "NaN priority": (
        lambda r: r.chunks[0].priorities.CopyFrom(to_tensor(np.array([1.0, np.nan, 1.0, 1.0]))),
        "chunks[0].priorities has non-finite values",
    ),
    "flag before the last step": (
        lambda r: r.chunks[0].terminated.CopyFrom(to_tensor(np.array([True, False, False, False]))),
        "only the last step of a chunk may be terminated or truncated",
    ),
    "bad second chunk": (  # all or nothing: the valid first chunk is not stored either
        lambda r: r.chunks.append(
            replay_pb2.Chunk(
                obs=r.chunks[0].obs,
                actions=r.chunks[0].actions,
                prev_actions=r.chunks[0].prev_actions,
                rewards=to_tensor(np.zeros(4, np.float64)),
                terminated=r.chunks[0].terminated,
                truncated=r.chunks[0].truncated,
                behaviour_logp=r.chunks[0].behaviour_logp,
                rnn_state=r.chunks[0].rnn_state,
            )
        ),
        "chunks[1].rewards is float64 of shape [4], expected float32 of shape [T]",
    ),
    "negative timeout": (
        lambda r: setattr(r, "timeout_s", -1.0),
        "timeout_s must be >= 0, got -1.0",
    ),
    "sequence without producer": (
        lambda r: r.sequence.append(3),
        "InsertRequest: sequence and acked_below need a producer, but producer is 0",
    ),
    "producer without sequence": (
        lambda r: setattr(r, "producer", 77),
        "insert ids: 0 sequence numbers for 1 chunks",
    ),
    "repeated sequence number": (
        lambda r: (r.chunks.append(r.chunks[0]), setattr(r, "producer", 77), r.sequence.extend([5, 5])),
        "insert ids: sequence numbers repeat within one request: [5, 5]",
    ),
}


@pytest.mark.parametrize("case", list(BAD_INSERTS))
def test_malformed_insert_is_invalid_argument_and_changes_nothing(served: Served, case: str) -> None:
    corrupt, message = BAD_INSERTS[case]
    request = valid_insert(served)
    corrupt(request)
    with pytest.raises(grpc.RpcError) as e:
        served.stub.Insert(request, timeout=10)
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert message in e.value.details()
    assert_unchanged(served)
    served.insert(4)  # and still serves
    assert_unchanged(served)


@pytest.mark.parametrize(
    ("keys", "priorities", "message"),
    [
        (np.array([0, 1], np.uint64), np.array([1.0, -1.0]), "priorities must be >= 0"),
        (np.array([0, 1], np.uint64), np.array([np.nan, 1.0]), "priorities has non-finite values"),
        (
            np.array([0, 1], np.uint64),
            np.array([1.0]),
            "priorities is float64 of shape [1], expected float64 of shape [N] with N = 2",
        ),  # fmt: skip
        (np.array([0, 1], np.int64), np.array([1.0, 1.0]), "keys is int64 of shape [2], expected uint64 of shape [N]"),
        (np.array([0, 1], np.uint64), np.array([1.0, 1.0], np.float32), "priorities is float32"),
    ],
)
def test_malformed_priority_update_is_invalid_argument_and_changes_nothing(
    served: Served, keys: np.ndarray, priorities: np.ndarray, message: str
) -> None:
    request = replay_pb2.UpdatePrioritiesRequest(keys=to_tensor(keys), priorities=to_tensor(priorities))
    with pytest.raises(grpc.RpcError) as e:
        served.stub.UpdatePriorities(request, timeout=10)
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert message in e.value.details()
    assert_unchanged(served)


def test_client_raises_the_servers_message_as_a_value_error(served: Served, tmp_path: Path) -> None:
    bad = dataclasses.replace(chunk(4, 0), actions=np.zeros((4, 2), np.float64))
    with pytest.raises(ReplayRequestRejected, match=r"chunks\[0\]\.actions is float64") as e:
        served.client.insert(bad)
    assert isinstance(e.value, ValueError) and e.value.code == grpc.StatusCode.INVALID_ARGUMENT
    with pytest.raises(ReplayRequestRejected, match="batch_size must be >= 1"):
        served.client.sample(0)
    with pytest.raises(ReplayRequestRejected, match="path '/.*' is absolute"):  # tmp_path is its snapshot folder
        served.client.save(tmp_path / "replay.npz")
    (tmp_path / "a file").write_text("")
    with pytest.raises(ReplayRpcError, match="(FileExists|NotADirectory)Error") as failed:
        served.client.save("a file/replay.npz")  # a folder that cannot be made
    assert failed.value.code == grpc.StatusCode.FAILED_PRECONDITION
    with pytest.raises(ReplayRequestRejected, match="not a readable replay file"):
        served.client.load("missing.npz")
    assert_unchanged(served)


def test_oversize_messages_are_resource_exhausted_and_the_server_goes_on(served: Served) -> None:
    # A message over the server's limit is refused by gRPC before it is even parsed.
    request = valid_insert(served)
    request.chunks[0].rewards.data = b"\x00" * (LIMIT + 1)
    with pytest.raises(grpc.RpcError) as e:
        served.stub.Insert(request, timeout=10)
    assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert_unchanged(served)

    # The client refuses to send one, naming its size and the limit.
    message = r"InsertRequest of 1 chunks of 12000 steps is \d+ bytes, over the replay message limit of 1048576 bytes"
    with pytest.raises(WireError, match=message):
        served.client.insert(chunk(12000, served.twin.info()["next_key"]))

    # A batch whose reply would exceed the limit is refused before anything is drawn.
    with pytest.raises(ReplayRpcError, match=r"a batch of 20000 windows .* over this replay server's message limit"):
        served.client.sample(20000)
    assert_unchanged(served)


def test_message_limit_follows_the_batch_size() -> None:
    pixels = dataclasses.replace(IMAGE, shape=(84, 84, 3))
    small = message_limit_bytes((VECTOR,), 2, batch_size=256, window=2)
    assert small == 4 * 1024 * 1024  # never below gRPC's default
    batch = 256 * 3 * 84 * 84 * 3  # uint8 observations dominate: [B, L + 1, 84, 84, 3]
    limit = message_limit_bytes((VECTOR, pixels), 6, batch_size=256, window=2, rnn_state_size=32)
    assert 2 * batch + (1 << 20) < limit < 2 * batch * 1.01 + (1 << 20)
    chunk_limit = message_limit_bytes((VECTOR, pixels), 6, batch_size=1, window=2, max_chunk_steps=1000)
    assert chunk_limit > 2 * 1001 * 84 * 84 * 3
    with pytest.raises(ValueError, match="over protobuf's 2 GiB"):
        message_limit_bytes((pixels,), 6, batch_size=100_000, window=3)


def test_a_real_image_batch_fits_the_limit_made_for_it(over_grpc: ServeOverGrpc) -> None:
    pixels = dataclasses.replace(IMAGE, shape=(84, 84, 3))
    table = PrioritizedTable(600, (VECTOR, pixels), 2, window=3, seed=0)
    limit = message_limit_bytes((VECTOR, pixels), 2, batch_size=64, window=3, max_chunk_steps=500)
    assert limit > 4 * 1024 * 1024  # the default would not carry these messages
    client = over_grpc(table, max_message_bytes=limit)
    client.insert(make_chunk(500, 0, (VECTOR, pixels)))
    batch = client.sample(64)
    assert batch.obs[1].dtype == np.uint8 and batch.obs[1].shape == (64, 4, 84, 84, 3)


def test_timeouts_are_deadline_exceeded_and_the_tables_exceptions(over_grpc: ServeOverGrpc) -> None:
    limiter = RateLimiter(samples_per_insert=1.0, min_size_to_sample=10, tolerance=0.0)
    client = over_grpc(PrioritizedTable(100, (VECTOR,), 2, 1, rate_limiter=limiter))
    client.insert(make_chunk(3, 0))
    start = time.monotonic()
    with pytest.raises(SampleTimeout, match="3 steps stored < min_size_to_sample 10"):
        client.sample(4, timeout=0.2)
    assert 0.2 <= time.monotonic() - start < 5.0
    client.insert(make_chunk(9, 4))  # 12 steps: surplus 2 windows, so inserts are held back
    with pytest.raises(InsertTimeout, match="the learner is behind"):
        client.insert(make_chunk(2, 14), timeout=0.1)
    assert client.info()["size"] == 12
    raw = replay_pb2_grpc.ReplayServiceStub(client.channel)
    with pytest.raises(grpc.RpcError) as e:
        raw.Insert(replay_pb2.InsertRequest(chunks=[chunk_to_proto(make_chunk(2, 14))], timeout_s=0.0), timeout=5)
    assert e.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED and "rate limiter" in e.value.details()


def test_a_waiting_sample_returns_once_actors_catch_up(over_grpc: ServeOverGrpc) -> None:
    table = PrioritizedTable(100, (VECTOR,), 2, 1, rate_limiter=RateLimiter(1.0, 5, enforce_ratio=False))
    learner = over_grpc(table)
    learner.poll_s = 0.1  # timeout=None is a series of short calls: exercise more than one
    got: list[Batch] = []
    waiter = threading.Thread(target=lambda: got.append(learner.sample(8)))
    waiter.start()
    time.sleep(0.4)
    assert not got
    table.insert(make_chunk(6, 0))
    waiter.join(10)
    assert got and got[0].batch_size == 8


@pytest.mark.parametrize("timeout_s", [None, math.inf, 1e300], ids=["absent", "inf", "1e300"])
def test_a_call_without_deadline_or_timeout_waits_until_it_can_be_served(
    over_grpc: ServeOverGrpc, timeout_s: float | None
) -> None:
    """An infinite (or longer than a lock can wait) timeout_s waits like an absent one."""
    table = PrioritizedTable(100, (VECTOR,), 2, 1, rate_limiter=RateLimiter(1.0, 5, enforce_ratio=False))
    client = over_grpc(table)  # kept: its server stops when it is collected
    raw = replay_pb2_grpc.ReplayServiceStub(client.channel)
    request = replay_pb2.SampleRequest(batch_size=3)
    if timeout_s is not None:
        request.timeout_s = timeout_s
    waiting = raw.Sample.future(request)
    time.sleep(0.3)
    assert not waiting.done()
    table.insert(make_chunk(6, 0))
    reply = waiting.result(timeout=10)
    assert (reply.batch_size, len(reply.table_size)) == (3, 1)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_unavailable_is_retried_with_backoff_then_surfaces() -> None:
    port = free_port()
    retry = RetryPolicy(attempts=4, initial_backoff_s=0.05, max_backoff_s=0.1)
    client = ReplayClient(f"127.0.0.1:{port}", (VECTOR,), 2, retry=retry)
    start = time.monotonic()
    with pytest.raises(ReplayRpcError, match="unavailable after 4 attempts") as e:
        client.info()
    assert e.value.code == grpc.StatusCode.UNAVAILABLE
    assert isinstance(e.value, ReplayUnavailable)  # the table protocol's error: callers need not know gRPC
    assert time.monotonic() - start >= 0.5 * (0.05 + 0.1 + 0.1)  # three jittered sleeps

    # A server that comes up while the client backs off is reached.
    client.retry = RetryPolicy(attempts=30, initial_backoff_s=0.05, max_backoff_s=0.2)
    table = PrioritizedTable(20, (VECTOR,), 2, 1)
    result: list[dict[str, Any]] = []
    caller = threading.Thread(target=lambda: result.append(client.info()))
    caller.start()
    time.sleep(0.3)
    server, _ = serve_replay(table, f"127.0.0.1:{port}")
    try:
        caller.join(20)
        assert result and result[0]["capacity"] == 20
    finally:
        client.close()
        server.stop(None)


def test_concurrent_clients_do_not_corrupt_the_table() -> None:
    """4 actor threads insert through their own clients while a learner samples and updates
    priorities; every sampled window must be a stretch of the one chunk its key was issued for."""
    table = PrioritizedTable(500, (VECTOR,), 2, window=4, alpha=0.8, seed=0)
    server, port = serve_replay(table, max_workers=8)
    address = f"127.0.0.1:{port}"
    issued: dict[int, tuple[float, int]] = {}  # key -> (value its chunk wrote at that step, chunk end key)
    issued_lock = threading.Lock()
    batches: list[Batch] = []
    errors: list[BaseException] = []
    stop = time.monotonic() + 2.0

    def actor(i: int) -> None:
        rng = np.random.default_rng(i)
        base = (i + 1) * 1_000_000  # each actor's chunks write values no other actor writes
        with ReplayClient(address, (VECTOR,), 2) as client:
            while time.monotonic() < stop:
                t = int(rng.integers(1, 30))
                keys = client.insert(make_chunk(t, base))  # values base, base + 1, ... at its steps
                with issued_lock:
                    issued.update((int(k), (float(base + j), int(keys[-1]) + 1)) for j, k in enumerate(keys))
                base += t + 1

    def learner() -> None:
        rng = np.random.default_rng(9)
        with ReplayClient(address, (VECTOR,), 2) as client:
            while time.monotonic() < stop:
                try:
                    batch = client.sample(64, timeout=0.05)
                except SampleTimeout:
                    continue
                batches.append(batch)
                client.update_priorities(batch.keys, rng.uniform(0.0, 2.0, 64))
                client.info()

    def guarded(work: Callable[[], None]) -> Callable[[], None]:
        def run() -> None:
            try:
                work()
            except BaseException as e:  # reported by the test
                errors.append(e)

        return run

    threads = [threading.Thread(target=guarded(lambda i=i: actor(i))) for i in range(4)]
    threads.append(threading.Thread(target=guarded(learner)))
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join(30)
        assert not any(t.is_alive() for t in threads), "a client hung"
        assert not errors, errors
        info = table.info()
        assert len(batches) > 5 and info["inserted_chunks"] > 20
        assert info["sampled_windows"] == 64 * len(batches)
        assert info["inserted_steps"] == len(issued)
        for batch in batches:
            for b, key in enumerate(batch.keys.tolist()):
                value, end = issued[key]
                pos = key + np.arange(batch.window + 1)
                # one chunk only: consecutive values from the key's own step, clamped at its end
                np.testing.assert_array_equal(batch.obs[0][b, :, 0], value + np.minimum(pos, end) - key)
                np.testing.assert_array_equal(batch.mask[b], pos[:-1] < end)
                np.testing.assert_array_equal(
                    batch.rewards[b], np.where(pos[:-1] < end, value + pos[:-1] - key + 0.5, 0)
                )
        leaves = np.asarray(table._tree.leaves)
        assert math.isclose(info["total_priority"], math.fsum(leaves), rel_tol=1e-12)
        steps = (table._ring.row_key >= 0) & (table._ring.row_key != table._ring.end_key)
        assert info["size"] == int(steps.sum()) and (leaves[~steps] == 0).all()
    finally:
        server.stop(None)


def test_health_is_not_serving_until_ready_then_serving() -> None:
    checker = health.HealthServicer()
    server, port = serve_replay(PrioritizedTable(20, (VECTOR,), 2, 1), health_servicer=checker, ready=False)
    channel = grpc.insecure_channel(f"127.0.0.1:{port}")
    try:
        stub = health_pb2_grpc.HealthStub(channel)
        serving = health_pb2.HealthCheckResponse.SERVING
        not_serving = health_pb2.HealthCheckResponse.NOT_SERVING
        for name in ("", "asac.ReplayService"):
            assert stub.Check(health_pb2.HealthCheckRequest(service=name), timeout=5).status == not_serving
        set_serving(checker, SERVICE_NAME, True)
        for name in ("", "asac.ReplayService"):
            assert stub.Check(health_pb2.HealthCheckRequest(service=name), timeout=5).status == serving
    finally:
        channel.close()
        server.stop(None)


def test_health_is_serving_once_serve_replay_returns(served: Served) -> None:
    stub = health_pb2_grpc.HealthStub(served.client.channel)
    reply = stub.Check(health_pb2.HealthCheckRequest(service="asac.ReplayService"), timeout=5)
    assert reply.status == health_pb2.HealthCheckResponse.SERVING
