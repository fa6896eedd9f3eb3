"""Recurrent SAC (``use_rnn``): the sequence pass equals stepping, masked look-back rows keep the
stored state, burn-in rows get no gradient unless configured, and actors store the state they used."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import torch

from algorithm.config.load import load_config
from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.nn.models import VectorRepresentation
from algorithm.nn.recurrent import RecurrentRepresentation
from algorithm.run.trainer import EmbeddedTrainer
from algorithm.sac.learner import SAC
from algorithm.sac.window import sequence_states
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from algorithm.types import Batch
from envs.make import vector_env_factory

ROOT = Path(__file__).resolve().parents[3]
OBS, ACT, H = 3, 2, 8


def recurrent(rnn_type: str = "gru") -> RecurrentRepresentation:
    torch.manual_seed(0)
    return RecurrentRepresentation(VectorRepresentation([SensorSpec("obs", (OBS,))]), ACT, H, rnn_type)  # type: ignore[arg-type]


@pytest.mark.parametrize("rnn_type", ["gru", "lstm"])
def test_sequence_equals_stepping_and_masked_rows_keep_the_state(rnn_type: str) -> None:
    rep = recurrent(rnn_type)
    assert rep.rnn_state_size == (2 * H if rnn_type == "lstm" else H)
    b, p = 4, 6
    obs, prev = torch.randn(b, p, OBS), torch.randn(b, p, ACT)
    initial = torch.randn(b, rep.rnn_state_size)
    first = torch.tensor([0, 1, 3, 0])  # rows before these positions are look-back padding
    valid = torch.arange(p)[None, :] >= first[:, None]
    out = rep.sequence([obs], prev, initial, valid)
    for i in range(b):
        state = initial[i : i + 1]
        for t in range(p):
            if t < first[i]:
                torch.testing.assert_close(out[i, t], initial[i, :H])  # untouched: the stored state's h
                continue
            h, state = rep.step([obs[i : i + 1, t]], prev[i : i + 1, t], state)
            torch.testing.assert_close(out[i, t], h[0], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("burn_in_gradient", [False, True])
def test_burn_in_rows_get_no_gradient_unless_configured(burn_in_gradient: bool) -> None:
    rep = recurrent()
    obs = torch.randn(3, 7, OBS, requires_grad=True)
    out = rep.sequence([obs], torch.zeros(3, 7, ACT), torch.zeros(3, H), torch.ones(3, 7, dtype=torch.bool),
                       burn_in=4, burn_in_gradient=burn_in_gradient)  # fmt: skip
    out[:, 4:].sum().backward()
    assert obs.grad is not None
    burn_in_grad = obs.grad[:, :4].abs().sum()
    assert (burn_in_grad > 0) == burn_in_gradient
    assert obs.grad[:, 4:].abs().sum() > 0


def make_sac(**sac: object) -> SAC:
    spec = EnvSpec((SensorSpec("obs", (OBS,)),), ActionSpec((), ACT, (-1.0,) * ACT, (1.0,) * ACT))
    cfg = SacConfig(**{"seed": 2, "use_rnn": True, "burn_in_step": 3, "n_step": 2, **sac})  # type: ignore[arg-type]
    return SAC(spec, cfg, NNConfig(hidden_units=[16], rnn_units=H), ReplayConfig())


def test_a_recurrent_policy_acts_through_act_recurrent_only() -> None:
    sac = make_sac()
    obs = [np.zeros((2, OBS), np.float32)]
    with pytest.raises(TypeError, match="act_recurrent"):
        sac.act(obs)
    actions, logp, state = sac.act_recurrent(obs, np.zeros((2, ACT), np.float32), sac.initial_rnn_state(2))
    assert actions.shape == (2, ACT) and logp.shape == (2,) and state.shape == (2, H) and np.abs(state).sum() > 0
    with pytest.raises(ValueError, match="rnn_state"):
        sac.act_recurrent(obs, np.zeros((2, ACT), np.float32), np.zeros((2, H + 1), np.float32))


def test_a_recurrent_config_backpropagates_through_its_burn_in_unless_told_not_to() -> None:
    # Issue 15, defect 1: burn_in_gradient defaulted to false, so a recurrent config that did not
    # name it (as the original's never did: it always backpropagated through burn-in) trained its
    # cell with one step of backpropagation through time and could not learn memory.
    overrides = ["sac.use_rnn=true", "sac.burn_in_step=4"]
    assert load_config(None, None, overrides).config.sac_config.burn_in_gradient
    assert SacConfig(use_rnn=True, burn_in_step=4).burn_in_gradient
    off = load_config(None, None, [*overrides, "sac.burn_in_gradient=false"]).config.sac_config
    assert not off.burn_in_gradient


@pytest.mark.parametrize("cut", [2, 4, 5])  # the bootstrap row at 2, at 4 (inside), at L = 5 (a full window)
def test_the_bootstrap_position_is_fed_the_last_action_taken(cut: int) -> None:
    # Issue 15, defect 3: a window cut short by its chunk's end (or a time-limit truncation, which
    # ends a chunk) fed its bootstrap position the zeros the table stores on a bootstrap row as
    # previous action, where the action taken before it is in the window.
    sac, length, b = make_sac(), 5, 3
    rng = np.random.default_rng(cut)
    mask = np.zeros((b, length), bool)
    mask[:, :cut] = True
    actions = np.where(mask[..., None], rng.uniform(-1, 1, (b, length, ACT)), 0.0).astype(np.float32)
    prev_actions = np.concatenate([rng.uniform(-1, 1, (b, 1, ACT)), actions[:, :-1]], axis=1).astype(np.float32)
    prev_actions[~mask] = 0.0  # what the table's bootstrap row holds
    obs = torch.from_numpy(rng.standard_normal((b, length + 1, OBS), dtype=np.float32))
    state = torch.from_numpy(rng.standard_normal((b, H), dtype=np.float32))
    with torch.no_grad():
        online, _, _ = sequence_states([obs], torch.from_numpy(actions), torch.from_numpy(prev_actions),
                                       torch.from_numpy(mask), state, sac.sac, sac.models,
                                       sac.target_representation)  # fmt: skip
        rep = sac.models.representation
        assert isinstance(rep, RecurrentRepresentation)
        for t in range(cut + 1):  # the step rows, then the bootstrap position
            prev = prev_actions[:, t] if t < cut else actions[:, cut - 1]
            h, state = rep.step([obs[:, t]], torch.from_numpy(prev), state)
            torch.testing.assert_close(online[:, t], h, rtol=1e-5, atol=1e-6)


def test_burn_in_needs_use_rnn() -> None:
    with pytest.raises(ValueError, match="use_rnn"):
        SacConfig(burn_in_step=2)


def small_trainer(tmp: Path, *extra: str) -> EmbeddedTrainer:
    overrides = ["sac.seed=3", "nn.hidden_units=[16, 16]", "nn.rnn_units=8", "replay.batch_size=16",
                 "replay.min_size_to_sample=64", "replay.samples_per_insert=null", "actor.chunk_length=16",
                 "eval.eval_per_step=0", "base.max_step=300", *extra]  # fmt: skip
    config = load_config(ROOT / "envs/gym/pendulum_novel", None, overrides).config
    factory = vector_env_factory(config.base_config.build_path, max_episode_steps=40)
    return EmbeddedTrainer(config, tmp, factory, evaluate=False, progress=False)


def test_actors_store_the_state_they_acted_with_and_learning_resumes_exactly(tmp_path: Path) -> None:
    trainer = small_trainer(tmp_path / "a")
    chunks = []
    insert = trainer.actor.sink

    def sink(chunk):  # noqa: ANN001, ANN202
        chunks.append(chunk)
        return insert(chunk)

    trainer.actor.sink = sink
    trainer.run(until_step=200)
    assert trainer.sac.updates > 50
    assert all(c.rnn_state is not None and c.rnn_state.shape == (len(c), 8) for c in chunks)
    # episodes are 40 steps and chunks 16: chunks 0, 3, 6, ... start an episode (state zeros), others do not
    starts = [c for i, c in enumerate(chunks) if i % 3 == 0]
    assert all(np.all(c.rnn_state[0] == 0) for c in starts)
    assert all(np.abs(c.rnn_state[1:]).sum() > 0 for c in chunks)
    # chunk 1 (steps 16..31) was collected before the first update (64 stored steps), by the initial
    # parameters: replaying its steps through the fresh policy gives exactly the stored next states
    fresh = small_trainer(tmp_path / "b").sac
    c = chunks[1]
    _, _, next_states = fresh.act_recurrent([c.obs[0][:-2]], c.prev_actions[:-1], c.rnn_state[:-1])
    np.testing.assert_allclose(next_states, c.rnn_state[1:], rtol=1e-5, atol=1e-6)

    batch = trainer.table.sample(16)
    resumed = copy.deepcopy(trainer.sac)
    resumed.load_state_dict(copy.deepcopy(trainer.sac.state_dict()))
    np.testing.assert_array_equal(trainer.sac.update(batch).td_abs, resumed.update(batch).td_abs)


def test_refreshed_states_are_what_the_pre_update_network_feeds_at_each_valid_window_row() -> None:
    """sac.refresh_rnn_states: one (key, state) per valid window row; the first valid row keeps its
    stored state, later rows get the state the network (before this update) carries there."""
    sac = make_sac(refresh_rnn_states=True)
    before = copy.deepcopy(sac)
    b, length = 4, 5  # burn_in 3 + n_step 2
    rng = np.random.default_rng(0)
    mask = np.ones((b, length), dtype=bool)
    mask[1, :2] = False  # look-back rows before window 1's chunk start
    mask[2, 4:] = False  # window 2's chunk ends after its step 3
    keys = np.array([10, 21, 32, 43], dtype=np.uint64)  # the trained step: window position 3
    batch = Batch(
        keys=keys, probabilities=np.full(b, 0.01), table_size=100,
        obs=[rng.standard_normal((b, length + 1, OBS), dtype=np.float32)],
        actions=rng.uniform(-1, 1, (b, length, ACT)).astype(np.float32),
        prev_actions=rng.uniform(-1, 1, (b, length, ACT)).astype(np.float32),
        rewards=rng.standard_normal((b, length), dtype=np.float32),
        terminated=np.zeros((b, length), bool), truncated=np.zeros((b, length), bool),
        behaviour_logp=np.zeros((b, length), np.float32), mask=mask,
        rnn_state=rng.standard_normal((b, H), dtype=np.float32),
    )  # fmt: skip
    result = sac.update(batch)
    assert result.refreshed_rnn_states is not None
    row_keys, states = result.refreshed_rnn_states
    expected_keys = [k - 3 + j for i, k in enumerate(keys.tolist()) for j in range(length) if mask[i, j]]
    assert row_keys.tolist() == expected_keys and row_keys.dtype == np.uint64
    rep = before.models.representation
    assert isinstance(rep, RecurrentRepresentation)
    prev = torch.cat([torch.from_numpy(batch.prev_actions), torch.from_numpy(batch.actions[:, -1:])], dim=1)
    first = torch.from_numpy(mask).long().argmax(dim=1)
    valid = torch.arange(length + 1)[None, :] >= first[:, None]
    with torch.no_grad():
        _, fed = rep.sequence_with_states(
            [torch.from_numpy(batch.obs[0])], prev, torch.from_numpy(batch.rnn_state), valid
        )
    np.testing.assert_allclose(states, fed[:, :-1].numpy()[mask], rtol=1e-5, atol=1e-6)
    first_rows = [expected_keys.index(int(k) - 3 + int(first[i])) for i, k in enumerate(keys)]
    np.testing.assert_array_equal(states[first_rows], batch.rnn_state)
    assert make_sac().update(batch).refreshed_rnn_states is None  # off by default


def test_a_trainer_with_refresh_writes_states_back_into_replay(tmp_path: Path) -> None:
    trainer = small_trainer(tmp_path, "sac.refresh_rnn_states=true")
    trainer.run(until_step=150)
    assert trainer.sac.updates > 10
    assert trainer.table.info()["rnn_state_updates"] > 0
