"""A learner that joins a population after a CEM round starts from a draw of that round's Gaussian
(issue 15, defect 6: a late learner starts from the CEM distribution), as the original system did;
one that joins before any round, or comes back with its id, keeps its own weights. On loopback: the
evolver's server, learner servers for its GetWeights, and a real SAC learner with its EvolverLink."""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from algorithm.config.load import load_config
from algorithm.config.schema import Config
from algorithm.replay import PrioritizedTable
from algorithm.sac.learner import SAC
from ds.evolver.client import EvolverClient
from ds.evolver.evolver import Evolver
from ds.evolver.state import STATE_FILE, EvolverStateError, Instruction, save_state
from ds.learner.learner import Learner
from ds.learner.service import ActorRegistry, LearnerServicer, ParamsStore, serve_learner
from ds.member.link import EvolverLink, Membership, WeightsSnapshot
from ds.member.population import LearnerAddress, join_population
from ds.net.params import ParamsPublisher, encode_params, params_spec
from envs.make import make_vector_env
from tests.ds.conftest import ServeOverGrpc
from tests.ds.evolver.evolver_setup import LEASE_S, SPEC, Setup, evolver_config, register, until, weights_of

pytestmark = pytest.mark.grpc
ROOT = Path(__file__).resolve().parents[3]
TINY_STD = 1e-6  # evolver_cem_std_max: a sample is the elites' mean within a few 1e-6
JOINED = "joined after round 1: starting from a sample of the CEM distribution"


def tiny_std_config(**base: object) -> Config:
    return evolver_config(evolver_cem_best=1.0, evolver_cem_std_max=TINY_STD, **base)


def run_round(evolver: Evolver, client: EvolverClient, ids: list[int]) -> None:
    for i in ids:
        client.post_reward(i, float(i), 10)
        client.post_reward(i, float(i), 20)
    result = evolver.run_round_if_due()
    assert result is not None and sorted(result.elites) == sorted(ids) and not result.samples_for


# ---------------------------------------------------------------------- the evolver's side


def test_a_learner_registering_after_a_round_gets_a_sample_of_its_distribution(
    setup: Setup, caplog: pytest.LogCaptureFixture
) -> None:
    # Pins issue 15, defect 6: a late learner starts from the CEM distribution.
    fakes = [setup.learner(v) for v in (1.0, 3.0)]
    evolver, client = setup.evolver(tiny_std_config())
    ids = register(client, fakes)
    for i in ids:  # before any round: no sample, today's behaviour
        assert client.get_sample(i) is None and client.heartbeat(i, 1).instruction is Instruction.CONTINUE
    run_round(evolver, client, ids)  # both elite: mean 2.0, std capped at TINY_STD
    caplog.set_level(logging.INFO, logger="asac.evolver")

    late = client.register_learner("late", "127.0.0.1", 61009)
    assert late.rounds == 1
    assert f"learner {late.learner_id} {JOINED}" in caplog.text
    orders = client.heartbeat(late.learner_id, 0)
    assert (orders.instruction, orders.sample_round) == (Instruction.LOAD_WEIGHTS, 1)
    sample = client.get_sample(late.learner_id, params_spec(weights_of(0.0)))
    assert sample is not None and sample.round == 1
    for name in ("q.weight", "policy.bias"):
        np.testing.assert_allclose(sample.weights[name], 2.0, atol=10 * TINY_STD)  # the mean, not an elite's
        assert sample.weights[name].dtype == weights_of(0.0)[name].dtype
    np.testing.assert_array_equal(sample.weights["normalizer.count"], [7])
    assert not client.post_reward(late.learner_id, 5.0, 10), "a return of its own random weights was counted"
    assert client.heartbeat(late.learner_id, 10, loaded_round=1).instruction is Instruction.CONTINUE
    assert client.post_reward(late.learner_id, 5.0, 20, weights_round=1)

    back = client.register_learner("l0 again", "127.0.0.1", fakes[0].port, previous_id=ids[0])
    assert back.learner_id == ids[0] and client.get_sample(ids[0]) is None  # back with its id: nothing drawn
    assert "learner 0 joined" not in caplog.text


def test_the_distribution_survives_an_evolver_restart_and_old_states_load_without_one(setup: Setup) -> None:
    fakes = [setup.learner(v) for v in (1.0, 3.0)]
    evolver, client = setup.evolver(tiny_std_config())
    ids = register(client, fakes)
    run_round(evolver, client, ids)
    setup.close()
    assert (setup.state_dir / "cem.round_1.npz").is_file()

    _, client = setup.evolver(tiny_std_config())
    late = client.register_learner("late", "127.0.0.1", 61009).learner_id
    sample = client.get_sample(late)
    assert sample is not None and sample.round == 1
    np.testing.assert_allclose(sample.weights["q.weight"], 2.0, atol=10 * TINY_STD)
    setup.close()

    state = json.loads((setup.state_dir / STATE_FILE).read_text())  # as saved before the distribution was kept
    del state["sha256"], state["cem_round"]
    save_state(setup.state_dir, state)
    _, client = setup.evolver(tiny_std_config())
    assert not (setup.state_dir / "cem.round_1.npz").exists(), "a file no state names stayed"
    assert client.get_sample(client.register_learner("later", "127.0.0.1", 61010).learner_id) is None
    setup.close()


