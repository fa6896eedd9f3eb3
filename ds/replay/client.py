"""The replay table over gRPC, the client's side: :class:`ReplayClient` is a table (the interface of
:mod:`algorithm.replay.base`, with the same types and exceptions), so the replay contract tests run
unchanged against it (tests/ds/replay/test_client_contract.py). ds/replay/service.py is the server's side;
its docstring lists how every error maps to a gRPC status and back to the exception raised here.

    replay = ReplayClient("replay:50051", sensors, action_size, rnn_state_size, max_message_bytes=limit,
                          credentials=creds)   # creds: ds.net.security.load_credentials (token, TLS)
    keys = replay.insert(chunk)                      # actor
    pending = replay.insert_async(chunks, timeout=2.0, ids=ChunkIds(producer, seqs, acked_below))
    pending.result()                                 # actor's sink: keys and duplicate flags, or raises
    batch = replay.sample(256, timeout=1.0)          # learner: a Batch with the same dtypes as in-process
    replay.update_priorities(batch.keys, td_abs)     # learner
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TypeVar

import grpc
import numpy as np

from algorithm.replay import (
    ChunkIds,
    Inserted,
    InsertTimeout,
    NormalizerStats,
    ReplayInfo,
    ReplayUnavailable,
    SampleTimeout,
)
from algorithm.spaces import SensorSpec
from algorithm.types import Batch, Chunk
from ds.net import security
from ds.net.client import RpcClient
from ds.net.rpc import GRPC_DEFAULT_MESSAGE_BYTES, RetryPolicy, peer_gone
from ds.net.security import NO_CREDENTIALS, Credentials
from ds.net.wire import TensorSpec, WireError, from_tensor, to_tensor
from ds.replay.codec import (
    ReplaySpecs,
    batches_per_reply,
    chunk_to_proto,
    split_sample_reply,
)
from ds.replay.packed import Allocate
from ds.replay.shared import SHARED_DIR, SharedSlot
from protos import replay_pb2, replay_pb2_grpc

__all__ = [
    "LAST_INSERTS_WAIT_S",
    "PendingInsert",
    "ReplayClient",
    "ReplayRequestRejected",
    "ReplayRpcError",
    "ReplayUnreachable",
]

# How long an actor's last inserts at the end of a run may wait in the replay's rate limiter, all together. A
# stopping learner trains on until its actors have left, allowing them this long (ds/learner/learner.py), so
# the inserts are let in within a few of its updates; 10 s leaves room for a learner ~1,500 windows behind on
# a loaded 2-core machine.
LAST_INSERTS_WAIT_S = 10.0

_T = TypeVar("_T")
log = logging.getLogger("asac.replay")


class ReplayRpcError(RuntimeError):
    """A replay call failed; ``code`` is the gRPC status and the message carries the server's."""

    def __init__(self, code: grpc.StatusCode, message: str) -> None:
        super().__init__(message)
        self.code = code


class ReplayRequestRejected(ReplayRpcError, ValueError):
    """The server refused the request's contents (INVALID_ARGUMENT); nothing was changed."""


class ReplayUnreachable(ReplayRpcError, ReplayUnavailable):
    """The replay went away (UNAVAILABLE after the retries) or did not answer within the call's
    deadline (DEADLINE_EXCEEDED: a stopped or stalled process keeps its connections open): the
    table protocol's :class:`~algorithm.replay.base.ReplayUnavailable`, so a caller waits it out
    without knowing the transport."""


