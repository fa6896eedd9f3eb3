"""Peers that disappear: an actor keeps acting while its learner or replay is gone, and reconnects
when they come back on the same address (a restarted learner's versions start over; the actor
registers again under its old index and takes them)."""

from __future__ import annotations

import logging
import re
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import grpc
import pytest
import torch

from algorithm.config.load import load_config
from algorithm.replay import PrioritizedTable
from algorithm.sac.learner import SAC
from ds.actor import actor as actor_module
from ds.actor.actor import DistributedActor
from ds.learner.client import LearnerClient
from ds.learner.service import SERVICE_NAME, ActorRegistry, LearnerServicer, ParamsStore, serve_learner
from ds.net.params import ParamsError, ParamsPublisher
from ds.net.rpc import RetryPolicy, set_serving
from ds.net.stream_key import StreamKey
from ds.replay.client import ReplayClient
from ds.replay.service import serve_replay
from envs.make import vector_env_factory

pytestmark = pytest.mark.grpc
ROOT = Path(__file__).resolve().parents[3]
CONFIG = load_config(
    ROOT / "envs/gym/pendulum",
    None,
    ["sac.seed=0", "nn.hidden_units=[16,16]", "replay.samples_per_insert=null", "actor.chunk_length=16"],
).config
SPEC = vector_env_factory("Pendulum-v1")(1, 0).spec
FAST_RETRY = RetryPolicy(attempts=2, initial_backoff_s=0.05, max_backoff_s=0.1)


