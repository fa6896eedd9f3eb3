"""The learner service on loopback: registration and leases, GetParams returns the latest version,
a late-joining actor gets the current weights and fills the replay, GetAction acts for actors that
hold no weights and rejects malformed observations naming the field."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import grpc
import numpy as np
import pytest
import torch

from algorithm.config.load import load_config
from algorithm.config.schema import Config
from algorithm.replay import PrioritizedTable
from algorithm.sac.learner import SAC
from ds.actor.actor import DistributedActor, actor_noise
from ds.learner.client import LearnerClient, LeaseExpired, RemotePolicy
from ds.learner.service import SERVICE_NAME, ActorRegistry, LearnerServicer, ParamsStore, PublishedPolicy, serve_learner
from ds.net.params import ParamsPublisher, decode_params, params_spec
from ds.net.rpc import RetryPolicy, set_serving
from ds.net.stream_key import StreamKey
from ds.replay.client import ReplayClient
from ds.replay.service import serve_replay
from envs.make import vector_env_factory

pytestmark = pytest.mark.grpc
ROOT = Path(__file__).resolve().parents[3]
SMALL = ["nn.hidden_units=[16,16]", "replay.batch_size=16", "replay.samples_per_insert=null", "actor.chunk_length=64"]


def config(*overrides: str) -> Config:
    return load_config(ROOT / "envs/gym/pendulum", None, ["sac.seed=0", *SMALL, *overrides]).config


def pendulum_sac(cfg: Config, seed: int) -> SAC:
    spec = vector_env_factory("Pendulum-v1")(1, 0).spec
    cfg = cfg.model_copy(deep=True)
    cfg.sac_config.seed = seed
    return SAC(spec, cfg.sac_config, cfg.nn_config, cfg.replay_config)


@dataclass
class LearnerSide:
    sac: SAC
    publisher: ParamsPublisher
    store: ParamsStore
    registry: ActorRegistry
    client: LearnerClient
    address: str

    def publish(self, version: int) -> None:
        self.publisher.publish(version, self.sac.acting_state_dict())
        assert self.publisher.frames is not None
        self.store.put(version, self.publisher.frames)


@pytest.fixture
def learner_side(request: pytest.FixtureRequest) -> Iterator[LearnerSide]:
    cfg = config()
    sac = pendulum_sac(cfg, seed=1)
    acting = PublishedPolicy(pendulum_sac(cfg, seed=1)) if getattr(request, "param", False) else None
    publisher = ParamsPublisher("tcp://127.0.0.1:*", stream=StreamKey.fresh())
    store, registry = ParamsStore(), ActorRegistry(lease_s=30)
    port = int(publisher.address.rsplit(":", 1)[1])
    servicer = LearnerServicer(sac.spec, registry, store, port, acting, stream=publisher.stream)
    server, learner_port, health = serve_learner(servicer)
    set_serving(health, SERVICE_NAME, True)
    client = LearnerClient(f"127.0.0.1:{learner_port}", sac.spec)
    side = LearnerSide(sac, publisher, store, registry, client, f"127.0.0.1:{learner_port}")
    if acting is not None:
        original = side.publish

        def publish_and_load(version: int) -> None:
            original(version)
            acting.load(version, sac.acting_state_dict())

        side.publish = publish_and_load  # type: ignore[method-assign]
    yield side
    client.close()
    server.stop(None)
    publisher.close()


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_registry_gives_the_lowest_free_index_and_expires_leases() -> None:
    clock = Clock()
    registry = ActorRegistry(lease_s=10, clock=clock)
    a, b, c = (registry.register(f"actor {i}") for i in range(3))
    assert [a.index, b.index, c.index] == [0, 1, 2] and len({a.actor_id, b.actor_id, c.actor_id}) == 3
    clock.now = 8
    assert registry.renew(a.actor_id, 100) and registry.renew(c.actor_id, 5)
    clock.now = 12  # b's lease (to 10) expired; a and c renewed to 18
    assert [x.index for x in registry.alive()] == [0, 2] and registry.expired == 1
    assert not registry.renew(b.actor_id, 0)
    assert registry.register("restarted b", preferred_index=1).index == 1
    assert registry.register("wants a taken index", preferred_index=0).index == 3


def test_heartbeats_say_the_learners_updates_so_far(learner_side: LearnerSide) -> None:
    """What actors estimate their staleness from (ds/actor/staleness.py)."""
    updates = [10]
    learner_side.registry.updates = lambda: updates[0]
    reg = learner_side.client.register("a")
    assert learner_side.client.heartbeat(reg.actor_id, 5).updates == 10
    updates[0] = 40
    assert learner_side.client.heartbeat(reg.actor_id, 9).updates == 40


def test_heartbeat_of_an_unknown_actor_says_register_again(learner_side: LearnerSide) -> None:
    reg = learner_side.client.register("me")
    learner_id, version, run_done, live, _ = learner_side.client.heartbeat(reg.actor_id, 10)
    assert learner_id == reg.learner_id and version == -1 and not run_done and live == 1
    with pytest.raises(LeaseExpired):
        learner_side.client.heartbeat("actor-9-unknown", 0)
    # An id of 20 KB (bad input): still NOT_FOUND naming it, shortened to what a status carries
    # (unshortened, gRPC dropped the answer as RESOURCE_EXHAUSTED: its details passed 8 KiB).
    with pytest.raises(LeaseExpired, match=r"no live actor 'actor-x+ \.\.\.\[\d+ characters\]\.\.\. x+' \(lease"):
        learner_side.client.heartbeat("actor-" + "x" * 20_000, 0)


def test_heartbeats_tell_actors_when_the_runs_budget_is_spent_and_leaving_actors_are_forgotten(
    learner_side: LearnerSide,
) -> None:
    # The learner, not the replay, knows the run's env steps (a restarted replay counts from 0):
    # once it says the run is done, every heartbeat answers so; an actor that has sent its last
    # inserts says it leaves, and once none is live the learner knows nothing more is on its way.
    a, b = learner_side.client.register("a"), learner_side.client.register("b")
    assert (a.live_actors, b.live_actors) == (1, 2)  # each actor's share of the budget's rest is 1 / live
    registry = learner_side.registry
    assert not learner_side.client.heartbeat(a.actor_id, 5).run_done
    assert learner_side.client.heartbeat(b.actor_id, 5).live_actors == 2
    registry.run_done.set()
    assert learner_side.client.heartbeat(a.actor_id, 6).run_done
    assert learner_side.client.leave(a.actor_id, 7)
    assert [lease.index for lease in registry.alive()] == [b.index] and registry.left == 1
    assert learner_side.client.heartbeat(b.actor_id, 6).live_actors == 1  # the one that left is not counted
    with pytest.raises(LeaseExpired):  # gone: a heartbeat without leaving is refused
        learner_side.client.heartbeat(a.actor_id, 7)
    assert learner_side.client.leave(a.actor_id, 7)  # a repeated goodbye is harmless
    assert learner_side.client.leave(b.actor_id, 6)
    assert registry.alive() == [] and registry.left == 2 and registry.expired == 0
    assert learner_side.client.register("c").index == 0  # the indexes are free again


def test_get_params_returns_the_latest_version(learner_side: LearnerSide) -> None:
    with pytest.raises(grpc.RpcError) as e:
        LearnerClient(learner_side.address, learner_side.sac.spec, retry=RetryPolicy(attempts=1)).get_params()
    assert e.value.code() == grpc.StatusCode.UNAVAILABLE and "no parameters published" in e.value.details()
    spec = params_spec(learner_side.sac.acting_state_dict())
    for version in (1, 2, 5):
        with torch.no_grad():
            next(learner_side.sac.models.policy.parameters()).add_(1.0)  # type: ignore[union-attr]
        learner_side.publish(version)
    version, frames = learner_side.client.get_params()
    decoded_version, params = decode_params(frames, spec, stream=learner_side.publisher.stream)
    assert version == decoded_version == 5
    for name, value in learner_side.sac.acting_state_dict().items():
        np.testing.assert_array_equal(params[name], value.numpy(), err_msg=name)


def test_a_late_actor_gets_the_current_weights_and_fills_the_replay(learner_side: LearnerSide, tmp_path: Path) -> None:
    learner_side.publish(3)  # published before the actor exists: a broadcast it can never receive
    cfg = config("base.max_iter=1", "actor.noise_increasing_rate=0.05")  # one 200-step episode
    table = PrioritizedTable.from_config(cfg.replay_config, learner_side.sac.spec.sensors, 1, window=3)
    server, port = serve_replay(table)
    replay = ReplayClient(f"127.0.0.1:{port}", table.sensors, 1)
    learner_side.registry.register("an actor that came first")  # takes index 0
    try:
        actor = DistributedActor(cfg, tmp_path, vector_env_factory("Pendulum-v1"), pendulum_sac(cfg, seed=7),
                                 replay, learner_side.client, "127.0.0.1")  # fmt: skip
        summary = actor.run()
    finally:
        replay.close()
        server.stop(None)
    assert not summary.interrupted and summary.index == 1 and summary.env_steps == 200
    assert actor.params_version == 3 and actor.sac.exploration_noise == pytest.approx(0.05)
    for name, value in learner_side.sac.acting_state_dict().items():
        torch.testing.assert_close(actor.sac.acting_state_dict()[name], value, msg=name)
    assert table.info()["inserted_steps"] == 200  # every chunk arrived (64 + 64 + 64 + 8)
    assert any((tmp_path / "log/actor_1").iterdir())


def test_actor_noise_follows_its_index_up_to_the_maximum() -> None:
    cfg = config("actor.noise_increasing_rate=0.03", "actor.noise_max=0.1")
    assert [actor_noise(cfg, i) for i in range(6)] == pytest.approx([0.0, 0.03, 0.06, 0.09, 0.1, 0.1])
    assert actor_noise(cfg, 5, override=0.5) == 0.5


@pytest.mark.parametrize("learner_side", [True], indirect=True)
def test_get_action_acts_with_the_published_weights(learner_side: LearnerSide) -> None:
    learner_side.publish(1)
    policy = RemotePolicy(learner_side.client, noise=0.2)
    obs = [np.random.default_rng(0).normal(size=(4, 3)).astype(np.float32)]
    actions, logp = policy.act(obs)
    assert actions.shape == (4, 1) and logp.shape == (4,) and np.all(np.abs(actions) <= 1)
    greedy, _ = policy.act(obs, deterministic=True)
    expected, _ = learner_side.sac.act(obs, deterministic=True)
    np.testing.assert_allclose(greedy, expected, rtol=1e-6)

    with pytest.raises(grpc.RpcError) as e:
        learner_side.client.act([obs[0].astype(np.float64)])
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "obs[0] (obs) is float64" in e.value.details()
    with pytest.raises(grpc.RpcError) as e:
        learner_side.client.act(obs, noise=-1.0)
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "noise" in e.value.details()


def test_get_action_without_an_acting_copy_is_a_failed_precondition(learner_side: LearnerSide) -> None:
    learner_side.publish(1)
    with pytest.raises(grpc.RpcError) as e:
        learner_side.client.act([np.zeros((1, 3), np.float32)])
    assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "update_policy_mode" in e.value.details()


def test_the_acting_copy_serves_concurrent_calls() -> None:
    sac = pendulum_sac(config(), seed=1)
    servicer_acting = PublishedPolicy(pendulum_sac(config(), seed=2))
    servicer_acting.load(1, sac.acting_state_dict())
    assert servicer_acting.version == 1
    results: list[np.ndarray] = []
    obs = [np.zeros((2, 3), np.float32)]
    threads = [
        threading.Thread(target=lambda: results.append(servicer_acting.act(obs, None, None, 0.1, False)[0]))
        for _ in range(8)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert len(results) == 8 and all(r.shape == (2, 1) for r in results)
