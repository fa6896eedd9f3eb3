"""sac_config.numpy_acting: the NumPy forward acts exactly like the torch one, sees every weight
change, draws the same noise, and is used only where it computes the same thing."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import torch

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.nn.models import stored_action_log_prob
from algorithm.nn.numpy_acting import NumpyGaussianActor
from algorithm.sac.learner import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from tests.algorithm.sac.test_learner import make_batch

ACT = 3
TWO_SENSORS = EnvSpec(
    (SensorSpec("joints", (4,)), SensorSpec("grid", (2, 3))), ActionSpec((), ACT, (-1.0,) * ACT, (1.0,) * ACT)
)


def pair(spec: EnvSpec = TWO_SENSORS, nn: dict[str, Any] | None = None, **sac: Any) -> tuple[SAC, SAC]:
    """Two identically seeded SACs: one acting in NumPy, one in torch."""
    nn_cfg = NNConfig(**{"hidden_units": [32, 16], **(nn or {})})
    made = [
        SAC(spec, SacConfig(**{"seed": 3, **sac, "numpy_acting": numpy}), nn_cfg, ReplayConfig())
        for numpy in (True, False)
    ]
    assert isinstance(made[0]._numpy_actor, NumpyGaussianActor) and made[1]._numpy_actor is None
    return made[0], made[1]


def observations(n: int, seed: int = 0, spec: EnvSpec = TWO_SENSORS) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [3.0 * rng.standard_normal((n, *s.shape)).astype(np.float32) for s in spec.sensors]


def torch_sample(
    sac: SAC, obs: list[np.ndarray], noise: np.ndarray, extra: float, stored: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """What torch acting computes for the given standard-normal ``noise``: the action, and the
    behaviour log-prob of the action as ``stored`` (both paths evaluate it at the stored float32
    action, where atanh turns a 1e-6 difference near |a| = 1 into a visible one)."""
    with torch.no_grad():
        state = sac.models.representation(sac.obs_tensors(obs))
        assert sac.models.policy is not None
        action, _ = sac._behaviour_sample(state, torch.from_numpy(noise), extra)
        mean, log_std = sac.models.policy(state)
        if extra > 0:
            log_std = 0.5 * torch.logaddexp(2.0 * log_std, torch.full_like(log_std, 2.0 * math.log(extra)))
        log_prob = stored_action_log_prob(mean, log_std, torch.from_numpy(stored))
    return action.numpy(), log_prob.numpy()


def assert_same_acting(a: SAC, b: SAC, obs: list[np.ndarray], extra: float = 0.0, seed: int = 0) -> None:
    """Deterministic acting through ``act`` on both; stochastic acting with the same noise given to
    the NumPy policy and to torch (each path draws from its own generator)."""
    (x, logp_x), (y, logp_y) = a.act(obs, deterministic=True), b.act(obs, deterministic=True)
    compared = [(x, logp_x, y, logp_y)]
    noise = np.random.default_rng(seed).standard_normal((obs[0].shape[0], a.spec.action.continuous_dim))
    assert a._numpy_actor is not None
    noise = noise.astype(np.float32)
    x, logp_x = a._numpy_actor.act(obs, noise, extra)
    compared.append((x, logp_x, *torch_sample(b, obs, noise, extra, stored=x)))
    for x, logp_x, y, logp_y in compared:
        assert x.dtype == y.dtype == logp_x.dtype == logp_y.dtype == np.float32
        assert x.shape == y.shape and logp_x.shape == logp_y.shape
        np.testing.assert_allclose(x, y, atol=2e-6)
        assert np.isfinite(logp_x).all()
        np.testing.assert_allclose(logp_x, logp_y, rtol=1e-5, atol=2e-5)


@pytest.mark.parametrize("activation", ["relu", "tanh", "elu", "silu"])
@pytest.mark.parametrize("n", [1, 5, 8, 40])  # both sides of the transposed-copy threshold (8 rows)
def test_numpy_acting_matches_torch(activation: str, n: int) -> None:
    a, b = pair(nn={"activation": activation})
    assert_same_acting(a, b, observations(n))


def test_extra_exploration_noise_and_saturated_actions_match() -> None:
    a, b = pair()
    for extra in (0.3, 5.0, 1e6):  # 1e6: every action saturates; the log-prob must stay finite and equal
        assert_same_acting(a, b, observations(16, seed=int(extra)), extra=extra, seed=1)


def test_normalized_observations_match_once_statistics_arrive() -> None:
    a, b = pair(use_normalization=True)
    obs = observations(12)
    assert_same_acting(a, b, obs)  # identity before statistics
    stats = {
        "joints": {"count": 10, "mean": np.arange(4.0), "var": np.full(4, 0.25)},
        "grid": {"count": 10, "mean": np.ones((2, 3)), "var": np.full((2, 3), 4.0)},
    }
    for sac in (a, b):
        sac.load_normalizer_stats(stats)
    assert_same_acting(a, b, [o * 10 for o in obs])  # x10: some entries hit the clip at 5 std


def test_weights_changed_in_place_are_seen_by_the_numpy_policy() -> None:
    """Optimizer steps, loading a checkpoint and loading published weights all change the torch
    parameters in place; the NumPy views (and the transposed copies of >= 8-row batches) follow."""
    spec = EnvSpec((SensorSpec("obs", (3,)),), ActionSpec((), 2, (-1.0,) * 2, (1.0,) * 2))
    a, b = pair(spec)
    obs = observations(16, spec=spec)
    a.act(obs), b.act(obs)  # builds the transposed copies
    for sac in (a, b):
        sac.update(make_batch(seed=4))
    assert_same_acting(a, b, obs)

    trained, _ = pair(spec, seed=9)
    for _ in range(3):
        trained.update(make_batch(seed=5))
    before = a.act(obs, deterministic=True)[0]
    a.load_acting_state_dict(trained.acting_state_dict())
    b.load_state_dict(trained.state_dict())
    after = a.act(obs, deterministic=True)[0]
    assert not np.allclose(before, after)
    np.testing.assert_allclose(after, trained.act(obs, deterministic=True)[0], atol=2e-6)
    assert_same_acting(a, b, obs)


def test_numpy_acting_noise_is_seeded_and_checkpointed() -> None:
    """The same seed acts the same; a SAC restored from a state dict continues the same noise."""
    a, _ = pair()
    twin, _ = pair()
    obs = observations(6)
    torch_rng, numpy_rng = a._act_rng.get_state(), a._act_np_rng.bit_generator.state
    first = [a.act(obs)[0] for _ in range(3)]
    # act() took the NumPy path: its generator moved, torch's did not
    assert torch.equal(a._act_rng.get_state(), torch_rng) and a._act_np_rng.bit_generator.state != numpy_rng
    np.testing.assert_array_equal(np.stack(first), np.stack([twin.act(obs)[0] for _ in range(3)]))
    assert not np.array_equal(first[0], first[1])  # fresh noise every call
    saved = a.state_dict()
    expected = a.act(obs)[0]
    restored, _ = pair(seed=11)
    restored.load_state_dict(saved)
    np.testing.assert_array_equal(restored.act(obs)[0], expected)
    a.act(obs, deterministic=True)  # deterministic acting draws nothing
    np.testing.assert_array_equal(a.act(obs)[0], restored.act(obs)[0])


def test_bad_observations_are_refused_as_by_the_torch_path() -> None:
    a, _ = pair()
    with pytest.raises(ValueError, match="expected 2 sensors"):
        a.act(observations(2)[:1])
    with pytest.raises(ValueError, match="sensor 'grid' must be"):
        a.act([observations(2)[0], np.zeros((2, 6), dtype=np.float32)])


CONTINUOUS = ActionSpec((), ACT, (-1.0,) * ACT, (1.0,) * ACT)


@pytest.mark.parametrize(
    ("spec", "sac", "nn"),
    [
        (TWO_SENSORS, {"numpy_acting": False}, {}),
        (TWO_SENSORS, {}, {"noisy_policy": True}),
        (TWO_SENSORS, {"use_rnd": True}, {}),
        (TWO_SENSORS, {"use_rnn": True}, {"rnn_units": 8}),
        (TWO_SENSORS, {}, {"critic_only": ["grid"]}),
        (EnvSpec((SensorSpec("obs", (4,)),), ActionSpec((3,), 0, (), ())), {}, {}),
        (EnvSpec((SensorSpec("obs", (4,)),), ActionSpec((3,), ACT, (-1.0,) * ACT, (1.0,) * ACT)), {}, {}),
        (EnvSpec((SensorSpec("pixels", (12, 12, 3), np.dtype(np.uint8)),), CONTINUOUS), {}, {}),
    ],
    ids=["switched-off", "noisy-policy", "rnd", "recurrent", "critic-only", "discrete", "mixed", "image"],
)
def test_models_numpy_cannot_mirror_act_with_torch(spec: EnvSpec, sac: dict[str, Any], nn: dict[str, Any]) -> None:
    model = SAC(spec, SacConfig(seed=0, **sac), NNConfig(hidden_units=[16], **nn), ReplayConfig())
    assert model._numpy_actor is None