class ReplayClient(RpcClient):
    """The replay table interface over gRPC: ``insert``, ``insert_many``, ``insert_once``, ``sample``,
    ``update_priorities``, ``info``, ``normalizer_stats``, ``save``, ``load``.

    Takes and returns the same types as :class:`PrioritizedTable` (Chunk in, Batch out, numpy
    arrays with the same dtypes) and raises the same exceptions: ``ValueError`` for data the
    server rejects, :class:`SampleTimeout` / :class:`InsertTimeout` when the rate limiter holds a
    call back. Every call has a deadline: ``rpc_timeout_s``, plus the wait the caller asked for
    on ``insert``/``sample`` (a wait without end, ``timeout=None``, is a series of
    ``poll_s``-second calls), or ``file_timeout_s`` for ``save``/``load``. UNAVAILABLE is
    retried per ``retry``; every other error surfaces at once with the server's message.
    ``credentials``: TLS and the token (:func:`ds.net.security.open_channel`; the server must be a replay).
    Thread-safe: share one client between threads.
    """

    def __init__(
        self,
        address: str,
        sensors: tuple[SensorSpec, ...],
        action_size: int,
        rnn_state_size: int = 0,
        *,
        max_message_bytes: int = GRPC_DEFAULT_MESSAGE_BYTES,
        rpc_timeout_s: float = 30.0,
        file_timeout_s: float = 600.0,
        poll_s: float = 10.0,
        retry: RetryPolicy | None = None,
        credentials: Credentials = NO_CREDENTIALS,
        shared_memory: bool = True,
    ) -> None:
        super().__init__(
            address,
            security.REPLAY,
            replay_pb2_grpc.ReplayServiceStub,
            max_message_bytes=max_message_bytes,
            rpc_timeout_s=rpc_timeout_s,
            retry=retry,
            credentials=credentials,
        )
        self.sensors = tuple(sensors)
        self.action_size = int(action_size)
        self.rnn_state_size = int(rnn_state_size)
        self.specs = ReplaySpecs(self.sensors, self.action_size, self.rnn_state_size)
        self.max_message_bytes = int(max_message_bytes)
        self.file_timeout_s = float(file_timeout_s)
        self.poll_s = float(poll_s)
        # Sample's reply as the bytes received: batches are read from them (split_sample_reply)
        self._sample_bytes = self.channel.unary_unary(
            "/asac.ReplayService/Sample", request_serializer=replay_pb2.SampleRequest.SerializeToString
        )
        # Sampled batches through a file in /dev/shm while the server can open it (ds/replay/shared.py)
        self._shared_on = bool(shared_memory)
        self._shared: SharedSlot | None = None
        self._shared_lock = threading.Lock()  # one sample at a time uses the file; others go without it
        self._window = 0  # the table's window, from its first reply: the file is sized by it

    # ------------------------------------------------------------------ the table interface

    def insert(self, chunk: Chunk, priorities: np.ndarray | None = None, timeout: float | None = None) -> np.ndarray:
        """Store ``chunk``; returns its ``T`` uint64 keys. See :meth:`PrioritizedTable.insert`."""
        return self.insert_many([chunk], None if priorities is None else [priorities], timeout)[0]

    def insert_many(
        self,
        chunks: Sequence[Chunk],
        priorities: Sequence[np.ndarray | None] | None = None,
        timeout: float | None = None,
    ) -> list[np.ndarray]:
        """Store several chunks in one request, all or nothing; returns each chunk's keys.

        Raises :class:`~ds.replay.codec.WireError` (a ``ValueError``) before sending if a field is
        not a numpy array or the request is over ``max_message_bytes``.
        """
        request = self._insert_request(chunks, priorities)
        reply = self._blocking("Insert", self._stub.Insert, request, timeout, InsertTimeout)
        return _inserted(reply, chunks, None).keys

    def insert_once(
        self,
        chunks: Sequence[Chunk],
        ids: ChunkIds,
        priorities: Sequence[np.ndarray | None] | None = None,
        timeout: float | None = None,
        producer_stopping: bool = False,
    ) -> Inserted:
        """Store chunks unless already stored under their ids; see :meth:`PrioritizedTable.insert_once`.
        Retrying UNAVAILABLE is harmless here: a copy that was stored comes back as a duplicate."""
        request = self._insert_request(chunks, priorities, ids)
        request.producer_stopping = producer_stopping
        reply = self._blocking("Insert", self._stub.Insert, request, timeout, InsertTimeout)
        return _inserted(reply, chunks, ids)

    def insert_async(
        self,
        chunks: Sequence[Chunk],
        timeout: float = 0.0,
        ids: ChunkIds | None = None,
        producer_stopping: bool = False,
    ) -> PendingInsert:
        """Send one insert of ``chunks`` (all or nothing) without waiting for the answer: the
        caller goes on (an actor steps its envs) and collects it with :meth:`PendingInsert.result`.
        One attempt, no retries: the caller keeps the chunks until the result says they are stored,
        and sends them again with the same ``ids`` if it does not (then a copy that was stored is
        answered as a duplicate, not stored twice). ``timeout`` is how long the server's rate
        limiter may hold the insert back; with ``producer_stopping`` (and ``ids``) the chunks are
        stored after it even if the limiter still holds inserts back."""
        request = self._insert_request(chunks, None, ids)
        request.timeout_s = max(0.0, float(timeout))
        request.producer_stopping = producer_stopping
        future = self._stub.Insert.future(request, timeout=request.timeout_s + self.rpc_timeout_s)
        return PendingInsert(self.address, future, list(chunks), ids)

    def _insert_request(
        self, chunks: Sequence[Chunk], priorities: Sequence[np.ndarray | None] | None, ids: ChunkIds | None = None
    ) -> replay_pb2.InsertRequest:
        if priorities is not None and len(priorities) != len(chunks):
            raise ValueError(f"insert: {len(priorities)} priority arrays for {len(chunks)} chunks")
        if ids is not None:
            ids.check(len(chunks))
        request = replay_pb2.InsertRequest(
            chunks=[
                chunk_to_proto(c, None if priorities is None else priorities[i], f"chunks[{i}]")
                for i, c in enumerate(chunks)
            ]
        )
        if ids is not None:
            request.producer, request.acked_below = ids.producer, ids.acked_below
            request.sequence.extend(ids.seqs)
        self._check_size(request, f"{len(chunks)} chunks of {sum(len(c) for c in chunks)} steps")
        return request

    def sample(self, batch_size: int, timeout: float | None = None) -> Batch:
        """Draw ``batch_size`` windows; raises :class:`SampleTimeout` after ``timeout`` seconds
        (None: wait forever). See :meth:`PrioritizedTable.sample`."""
        return self.sample_many(batch_size, 1, timeout)[0]

    def sample_many(
        self, batch_size: int, count: int, timeout: float | None = None, allocate: Allocate | None = None
    ) -> list[Batch]:
        """Draw up to ``count`` batches of ``batch_size`` windows in one call (at least one; the others
        as far as the rate limiter allows at once and the message limit holds), each a sample of its
        own. The reply is copied once into ``allocate(nbytes)`` (a writable uint8 array: pinned memory
        on CUDA; None: new memory) and the batches are views of it. From the second call on, the
        reply's batches come through a file in /dev/shm while the server writes them there (same
        host; ``shared_memory``, ds/replay/shared.py). Raises :class:`SampleTimeout` as
        :meth:`sample` does."""
        request = replay_pb2.SampleRequest(batch_size=int(batch_size), batches=int(count))
        if self._shared_on and self._window and self._shared_lock.acquire(blocking=False):
            try:
                slot = self._shared_slot(int(batch_size), int(count))
                if slot is not None:
                    return self._sample_shared(slot, request, timeout, allocate)
            finally:
                self._shared_lock.release()
        reply, data = split_sample_reply(self._blocking("Sample", self._sample_bytes, request, timeout, SampleTimeout))
        return self._batches(reply, request, data, allocate)

    def _batches(
        self, reply: replay_pb2.SampleReply, request: replay_pb2.SampleRequest, data: memoryview,
        allocate: Allocate | None,
    ) -> list[Batch]:  # fmt: skip
        count = max(request.batches, 1)
        if not 1 <= len(reply.table_size) <= count:
            raise WireError("table_size", f"holds {len(reply.table_size)} batches, expected 1 to {count}")
        batches = self.specs.batches_from_reply(reply, request.batch_size, allocate=allocate, data=data)
        self._window = reply.window
        return batches

    def _sample_shared(
        self, slot: SharedSlot, request: replay_pb2.SampleRequest, timeout: float | None, allocate: Allocate | None
    ) -> list[Batch]:
        request.shared_name, request.shared_size = slot.name, slot.size

        def attempt(req: replay_pb2.SampleRequest, timeout: float) -> bytes:  # a new fence for every attempt
            req.shared_seq = slot.fence()
            return self._sample_bytes(req, timeout=timeout)

        reply, data = split_sample_reply(self._blocking("Sample", attempt, request, timeout, SampleTimeout))
        if reply.shared_bytes:
            return self._batches(reply, request, slot.payload(reply.shared_bytes), allocate)
        log.info("the replay at %s does not write into %s (another host, another /dev/shm or another user): "
                 "batches come over gRPC", self.address, slot.path)  # fmt: skip
        self._shared_on = False
        self._close_shared()
        return self._batches(reply, request, data, allocate)

    def _shared_slot(self, batch_size: int, count: int) -> SharedSlot | None:
        """The file for a reply of ``count`` batches of ``batch_size`` windows (as many as the message
        limit allows at most), made or grown on demand; None where it cannot be made."""
        layout = self.specs.layout(batch_size, self._window)
        fitting = batches_per_reply(self.sensors, self.action_size, batch_size, self._window, self.rnn_state_size,
                                    self.max_message_bytes)  # fmt: skip
        needed = max(min(max(count, 1), fitting), 1) * layout.batch_bytes
        if self._shared is not None and self._shared.capacity >= needed:
            return self._shared
        self._close_shared()
        try:
            self._shared = SharedSlot(needed)
        except OSError as e:
            log.info("no file for batches in %s (%s): batches come over gRPC", SHARED_DIR, e)
            self._shared_on = False
            return None
        log.info("batches from the replay at %s come through %s (%d bytes) while it can open it",
                 self.address, self._shared.path, self._shared.size)  # fmt: skip
        return self._shared

    def _close_shared(self) -> None:
        if self._shared is not None:
            self._shared.close()
            self._shared = None

    def close(self) -> None:
        self._shared_on = False
        if self._shared_lock.acquire(timeout=1.0):
            try:
                self._close_shared()
            finally:
                self._shared_lock.release()
        elif self._shared is not None:  # a sample still waits on the server: its file goes, its mapping with it
            self._shared.path.unlink(missing_ok=True)
        super().close()

    def windows_after(self, key: int, limit: int) -> Batch | None:
        """The windows of the oldest ``limit`` stored steps with keys ``>= key`` (None: none); see
        :meth:`PrioritizedTable.windows_after`."""
        if int(key) < 0:  # uint64 on the wire: say it as the table does
            raise ValueError(f"windows_after: key must be >= 0, got {key}")
        request = replay_pb2.WindowsRequest(from_key=int(key), max_windows=int(limit))
        reply = self._call("Windows", self._stub.Windows, request, self.rpc_timeout_s)
        if not reply.table_size:
            return None
        if not 1 <= reply.batch_size <= int(limit) or len(reply.table_size) != 1:
            shape = f"{len(reply.table_size)} x {reply.batch_size}"
            raise WireError("batch_size", f"holds {shape} windows, expected one batch of 1 to {limit}")
        return self.specs.batches_from_reply(reply, reply.batch_size)[0]

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> None:
        """Set raw priorities of ``keys`` (any integer dtype; evicted keys are ignored)."""
        k = np.asarray(keys)
        if k.ndim != 1 or (k.size and k.dtype.kind not in "ui"):
            raise WireError("keys", f"must be a 1-D integer array, got {k.dtype} {k.shape}")
        # Negative keys become huge uint64 ones: never issued, so ignored, as in the table.
        request = replay_pb2.UpdatePrioritiesRequest(
            keys=to_tensor(k.astype(np.uint64), "keys"),
            priorities=to_tensor(np.asarray(priorities, dtype=np.float64), "priorities"),
        )
        self._check_size(request, f"{k.shape[0]} priorities")
        self._call("UpdatePriorities", self._stub.UpdatePriorities, request, self.rpc_timeout_s)

    def update_rnn_states(self, keys: np.ndarray, states: np.ndarray) -> None:
        """Overwrite the stored recurrent states of ``keys`` (see :meth:`PrioritizedTable.update_rnn_states`)."""
        request = replay_pb2.UpdateRnnStatesRequest(
            keys=to_tensor(np.asarray(keys).astype(np.uint64), "keys"), states=to_tensor(np.asarray(states), "states")
        )
        self._check_size(request, f"{len(keys)} recurrent states")
        self._call("UpdateRnnStates", self._stub.UpdateRnnStates, request, self.rpc_timeout_s)

    def info(self) -> ReplayInfo:
        """The server table's ``info()``: the same keys, ``int`` counters and ``float`` values."""
        reply = self._call("Info", self._stub.Info, replay_pb2.InfoRequest(), self.rpc_timeout_s)
        return self.specs.info_from_proto(reply)

    def normalizer_stats(self) -> dict[str, NormalizerStats]:
        """``{sensor name: {"count", "mean", "var"}}`` of every vector sensor, as in the table."""
        reply = self._call("Info", self._stub.Info, replay_pb2.InfoRequest(), self.rpc_timeout_s)
        return self.specs.normalizer_from_proto(reply)

    def save(self, path: str | Path = "") -> None:
        """Save the table atomically to ``path``, a file name inside the replay server's snapshot
        folder (relative, no ``..``; empty: its default snapshot ``replay.npz``; ds/replay/files.py)."""
        self._call("Save", self._stub.Save, replay_pb2.SaveRequest(path=str(path)), self.file_timeout_s)

    def load(self, path: str | Path = "") -> None:
        """Replace the server table's contents with ``path``, a file name inside the replay
        server's snapshot folder (as for :meth:`save`); a bad file or name raises ``ValueError``
        and changes nothing."""
        self._call("Load", self._stub.Load, replay_pb2.LoadRequest(path=str(path)), self.file_timeout_s)

    # ------------------------------------------------------------------ calls

    def _check_size(self, request: Any, what: str) -> None:
        size = request.ByteSize()
        if size > self.max_message_bytes:
            raise WireError(
                type(request).__name__,
                f"of {what} is {size} bytes, over the replay message limit of {self.max_message_bytes} bytes: "
                "send less per call, or start server and clients with a larger max_message_bytes "
                "(message_limit_bytes(..., max_chunk_steps=...))",
            )

    def _blocking(
        self,
        method: str,
        rpc: Callable[..., _T],
        request: Any,
        timeout: float | None,
        timeout_error: type[TimeoutError],
    ) -> _T:
        """A call that may wait in the rate limiter for ``timeout`` seconds (None: forever)."""
        while True:
            wait = self.poll_s if timeout is None else max(0.0, float(timeout))
            request.timeout_s = wait
            try:
                return self._call(method, rpc, request, wait + self.rpc_timeout_s)
            except ReplayRpcError as e:
                if e.code != grpc.StatusCode.DEADLINE_EXCEEDED:
                    raise
                if timeout is not None:
                    raise timeout_error(str(e)) from None

    def _call(self, method: str, rpc: Callable[..., _T], request: Any, deadline_s: float) -> _T:
        """One unary call with a deadline of ``deadline_s`` seconds, retrying UNAVAILABLE with
        backoff; other errors become :class:`ReplayRpcError` carrying the server's message."""
        try:
            return self._unary(rpc, request, deadline_s)
        except grpc.RpcError as e:
            message = f"replay {method} at {self.address}: {e.details()}"
            raise _client_error(e.code(), message, self.retry.attempts) from None


