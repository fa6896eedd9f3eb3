"""bench/sb3_update_check.py: ASAC's SAC update against SB3's from the same weights, batches and noise.

The comparison itself needs SB3 (the optional peer, ``pip install -e '.[bench]'``) and is skipped without
it; the gap it reports and its rounding floor are checked without SB3 (the density option itself:
tests/algorithm/sac/test_tanh_log_det_epsilon.py)."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from bench import sb3_update_check as check

UPDATES = 20


def test_the_gap_is_zero_for_the_same_change_and_relative_per_group() -> None:
    start = {
        "policy.w": torch.zeros(4),
        "q.w": torch.zeros(2),
        "target_q.w": torch.zeros(2),
        "log_alpha": torch.zeros(()),
    }
    theirs = {
        "policy.w": torch.ones(4),
        "q.w": torch.full((2,), 2.0),
        "target_q.w": torch.ones(2),
        "log_alpha": torch.ones(()),
    }
    ours = {**theirs, "q.w": torch.tensor([2.0, 0.0])}
    gaps = check.relative_gaps(start, ours, theirs)
    assert gaps == {"policy": 0.0, "q": pytest.approx(2 / math.sqrt(8)), "target_q": 0.0, "log_alpha": 0.0}


def test_the_floor_is_two_asac_learners_apart_by_rounding_only() -> None:
    """Without SB3: the same update on each batch's rows in another order (noise reordered with them) is the
    same update, so a row paired with another row's noise or a loss that depends on row order shows here."""
    seen: list[dict[str, float]] = []
    last = check.rounding_floor("hopper", 5, 0, lambda update, gaps: seen.append(gaps), reorder=1)
    assert len(seen) == 5 and seen[-1] == last
    assert max(last.values()) < 1e-4, last


@pytest.fixture(scope="module")
def gaps() -> dict[tuple[str, str, str], dict[str, float]]:
    pytest.importorskip("stable_baselines3")
    return {
        v: check.compare("hopper", UPDATES, v, 0, lambda update, gaps: None)
        for v in (check.VARIANTS[0], check.VARIANTS[-1])
    }


def test_with_sb3s_three_choices_asacs_update_is_sb3s_to_rounding(
    gaps: dict[tuple[str, str, str], dict[str, float]],
) -> None:
    """Any change to ASAC's losses, targets or optimizers that SB3 does not share shows up here."""
    assert max(gaps[check.VARIANTS[-1]].values()) < 1e-4, gaps


def test_asacs_default_is_told_apart_from_sb3(gaps: dict[tuple[str, str, str], dict[str, float]]) -> None:
    """The check can fail: ASAC's exact density and joint order move the policy's update measurably."""
    assert gaps[check.VARIANTS[0]]["policy"] > 1e-3, gaps


def test_the_critics_rows_on_either_side_of_a_relu_are_found_only_where_they_are() -> None:
    """The same weights put every row on the same side of every ReLU, to rounding; one input weight of one
    unit moved puts the rows whose input to it is near 0 on the other side, named by head, layer and unit."""
    pytest.importorskip("stable_baselines3")
    sac, sb3, batch = check.paired_learners("hopper", "critic_first", 0)
    data = check.random_transitions(check.MUJOCO_TASKS["hopper"], 500, 0)
    rows = np.arange(batch)
    assert check.relu_disagreements(sac, sb3, data, rows) == []
    with torch.no_grad():
        sb3.policy.critic.qf1[0].bias[7] += 0.05
    found = check.relu_disagreements(sac, sb3, data, rows)
    assert found and all(line.startswith(("Q head 1 layer 0 unit 7 row ", "Q head 1 layer 1 ")) for line in found)
    assert any(line.startswith("Q head 1 layer 0 unit 7 row ") for line in found), found


def test_the_peer_trains_without_leaving_folders_in_the_temporary_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The SB3 model the suite builds (bench.systems.sb3_model) records to a logger of its own: SB3's
    learn() at verbose 0 otherwise makes an empty SB3-<date> folder in the temporary directory on every
    call, which the test suite and the MuJoCo suite left there by the hundred."""
    pytest.importorskip("stable_baselines3")
    from bench.systems import sb3_model

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.delenv("SB3_LOGDIR", raising=False)
    model = sb3_model("Pendulum-v1", seed=0, learning_starts=4, buffer_size=100)
    model.learn(total_timesteps=8)
    model.learn(total_timesteps=4, reset_num_timesteps=False)
    assert model.num_timesteps == 12
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith("SB3-")] == []  # torch may cache there
