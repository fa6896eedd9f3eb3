"""The replay table over gRPC: a servicer wrapping the in-process table, and a client that is one.

Usage, a replay process and its peers (protos/replay.proto documents every rpc)::

    limit = message_limit_bytes(sensors, action_size, batch_size, window, rnn_state_size, chunk_length)
    server, port = serve_replay(table, "0.0.0.0:50051", max_message_bytes=limit, credentials=creds,
                                snapshot_dir=run / "replay")  # replay role: Save/Load name files in there
    ...
    replay = ReplayClient("replay:50051", sensors, action_size, rnn_state_size, max_message_bytes=limit,
                          credentials=creds)   # creds: ds.net.security.load_credentials (token, TLS)
    keys = replay.insert(chunk)                      # actor
    pending = replay.insert_async(chunks, timeout=2.0, ids=ChunkIds(producer, seqs, acked_below))
    pending.result()                                 # actor's sink: keys and duplicate flags, or raises
    batch = replay.sample(256, timeout=1.0)          # learner: a Batch with the same dtypes as in-process
    replay.update_priorities(batch.keys, td_abs)     # learner
    server.stop(grace=5.0)

:class:`ReplayClient` implements the table interface of :mod:`algorithm.replay.base` with the same
types and exceptions (``ValueError`` for rejected data, :class:`SampleTimeout`/:class:`InsertTimeout`),
so the replay contract tests run unchanged against it (tests/ds/test_replay_contract.py).

Errors map to gRPC status codes on the server and back to exceptions on the client:

- bad data or a bad file (``WireError``, ``ValueError``): INVALID_ARGUMENT -> :class:`ReplayRequestRejected`,
  a ``ValueError`` carrying the server's message; so is a Save/Load path the server does not own
  (outside its snapshot folder, or not a regular file: ds/replay/files.py);
- the rate limiter's ``SampleTimeout`` / ``InsertTimeout``: DEADLINE_EXCEEDED -> the same exception;
- a file the server cannot write (``OSError``), a server without a snapshot folder: FAILED_PRECONDITION ->
  :class:`ReplayRpcError`; a full disk (ENOSPC, EDQUOT): RESOURCE_EXHAUSTED, the snapshot before it kept;
- a Save or Load while another runs: ABORTED; one past its deadline is abandoned having changed
  nothing: DEADLINE_EXCEEDED -> :class:`ReplayRpcError`;
- a message over the size limit: RESOURCE_EXHAUSTED -> :class:`ReplayRpcError` (the client refuses
  to send an oversize request itself, with a ``WireError`` naming the size and the limit);
- an Insert from a new producer past ``replay_config.max_producers`` (``ProducerLimitReached``):
  RESOURCE_EXHAUSTED -> :class:`ReplayRpcError` carrying the server's message;
- server unreachable: UNAVAILABLE -> retried with backoff, then :class:`ReplayRpcError`;
- a missing or wrong token, a caller whose certificate names no role that may call the rpc
  (:data:`CALLERS`, ds/net/security.py): UNAUTHENTICATED / PERMISSION_DENIED -> :class:`ReplayRpcError`.
"""

from __future__ import annotations

import errno
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import grpc
import numpy as np
from grpc_health.v1 import health, health_pb2_grpc

from algorithm.replay import (
    ChunkIds,
    Inserted,
    InsertTimeout,
    NormalizerStats,
    PrioritizedTable,
    ProducerLimitReached,
    ReplayInfo,
    ReplayUnavailable,
    SampleTimeout,
)
from algorithm.spaces import SensorSpec
from algorithm.types import Batch, Chunk
from ds.net import rpc, security
from ds.net.client import RpcClient
from ds.net.rpc import RetryPolicy, channel_options, peer_gone
from ds.net.security import ACTOR, LEARNER, NO_CREDENTIALS, Credentials
from ds.net.wire import TensorSpec, WireError, from_tensor, to_tensor
from ds.replay.codec import (
    GRPC_DEFAULT_MESSAGE_BYTES,
    ReplaySpecs,
    batch_to_proto,
    chunk_to_proto,
    info_to_proto,
    message_limit_bytes,
    sample_reply_bytes,
)
from ds.replay.files import FileWork, FileWorkAbandoned, FileWorkBusy, SnapshotFolder
from protos import replay_pb2, replay_pb2_grpc

__all__ = [
    "CALLERS",
    "SERVICE_NAME",
    "ReplayClient",
    "ReplayRequestRejected",
    "ReplayRpcError",
    "ReplayServicer",
    "RetryPolicy",
    "message_limit_bytes",
    "serve_replay",
    "set_serving",
]

