"""Curiosity and RND in the learner: intrinsic rewards reach the targets only, the models train,
RND's target stays frozen and checkpointed, and acting picks the most novel candidate."""

from __future__ import annotations

import copy
import logging
import math
from typing import Any

import numpy as np
import pytest
import torch

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.run.actor import ActorLoop
from algorithm.sac.learner import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from algorithm.types import ActingProgress
from envs.make import vector_env_factory
from tests.algorithm.sac.test_learner import make_batch

OBS, ACT = 3, 2
SPEC = EnvSpec((SensorSpec("obs", (OBS,)),), ActionSpec((), ACT, (-1.0,) * ACT, (1.0,) * ACT))


def predictable_batch():  # noqa: ANN201
    """32 one-step windows whose next observation is a fixed function of observation and action."""
    batch = make_batch(b=32)
    obs, action = batch.obs[0], batch.actions[:, 0]
    obs[:, 1] = obs[:, 0] + np.concatenate([action, action[:, :1]], axis=1)
    return batch


def make_sac(**sac: Any) -> SAC:
    return SAC(
        SPEC, SacConfig(**{"seed": 1, "use_priority": False, **sac}), NNConfig(hidden_units=[16]), ReplayConfig()
    )


@pytest.mark.parametrize("inverse", [False, True])
def test_curiosity_adds_its_reward_to_the_target_only_and_learns_to_predict(inverse: bool) -> None:
    batch = predictable_batch()
    rewards_before = batch.rewards.copy()
    plain = make_sac(learning_rate=3e-3).update(batch, with_metrics=True).metrics
    curious_sac = make_sac(use_curiosity=True, curiosity_strength=2.0, curiosity_inverse=inverse, learning_rate=3e-3)
    curious = curious_sac.update(batch, with_metrics=True).metrics
    np.testing.assert_array_equal(batch.rewards, rewards_before)  # stored rewards never change
    assert curious["learner/curiosity_reward"] > 0
    # one-step windows: y = r + 2 * forward error + gamma V(o_1), with everything else identical
    assert curious["learner/target_mean"] == pytest.approx(
        plain["learner/target_mean"] + curious["learner/curiosity_reward"], rel=1e-5
    )
    first = curious["learner/curiosity_reward"]
    for _ in range(100):
        last = curious_sac.update(batch, with_metrics=True).metrics["learner/curiosity_reward"]
    assert last < 0.5 * first  # the forward model learns the transitions it sees


def test_rnd_target_stays_frozen_its_predictor_learns_and_both_are_checkpointed() -> None:
    sac = make_sac(use_rnd=True, learning_rate=3e-3)
    assert sac.models.rnd is not None
    target = copy.deepcopy(sac.models.rnd.target.state_dict())
    batch = make_batch(b=32)
    first = sac.update(batch, with_metrics=True).metrics["learner/rnd_novelty"]
    for _ in range(100):
        last = sac.update(batch, with_metrics=True).metrics["learner/rnd_novelty"]
    assert last < 0.5 * first
    for name, value in sac.models.rnd.target.state_dict().items():
        assert torch.equal(value, target[name]), name
    state = sac.state_dict()
    assert any(k.startswith("rnd.target.") for k in state["models"])
    assert any(k.startswith("rnd.") for k in sac.acting_state_dict())  # actors need it to choose
    restored = make_sac(use_rnd=True, learning_rate=3e-3, seed=9)
    restored.load_state_dict(copy.deepcopy(state))
    for name, value in restored.models.rnd.state_dict().items():  # type: ignore[union-attr]
        assert torch.equal(value, sac.models.rnd.state_dict()[name]), name


def test_rnd_strength_adds_novelty_to_the_target_only_and_it_fades_as_the_pairs_become_familiar() -> None:
    batch = make_batch(b=32)
    rewards_before = batch.rewards.copy()
    plain = make_sac(use_rnd=True, learning_rate=3e-3).update(batch, with_metrics=True).metrics
    rewarded_sac = make_sac(use_rnd=True, rnd_strength=50.0, learning_rate=3e-3)
    rewarded = rewarded_sac.update(batch, with_metrics=True).metrics
    np.testing.assert_array_equal(batch.rewards, rewards_before)  # stored rewards never change
    assert rewarded["learner/rnd_reward"] == pytest.approx(50.0 * rewarded["learner/rnd_novelty"], rel=1e-5)
    # one-step windows: y = r + 50 * novelty(o_0, a_0) + gamma V(o_1), with everything else identical
    assert rewarded["learner/target_mean"] == pytest.approx(
        plain["learner/target_mean"] + rewarded["learner/rnd_reward"], rel=1e-5
    )
    first = rewarded["learner/rnd_reward"]
    for _ in range(100):
        last = rewarded_sac.update(batch, with_metrics=True).metrics["learner/rnd_reward"]
    assert last < 0.5 * first
    assert "learner/rnd_reward" not in plain  # rnd_strength 0 (the default): no bonus


def test_rnd_acting_picks_more_novel_actions_than_the_policy_alone() -> None:
    with_rnd, without = make_sac(use_rnd=True, rnd_n_sample=10), make_sac(use_rnd=True, rnd_n_sample=1)
    without.load_state_dict(copy.deepcopy(with_rnd.state_dict()))
    obs = [np.tile(np.array([[0.2, -0.4, 0.7]], dtype=np.float32), (500, 1))]
    rnd = with_rnd.models.rnd
    assert rnd is not None

    def novelty(actions: np.ndarray) -> float:
        state = with_rnd.models.representation([torch.from_numpy(obs[0])])
        with torch.no_grad():
            return float(rnd.novelty(state, torch.from_numpy(actions)).mean())

    picked, _ = with_rnd.act(obs)
    plain, _ = without.act(obs)
    assert novelty(picked) > 1.2 * novelty(plain)
    deterministic_a, _ = with_rnd.act(obs, deterministic=True)
    deterministic_b, _ = without.act(obs, deterministic=True)
    np.testing.assert_array_equal(deterministic_a, deterministic_b)  # evaluation ignores novelty


