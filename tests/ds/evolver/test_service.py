"""The evolver on loopback: registration with sampled configs, PostReward that never waits for a round,
CEM rounds over the elites' weights fetched from real learner servers, retirement, actor and replay
assignment, leases, and clear status codes for bad input (restart from the saved state:
test_state.py)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import grpc
import numpy as np
import pytest

from algorithm.config.load import config_from_yaml
from ds.evolver.client import EvolverRequestRejected
from ds.evolver.state import (
    Instruction,
    LearnerRetired,
    NoWorkYet,
    UnknownAssignment,
    UnknownLearner,
)
from ds.learner.client import LearnerClient
from ds.learner.service import ActorRegistry, LearnerServicer, ParamsStore, serve_learner
from ds.net.params import decode_params, params_spec
from protos import evolver_pb2, evolver_pb2_grpc
from tests.ds.evolver.evolver_setup import LEASE_S, SPEC, Setup, evolver_config, register, until, weights_of

pytestmark = pytest.mark.grpc


# ---------------------------------------------------------------------- learners


def test_registration_gives_distinct_ids_and_configs_with_their_draws(setup: Setup) -> None:
    _, client = setup.evolver(evolver_config())
    registrations = [client.register_learner(f"l{k}", "", 61001 + k) for k in range(4)]
    assert [r.learner_id for r in registrations] == [0, 1, 2, 3]
    for r in registrations:
        config = config_from_yaml(r.config_yaml, f"learner {r.learner_id}")
        assert set(r.params) == {"sac_config.n_step", "sac_config.gamma"}
        assert config.sac_config.n_step == r.params["sac_config.n_step"] in (1, 3, 5)
        assert config.sac_config.gamma == r.params["sac_config.gamma"] and 0.9 <= config.sac_config.gamma <= 0.99
        assert config.random_params == {} and r.experiment == "exp" and r.lease_s == LEASE_S
    assert len({r.params["sac_config.gamma"] for r in registrations}) == 4
    info = client.info()
    assert [(x.host, x.learner_port, x.live) for x in info.learners] == [
        ("127.0.0.1", 61001 + k, True) for k in range(4)
    ]


def test_post_reward_answers_at_once_while_a_round_waits_for_slow_weights(setup: Setup) -> None:
    slow, fast = setup.learner(2.0, delay_s=1.5), setup.learner(1.0)
    evolver, client = setup.evolver(evolver_config(), real_clock=True, check_every_s=0.05, save_every_s=0.05)
    evolver.start()
    a, b = register(client, [slow, fast])
    for value_a, value_b in [(10.0, 1.0), (12.0, 2.0)]:
        client.post_reward(a, value_a, 100)
        client.post_reward(b, value_b, 100)
    assert slow.fetching.wait(5.0), "no round started"
    latencies = []
    for k in range(20):
        start = time.perf_counter()
        assert client.post_reward(b, -float(k), 200)
        client.heartbeat(b, 200)
        latencies.append(time.perf_counter() - start)
    assert client.info().rounds == 0, "the round finished before the posts: they did not overlap it"
    assert max(latencies) < 0.25, latencies
    until(lambda: client.heartbeat(b, 300).instruction is Instruction.LOAD_WEIGHTS)
    assert client.info().last_elites == [a]


def test_a_round_sends_every_non_elite_a_sample_between_the_elites(setup: Setup) -> None:
    fakes = [setup.learner(v) for v in (0.0, 5.0, 1.0, 3.0)]
    evolver, client = setup.evolver(evolver_config())
    ids = register(client, fakes)
    for i, mean in zip(ids, (-5.0, -4.0, 10.0, 20.0), strict=True):
        client.post_reward(i, mean - 1, 10)
        client.post_reward(i, mean + 1, 20)
    result = evolver.run_round_if_due()
    assert result is not None and result.elites == [ids[3], ids[2]]
    expected = params_spec(weights_of(0.0))
    for i in ids[:2]:
        orders = client.heartbeat(i, 30)
        assert (orders.instruction, orders.sample_round) == (Instruction.LOAD_WEIGHTS, 1)
        assert not client.post_reward(i, 99.0, 30), "a return of the replaced weights was accepted"
        sample = client.get_sample(i, expected)
        assert sample is not None and sample.round == 1
        for name in ("q.weight", "policy.bias"):
            # Elites at 1.0 and 3.0: every element ~ N(2, 0.1^2) with the std capped at 0.1, so within
            # 2 +- 0.5 (5 sigma); uncapped (std 1), all 14 elements would land there with p ~ 1e-5,
            # and a copy of either elite (1 or 3) or the mean of all four learners (2.25) would not pass
            # the mean check.
            w = sample.weights[name]
            assert np.all(np.abs(w - 2.0) < 0.5), w
            assert abs(w.mean() - 2.0) < 0.2 and w.std() > 0
        np.testing.assert_array_equal(sample.weights["normalizer.count"], [7])  # not floating: the best elite's
        assert client.heartbeat(i, 40, loaded_round=1).instruction is Instruction.CONTINUE
        assert client.get_sample(i) is None
        assert client.post_reward(i, 1.0, 40, weights_round=1)
    for i in ids[2:]:
        assert client.heartbeat(i, 30).instruction is Instruction.CONTINUE and client.get_sample(i) is None
    info = client.info()
    assert (info.rounds, info.last_elites) == (1, [ids[3], ids[2]])
    assert [(x.rounds, x.times_elite, x.returns) for x in info.learners] == [(1, 0, 1), (1, 0, 1), (1, 1, 0), (1, 1, 0)]


def test_a_learner_never_elite_is_retired_and_told_so(setup: Setup) -> None:
    fakes = [setup.learner(v) for v in (0.0, 1.0, 2.0)]
    evolver, client = setup.evolver(evolver_config(evolver_cem_best=0.3, evolver_remove_worst=2))
    worst, middle, best = register(client, fakes)
    job = client.assign_actor("a0")
    assert job.learner_id == worst
    loaded = {i: 0 for i in (worst, middle, best)}
    for round_ in (1, 2):
        for i, mean in ((worst, -9.0), (middle, 0.0), (best, 9.0)):
            for _ in range(2):
                assert client.post_reward(i, mean, 10, weights_round=loaded[i])
        result = evolver.run_round_if_due()
        assert result is not None and result.elites == [best]
        for i in result.samples_for:
            loaded[i] = round_
    assert result is not None and result.retired == [worst]  # middle was never elite either, but the population keeps 2
    assert client.heartbeat(worst, 50).instruction is Instruction.RETIRE
    assert client.heartbeat(middle, 50, loaded_round=2).instruction is Instruction.CONTINUE
    with pytest.raises(LearnerRetired, match=f"learner {worst} was retired in round 2"):
        client.post_reward(worst, 1.0, 60)
    with pytest.raises(LearnerRetired, match=f"learner {worst} was retired"):
        client.register_learner("back", "127.0.0.1", fakes[0].port, previous_id=worst)
    with pytest.raises(UnknownAssignment):
        client.renew_assignment(job.assignment_id)
    info = client.info()
    assert [(x.retired, x.live) for x in info.learners] == [(True, False), (False, True), (False, True)]
    assert client.assign_actor("a1").learner_id != worst


# ---------------------------------------------------------------------- actors and replays


def test_assign_spreads_actors_least_loaded_up_to_the_maximum(setup: Setup) -> None:
    _, client = setup.evolver(evolver_config(max_actors_each_learner=2))
    with pytest.raises(NoWorkYet, match="0 live learners"):
        client.assign_actor("early")
    ids = [client.register_learner(f"l{k}", "10.0.0.1", 61001, 61003, f"replay-{k}:61002").learner_id for k in range(2)]
    client.register_learner("no replay yet", "10.0.0.2", 61001)
    jobs = [client.assign_actor(f"a{k}") for k in range(4)]
    assert [j.learner_id for j in jobs] == [ids[0], ids[1], ids[0], ids[1]]
    assert (jobs[1].learner_host, jobs[1].learner_port, jobs[1].params_port) == ("10.0.0.1", 61001, 61003)
    assert jobs[1].replay_address == "replay-1:61002" and jobs[1].learner_live
    assert (
        config_from_yaml(jobs[1].config_yaml).sac_config.n_step == client.info().learners[1].params["sac_config.n_step"]
    )
    with pytest.raises(NoWorkYet, match="1 of them without a replay yet, the others at max_actors_each_learner=2"):
        client.assign_actor("a4")
    assert client.assign_actor("a0 again", previous=jobs[0].assignment_id).assignment_id == jobs[0].assignment_id
    assert [x.actors for x in client.info().learners] == [2, 2, 0]
    setup.clock.t += 0.6 * LEASE_S  # everyone but actor 3 renews; then actor 3's lease runs out
    for k in range(3):
        client.renew_assignment(jobs[k].assignment_id)
    for i in range(3):
        client.heartbeat(i, 0)
    setup.clock.t += 0.6 * LEASE_S
    with pytest.raises(UnknownAssignment):
        client.renew_assignment(jobs[3].assignment_id)
    assert client.assign_actor("a5").learner_id == ids[1]


def test_after_a_partition_each_actor_and_replay_returns_to_its_own_learner(setup: Setup) -> None:
    """Everyone was cut off from the evolver for longer than the leases; learner 0 calls back first. An
    actor and a replay of learner 1 that call Assign with their lapsed assignment get learner 1 back (same
    assignment), not learner 0, the only one live at that moment (tests/test_partitions.py saw both actors
    of a population land on the first learner back, starving the other)."""
    _, client = setup.evolver(evolver_config(max_actors_each_learner=2))
    ids = [client.register_learner(f"l{k}", "10.0.0.1", 61001 + k, 61003).learner_id for k in range(2)]
    replays = [client.assign_replay(f"r{k}", f"10.0.0.{7 + k}:61002") for k in range(2)]
    actors = [client.assign_actor(f"a{k}") for k in range(2)]
    assert [a.learner_id for a in actors] == ids and [r.learner_id for r in replays] == ids
    setup.clock.t += 1.5 * LEASE_S  # the cut: nobody heard from
    client.register_learner("l0", "10.0.0.1", 61001, 61003, previous_id=ids[0])  # learner 0 back first
    for previous in (actors[1], replays[1]):
        with pytest.raises(UnknownAssignment):
            client.renew_assignment(previous.assignment_id)
    back = client.assign_actor("a1", previous=actors[1].assignment_id)
    assert (back.learner_id, back.assignment_id) == (ids[1], actors[1].assignment_id)
    replay = client.assign_replay("r1", "10.0.0.8:61002", previous=replays[1].assignment_id)
    assert (replay.learner_id, replay.assignment_id) == (ids[1], replays[1].assignment_id)
    assert client.assign_actor("a0", previous=actors[0].assignment_id).learner_id == ids[0]
    assert [x.actors for x in client.info().learners] == [1, 1]
    # One that lapsed too long ago, or whose learner retired meanwhile, is placed afresh.
    setup.clock.t += 12 * LEASE_S
    client.register_learner("l0", "10.0.0.1", 61001, 61003, previous_id=ids[0])
    assert client.assign_actor("a1", previous=back.assignment_id).learner_id == ids[0]


def test_replay_assignment_pairs_one_replay_with_each_learner(setup: Setup) -> None:
    _, client = setup.evolver(evolver_config())
    ids = [client.register_learner(f"l{k}", "127.0.0.1", 61001 + k).learner_id for k in range(2)]
    with pytest.raises(NoWorkYet, match="without a replay yet"):
        client.assign_actor("a0")
    r0 = client.assign_replay("r0", "10.0.0.7:61002")
    r1 = client.assign_replay("r1", "10.0.0.8:61002")
    assert (r0.learner_id, r1.learner_id) == (ids[0], ids[1])
    assert r0.config_yaml == client.register_learner("l0", "127.0.0.1", 61001, previous_id=ids[0]).config_yaml
    assert client.heartbeat(ids[0], 0).replay_address == "10.0.0.7:61002"
    with pytest.raises(NoWorkYet, match="each has one"):
        client.assign_replay("r2", "10.0.0.9:61002")
    assert client.assign_replay("r0 restarted", "10.0.0.7:61002").assignment_id == r0.assignment_id
    assert client.assign_actor("a0").replay_address in ("10.0.0.7:61002", "10.0.0.8:61002")
    with pytest.raises(EvolverRequestRejected, match="address: a replay must say where it serves"):
        client.assign_replay("r3", "")
    setup.clock.t += 0.6 * LEASE_S  # replay r0 stops renewing; the learners and r1 go on
    for _ in range(2):
        client.renew_assignment(r1.assignment_id)
        for i in ids:
            client.heartbeat(i, 0)
        setup.clock.t += 0.6 * LEASE_S
    moved = client.assign_replay("r0 elsewhere", "10.0.0.9:61002")
    assert moved.learner_id == ids[0] and client.heartbeat(ids[0], 0).replay_address == "10.0.0.9:61002"


# ---------------------------------------------------------------------- leases and failures


def test_a_gone_learner_neither_holds_up_nor_joins_a_round_and_can_come_back(setup: Setup) -> None:
    fakes = [setup.learner(v) for v in (0.0, 1.0, 2.0)]
    evolver, client = setup.evolver(evolver_config())
    a, b, gone = register(client, fakes)
    client.post_reward(gone, 50.0, 10)
    setup.clock.t += LEASE_S / 2
    for i in (a, b):
        client.post_reward(i, float(i), 10)
        client.post_reward(i, float(i), 20)
    assert evolver.run_round_if_due() is None, "the gone learner's lease has not expired yet"
    setup.clock.t += LEASE_S * 0.6
    with pytest.raises(UnknownLearner, match="lease expired"):
        client.heartbeat(gone, 30)
    result = evolver.run_round_if_due()
    assert result is not None and set(result.mean_returns) == {a, b} and result.elites == [b]
    back = client.register_learner("back", "127.0.0.1", fakes[2].port, previous_id=gone)
    assert back.learner_id == gone and back.replay_address == "replay-2:1"
    info = client.info().learners[gone]
    assert (info.live, info.returns, info.rounds, info.pending_round) == (True, 1, 0, 0)


def test_an_elite_that_does_not_answer_sits_the_round_out(setup: Setup) -> None:
    fakes = [setup.learner(v) for v in (0.0, 1.0, 2.0)]
    evolver, client = setup.evolver(evolver_config(evolver_cem_best=0.3), weights_timeout_s=1.0)
    low, mid, silent = register(client, fakes)
    for i in (low, mid, silent):
        client.post_reward(i, float(i), 10)
        client.post_reward(i, float(i), 20)
    fakes[2].server.stop(None)
    result = evolver.run_round_if_due()
    assert result is not None and result.elites == [mid] and set(result.samples_for) == {low}
    info = client.info().learners
    assert (info[silent].returns, info[silent].rounds, info[silent].pending_round) == (2, 0, 0)


def test_bad_requests_get_clear_status_codes_and_the_server_keeps_serving(setup: Setup) -> None:
    _, client = setup.evolver(evolver_config())
    me = client.register_learner("l0", "127.0.0.1", 61001).learner_id
    stub = evolver_pb2_grpc.EvolverServiceStub(client.channel)
    bad: list[tuple[Callable[..., Any], Any, grpc.StatusCode, str]] = [
        (stub.LearnerHeartbeat, evolver_pb2.LearnerHeartbeatRequest(learner_id=42), grpc.StatusCode.NOT_FOUND,
         "learner 42 is not registered"),
        (stub.PostReward, evolver_pb2.PostRewardRequest(learner_id=me, mean_return=float("nan")),
         grpc.StatusCode.INVALID_ARGUMENT, "mean_return: must be finite"),
        (stub.PostReward, evolver_pb2.PostRewardRequest(learner_id=me, mean_return=1.0, env_steps=-1),
         grpc.StatusCode.INVALID_ARGUMENT, "env_steps: must be >= 0"),
        (stub.GetSample, evolver_pb2.GetSampleRequest(learner_id=7), grpc.StatusCode.NOT_FOUND, "learner 7"),
        (stub.Assign, evolver_pb2.AssignRequest(name="x"), grpc.StatusCode.INVALID_ARGUMENT,
         "role: must be ACTOR or REPLAY, got ROLE_UNSPECIFIED"),
        (stub.Assign, evolver_pb2.AssignRequest(role=cast(Any, 7), name="x"), grpc.StatusCode.INVALID_ARGUMENT,
         "got 7"),
        (stub.AssignmentHeartbeat, evolver_pb2.AssignmentHeartbeatRequest(assignment_id="actor-9"),
         grpc.StatusCode.NOT_FOUND, "assignment 'actor-9' is unknown"),
        (stub.RegisterLearner, evolver_pb2.RegisterLearnerRequest(host="h", learner_port=0),
         grpc.StatusCode.INVALID_ARGUMENT, "learner_port: must be in 1..65535"),
        (stub.RegisterLearner, evolver_pb2.RegisterLearnerRequest(host="h", learner_port=1, previous_id=99),
         grpc.StatusCode.NOT_FOUND, "learner 99 is not known to this evolver"),
    ]  # fmt: skip
    for method, request, code, message in bad:
        with pytest.raises(grpc.RpcError) as e:
            method(request, timeout=5.0)
        assert (e.value.code(), message in e.value.details()) == (code, True), e.value.details()
    with pytest.raises(UnknownLearner):
        client.heartbeat(42, 0)
    with pytest.raises(EvolverRequestRejected, match="loaded_round: must be >= 0"):
        client.heartbeat(me, 0, loaded_round=-1)
    assert client.post_reward(me, 1.0, 10) and len(client.info().learners) == 1


# ---------------------------------------------------------------------- the learner's GetWeights and metrics


def test_learner_get_weights_serves_the_hook_or_is_unimplemented(setup: Setup) -> None:
    fake = setup.learner(2.5)
    with_hook = LearnerClient(f"127.0.0.1:{fake.port}")
    version, frames = with_hook.get_weights()
    with_hook.close()
    assert version == 5
    np.testing.assert_array_equal(
        decode_params(frames, params_spec(fake.weights))[1]["q.weight"], fake.weights["q.weight"]
    )
    server, port, _ = serve_learner(LearnerServicer(SPEC, ActorRegistry(), ParamsStore(), params_port=0))
    without_hook = LearnerClient(f"127.0.0.1:{port}")
    try:
        with pytest.raises(grpc.RpcError) as e:
            without_hook.get_weights()
        assert e.value.code() == grpc.StatusCode.UNIMPLEMENTED and "without an evolver" in e.value.details()
    finally:
        without_hook.close()
        server.stop(None)


def test_metrics_reach_tensorboard(setup: Setup, tmp_path: Path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from algorithm.run.logging import MetricsWriter

    fakes = [setup.learner(v) for v in (0.0, 1.0)]
    metrics = MetricsWriter(tmp_path / "log" / "evolver")
    evolver, client = setup.evolver(evolver_config(evolver_cem_best=1.0), metrics=metrics)
    ids = register(client, fakes)
    for i in ids:
        client.post_reward(i, float(i), 10)
        client.post_reward(i, float(i) + 2, 20)
    assert evolver.run_round_if_due() is not None
    evolver.stop()
    metrics.close()
    events = EventAccumulator(str(tmp_path / "log" / "evolver"))
    events.Reload()
    scalars = set(events.Tags()["scalars"])
    assert {"evolver/learner_1/mean_return", "evolver/cem_std", "evolver/learner_0/elite"} <= scalars
    assert [e.value for e in events.Scalars("evolver/learner_1/mean_return")] == [1.0, 2.0]
    assert events.Scalars("evolver/cem_std")[0].value == pytest.approx(0.1)  # elites 0 and 1: std 0.5, capped
    assert "evolver/learner_0/params/text_summary" in events.Tags()["tensors"]
