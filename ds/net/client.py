"""What every gRPC client of ASAC shares: the channel to one server, its stub, a deadline and a
retry policy for each call, and closing.

Usage, for a service's client::

    class ReplayClient(RpcClient):
        def __init__(self, address, ..., credentials=NO_CREDENTIALS):
            super().__init__(address, security.REPLAY, replay_pb2_grpc.ReplayServiceStub,
                             max_message_bytes=..., rpc_timeout_s=..., retry=..., credentials=credentials)

        def info(self):
            return self._unary(self._stub.Info, replay_pb2.InfoRequest())  # errors mapped by the subclass

The channel reconnects by itself; other services of the same server (health) may use it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Self, TypeVar

import grpc

from ds.net import security
from ds.net.rpc import RetryPolicy, call_with_retry, channel_options
from ds.net.security import NO_CREDENTIALS, Credentials

_T = TypeVar("_T")


class RpcClient:
    """A channel to the ``role`` server at ``address`` and its ``stub``; thread-safe, as gRPC's are.
    Every call through :meth:`_unary` has a deadline (``rpc_timeout_s`` unless given) and retries
    UNAVAILABLE per ``retry``; other errors surface as ``grpc.RpcError`` for the subclass to name."""

    def __init__(
        self,
        address: str,
        role: str,
        stub: Callable[[grpc.Channel], Any],
        *,
        max_message_bytes: int,
        rpc_timeout_s: float,
        retry: RetryPolicy | None = None,
        credentials: Credentials = NO_CREDENTIALS,
    ) -> None:
        self.address = address
        self.rpc_timeout_s = float(rpc_timeout_s)
        self.retry = retry or RetryPolicy()
        self.channel = security.open_channel(address, role, credentials, channel_options(max_message_bytes))
        self._stub = stub(self.channel)

    def close(self) -> None:
        self.channel.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _unary(self, rpc: Callable[..., _T], request: Any, deadline_s: float | None = None) -> _T:
        """One unary call with a deadline, retrying UNAVAILABLE with backoff (:func:`call_with_retry`)."""
        return call_with_retry(rpc, request, self.rpc_timeout_s if deadline_s is None else deadline_s, self.retry)