class PendingInsert:
    """An insert on its way (:meth:`ReplayClient.insert_async`); ``chunks`` are what it carries,
    under ``ids`` (None: none). ``final`` is the sender's mark for a last try (the actor's sink
    sets it once stopping)."""

    def __init__(self, address: str, future: grpc.Future, chunks: list[Chunk], ids: ChunkIds | None = None) -> None:
        self.address = address
        self.chunks = chunks
        self.ids = ids
        self.final = False
        self.sent_at = time.monotonic()
        self.answered_at: float | None = None
        self.served_s: float | None = None  # the server's part of the round trip (InsertReply.served_s)
        self._future = future
        future.add_done_callback(self._answered)

    def _answered(self, _: grpc.Future) -> None:
        self.answered_at = time.monotonic()

    def link_s(self) -> float | None:
        """The link's part of this insert's round trip (its whole round trip less the server's time on
        it, waiting in the rate limiter included), once answered by a server that says its time."""
        if self.answered_at is None or not self.served_s:
            return None
        return max(0.0, self.answered_at - self.sent_at - self.served_s)

    def steps(self) -> int:
        return sum(len(c) for c in self.chunks)

    def result(self, while_waiting: Callable[[], None] | None = None, every_s: float = 0.05) -> Inserted:
        """Wait for the answer: each chunk's keys and whether it was a duplicate, or the exceptions
        :meth:`ReplayClient.insert_many` raises (:class:`InsertTimeout` when the rate limiter held
        it back for its whole timeout, :class:`ReplayRpcError` with UNAVAILABLE when the replay is
        gone or the answer was lost, ``ValueError`` if refused). ``while_waiting`` is called every
        ``every_s`` until the answer is in (an actor takes new weights meanwhile)."""
        if while_waiting is not None:
            answered = threading.Event()
            self._future.add_done_callback(lambda _: answered.set())
            while not answered.wait(every_s):
                while_waiting()
        try:
            reply = self._future.result()
        except grpc.RpcError as e:
            message = f"replay Insert at {self.address}: {e.details()}"
            if e.code() == grpc.StatusCode.DEADLINE_EXCEEDED:
                raise InsertTimeout(message) from None
            raise _client_error(e.code(), message, 1) from None
        self.served_s = reply.served_s
        return _inserted(reply, self.chunks, self.ids)


