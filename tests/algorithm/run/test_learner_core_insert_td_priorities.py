"""``sac_config.insert_td_priorities`` (issue 15, item 6): new data's priority is its |TD| under the
learner's networks, scored right after it is stored, instead of the table's maximum priority (the
original's ``use_add_with_td``). The same learner core does it in both modes; over gRPC the
learner reads the new windows with the replay's ``Windows`` rpc (tests/ds/replay/test_client_contract.py
runs the table's ``windows_after`` contract against the server)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from algorithm.config.schema import Config
from algorithm.replay import PrioritizedTable
from algorithm.run.learner_core import LearnerCore
from algorithm.sac.learner import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from algorithm.types import Chunk

SPEC = EnvSpec((SensorSpec("state", (3,)),), ActionSpec((), 2, (-1.0, -1.0), (1.0, 1.0)))


def random_chunk(rng: np.random.Generator, t: int) -> Chunk:
    return Chunk(
        obs=[rng.standard_normal((t + 1, 3)).astype(np.float32)],
        actions=rng.uniform(-0.9, 0.9, (t, 2)).astype(np.float32),
        prev_actions=np.zeros((t, 2), np.float32),
        rewards=0.01 * rng.standard_normal(t).astype(np.float32),  # |TD| well under td_error_max
        terminated=np.zeros(t, bool),
        truncated=np.zeros(t, bool),
        behaviour_logp=np.zeros(t, np.float32),
    )


def core_and_table(tmp_path: Path, insert_td: bool) -> tuple[LearnerCore, PrioritizedTable, SAC]:
    config = Config.model_validate(
        {
            "sac_config": {"seed": 0, "insert_td_priorities": insert_td, "n_step": 3},
            "nn_config": {"hidden_units": [16]},
            "replay_config": {"batch_size": 8, "alpha": 0.9, "min_size_to_sample": 1},
            "eval_config": {"eval_per_step": 0},
        }
    )
    table = PrioritizedTable.from_config(config.replay_config, SPEC.sensors, SPEC.action.size, window=3, seed=0)
    sac = SAC(SPEC, config.sac_config, config.nn_config, config.replay_config)
    return LearnerCore(config, tmp_path, sac, log_dir=tmp_path / "log"), table, sac


@pytest.mark.parametrize("insert_td", [False, True], ids=["maximum priority", "scored"])
def test_new_data_gets_its_td_error_as_priority_only_with_the_option(tmp_path: Path, insert_td: bool) -> None:
    core, table, sac = core_and_table(tmp_path, insert_td)
    rng = np.random.default_rng(0)
    for _ in range(30):  # 1,920 old steps: a batch of 8 rarely draws one of the new ones
        table.insert(random_chunk(rng, 64))
    core.train_on(table.sample(8), table)  # scores (with the option) everything stored so far
    new_keys = table.insert(random_chunk(rng, 64))
    score_noise = sac._score_rng.get_state()
    core.train_on(table.sample(8), table)

    new = table.windows_after(int(new_keys[0]), 64)
    assert new is not None and new.keys.tolist() == new_keys.tolist()
    at_max = np.isclose(new.probabilities, table.info()["max_priority"] / table.info()["total_priority"])
    if not insert_td:
        assert at_max.sum() >= 64 - 8  # only what the update sampled has left the maximum
        assert core.counters.scored_below == 0
        return
    assert not at_max.any()
    assert core.counters.scored_below == int(new_keys[-1]) + 1
    # Each new step's priority is (clipped |TD| under the weights after the update) ** alpha: scored
    # again here a batch at a time with the same noise, the values come out the same.
    sac._score_rng.set_state(score_noise)
    pieces = [table.windows_after(int(k), 8) for k in new_keys[::8]]
    td = np.concatenate([sac.td_errors(piece) for piece in pieces if piece is not None])
    rc = core.config.replay_config
    expected = np.clip(td, rc.td_error_min, rc.td_error_max) ** rc.alpha
    np.testing.assert_allclose(new.probabilities * table.info()["total_priority"], expected, rtol=1e-5)


def test_the_option_needs_prioritized_replay() -> None:
    with pytest.raises(ValidationError, match=r"insert_td_priorities.*replay_config\.alpha is 0"):
        Config.model_validate({"sac_config": {"insert_td_priorities": True}, "replay_config": {"alpha": 0.0}})


def test_scoring_does_not_change_the_updates_random_stream(tmp_path: Path) -> None:
    """td_errors draws its noise from a generator of its own: a run with scoring trains on the same
    noise as one without, so the option changes priorities and nothing else of an update."""
    rng = np.random.default_rng(1)
    chunk = random_chunk(rng, 64)
    _, table, sac = core_and_table(tmp_path, False)
    table.insert(chunk)
    batch = table.sample(8)
    before = sac._learn_rng.get_state().clone()
    sac.td_errors(batch)
    assert bool((sac._learn_rng.get_state() == before).all())
