"""Parameters come only from the learner an actor registered with (issue 17): a process that sends on
the learner's parameter port (after a kill -9 it may bind the freed port) under another stream key is
refused, whatever version it claims, with a token and without; the real learner's next version is
taken; and once the actor registers with a restarted learner (a new key) it follows that one.

Real ZeroMQ sockets and, for the actor, a real learner service and replay on loopback (the ones of
tests/ds/actor/test_actor_reconnect.py)."""

from __future__ import annotations

import secrets
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import zmq

from algorithm.sac.learner import SAC
from ds.net.params import ParamsError, ParamsPublisher, ParamsSubscriber, decode_params, encode_params
from ds.net.stream_key import StreamKey
from tests.ds.actor.test_actor_reconnect import CONFIG, Learner, Replay, free_port, running_actor, same_weights
from tests.ds.actor.test_actor_reconnect import SPEC as PENDULUM
from tests.ds.net.test_params import SPEC, counts, ctx, reaches, small_params, until

__all__ = ["ctx"]  # the fixture
FORGED = 10**12
TOKENS = pytest.mark.parametrize("token", [None, b"run secret"], ids=["no token", "token"])


def forger_of(stream: StreamKey) -> StreamKey:
    """What a process that is not that learner can have: its id (heartbeats and logs show it), not its secret."""
    return StreamKey(stream.learner_id, secrets.token_bytes(32))


def paced(action: Callable[[], object]) -> Callable[[], None]:
    def step() -> None:
        action()
        time.sleep(0.05)

    return step


@TOKENS
def test_a_subscriber_refuses_another_publisher_whatever_its_version_and_takes_its_learners_next(
    ctx: zmq.Context, token: bytes | None
) -> None:
    """The forger holds the run's token too (a token holder that is not the learner): another stream
    key is enough to be refused. ``GetParams`` hands out the same frames: refused the same way."""
    real = StreamKey.fresh()
    with (
        ParamsPublisher("tcp://127.0.0.1:*", token=token, stream=real, context=ctx) as learner,
        ParamsPublisher("tcp://127.0.0.1:*", token=token, stream=forger_of(real), context=ctx) as forger,
        ParamsSubscriber(learner.address, SPEC, token=token, stream=real, context=ctx) as sub,
    ):
        sub._socket.connect(forger.address)  # the forger's messages reach it, as on the learner's port
        learner.publish(1, small_params(1))
        until(reaches(sub, 1), learner.republish)
        forger.publish(FORGED, small_params(9))
        until(counts(sub, "rejected", 3), forger.republish)
        assert sub.version == 1 and sub.last_error is not None
        assert f"not signed by learner {real.learner_id}" in sub.last_error, sub.last_error
        learner.publish(2, small_params(2))
        until(reaches(sub, 2), lambda: (forger.republish(), learner.republish()))  # the learner's next is taken
        assert sub.accepted == 2
        assert forger.frames is not None and learner.frames is not None
        with pytest.raises(ParamsError, match="MAC does not verify"):
            decode_params(forger.frames, SPEC, token, stream=real)
        version, params = decode_params(learner.frames, SPEC, token, stream=real)
        assert version == 2
        np.testing.assert_array_equal(params["b"], np.arange(5) + 2)


def test_with_a_token_the_learners_secret_alone_does_not_sign() -> None:
    """With a token, a copy of the learner's secret (it travels in RegisterActorReply, in plaintext
    without TLS) is not enough to forge: the MAC key needs the token as well."""
    real = StreamKey.fresh()
    for guess in (None, b"another secret"):
        frames = encode_params(FORGED, small_params(9), guess, stream=real)
        with pytest.raises(ParamsError, match="MAC does not verify"):
            decode_params(frames, SPEC, b"run secret", stream=real)


def bind_when_free(address: str, token: bytes | None, stream: StreamKey) -> ParamsPublisher:
    """A publisher on ``address`` as soon as the OS lets it bind there."""
    deadline = time.monotonic() + 10
    while True:
        try:
            return ParamsPublisher(address, token=token, stream=stream)
        except zmq.ZMQError:
            assert time.monotonic() < deadline, f"{address} stayed taken"
            time.sleep(0.05)


@pytest.mark.grpc
@TOKENS
def test_an_actor_refuses_a_process_that_took_its_dead_learners_port_and_follows_the_restarted_learner(
    tmp_path: Path, token: bytes | None
) -> None:
    """The probe of issue 17: the learner dies (kill -9 frees its ports); another process binds its
    parameter port and publishes other weights as version 10**12 (signed with the run's token, if
    any, but not under the learner's key). The actor refuses every message (counted), keeps the
    weights it has, and takes the restarted learner's weights once it registers with it."""
    cfg = CONFIG.model_copy(deep=True)
    cfg.sac_config.seed = 3
    forged_policy = SAC(PENDULUM, cfg.sac_config, cfg.nn_config, cfg.replay_config).acting_state_dict()
    replay_port, learner_port = free_port(), free_port()
    replay, first = Replay(replay_port), Learner(learner_port, version=1, seed=1, token=token)
    try:
        with running_actor(replay_port, learner_port, tmp_path, token=token) as actor:
            until(lambda: actor.params_version == 1 and same_weights(actor, first.sac), paced(lambda: None), 30)
            first.stop()  # as kill -9: both of its ports are free
            assert first.publisher.stream is not None
            forger = bind_when_free(first.publisher.address, token, forger_of(first.publisher.stream))
            try:
                forger.publish(FORGED, forged_policy)
                until(lambda: actor.params_rejected >= 3, paced(forger.republish), 30)
                assert actor.params_version == 1 and same_weights(actor, first.sac)
                second = Learner(learner_port, version=2, seed=2, token=token)  # restarted: a new id and key
                try:
                    until(lambda: actor.params_version == 2 and same_weights(actor, second.sac),
                          paced(forger.republish), 30)  # fmt: skip
                    assert actor.registration is not None
                    assert actor.registration.learner_id == second.servicer.learner_id
                    rejected = actor.params_rejected
                    second.publish(3)
                    until(lambda: actor.params_version == 3, paced(second.publisher.republish), 30)
                    assert same_weights(actor, second.sac) and actor.params_rejected == rejected
                finally:
                    second.stop()
            finally:
                forger.close()
    finally:
        replay.stop()