def _inserted(reply: replay_pb2.InsertReply, chunks: Sequence[Chunk], ids: ChunkIds | None) -> Inserted:
    """Check an InsertReply against the request: one key tensor per chunk of ``T`` keys (a
    duplicate's may be empty: the server forgot them) and, with ``ids``, one duplicate flag each."""
    if len(reply.keys) != len(chunks):
        raise WireError("keys", f"has {len(reply.keys)} tensors for {len(chunks)} chunks")
    duplicate = list(reply.duplicate)
    if len(duplicate) != (0 if ids is None else len(chunks)):
        raise WireError("duplicate", f"has {len(duplicate)} flags for {len(chunks)} chunks")
    keys = []
    for i, (k, c) in enumerate(zip(reply.keys, chunks, strict=True)):
        t = 0 if duplicate and duplicate[i] and tuple(k.shape) == (0,) else len(c)
        keys.append(from_tensor(k, TensorSpec(f"keys[{i}]", np.dtype(np.uint64), leading=("T",)), {"T": t}))
    return Inserted(keys, duplicate or [False] * len(chunks), reply.inserted_steps)


def _client_error(code: grpc.StatusCode, message: str, attempts: int) -> ReplayRpcError:
    if code == grpc.StatusCode.INVALID_ARGUMENT:
        return ReplayRequestRejected(code, message)
    if peer_gone(code):  # callers handle one code for "the replay went away"
        return ReplayUnreachable(grpc.StatusCode.UNAVAILABLE, f"{message} (unavailable after {attempts} attempts)")
    if code == grpc.StatusCode.DEADLINE_EXCEEDED:
        return ReplayUnreachable(code, f"{message} ({code.name})")
    return ReplayRpcError(code, f"{message} ({code.name})")
