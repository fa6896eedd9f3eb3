"""The replay table over gRPC, the server's side: a servicer wrapping the in-process table (the client,
which is a table itself, is ds/replay/client.py).

Usage, a replay process and its peers (protos/replay.proto documents every rpc)::

    limit = message_limit_bytes(sensors, action_size, batch_size, window, rnn_state_size, chunk_length)
    server, port = serve_replay(table, "0.0.0.0:50051", max_message_bytes=limit, credentials=creds,
                                snapshot_dir=run / "replay")  # replay role: Save/Load name files in there
    ...                                              # clients: ds/replay/client.py
    server.stop(grace=5.0)

Errors map to gRPC status codes on the server and back to exceptions on the client (the exception
classes are ds/replay/client.py's):

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
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import grpc
from grpc_health.v1 import health, health_pb2_grpc

from algorithm.replay import (
    ChunkIds,
    InsertTimeout,
    PrioritizedTable,
    ProducerLimitReached,
    SampleTimeout,
)
from algorithm.spaces import SensorSpec
from ds.net import rpc, security
from ds.net.rpc import GRPC_DEFAULT_MESSAGE_BYTES, channel_options
from ds.net.security import ACTOR, LEARNER, NO_CREDENTIALS, Credentials
from ds.net.wire import WireError, to_tensor
from ds.replay.codec import (
    ReplaySpecs,
    batches_per_reply,
    info_to_proto,
    message_limit_bytes,
    sample_reply,
    sample_reply_bytes,
)
from ds.replay.files import FileWork, FileWorkAbandoned, FileWorkBusy, SnapshotFolder
from ds.replay.packed import pack_batches_into
from ds.replay.shared import HEADER_BYTES, write_shared
from protos import replay_pb2, replay_pb2_grpc

__all__ = [
    "CALLERS",
    "SERVICE_NAME",
    "ReplayServicer",
    "message_limit_bytes",
    "serve_replay",
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
        started = time.perf_counter()
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
                    served_s=time.perf_counter() - started,
                )
            if request.sequence or request.acked_below:
                raise ValueError("InsertRequest: sequence and acked_below need a producer, but producer is 0")
            keys = self.table.insert_many(chunks, priorities, wait)
        return replay_pb2.InsertReply(keys=[to_tensor(k) for k in keys], served_s=time.perf_counter() - started)

    def Sample(self, request: replay_pb2.SampleRequest, context: grpc.ServicerContext) -> replay_pb2.SampleReply:
        spec, b, window = self.specs, request.batch_size, self.table.window
        fitting = batches_per_reply(spec.sensors, spec.action_size, b, window, spec.rnn_state_size,
                                    self.max_message_bytes)  # fmt: skip
        if not fitting:  # refuse before drawing: a drawn batch would be lost
            size = sample_reply_bytes(spec.sensors, spec.action_size, b, window, spec.rnn_state_size)
            context.abort(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"a batch of {b} windows of {window} steps is about {size} bytes, over this replay "
                f"server's message limit of {self.max_message_bytes} bytes: start server and clients with "
                f"max_message_bytes=message_limit_bytes(..., batch_size={b}, ...)",
            )
        if request.batches < 0:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, f"batches must be >= 0, got {request.batches}")
        wanted = min(max(request.batches, 1), fitting)
        layout = self.specs.layout(b, window)
        shared = bool(request.shared_name) and request.shared_size - HEADER_BYTES >= layout.batch_bytes
        if shared:  # no more than the caller's file holds
            wanted = min(wanted, (request.shared_size - HEADER_BYTES) // layout.batch_bytes)
        with _status_codes(context):
            batches = [self.table.sample(b, _wait_seconds(request, context))]
            while len(batches) < wanted:  # the rest only while the rate limiter allows them at once
                try:
                    batches.append(self.table.sample(b, 0.0))
                except SampleTimeout:
                    break
        nbytes = layout.batch_bytes * len(batches)
        if shared and write_shared(request.shared_name, request.shared_size, request.shared_seq, nbytes,
                                   lambda out: pack_batches_into(layout, batches, out)):  # fmt: skip
            return replay_pb2.SampleReply(
                batch_size=b, window=window, table_size=[x.table_size for x in batches], shared_bytes=nbytes
            )
        return sample_reply(layout, batches)  # the caller's file out of reach: the batches in the reply

    def Windows(self, request: replay_pb2.WindowsRequest, context: grpc.ServicerContext) -> replay_pb2.SampleReply:
        spec, n, window = self.specs, request.max_windows, self.table.window
        size = sample_reply_bytes(spec.sensors, spec.action_size, max(n, 1), window, spec.rnn_state_size)
        if size > self.max_message_bytes:
            context.abort(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"{n} windows of {window} steps are about {size} bytes, over this replay server's "
                f"message limit of {self.max_message_bytes} bytes: ask for fewer (max_windows)",
            )
        with _status_codes(context):
            batch = self.table.windows_after(request.from_key, n)
        if batch is None:
            return replay_pb2.SampleReply(window=window)
        return sample_reply(self.specs.layout(batch.batch_size, window), [batch])

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
    and your own ``health_servicer`` to flip it later with
    ``ds.net.rpc.set_serving(health_servicer, SERVICE_NAME, True)`` (after loading a saved table,
    say). ``credentials`` and ``health_port``: see :func:`ds.net.security.listen` (TLS, the token, who
    may call what); plaintext on loopback by default (docs/security.md section 1: without credentials
    servers bind to loopback). ``interceptors`` wrap every call after those checks (tests inject
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
    rpc.set_serving(health_servicer, SERVICE_NAME, False)
    port = security.listen(server, address, credentials, "replay", health_port)
    server.start()
    if ready:
        rpc.set_serving(health_servicer, SERVICE_NAME, True)
    return server, port