SERVICE_NAME = "asac.ReplayService"
# Who calls what (under mutual TLS, no other role may): actors insert; the learner samples, updates
# and saves; both read Info (the actor checks the step budget, the learner the normalizer).
CALLERS: security.Callers = {
    "Insert": frozenset({ACTOR}),
    "Sample": frozenset({LEARNER}),
    "UpdatePriorities": frozenset({LEARNER}),
    "UpdateRnnStates": frozenset({LEARNER}),
    "Windows": frozenset({LEARNER}),
    "Info": frozenset({ACTOR, LEARNER}),
    "Save": frozenset({LEARNER}),
    "Load": frozenset({LEARNER}),
}
_T = TypeVar("_T")


# ---------------------------------------------------------------------- server


class ReplayServicer(replay_pb2_grpc.ReplayServiceServicer):
    """Serves one :class:`PrioritizedTable`; every request is checked against the registered specs.

    ``sensors``, ``action_size`` and ``rnn_state_size`` are what clients must send (they must
    equal the table's). The table has its own lock, so the servicer is safe under any number of
    concurrent RPCs. ``snapshot_dir`` is the one folder whose files Save and Load may name (the
    replay role's ``<run>/replay/``; rules in ds/replay/files.py); None: Save and Load are refused
    with FAILED_PRECONDITION. They run one at a time on a thread of their own, bounded by their
    call's deadline, so that file work never holds the workers the other rpcs need.
    """

    def __init__(
        self,
        table: PrioritizedTable,
        sensors: tuple[SensorSpec, ...],
        action_size: int,
        rnn_state_size: int = 0,
        max_message_bytes: int = GRPC_DEFAULT_MESSAGE_BYTES,
        snapshot_dir: str | Path | None = None,
    ) -> None:
        self.specs = ReplaySpecs(tuple(sensors), int(action_size), int(rnn_state_size))
        stored = ReplaySpecs(table.sensors, table.action_size, table.rnn_state_size)
        if self.specs != stored:
            raise ValueError(f"replay servicer specs {self.specs} differ from the table's {stored}")
        self.table = table
        self.max_message_bytes = int(max_message_bytes)
        self.snapshots = None if snapshot_dir is None else SnapshotFolder(snapshot_dir)
        self._file_work = FileWork()

    def Insert(self, request: replay_pb2.InsertRequest, context: grpc.ServicerContext) -> replay_pb2.InsertReply:
        with _status_codes(context):
            if not request.chunks and not request.producer:
                raise WireError("chunks", "is empty: an Insert carries at least one chunk (or, with a producer, none: "
                                "it only acknowledges)")  # fmt: skip
            # Decode every chunk first: a bad one anywhere rejects the whole request untouched.
            decoded = [self.specs.chunk_from_proto(c, f"chunks[{i}]") for i, c in enumerate(request.chunks)]
            chunks, priorities = [chunk for chunk, _ in decoded], [p for _, p in decoded]
            wait = _wait_seconds(request, context)
            if request.producer:
                ids = ChunkIds(request.producer, tuple(request.sequence), request.acked_below)
                inserted = self.table.insert_once(chunks, ids, priorities, wait, request.producer_stopping)
                return replay_pb2.InsertReply(
                    keys=[to_tensor(k) for k in inserted.keys],
                    duplicate=inserted.duplicate,
                    inserted_steps=inserted.inserted_steps,
                )
            if request.sequence or request.acked_below:
                raise ValueError("InsertRequest: sequence and acked_below need a producer, but producer is 0")
            keys = self.table.insert_many(chunks, priorities, wait)
        return replay_pb2.InsertReply(keys=[to_tensor(k) for k in keys])

    def Sample(self, request: replay_pb2.SampleRequest, context: grpc.ServicerContext) -> replay_pb2.SampleReply:
        spec, b = self.specs, request.batch_size
        size = sample_reply_bytes(spec.sensors, spec.action_size, b, self.table.window, spec.rnn_state_size)
        if size > self.max_message_bytes:  # refuse before drawing: a drawn batch would be lost
            context.abort(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"a batch of {b} windows of {self.table.window} steps is about {size} bytes, over this replay "
                f"server's message limit of {self.max_message_bytes} bytes: start server and clients with "
                f"max_message_bytes=message_limit_bytes(..., batch_size={b}, ...)",
            )
        with _status_codes(context):
            batch = self.table.sample(b, _wait_seconds(request, context))
        return batch_to_proto(batch)

    def Windows(self, request: replay_pb2.WindowsRequest, context: grpc.ServicerContext) -> replay_pb2.SampleReply:
        spec, n = self.specs, request.max_windows
        size = sample_reply_bytes(spec.sensors, spec.action_size, max(n, 1), self.table.window, spec.rnn_state_size)
        if size > self.max_message_bytes:
            context.abort(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"{n} windows of {self.table.window} steps are about {size} bytes, over this replay server's "
                f"message limit of {self.max_message_bytes} bytes: ask for fewer (max_windows)",
            )
        with _status_codes(context):
            batch = self.table.windows_after(request.from_key, n)
        return replay_pb2.SampleReply() if batch is None else batch_to_proto(batch)

    def UpdatePriorities(
        self, request: replay_pb2.UpdatePrioritiesRequest, context: grpc.ServicerContext
    ) -> replay_pb2.UpdatePrioritiesReply:
        with _status_codes(context):
            self.table.update_priorities(*self.specs.priorities_from_proto(request))
        return replay_pb2.UpdatePrioritiesReply()

    def UpdateRnnStates(
        self, request: replay_pb2.UpdateRnnStatesRequest, context: grpc.ServicerContext
    ) -> replay_pb2.UpdateRnnStatesReply:
        with _status_codes(context):
            self.table.update_rnn_states(*self.specs.rnn_states_from_proto(request))
        return replay_pb2.UpdateRnnStatesReply()

    def Info(self, request: replay_pb2.InfoRequest, context: grpc.ServicerContext) -> replay_pb2.InfoReply:
        return info_to_proto(self.table.info())

    def Save(self, request: replay_pb2.SaveRequest, context: grpc.ServicerContext) -> replay_pb2.SaveReply:
        with _status_codes(context):
            path = self._snapshots().for_save(request.path)
            self._file_work.run(
                f"Save of {request.path or path.name!r}",
                lambda gate: self.table.save(path, before_replace=gate),
                _deadline_seconds(context),
            )
        return replay_pb2.SaveReply()

    def Load(self, request: replay_pb2.LoadRequest, context: grpc.ServicerContext) -> replay_pb2.LoadReply:
        with _status_codes(context):
            path = self._snapshots().for_load(request.path)
            self._file_work.run(
                f"Load of {request.path or path.name!r}",
                lambda gate: self.table.load(path, follow_symlinks=False, before_install=gate),
                _deadline_seconds(context),
            )
        return replay_pb2.LoadReply()

    def _snapshots(self) -> SnapshotFolder:
        if self.snapshots is None:
            raise _NoSnapshotFolder(
                "this replay server was started without a snapshot folder (serve_replay(..., snapshot_dir=None)): "
                "Save and Load are off"
            )
        return self.snapshots


