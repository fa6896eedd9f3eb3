"""An actor held back by the replay's rate limiter, end to end (ds/actor/actor.py with its sink,
ds/actor/sink.py): at the end of the run's budget while the learner is behind, the actor stops
stepping once what it holds takes the replay to the budget, and ends on it; stopped by a signal
while held back, it stops promptly and stores what it holds past the rate limiter. Either way
every step it collected is stored (none is thrown away, nothing is logged as unsent). Its heartbeat
thread ends quietly when the channel closes under a heartbeat on its way."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from algorithm.replay import PrioritizedTable, RateLimiter, SampleTimeout
from algorithm.sac.learner import SAC
from ds.actor.actor import DistributedActor
from ds.learner.client import LearnerClient, Registration
from ds.replay.client import LAST_INSERTS_WAIT_S, ReplayClient
from ds.replay.service import serve_replay
from envs.make import vector_env_factory
from tests.ds.actor.test_actor_reconnect import CONFIG, FAST_RETRY, SPEC, Learner, free_port

pytestmark = pytest.mark.grpc
MAX_STEP = 600
N_ENVS = 2


class HeldBackRun:
    """A replay whose rate limiter holds inserts back (a sampler standing in for the learner draws 8
    windows per inserted step, slower than actors step, until the replay holds ``learn_until``
    steps), a learner service, and actors of ``N_ENVS`` Pendulum envs built against them; the run's
    budget is ``MAX_STEP``. :meth:`close` stops all of it."""

    def __init__(self, learn_until: int, sample_every_s: float) -> None:
        limiter = RateLimiter(samples_per_insert=8.0, min_size_to_sample=64, tolerance=64.0)
        self.table = table = PrioritizedTable(100_000, SPEC.sensors, SPEC.action.size, 3, rate_limiter=limiter, seed=0)
        self.server, self.replay_port = serve_replay(table, "127.0.0.1:0")
        self.learner_port = free_port()
        self.learner = Learner(self.learner_port, version=1, seed=1)
        self.learning = threading.Event()

        def learn() -> None:
            while not self.learning.wait(sample_every_s) and table.info()["inserted_steps"] < learn_until:
                with contextlib.suppress(SampleTimeout):
                    table.sample(64, timeout=0)

        self.sampler = threading.Thread(target=learn, daemon=True)
        self.sampler.start()
        self.config = CONFIG.model_copy(deep=True)
        self.config.base_config.max_step, self.config.base_config.n_agents = MAX_STEP, N_ENVS
        self.clients: list[ReplayClient | LearnerClient] = []

    def actor(self, run_dir: Path, name: str) -> DistributedActor:
        config = self.config
        replay = ReplayClient(f"127.0.0.1:{self.replay_port}", SPEC.sensors, SPEC.action.size, retry=FAST_RETRY)
        learner = LearnerClient(f"127.0.0.1:{self.learner_port}", SPEC, retry=FAST_RETRY, rpc_timeout_s=2.0)
        self.clients += [replay, learner]
        sac = SAC(SPEC, config.sac_config, config.nn_config, config.replay_config)
        make_env = vector_env_factory("Pendulum-v1")
        return DistributedActor(
            config, run_dir, make_env, sac, replay, learner, "127.0.0.1", heartbeat_s=0.2, name=name
        )

    def close(self) -> None:
        self.learning.set()
        self.sampler.join()
        for client in self.clients:
            client.close()
        self.learner.stop()
        self.server.stop(None)


@pytest.mark.parametrize("stopped_by", ["budget", "signal"])
def test_an_actor_held_back_at_the_end_stops_at_once_and_stores_everything_it_collected(
    stopped_by: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # The rate limiter holds the actor's inserts back. "budget": the learner stops drawing once the
    # replay has MAX_STEP steps (finished). "signal": it stops drawing at half of it, and the actor
    # is stopped (Ctrl-C) while held back, so what it holds can only be stored past the rate limiter.
    run = HeldBackRun(MAX_STEP if stopped_by == "budget" else MAX_STEP // 2, sample_every_s=0.01)
    table, sampler = run.table, run.sampler
    actor = run.actor(tmp_path, "actor 0")
    thread = threading.Thread(target=actor.run, daemon=True)

    def stopping() -> bool:
        if stopped_by == "signal" and not sampler.is_alive() and actor.sink.backlog() > 0:
            actor.stop.set()  # held back, the learner gone: Ctrl-C
        return actor.done or actor.stop.is_set()

    try:
        with caplog.at_level(logging.INFO, logger="asac.actor"):
            thread.start()
            deadline = time.monotonic() + 60
            while not stopping():
                assert time.monotonic() < deadline and thread.is_alive(), "the actor never stopped"
                time.sleep(0.02)
            done_at = time.monotonic()
            thread.join(30)
            stopped_s = time.monotonic() - done_at
    finally:
        run.close()
    assert not thread.is_alive()
    sink, info = actor.sink, table.info()
    assert info["insert_waits"] > 0  # the rate limiter held the actor back
    # The last inserts wait for the learner LAST_INSERTS_WAIT_S in all (here in vain: this learner
    # stopped, a real one trains until the actors leave); an insert already waiting finishes its
    # wait; nothing else waits.
    assert stopped_s < LAST_INSERTS_WAIT_S + 3 * sink.timeout_s
    # Nothing thrown away: every collected step stored, the open chunks included.
    assert actor.env_steps == sink.inserted_steps == info["inserted_steps"] and sink.unsent_steps == 0
    assert not [r.getMessage() for r in caplog.records if "were not inserted" in r.getMessage()]
    if stopped_by == "signal":  # what it held when stopped: after the wait, past the rate limiter
        assert info["stored_past_limiter"] > 0 and info["inserted_steps"] < MAX_STEP
    else:
        # The budget is exact: the actor stopped stepping once what it held (in flight, queued, in
        # open chunks) would take the replay to MAX_STEP, so it ends within one step of its envs past
        # it (it stepped on up to 2 chunks per env, 64 steps here, until the replay's answer said so).
        assert MAX_STEP <= info["inserted_steps"] < MAX_STEP + N_ENVS, info["inserted_steps"]


ACTORS = 4


def test_several_actors_held_back_at_the_end_pass_the_budget_by_less_than_a_chunk_per_env(tmp_path: Path) -> None:
    # Four actors against one replay whose rate limiter holds them back (the learner is behind), up
    # to the budget. Each stops once what it holds reaches its share of what is left, (max_step -
    # count) / live actors, so together they pass MAX_STEP by less than a chunk per env of each
    # actor; with the whole rest as each one's share (each stopping on count + its own holdings
    # alone) the others' holdings came on top (840 for 600).
    run = HeldBackRun(MAX_STEP, sample_every_s=0.005)
    table, config = run.table, run.config
    actors = [run.actor(tmp_path / f"a{i}", f"actor {i}") for i in range(ACTORS)]
    threads = [threading.Thread(target=actor.run, daemon=True) for actor in actors]
    try:
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(90)
    finally:
        run.close()
    assert not any(thread.is_alive() for thread in threads)
    info = table.info()
    assert info["insert_waits"] > 0  # the rate limiter held the actors back
    assert sum(actor.env_steps for actor in actors) == info["inserted_steps"]  # nothing thrown away
    assert max(actor.live_actors for actor in actors) == ACTORS
    # Measured 28-106 past the budget (240 without the shares): less than a chunk per env of each actor.
    chunk = config.actor_config.chunk_length
    assert MAX_STEP <= info["inserted_steps"] < MAX_STEP + ACTORS * N_ENVS * chunk, info["inserted_steps"]


def test_a_heartbeat_on_its_way_when_the_channel_closes_ends_quietly(tmp_path: Path) -> None:
    """The run is over (``_beats_done``) and the role closes the learner channel while a heartbeat
    is on its way: gRPC raises ``ValueError: Cannot invoke RPC on closed channel!``; the heartbeat
    thread ends without it (no traceback, nothing for the acting thread to raise)."""
    replay = ReplayClient(f"127.0.0.1:{free_port()}", SPEC.sensors, SPEC.action.size)
    learner = LearnerClient(f"127.0.0.1:{free_port()}", SPEC, retry=FAST_RETRY, rpc_timeout_s=1.0)
    sac = SAC(SPEC, CONFIG.sac_config, CONFIG.nn_config, CONFIG.replay_config)
    make_env = vector_env_factory("Pendulum-v1")
    actor = DistributedActor(CONFIG, tmp_path, make_env, sac, replay, learner, "127.0.0.1", heartbeat_s=0.01)
    actor.registration = Registration("actor-0-x", 0, "learner-x", 0, 30.0)
    heartbeat = learner.heartbeat

    def closing_heartbeat(*args: Any) -> tuple[str, int]:
        actor._beats_done.set()  # run() has ended meanwhile ...
        learner.close()  # ... and the role closed the channel
        return heartbeat(*args)

    learner.heartbeat = closing_heartbeat  # type: ignore[method-assign]
    actor._heartbeats()  # returns: no ValueError
    assert actor._beat_error is None
    with pytest.raises(ValueError, match="closed channel"):
        heartbeat("actor-0-x", 0)  # what the heartbeat on its way met
    replay.close()