def test_a_damaged_distribution_is_an_error_naming_it(setup: Setup) -> None:
    fakes = [setup.learner(v) for v in (1.0, 3.0)]
    evolver, client = setup.evolver(tiny_std_config())
    run_round(evolver, client, register(client, fakes))
    setup.close()
    path = setup.state_dir / "cem.round_1.npz"
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(EvolverStateError, match=f"CEM distribution {path} .* is unreadable"):
        Evolver(tiny_std_config(), setup.state_dir, "exp")


# ---------------------------------------------------------------------- the learner's side


def pendulum_sac(seed: int) -> tuple[Config, SAC, PrioritizedTable]:
    """A small Pendulum SAC initialised from ``seed``, its config, and an empty table for its replay."""
    config = load_config(ROOT / "envs/gym/pendulum", None, ["nn.hidden_units=[16,16]", "eval.eval_per_step=0"]).config
    spec = make_vector_env("Pendulum-v1", 1, seed=0).spec
    torch.manual_seed(seed)
    sac = SAC(spec, config.sac_config, config.nn_config, config.replay_config)
    return config, sac, PrioritizedTable(1000, spec.sensors, spec.action.size, window=3, seed=0)


def weights(sac: SAC) -> dict[str, np.ndarray]:
    return {name: t.detach().cpu().numpy().copy() for name, t in sac.models.state_dict().items()}


class SacServer:
    """A learner server whose GetWeights serves one SAC's full weights."""

    def __init__(self, seed: int) -> None:
        self.weights = weights(pendulum_sac(seed)[1])
        servicer = LearnerServicer(SPEC, ActorRegistry(), ParamsStore(), params_port=0, weights=self.snapshot)
        self.server, self.port, _ = serve_learner(servicer)

    def snapshot(self) -> tuple[int, list[bytes]]:
        return 1, encode_params(1, self.weights)


@pytest.fixture
def servers() -> Iterator[list[SacServer]]:
    servers = [SacServer(seed) for seed in (1, 2)]
    yield servers
    for s in servers:
        s.server.stop(None)


def start_learner(
    client: EvolverClient, tmp_path: Path, over_grpc: ServeOverGrpc, seed: int
) -> tuple[Learner, EvolverLink, dict[str, np.ndarray]]:
    """A new learner joined as ``join_population`` and ds/learner/role.py join it, its link started; its
    own initial weights. Its stop is set: :meth:`Learner.run` does everything before the first update."""
    config, sac, table = pendulum_sac(seed)
    own = weights(sac)
    run_dir = tmp_path / f"run_{seed}"  # no folder of an earlier learner to claim: it registers as new
    joined = join_population(client, run_dir, LearnerAddress(f"l{seed}", "127.0.0.1", 61009, 0, ""), threading.Event())
    assert joined is not None
    link = EvolverLink(client, joined, params_spec(sac.models.state_dict()))
    link.start()
    replay = over_grpc(table)
    member = Membership(link, WeightsSnapshot(), lambda address: replay)
    learner = Learner(config, joined.slot.path, sac, replay,
                      ParamsPublisher("tcp://127.0.0.1:*"), ParamsStore(), stop=threading.Event(),
                      member=member)  # fmt: skip
    learner.stop.set()
    return learner, link, own


def test_a_late_learner_loads_the_distributions_sample_before_its_first_update(
    setup: Setup, servers: list[SacServer], tmp_path: Path, over_grpc: ServeOverGrpc, caplog: pytest.LogCaptureFixture
) -> None:
    # Pins issue 15, defect 6: a late learner starts from the CEM distribution.
    evolver, client = setup.evolver(tiny_std_config())
    caplog.set_level(logging.INFO)
    early, early_link, early_own = start_learner(client, tmp_path, over_grpc, seed=3)
    try:
        early.run()
        assert early.updates == 0 and early.core.counters.weights_round == 0
        for name, value in weights(early.sac).items():  # before any round: its own weights
            np.testing.assert_array_equal(value, early_own[name], err_msg=name)
    finally:
        early_link.close()
        early_link.joined.slot.release()
        early.publisher.close()
    setup.clock.t += 2 * LEASE_S  # the early learner is gone: it sits the round out
    ids = [client.register_learner(f"s{k}", "127.0.0.1", s.port).learner_id for k, s in enumerate(servers)]
    run_round(evolver, client, ids)  # both elite, std capped at TINY_STD: a sample is their mean
    mean = {n: (servers[0].weights[n].astype(np.float64) + servers[1].weights[n]) / 2 for n in servers[0].weights}

    late, link, own = start_learner(client, tmp_path, over_grpc, seed=4)
    try:
        late.run()
        assert late.updates == 0 and late.core.counters.weights_round == 1 and link.loaded_round == 1
        loaded = weights(late.sac)
        floating = [n for n in loaded if np.issubdtype(loaded[n].dtype, np.floating)]
        for name in floating:
            np.testing.assert_allclose(loaded[name], mean[name], atol=1e-4, err_msg=name)
        assert any(not np.allclose(loaded[n], own[n], atol=1e-3) for n in floating), "its own init was kept"
        for name, value in late.sac.target_q.state_dict().items():  # targets hard-copied
            np.testing.assert_array_equal(value.cpu().numpy(), loaded[f"q.{name}"], err_msg=name)
        until(lambda: client.info().learners[link.learner_id].pending_round == 0)  # acknowledged
        assert caplog.text.count(f"learner {link.learner_id} {JOINED}") == 2  # the evolver's line and the learner's
    finally:
        link.close()
        link.joined.slot.release()
        late.publisher.close()
