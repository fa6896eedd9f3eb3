"""Which failed calls are retried: a server that went away (UNAVAILABLE, or CANCELLED because it
shut down with the call in flight) is retried; a refusal surfaces at once."""

from __future__ import annotations

import logging
import threading
import time

import grpc
import pytest

from ds.launch.local import free_port
from ds.net.rpc import (
    LOCAL_HOST,
    MAX_STATUS_DETAILS,
    RetryPolicy,
    call_with_retry,
    peer_gone,
    peer_unresponsive,
    status_details,
    wait_until_serving,
)

NO_WAIT = RetryPolicy(attempts=3, initial_backoff_s=0.0, max_backoff_s=0.0)


class Failure(grpc.RpcError):
    def __init__(self, code: grpc.StatusCode) -> None:
        self._code = code

    def code(self) -> grpc.StatusCode:
        return self._code


class FlakyRpc:
    """Fails with ``codes`` in turn, then answers "ok"; counts the calls."""

    def __init__(self, *codes: grpc.StatusCode) -> None:
        self.codes = list(codes)
        self.calls = 0

    def __call__(self, request: object, timeout: float) -> str:
        self.calls += 1
        if self.codes:
            raise Failure(self.codes.pop(0))
        return "ok"


@pytest.mark.parametrize("code", [grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.CANCELLED])
def test_a_server_that_went_away_is_retried(code: grpc.StatusCode) -> None:
    rpc = FlakyRpc(code, grpc.StatusCode.UNAVAILABLE)
    assert call_with_retry(rpc, None, 1.0, NO_WAIT) == "ok"
    assert rpc.calls == 3


def test_retries_end_with_the_last_failure() -> None:
    rpc = FlakyRpc(*[grpc.StatusCode.UNAVAILABLE] * 2, grpc.StatusCode.CANCELLED)
    with pytest.raises(grpc.RpcError) as raised:
        call_with_retry(rpc, None, 1.0, NO_WAIT)
    assert raised.value.code() == grpc.StatusCode.CANCELLED
    assert rpc.calls == 3


@pytest.mark.parametrize(
    "code", [grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.RESOURCE_EXHAUSTED]
)
def test_a_refusal_is_not_retried(code: grpc.StatusCode) -> None:
    rpc = FlakyRpc(code)
    with pytest.raises(grpc.RpcError):
        call_with_retry(rpc, None, 1.0, NO_WAIT)
    assert rpc.calls == 1


@pytest.mark.parametrize("code", list(grpc.StatusCode))
def test_an_unresponsive_peer_is_one_gone_or_past_its_deadline(code: grpc.StatusCode) -> None:
    """What the roles wait out (a stopped process keeps its connections: only the deadline tells)
    versus what surfaces: a refusal is never mistaken for a peer to wait for."""
    waited = {grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.CANCELLED, grpc.StatusCode.DEADLINE_EXCEEDED}
    assert peer_unresponsive(code) == (code in waited)
    assert peer_gone(code) == (code in waited - {grpc.StatusCode.DEADLINE_EXCEEDED})


def test_status_details_keep_both_ends_within_what_a_status_carries() -> None:
    assert status_details("short") == "short"
    long = "/run/replay/bad.npz: not readable (" + "x" * 20_000 + ") the end"
    shortened = status_details(long)
    assert len(shortened) <= MAX_STATUS_DETAILS and shortened.startswith("/run/replay/bad.npz: not readable (")
    assert shortened.endswith(") the end") and f"...[{len(long) - MAX_STATUS_DETAILS + 40} characters]..." in shortened


def test_a_role_waiting_for_a_peer_says_once_after_a_bounded_time_what_it_waits_for_and_how_to_fix_it(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Nothing answers at the address: the wait goes on (peers start in any order), but after
    ``warn_after_s`` one WARNING names the peer, the address and what to do."""
    address = f"{LOCAL_HOST}:{free_port()}"
    stop = threading.Event()
    threading.Timer(1.5, stop.set).start()
    with grpc.insecure_channel(address) as channel, caplog.at_level(logging.INFO, logger="asac"):
        assert not wait_until_serving(channel, "asac.ReplayService", "replay", address, stop, warn_after_s=0.3)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1, warnings
    assert f"no replay has answered at {address} for" in warnings[0]
    assert "--replay_host/--replay_port" in warnings[0] and "net_config.replay_host" in warnings[0]


@pytest.mark.slow
def test_a_role_that_started_long_before_its_peer_connects_within_seconds_of_the_peer_serving() -> None:
    """A role waits for its peer through a channel from ``open_channel``; the peer starts 16.5 s later
    (a slow import, a pod rescheduled). gRPC's own reconnect backoff (1 s growing 1.6x) would next try
    at ~26 s and fail every health check in between; the channel's 2 s cap notices the peer in ~2 s."""
    from concurrent import futures

    from grpc_health.v1 import health, health_pb2, health_pb2_grpc

    from ds.net.security import Credentials, open_channel

    address = f"{LOCAL_HOST}:{free_port()}"
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=2))
    servicer = health.HealthServicer()
    servicer.set("asac.LearnerService", health_pb2.HealthCheckResponse.SERVING)
    health_pb2_grpc.add_HealthServicer_to_server(servicer, server)
    serving_at: list[float] = []

    def start() -> None:  # the port is bound here: gRPC listens from add_insecure_port on
        server.add_insecure_port(address)
        server.start()
        serving_at.append(time.monotonic())

    threading.Timer(16.5, start).start()
    try:
        with open_channel(address, "learner", Credentials(), []) as channel:
            assert wait_until_serving(channel, "asac.LearnerService", "learner", address, threading.Event())
            noticed_after = time.monotonic() - serving_at[0]
    finally:
        server.stop(0)
    assert noticed_after < 4.0, f"the waiting role noticed its peer {noticed_after:.1f} s after it was serving"
