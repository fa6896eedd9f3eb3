"""The actor loop on real (toy) gymnasium envs: chunks never mix episodes, final observations are
the real ones, previous actions and behaviour log-probs are stored as acted, nothing is lost."""

from __future__ import annotations

import numpy as np
import pytest

from algorithm.run.actor import ActorLoop, uniform_random_actions
from algorithm.types import Chunk
from envs.make import make_vector_env


class RecordingPolicy:
    """Random actions with a made-up log-prob that encodes the action, so rows can be checked."""

    def __init__(self, action_size: int, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.action_size = action_size

    def act(self, obs: list[np.ndarray], deterministic: bool = False) -> tuple[np.ndarray, np.ndarray]:
        n = obs[0].shape[0]
        actions = self.rng.uniform(-1, 1, size=(n, self.action_size)).astype(np.float32)
        return actions, actions.sum(axis=1).astype(np.float32)


def run_actor(
    num_envs: int,
    steps: int,
    chunk_length: int,
    env_kwargs: dict,
    max_episode_steps: int | None,
    reset_on_iteration: bool = False,
) -> tuple[list[Chunk], ActorLoop]:
    env = make_vector_env("asac/Chain-v0", num_envs, seed=3, env_kwargs=env_kwargs, max_episode_steps=max_episode_steps)
    chunks: list[Chunk] = []
    actor = ActorLoop(
        env,
        RecordingPolicy(env.spec.action.size),
        chunks.append,
        chunk_length=chunk_length,
        reset_on_iteration=reset_on_iteration,
        seed=3,
    )
    for _ in range(steps):
        actor.step()
    return chunks, actor


@pytest.mark.parametrize("chunk_length", [1, 3, 4, 64])
def test_chunks_never_mix_episodes_and_keep_real_final_obs(chunk_length: int) -> None:
    chunks, _ = run_actor(3, 60, chunk_length, {"terminate_at": 7}, max_episode_steps=5)
    assert chunks
    for c in chunks:
        episode, t = c.obs[0][:, 0], c.obs[0][:, 1]
        assert (episode == episode[0]).all(), "a chunk holds rows of two episodes"
        np.testing.assert_array_equal(np.diff(t), 1.0)  # consecutive steps, final obs included
        assert not c.terminated[:-1].any() and not c.truncated[:-1].any()
        if c.truncated[-1]:
            assert t[-1] == 5.0  # time limit: the real final observation, not the reset one (t == 0)
        assert not c.terminated.any()  # terminate_at=7 is never reached before the 5-step limit


def test_termination_is_not_truncation() -> None:
    chunks, _ = run_actor(2, 40, 16, {"terminate_at": 4}, max_episode_steps=10)
    ends = [c for c in chunks if c.terminated[-1] or c.truncated[-1]]
    assert ends
    for c in ends:
        assert c.terminated[-1] and not c.truncated[-1]
        assert c.obs[0][-1, 1] == 4.0


def test_prev_actions_and_behaviour_logp_are_as_acted() -> None:
    chunks, _ = run_actor(2, 30, 4, {}, max_episode_steps=6)
    for c in chunks:
        np.testing.assert_allclose(c.behaviour_logp, c.actions.sum(axis=1), rtol=1e-6)
        starts_episode = c.obs[0][0, 1] == 0.0
        if starts_episode:
            np.testing.assert_array_equal(c.prev_actions[0], 0.0)
        np.testing.assert_array_equal(c.prev_actions[1:], c.actions[:-1])


def test_rewards_match_the_env_definition() -> None:
    chunks, _ = run_actor(1, 12, 64, {}, max_episode_steps=6)
    for c in chunks:
        # Chain reward: t + sum(env action); env action = model action scaled from [-1,1] to [-2,2].
        expected = c.obs[0][:-1, 1] + 2.0 * c.actions.sum(axis=1)
        np.testing.assert_allclose(c.rewards, expected, rtol=1e-5, atol=1e-5)


def test_flush_hands_over_every_step() -> None:
    chunks, actor = run_actor(3, 23, 8, {}, max_episode_steps=None)  # Chain-v0's own limit: 10 steps
    open_steps = actor.builder._t.copy()
    assert actor.flush() == int((open_steps > 0).sum())
    assert sum(len(c) for c in chunks) == 3 * 23
    for c in chunks:
        assert c.truncated[-1] == (c.obs[0][-1, 1] == 10.0)  # only the time limit truncates


def test_reset_on_iteration_truncates_the_other_envs() -> None:
    env = make_vector_env("asac/Chain-v0", 2, seed=0, env_kwargs={"terminate_at": 3}, max_episode_steps=None)
    chunks: list[Chunk] = []
    actor = ActorLoop(env, RecordingPolicy(1), chunks.append, chunk_length=64, reset_on_iteration=True, seed=0)
    actor.step()
    # Put env 1 one step behind env 0: cut its chunk and restart its episode by hand.
    actor.builder.flush(1, [o[1] for o in actor.obs], truncate=False)
    for o, fresh in zip(actor.obs, env.reset_env(1), strict=True):
        o[1] = fresh
    chunks.clear()
    for _ in range(2):
        stats = actor.step()
    assert stats.iteration_ended  # env 0 terminated at t == 3 ...
    ends = {(bool(c.terminated[-1]), bool(c.truncated[-1]), float(c.obs[0][-1, 1])) for c in chunks}
    assert ends == {(True, False, 3.0), (False, True, 2.0)}  # ... and env 1 was cut at t == 2, truncated
    assert [float(o) for o in actor.obs[0][:, 1]] == [0.0, 0.0]  # both start the next iteration together


def test_by_default_each_env_runs_its_own_episodes() -> None:
    # Issue 15, defect 5: reset_on_iteration defaulted to true, so with several envs every episode
    # was cut when env 0's ended: on an early-terminating task the data skewed toward episode starts.
    from algorithm.config.load import load_config

    base = load_config(None, None, []).config.base_config
    assert not base.reset_on_iteration
    env = make_vector_env("asac/Chain-v0", 2, seed=0, env_kwargs={"terminate_at": 3}, max_episode_steps=None)
    chunks: list[Chunk] = []
    actor = ActorLoop(env, RecordingPolicy(1), chunks.append, chunk_length=64,
                      reset_on_iteration=base.reset_on_iteration, seed=0)  # fmt: skip
    actor.step()
    actor.builder.flush(1, [o[1] for o in actor.obs], truncate=False)  # env 1 one step behind env 0
    for o, fresh in zip(actor.obs, env.reset_env(1), strict=True):
        o[1] = fresh
    chunks.clear()
    for _ in range(3):
        actor.step()
    ends = [(bool(c.terminated[-1]), bool(c.truncated[-1]), float(c.obs[0][-1, 1])) for c in chunks]
    assert ends == [(True, False, 3.0), (True, False, 3.0)]  # env 0 at its step 3, env 1 one step later: neither cut


def test_envs_out_of_step_still_record_each_row_where_it_was_acted() -> None:
    """The chunk builder writes one slice while every env is at the same step and scatters per env
    otherwise; after env 1 is cut a step early both paths must leave every chunk as acted."""
    chunks, actor = run_actor(3, 2, 8, {}, max_episode_steps=None)
    actor.builder.flush(1, [o[1] for o in actor.obs], truncate=False)  # env 1's next chunk starts later
    assert len(set(actor.builder._t.tolist())) == 2
    for _ in range(40):
        actor.step()
    assert len(chunks) > 10
    for c in chunks:
        np.testing.assert_array_equal(np.diff(c.obs[0][:, 1]) % 10, 1.0)  # Chain's t, limit 10: consecutive
        assert (c.obs[0][:-1, 0] == c.obs[0][0, 0]).all()  # one episode per chunk
        np.testing.assert_allclose(c.behaviour_logp, c.actions.sum(axis=1), rtol=1e-6)
        np.testing.assert_array_equal(c.prev_actions[1:], c.actions[:-1])


def test_uniform_random_actions_log_density() -> None:
    from algorithm.spaces import ActionSpec

    spec = ActionSpec(discrete_branches=(3,), continuous_dim=2, low=(-1.0, -1.0), high=(1.0, 1.0))
    actions, logp = uniform_random_actions(spec, 100, np.random.default_rng(0))
    assert actions.shape == (100, 5)
    np.testing.assert_array_equal(actions[:, :3].sum(axis=1), 1.0)
    assert np.all(np.abs(actions[:, 3:]) <= 1.0)
    np.testing.assert_allclose(logp, -np.log(3) - 2 * np.log(2), rtol=1e-6)


def test_chunks_with_nan_or_inf_are_dropped_counted_and_logged(caplog: pytest.LogCaptureFixture) -> None:
    """tests/fault_envs.py's Pendulum: a NaN reward at step 60 of episode 1 and a NaN final
    observation in episode 2. Exactly the two chunks holding them are dropped, every other step
    reaches the sink, and the first drop is logged naming the field."""
    from tests import fault_envs

    env = make_vector_env(fault_envs.BUILD_PATH, 1, seed=0)
    chunks: list[Chunk] = []
    actor = ActorLoop(env, RecordingPolicy(env.spec.action.size), chunks.append, chunk_length=50, seed=0)
    dropped = []
    with caplog.at_level("WARNING", logger="asac.actor"):
        for _ in range(600):
            dropped.append(actor.step().nonfinite_steps)
    assert actor.nonfinite_chunks == 2 and actor.nonfinite_steps == sum(dropped) == 100
    assert [i for i, n in enumerate(dropped) if n] == [299, 599]  # each when its chunk was cut
    assert sum(len(c) for c in chunks) == 500
    for c in chunks:
        assert all(np.isfinite(a).all() for a in (*c.obs, c.actions, c.rewards, c.behaviour_logp))
    assert "dropped a chunk of 50 steps with non-finite values in rewards; 1 chunks (50 steps)" in caplog.text