def until(condition: Callable[[], bool], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out waiting for the condition"
        time.sleep(0.05)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Learner:
    """A learner service on ``port`` that has published ``version`` of a SAC initialised with ``seed``."""

    def __init__(self, port: int, version: int, seed: int, token: bytes | None = None) -> None:
        cfg = CONFIG.model_copy(deep=True)
        cfg.sac_config.seed = seed
        self.sac = SAC(SPEC, cfg.sac_config, cfg.nn_config, cfg.replay_config)
        self.publisher = ParamsPublisher("tcp://127.0.0.1:*", token=token, stream=StreamKey.fresh())
        self.store = store = ParamsStore()
        self.publish(version)
        params_port = int(self.publisher.address.rsplit(":", 1)[1])
        self.servicer = LearnerServicer(
            SPEC, ActorRegistry(lease_s=30), store, params_port, stream=self.publisher.stream
        )
        self.server, bound, health = serve_learner(self.servicer, f"127.0.0.1:{port}")
        assert bound == port
        set_serving(health, SERVICE_NAME, True)

    def publish(self, version: int) -> None:
        """Publish the SAC's acting weights as ``version`` (ZeroMQ and GetParams)."""
        self.publisher.publish(version, self.sac.acting_state_dict())
        assert self.publisher.frames is not None
        self.store.put(version, self.publisher.frames)

    def stop(self) -> None:
        self.server.stop(None)
        self.publisher.close()


class Replay:
    def __init__(self, port: int) -> None:
        self.table = PrioritizedTable(100_000, SPEC.sensors, SPEC.action.size, window=3)
        self.server, bound = serve_replay(self.table, f"127.0.0.1:{port}")
        assert bound == port

    def inserted(self) -> int:
        return int(self.table.info()["inserted_steps"])

    def stop(self) -> None:
        self.server.stop(None)


@contextmanager
def running_actor(
    replay_port: int, learner_port: int, tmp_path: Path, token: bytes | None = None
) -> Iterator[DistributedActor]:
    replay = ReplayClient(f"127.0.0.1:{replay_port}", SPEC.sensors, SPEC.action.size, retry=FAST_RETRY)
    learner = LearnerClient(f"127.0.0.1:{learner_port}", SPEC, retry=FAST_RETRY, rpc_timeout_s=2.0)
    sac = SAC(SPEC, CONFIG.sac_config, CONFIG.nn_config, CONFIG.replay_config)
    stop = threading.Event()
    actor = DistributedActor(CONFIG, tmp_path, vector_env_factory("Pendulum-v1"), sac, replay, learner,
                             "127.0.0.1", stop=stop, heartbeat_s=0.2, token=token)  # fmt: skip
    thread = threading.Thread(target=actor.run, daemon=True)
    thread.start()
    try:
        yield actor
    finally:
        stop.set()
        thread.join(30)
        replay.close()
        learner.close()
    assert not thread.is_alive()


def same_weights(actor: DistributedActor, sac: SAC) -> bool:
    mine = actor.sac.acting_state_dict()
    return all(torch.equal(mine[k], v) for k, v in sac.acting_state_dict().items())


def test_an_actor_reconnects_to_a_restarted_learner(tmp_path: Path) -> None:
    replay_port, learner_port = free_port(), free_port()
    replay, first = Replay(replay_port), Learner(learner_port, version=10, seed=1)
    try:
        with running_actor(replay_port, learner_port, tmp_path) as actor:
            until(lambda: actor.params_version == 10 and same_weights(actor, first.sac))
            first.stop()  # the learner dies: the actor acts on with what it has and fills the replay
            steps = replay.inserted()
            until(lambda: replay.inserted() > steps + 50)
            second = Learner(learner_port, version=2, seed=2)  # restarted: its versions start over
            try:
                until(lambda: actor.params_version == 2 and same_weights(actor, second.sac))
                assert actor.registration is not None
                assert actor.registration.learner_id == second.servicer.learner_id
                assert [a.index for a in second.servicer.registry.alive()] == [0]  # its old index
            finally:
                second.stop()
    finally:
        replay.stop()


def test_an_actor_keeps_its_chunks_while_the_replay_restarts(tmp_path: Path) -> None:
    replay_port, learner_port = free_port(), free_port()
    learner, first = Learner(learner_port, version=1, seed=1), Replay(replay_port)
    try:
        with running_actor(replay_port, learner_port, tmp_path) as actor:
            until(lambda: first.inserted() >= 32)
            first.stop()
            until(lambda: actor.sink.unavailable >= 1)  # inserts fail and are retried, not dropped
            second = Replay(replay_port)
            try:
                until(lambda: second.inserted() >= 32)
                assert actor.sink.unsent_steps == 0
            finally:
                second.stop()
    finally:
        learner.stop()


def test_an_actor_takes_only_parameters_signed_with_the_runs_token(tmp_path: Path) -> None:
    replay_port, learner_port = free_port(), free_port()
    replay, learner = Replay(replay_port), Learner(learner_port, version=1, seed=1, token=b"run secret")
    try:
        with running_actor(replay_port, learner_port, tmp_path, token=b"run secret") as actor:
            until(lambda: actor.params_version == 1)  # GetParams at registration, MAC checked
            with torch.no_grad():
                for p in learner.sac.models.parameters():
                    p.add_(0.5)
            version = 1
            while actor.params_version == 1:  # a subscriber that joined late misses early versions
                version += 1
                learner.publish(version)
                time.sleep(0.1)
                assert version < 300, "the actor never took a signed broadcast"
            assert same_weights(actor, learner.sac)

        replay_client = ReplayClient(f"127.0.0.1:{replay_port}", SPEC.sensors, SPEC.action.size)
        learner_client = LearnerClient(f"127.0.0.1:{learner_port}", SPEC)
        sac = SAC(SPEC, CONFIG.sac_config, CONFIG.nn_config, CONFIG.replay_config)
        for token in (b"another secret", None):
            stranger = DistributedActor(CONFIG, tmp_path, vector_env_factory("Pendulum-v1"), sac, replay_client,
                                        learner_client, "127.0.0.1", token=token)  # fmt: skip
            with pytest.raises(ParamsError, match="net_config.token_file"):
                stranger.run()
            assert stranger.params_version == -1
    finally:
        learner.stop()
        replay.stop()


def test_an_actor_warns_of_a_gone_learner_only_once_it_has_been_gone_a_while_and_never_when_told_to_stop(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A local run stops the learner before the actors (its orderly stop): a heartbeat of an actor
    already told to stop that finds no learner is expected, and so is one in the seconds between the
    learner closing its server and the launcher telling the actors (seen as a WARNING at the end of a
    Ctrl-C'd run). Neither warns; a learner unreachable for ``LEARNER_GONE_WARN_S`` is warned about."""
    monkeypatch.setattr(actor_module, "LEARNER_GONE_WARN_S", 0.5)
    port = free_port()  # nothing listens: a real UNAVAILABLE
    replay = ReplayClient(f"127.0.0.1:{free_port()}", SPEC.sensors, SPEC.action.size, retry=FAST_RETRY)
    learner = LearnerClient(f"127.0.0.1:{port}", SPEC, retry=FAST_RETRY, rpc_timeout_s=2.0)
    sac = SAC(SPEC, CONFIG.sac_config, CONFIG.nn_config, CONFIG.replay_config)
    stop = threading.Event()
    actor = DistributedActor(CONFIG, tmp_path, vector_env_factory("Pendulum-v1"), sac, replay, learner,
                             "127.0.0.1", stop=stop)  # fmt: skip
    try:
        with pytest.raises(grpc.RpcError) as gone:
            learner.heartbeat("actor-0", 0)
        assert gone.value.code() == grpc.StatusCode.UNAVAILABLE
        with caplog.at_level(logging.WARNING):
            stop.set()
            actor._learner_unreachable(gone.value)
            time.sleep(0.6)
            actor._learner_unreachable(gone.value)
            assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text
            stop.clear()
            actor._learner_unreachable(gone.value)  # the first failure of a running actor: no warning yet
            assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text
            time.sleep(0.6)
            actor._learner_unreachable(gone.value)
            assert re.search(r"learner at \S+ unreachable \(UNAVAILABLE\) for \d+ s", caplog.text), caplog.text
        served = Learner(port, version=0, seed=0)  # the learner is back: registering again restarts the clock
        try:
            actor._rejoin.set()
            deadline = time.monotonic() + 20
            while actor._rejoin.is_set() and time.monotonic() < deadline:  # the channel retries after its backoff
                actor._last_rejoin = -float("inf")
                actor._between()
                time.sleep(0.2)
            assert actor.registration is not None and not actor._rejoin.is_set()
            assert not actor._learner_link.down  # back: the next failure starts a new outage
        finally:
            served.stop()
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            actor._learner_unreachable(gone.value)  # gone again: the first failure of a new outage
            assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text
    finally:
        replay.close()
        learner.close()


class LearnerGoneAtGetParams(LearnerClient):
    """A client whose learner stops its server just as the actor asks for the first parameters (and,
    with ``stop``, the actor is told to stop at that moment: a Ctrl-C during a local run's start-up,
    whose launcher stops the learner first)."""

    def __init__(self, address: str, learner: Learner, stop: threading.Event | None) -> None:
        super().__init__(address, SPEC, retry=FAST_RETRY, rpc_timeout_s=2.0)
        self.served, self.stop_event = learner, stop

    def get_params(self) -> tuple[int, list[bytes]]:
        self.served.stop()
        if self.stop_event is not None:
            self.stop_event.set()
        return super().get_params()


@pytest.mark.parametrize("told_to_stop", [True, False])
def test_an_actor_stopped_during_start_up_while_its_learner_goes_ends_cleanly_and_only_then(
    tmp_path: Path, told_to_stop: bool
) -> None:
    """The race a Ctrl-C'd ``main_ds.py ... local`` run hit (a traceback from the actor's GetParams after the
    learner had stopped). Told to stop, the actor ends with a stopped summary; a learner that goes away
    without a stop is still an error."""
    replay_port, learner_port = free_port(), free_port()
    replay, served = Replay(replay_port), Learner(learner_port, version=1, seed=1)
    stop = threading.Event()
    replay_client = ReplayClient(f"127.0.0.1:{replay_port}", SPEC.sensors, SPEC.action.size, retry=FAST_RETRY)
    learner_client = LearnerGoneAtGetParams(f"127.0.0.1:{learner_port}", served, stop if told_to_stop else None)
    sac = SAC(SPEC, CONFIG.sac_config, CONFIG.nn_config, CONFIG.replay_config)
    actor = DistributedActor(CONFIG, tmp_path, vector_env_factory("Pendulum-v1"), sac, replay_client,
                             learner_client, "127.0.0.1", stop=stop)  # fmt: skip
    try:
        if told_to_stop:
            summary = actor.run()
            assert summary.interrupted and summary.env_steps == 0
        else:
            with pytest.raises(grpc.RpcError) as gone:
                actor.run()
            assert gone.value.code() == grpc.StatusCode.UNAVAILABLE
    finally:
        replay_client.close()
        learner_client.close()
        replay.stop()
        served.stop()