class _NoSnapshotFolder(Exception):
    """Save or Load on a server started without a snapshot folder (FAILED_PRECONDITION)."""


def _deadline_seconds(context: grpc.ServicerContext) -> float | None:
    """Seconds left of the call's deadline, a little less so that the answer reaches the caller
    before it gives up; None: the call has none."""
    remaining = context.time_remaining()  # about 9e18 for a call without deadline
    if remaining is None or remaining >= threading.TIMEOUT_MAX:
        return None
    return max(0.0, remaining - 0.05)


def _wait_seconds(request: Any, context: grpc.ServicerContext) -> float | None:
    """How long a blocking table call may wait: the request's ``timeout_s``, never past the call's
    deadline (a caller that gave up must not leave a server thread blocked); None: forever."""
    limits = []
    if request.HasField("timeout_s"):
        if not request.timeout_s >= 0:  # also NaN
            raise WireError("timeout_s", f"must be >= 0, got {request.timeout_s}")
        if request.timeout_s < threading.TIMEOUT_MAX:  # longer (inf) is no limit: the lock cannot wait that long
            limits.append(request.timeout_s)
    remaining = context.time_remaining()  # about 9e18 for a call without deadline
    if remaining is not None and remaining < threading.TIMEOUT_MAX:
        limits.append(max(0.0, remaining))
    return min(limits) if limits else None


@contextmanager
def _status_codes(context: grpc.ServicerContext) -> Iterator[None]:
    """Turn the table's exceptions into status codes with the exception's message."""
    try:
        yield
    except (SampleTimeout, InsertTimeout, FileWorkAbandoned) as e:  # before OSError: TimeoutError is an OSError
        context.abort(grpc.StatusCode.DEADLINE_EXCEEDED, str(e))
    except FileWorkBusy as e:
        context.abort(grpc.StatusCode.ABORTED, str(e))
    except _NoSnapshotFolder as e:
        context.abort(grpc.StatusCode.FAILED_PRECONDITION, str(e))
    except ValueError as e:
        context.abort(grpc.StatusCode.INVALID_ARGUMENT, str(e))
    except ProducerLimitReached as e:
        context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, str(e))
    except OSError as e:
        # gRPC's code for "the entire file system is out of space" (its status code guide); other
        # I/O errors leave the server's state as the precondition that failed.
        full = e.errno in (errno.ENOSPC, errno.EDQUOT)
        code = grpc.StatusCode.RESOURCE_EXHAUSTED if full else grpc.StatusCode.FAILED_PRECONDITION
        context.abort(code, f"{type(e).__name__}: {e}")


