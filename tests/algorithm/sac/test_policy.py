"""The acting side of SAC on its own: a :class:`Policy` acts exactly as the learner's :class:`SAC` of
the same seed and weights, and builds neither optimizers nor target networks (issue 16, item 1)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.sac.learner import SAC
from algorithm.sac.policy import Policy
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec

SPEC = EnvSpec((SensorSpec("obs", (3,)),), ActionSpec((), 2, (-1.0,) * 2, (1.0,) * 2))
DISCRETE = EnvSpec((SensorSpec("obs", (3,)),), ActionSpec((3, 2), 0, (), ()))
NN = NNConfig(hidden_units=[16, 16])
OBS = [np.random.default_rng(0).standard_normal((5, 3), dtype=np.float32)]


def count_adams(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    made: list[int] = []
    real = torch.optim.Adam

    def counting(*args: Any, **kwargs: Any) -> torch.optim.Adam:
        made.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(torch.optim, "Adam", counting)
    return made


def test_a_policy_builds_no_optimizer_and_no_target_network(monkeypatch: pytest.MonkeyPatch) -> None:
    made = count_adams(monkeypatch)
    policy = Policy(SPEC, SacConfig(seed=1), NN)
    assert made == []
    assert not any(hasattr(policy, name) for name in ("target_q", "target_representation", "critic_optimizer"))
    assert sum(p.numel() for p in policy.models.parameters()) > 0
    SAC(SPEC, SacConfig(seed=1), NN, ReplayConfig())
    assert len(made) >= 3  # the counter sees the learner's critic, policy and alpha optimizers


@pytest.mark.parametrize("spec", [SPEC, DISCRETE], ids=["continuous", "discrete"])
@pytest.mark.parametrize("numpy_acting", [True, False])
def test_a_policy_acts_as_the_learner_of_the_same_seed(spec: EnvSpec, numpy_acting: bool) -> None:
    cfg = SacConfig(seed=4, numpy_acting=numpy_acting)
    policy, sac = Policy(spec, cfg, NN), SAC(spec, cfg, NN, ReplayConfig())
    for deterministic in (True, False, False):
        a, logp_a = policy.act(OBS, deterministic)
        b, logp_b = sac.act(OBS, deterministic)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(logp_a, logp_b)


def test_a_policy_loads_a_learner_checkpoint_and_its_published_weights() -> None:
    sac = SAC(SPEC, SacConfig(seed=1), NN, ReplayConfig())
    with torch.no_grad():
        for p in sac.models.parameters():
            p.add_(0.1)
    fresh = Policy(SPEC, SacConfig(seed=2), NN)
    fresh.load_state_dict(sac.state_dict())  # a checkpoint's "sac": the learner parts are not read
    np.testing.assert_array_equal(fresh.act(OBS, True)[0], sac.act(OBS, True)[0])
    np.testing.assert_array_equal(fresh.act(OBS)[0], sac.act(OBS)[0])  # the acting generators came too

    published = Policy(SPEC, SacConfig(seed=3), NN)
    published.load_acting_state_dict(sac.acting_state_dict())
    np.testing.assert_array_equal(published.act(OBS, True)[0], sac.act(OBS, True)[0])
    with pytest.raises(KeyError, match="models"):
        published.load_state_dict({"rng": {}})
