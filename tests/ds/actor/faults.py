"""A server interceptor that makes a seeded fraction of calls fail with UNAVAILABLE, as a flaky
network does: either before the servicer sees the request (nothing happened) or after it answered
(it happened, but the reply is lost). Pass it to ``serve_replay(..., interceptors=[flaky])``.

Usage::

    flaky = FlakyCalls("Insert", before=0.1, after=0.1, seed=0)
    server, port = serve_replay(table, interceptors=[flaky])
    ...
    flaky.lost_chunks   # chunks whose Insert succeeded but whose reply was replaced by UNAVAILABLE
"""

from __future__ import annotations

import random
import threading
from typing import Any

import grpc


class FlakyCalls(grpc.ServerInterceptor):
    """Fails calls of the unary method ``method`` with UNAVAILABLE: a fraction ``before`` of them
    before the servicer runs, a fraction ``after`` after it returned normally (a call the servicer
    itself refused keeps its own status). Decisions come from ``random.Random(seed)`` in arrival
    order. ``before`` and ``after`` may be changed while serving. Counts what it did."""

    def __init__(self, method: str, before: float = 0.0, after: float = 0.0, seed: int = 0) -> None:
        self.method = method
        self.before = before
        self.after = after
        self.calls = 0
        self.failed_before = 0
        self.failed_after = 0
        self.lost_chunks = 0  # Insert only: chunks of the requests whose successful reply was dropped
        self.delivered_duplicates = 0  # Insert only: duplicate flags in the replies that got through
        self._rng = random.Random(seed)
        self._lock = threading.Lock()

    def intercept_service(self, continuation: Any, details: grpc.HandlerCallDetails) -> Any:
        handler = continuation(details)
        if handler is None or details.method.rsplit("/", 1)[-1] != self.method:  # type: ignore[attr-defined]
            return handler
        serve = handler.unary_unary

        def flaky(request: Any, context: grpc.ServicerContext) -> Any:
            with self._lock:
                self.calls += 1
                draw = self._rng.random()
                fail_before = draw < self.before
                fail_after = not fail_before and draw < self.before + self.after
                if fail_before:
                    self.failed_before += 1
            if fail_before:
                context.abort(grpc.StatusCode.UNAVAILABLE, "injected: the request never reached the servicer")
            reply = serve(request, context)  # raises if the servicer aborts: that status goes back
            with self._lock:
                if fail_after:
                    self.failed_after += 1
                    self.lost_chunks += len(getattr(request, "chunks", ()))
                else:
                    self.delivered_duplicates += sum(getattr(reply, "duplicate", ()))
            if fail_after:
                context.abort(grpc.StatusCode.UNAVAILABLE, "injected: the reply was lost after the servicer answered")
            return reply

        return grpc.unary_unary_rpc_method_handler(
            flaky, request_deserializer=handler.request_deserializer, response_serializer=handler.response_serializer
        )