def set_serving(health_servicer: health.HealthServicer, serving: bool) -> None:
    """Report SERVING or NOT_SERVING for the server as a whole and for the replay service."""
    rpc.set_serving(health_servicer, SERVICE_NAME, serving)


def serve_replay(
    table: PrioritizedTable,
    address: str = "127.0.0.1:0",
    *,
    max_message_bytes: int = GRPC_DEFAULT_MESSAGE_BYTES,
    max_workers: int = 32,
    health_servicer: health.HealthServicer | None = None,
    ready: bool = True,
    credentials: Credentials = NO_CREDENTIALS,
    health_port: int | None = None,
    interceptors: Sequence[grpc.ServerInterceptor] = (),
    snapshot_dir: str | Path | None = None,
) -> tuple[grpc.Server, int]:
    """Start a gRPC server for ``table`` on ``address`` (port 0: any free port); returns it and its port.

    ``max_message_bytes`` limits what the server sends and receives (see
    :func:`~ds.replay.codec.message_limit_bytes`). ``max_workers`` threads serve calls; a call
    blocked by the rate limiter holds one, so give at least one per actor and learner. The health
    service reports NOT_SERVING until the server has started, then SERVING; pass ``ready=False``
    and your own ``health_servicer`` to flip it with :func:`set_serving` later (after loading a
    saved table, say). ``credentials`` and ``health_port``: see :func:`ds.net.security.listen` (TLS, the
    token, who may call what); plaintext on loopback by default (docs/security.md section 1:
    without credentials servers bind to loopback). ``interceptors`` wrap every call after those checks (tests inject
    faults with them). ``snapshot_dir``: the folder whose files the Save and Load rpcs may name
    (a replay role's ``<run>/replay/``; ds/replay/files.py), None: Save and Load are refused. Stop
    it with ``server.stop(grace)``.
    """
    options = channel_options(max_message_bytes)
    server = security.new_server("replay", SERVICE_NAME, CALLERS, credentials, max_workers, options, interceptors)
    servicer = ReplayServicer(
        table, table.sensors, table.action_size, table.rnn_state_size, max_message_bytes, snapshot_dir
    )
    rpc.add_servicer(server, servicer, replay_pb2.DESCRIPTOR.services_by_name["ReplayService"])
    health_servicer = health_servicer or health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    set_serving(health_servicer, False)
    port = security.listen(server, address, credentials, "replay", health_port)
    server.start()
    if ready:
        set_serving(health_servicer, True)
    return server, port


# ---------------------------------------------------------------------- client


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
        request = replay_pb2.SampleRequest(batch_size=int(batch_size))
        reply = self._blocking("Sample", self._stub.Sample, request, timeout, SampleTimeout)
        return self.specs.batch_from_proto(reply, int(batch_size))

    def windows_after(self, key: int, limit: int) -> Batch | None:
        """The windows of the oldest ``limit`` stored steps with keys ``>= key`` (None: none); see
        :meth:`PrioritizedTable.windows_after`."""
        if int(key) < 0:  # uint64 on the wire: say it as the table does
            raise ValueError(f"windows_after: key must be >= 0, got {key}")
        request = replay_pb2.WindowsRequest(from_key=int(key), max_windows=int(limit))
        reply = self._call("Windows", self._stub.Windows, request, self.rpc_timeout_s)
        if not reply.HasField("keys"):
            return None
        n = reply.keys.shape[0] if reply.keys.shape else 0
        if not 1 <= n <= int(limit):
            raise WireError("keys", f"holds {n} windows, expected 1 to {limit}")
        return self.specs.batch_from_proto(reply, n)

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
        self._future = future

    def steps(self) -> int:
        return sum(len(c) for c in self.chunks)

    def result(self) -> Inserted:
        """Wait for the answer: each chunk's keys and whether it was a duplicate, or the exceptions
        :meth:`ReplayClient.insert_many` raises (:class:`InsertTimeout` when the rate limiter held
        it back for its whole timeout, :class:`ReplayRpcError` with UNAVAILABLE when the replay is
        gone or the answer was lost, ``ValueError`` if refused)."""
        try:
            reply = self._future.result()
        except grpc.RpcError as e:
            message = f"replay Insert at {self.address}: {e.details()}"
            if e.code() == grpc.StatusCode.DEADLINE_EXCEEDED:
                raise InsertTimeout(message) from None
            raise _client_error(e.code(), message, 1) from None
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