def test_rnd_choice_ends_after_its_env_steps_and_the_policy_acts_alone() -> None:
    ending = make_sac(use_rnd=True, rnd_n_sample=10, rnd_choice_steps=1000)
    state = copy.deepcopy(ending.state_dict())
    obs = [np.tile(np.array([[0.2, -0.4, 0.7]], dtype=np.float32), (500, 1))]

    def act_at(env_steps: int, sac: SAC) -> np.ndarray:
        sac.load_state_dict(copy.deepcopy(state))  # the same acting noise for every call
        sac.progress = ActingProgress(env_steps=env_steps)
        return sac.act(obs)[0]

    always, alone = make_sac(use_rnd=True, rnd_n_sample=10), make_sac(use_rnd=True, rnd_n_sample=1)
    for steps in (0, 999):  # before the end: the most novel, as without the option
        np.testing.assert_array_equal(act_at(steps, ending), act_at(steps, always))
    for steps in (1000, 50_000):  # after it: the policy's own sample
        np.testing.assert_array_equal(act_at(steps, ending), act_at(0, alone))
    assert not np.array_equal(act_at(0, always), act_at(0, alone))  # the two differ: the checks above can fail
    np.testing.assert_array_equal(act_at(50_000, always), act_at(0, always))  # 0: the choice for the whole run


def test_rnd_choice_ends_once_an_episode_returned_enough_and_the_loop_tells_the_policy(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # The acting loop hands the policy its progress each step: the best episode return ends the choice.
    env = vector_env_factory("Pendulum-v1")(2, 0)
    sac = SacConfig(seed=1, use_rnd=True, rnd_n_sample=10, rnd_choice_until_return=-100.0)
    ending = SAC(env.spec, sac, NNConfig(hidden_units=[16]), ReplayConfig())
    loop = ActorLoop(env, ending, lambda chunk: None, chunk_length=16)
    for _ in range(200):  # Pendulum: 200-step episodes
        assert ending.chooses_by_novelty()
        loop.step()
    assert ending.progress is loop.progress and loop.progress.env_steps == loop.total_steps - 2
    assert loop.progress.best_episode_return > -math.inf
    assert loop.progress.best_episode_return < -100.0 and ending.chooses_by_novelty()  # random-ish: far below
    loop.progress.best_episode_return = -99.0
    with caplog.at_level(logging.INFO, logger="asac.policy"):
        assert not ending.chooses_by_novelty() and not ending.chooses_by_novelty()
    ended = [r.getMessage() for r in caplog.records if "action choice ends" in r.getMessage()]
    assert len(ended) == 1 and "an episode returned -99.0" in ended[0], ended  # said once, with why
    env.close()


@pytest.mark.parametrize("option", [{"rnd_choice_steps": 10}, {"rnd_choice_until_return": 90.0}])
def test_rnd_choice_ends_need_rnd(option: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match="rnd_choice_steps and rnd_choice_until_return .* need use_rnd"):
        SacConfig(**option)


def test_rnd_normalize_centres_the_bonus_on_a_running_mean_of_replayed_novelty_which_is_checkpointed() -> None:
    batch = make_batch(b=32)
    sac = make_sac(use_rnd=True, rnd_strength=0.5, rnd_normalize=True, learning_rate=3e-3)
    assert sac.models.rnd is not None
    first = sac.update(batch, with_metrics=True).metrics
    assert first["learner/rnd_reward"] == pytest.approx(0.0, abs=1e-6)  # the first batch is its own mean
    mean = float(sac.models.rnd.novelty_mean)
    for _ in range(30):  # one-step windows: the bonus's pairs are the novelty metric's
        metrics = sac.update(batch, with_metrics=True).metrics
        mean = mean + 0.01 * (metrics["learner/rnd_novelty"] - mean)
        assert float(sac.models.rnd.novelty_mean) == pytest.approx(mean, rel=1e-4)
        expected = 0.5 * (metrics["learner/rnd_novelty"] / mean - 1.0)
        assert metrics["learner/rnd_reward"] == pytest.approx(expected, rel=1e-3, abs=1e-6)
    restored = make_sac(use_rnd=True, rnd_strength=0.5, rnd_normalize=True, seed=9)
    restored.load_state_dict(copy.deepcopy(sac.state_dict()))
    assert float(restored.models.rnd.novelty_mean) == float(sac.models.rnd.novelty_mean)  # type: ignore[union-attr]
    # without the option the models' keys are what runs before it saved
    assert not any("novelty_mean" in k for k in make_sac(use_rnd=True, rnd_strength=0.5).state_dict()["models"])
    with pytest.raises(ValueError, match="rnd_strength > 0"):
        SacConfig(use_rnd=True, rnd_normalize=True)


def test_scoring_new_data_leaves_the_rnd_running_mean_alone() -> None:
    """``td_errors`` (``insert_td_priorities``) runs the losses, which move RND's running novelty mean;
    the mean follows trained batches only, so scoring puts it back."""
    sac = make_sac(use_rnd=True, rnd_strength=0.5, rnd_normalize=True)
    assert sac.models.rnd is not None
    sac.update(make_batch(b=32))
    mean = float(sac.models.rnd.novelty_mean)
    sac.td_errors(make_batch(b=16, seed=5))
    assert float(sac.models.rnd.novelty_mean) == mean
