"""Which failed calls are retried: a server that went away (UNAVAILABLE, or CANCELLED because it
shut down with the call in flight) is retried; a refusal surfaces at once."""

from __future__ import annotations

import logging
import threading

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
