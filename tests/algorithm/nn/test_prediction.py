"""Prediction models (``use_prediction``): the models train, and each auxiliary gradient reaches
the representation only when its cosine with the critic's gradient there is positive."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.nn.builder import build_models
from algorithm.nn.models import Representation
from algorithm.nn.prediction import gated_gradients, observation_targets
from algorithm.sac.learner import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from tests.algorithm.sac.test_learner import make_batch

OBS, ACT = 3, 2
SPEC = EnvSpec((SensorSpec("obs", (OBS,)),), ActionSpec((), ACT, (-1.0,) * ACT, (1.0,) * ACT))


def test_the_cosine_gate_drops_an_opposing_gradient_and_keeps_an_aligned_one() -> None:
    w = nn.Parameter(torch.tensor([1.0, 2.0]))
    critic = [torch.tensor([1.0, 0.0])]
    losses = {"aligned": (w * torch.tensor([3.0, 1.0])).sum(), "opposing": (w * torch.tensor([-2.0, 0.5])).sum()}
    total, cosines = gated_gradients(losses, critic, [w])
    torch.testing.assert_close(total[0], torch.tensor([3.0, 1.0]))  # only the aligned gradient
    assert cosines["aligned"] > 0 > cosines["opposing"]


class LinearRepresentation(Representation):
    def __init__(self, spec: EnvSpec, nn_config: NNConfig) -> None:
        super().__init__()
        self.linear = nn.Linear(OBS, 8)
        self.state_dim = self.policy_state_dim = 8

    def forward(self, obs: list[Tensor]) -> Tensor:
        return torch.tanh(self.linear(obs[0]))


def make_sac(**sac: object) -> SAC:
    def build(spec: EnvSpec, sac_cfg: SacConfig, nn_cfg: NNConfig):  # noqa: ANN202
        return build_models(spec, sac_cfg, nn_cfg, representation=LinearRepresentation(spec, nn_cfg))

    cfg = SacConfig(**{"seed": 0, "use_priority": False, "learning_rate": 3e-3, **sac})  # type: ignore[arg-type]
    return SAC(SPEC, cfg, NNConfig(hidden_units=[16]), ReplayConfig(), build=build)


def test_prediction_models_train_and_gate_into_a_learned_representation() -> None:
    sac = make_sac(use_prediction=True)
    assert sac.models.prediction is not None
    batch = make_batch(b=32)
    batch.rewards[:, 0] = batch.obs[0][:, 0, 0]  # a reward the state determines
    first = sac.update(batch, with_metrics=True).metrics
    for key in ("transition", "reward", "observation"):
        assert np.isfinite(first[f"learner/prediction_{key}"])
        assert -1.0 <= first[f"learner/prediction_{key}_cosine"] <= 1.0
    for _ in range(80):
        last = sac.update(batch, with_metrics=True).metrics
    assert last["learner/prediction_reward"] < 0.5 * first["learner/prediction_reward"]
    assert last["learner/prediction_observation"] < 0.5 * first["learner/prediction_observation"]


def test_without_prediction_the_representation_sees_only_the_critic_gradient() -> None:
    # Same seed and batch: with prediction on, the representation's first step differs from the
    # plain learner's exactly when some auxiliary gradient was kept (a positive cosine).
    plain, predicting = make_sac(), make_sac(use_prediction=True)
    batch = make_batch(b=32)
    plain.update(batch)
    metrics = predicting.update(batch, with_metrics=True).metrics
    kept = any(metrics[f"learner/prediction_{k}_cosine"] > 0 for k in ("transition", "reward", "observation"))
    moved_differently = not torch.equal(
        plain.models.representation.linear.weight, predicting.models.representation.linear.weight
    )
    assert moved_differently == kept


def test_observation_targets_leave_out_images_masks_and_privileged_sensors_without_extra_data() -> None:
    sensors = [SensorSpec("action_mask", (2,)), SensorSpec("cam", (8, 8, 3), np.dtype(np.uint8)),
               SensorSpec("obs", (3,)), SensorSpec("truth", (2,))]  # fmt: skip
    assert observation_targets(sensors, ["truth"], use_extra_data=True) == [2, 3]
    assert observation_targets(sensors, ["truth"], use_extra_data=False) == [2]
