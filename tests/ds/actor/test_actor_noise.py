"""Actors built from one config explore differently: each reseeds its acting noise from its own seed.

Every actor's policy is built from the same config, hence from one ``sac.seed``; before each actor
reseeded its noise (``Policy.seed_acting`` in ``DistributedActor.run``), every actor of a run drew the
same exploration noise, step for step (a defect found in issue 15's review)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from algorithm.sac.learner import SAC
from ds.actor.actor import DistributedActor
from ds.learner.client import LearnerClient
from ds.replay.client import ReplayClient
from envs.make import vector_env_factory
from tests.ds.actor.test_actor_reconnect import CONFIG, FAST_RETRY, SPEC, Learner, Replay, free_port

pytestmark = pytest.mark.grpc


def one_episode_actor(replay_port: int, learner_port: int, run_dir: Path) -> DistributedActor:
    """An actor that registers, takes the learner's weights and acts for one episode of env 0, all its
    steps drawn from the policy (no random warm-up), at the same noise scale as any other."""
    config = CONFIG.model_copy(deep=True)
    config.base_config.max_iter = 1
    config.actor_config.random_steps = 0
    replay = ReplayClient(f"127.0.0.1:{replay_port}", SPEC.sensors, SPEC.action.size, retry=FAST_RETRY)
    learner = LearnerClient(f"127.0.0.1:{learner_port}", SPEC, retry=FAST_RETRY, rpc_timeout_s=2.0)
    sac = SAC(SPEC, config.sac_config, config.nn_config, config.replay_config)
    actor = DistributedActor(config, run_dir, vector_env_factory("Pendulum-v1"), sac, replay, learner,
                             "127.0.0.1", noise=1.0)  # fmt: skip
    try:
        summary = actor.run()
    finally:
        replay.close()
        learner.close()
    assert summary.env_steps > 0 and not summary.interrupted
    return actor


def test_two_actors_of_one_config_draw_different_exploration_noise(tmp_path: Path) -> None:
    replay_port, learner_port = free_port(), free_port()
    replay, learner = Replay(replay_port), Learner(learner_port, version=1, seed=3)
    try:
        first = one_episode_actor(replay_port, learner_port, tmp_path)
        # the first left, freeing index 0: something else holds it, so the second actor is index 1
        with LearnerClient(f"127.0.0.1:{learner_port}", SPEC) as holder:
            assert holder.register("holder", None).index == 0
            second = one_episode_actor(replay_port, learner_port, tmp_path)
    finally:
        learner.stop()
        replay.stop()
    assert first.registration is not None and second.registration is not None
    assert (first.registration.index, second.registration.index) == (0, 1)
    assert first.env_steps == second.env_steps  # as many draws each: one seed would leave them in step
    # The same weights (the learner's), the same observations and noise scale: only the noise tells
    # the two apart. Without the reseeding both stochastic action sets are equal.
    obs = [np.zeros((8, *sensor.shape), np.float32) for sensor in SPEC.sensors]
    for _ in range(3):
        mine, theirs = first.sac.act(obs)[0], second.sac.act(obs)[0]
        assert not np.allclose(mine, theirs), "two actors drew the same exploration noise"
    # the weights are the same: without noise the two act alike
    np.testing.assert_allclose(first.sac.act(obs, deterministic=True)[0], second.sac.act(obs, deterministic=True)[0])
