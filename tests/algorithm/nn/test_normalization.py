"""Observation normalization (``use_normalization``): the learner's statistics are the exact
mean/var of every observation inserted into replay, images and masks pass through, and the
statistics travel in checkpoints and acting weights."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from algorithm.nn.normalization import ObservationNormalizer
from algorithm.normalizer import RunningMeanStd
from algorithm.spaces import SensorSpec
from tests.algorithm.run.test_trainer import make_trainer, small_config


def test_normalizer_matches_numpy_and_leaves_images_and_masks_alone() -> None:
    sensors = [
        SensorSpec("vec", (3,)),
        SensorSpec("cam", (4, 4, 3), np.dtype(np.uint8)),
        SensorSpec("action_mask", (2,)),
    ]
    norm = ObservationNormalizer(sensors)
    rng = np.random.default_rng(0)
    data = rng.normal(5.0, 3.0, (1000, 3))
    obs = [torch.randn(7, 3) * 20, torch.randint(0, 255, (7, 4, 4, 3), dtype=torch.uint8), torch.ones(7, 2)]
    before = norm(obs)
    assert all(torch.equal(a, b) for a, b in zip(before, obs, strict=True))  # identity until stats arrive
    rms = RunningMeanStd((3,))
    rms.update(data)
    norm.load_stats({"vec": rms.state_dict()})
    out = norm(obs)
    expected = np.clip((obs[0].numpy() - data.mean(0)) / np.sqrt(data.var(0) + 1e-8), -5, 5)
    np.testing.assert_allclose(out[0].numpy(), expected, rtol=1e-5, atol=1e-5)
    assert out[1] is obs[1] and out[2] is obs[2]
    assert np.abs(out[0].numpy()).max() <= 5.0


def test_trainer_learns_on_exact_statistics_of_all_inserted_observations(tmp_path: Path) -> None:
    trainer = make_trainer(small_config("sac.use_normalization=true", "eval.eval_per_step=0"), tmp_path, False)
    seen: list[np.ndarray] = []
    insert = trainer.actor.sink

    def sink(chunk):  # noqa: ANN001, ANN202
        # every observation once: a chunk cut mid-episode shares its last row with the next chunk
        ended = chunk.terminated[-1] or chunk.truncated[-1]
        seen.append(chunk.obs[0] if ended else chunk.obs[0][:-1])
        return insert(chunk)

    trainer.actor.sink = sink
    trainer.run(until_step=300)  # paused, not finished: every inserted chunk has reached the learner
    rows = np.concatenate(seen)
    norm = trainer.sac.models.normalizer
    assert norm is not None and int(norm.count) > 0
    np.testing.assert_allclose(norm.mean_obs.numpy(), rows.mean(0), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(norm.std_obs.numpy(), np.sqrt(rows.var(0) + 1e-8), rtol=1e-4)
    assert {"normalizer.mean_obs", "normalizer.std_obs"} <= set(trainer.sac.acting_state_dict())
    assert "normalizer.mean_obs" in trainer.sac.state_dict()["models"]


def test_a_fresh_normalizer_is_the_identity_and_its_weights_pass_the_actors_check() -> None:
    """Issue 61: the bound started at +inf, and every actor of a distributed run refused the learner's
    first weights ("normalizer.clip: 1 non-finite values"). Every buffer is finite from the start, and
    the module still passes every finite input through unchanged."""
    from ds.net.params import decode_params, encode_params, params_spec

    norm = ObservationNormalizer([SensorSpec("vec", (3,)), SensorSpec("grid", (2, 2))])
    state = norm.state_dict()
    assert all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point()), state
    version, params = decode_params(encode_params(7, state), params_spec(state))  # raised ParamsError
    assert version == 7 and params.keys() == state.keys()
    huge = torch.finfo(torch.float32).max
    obs = [torch.tensor([[-huge, huge, 1e30]]), torch.tensor([[[-3.5, 0.0], [2.0, huge]]])]
    assert all(torch.equal(a, b) for a, b in zip(norm(obs), obs, strict=True))


def test_a_checkpoint_with_the_old_infinite_bound_loads_as_the_identity_and_publishes_finite_weights() -> None:
    sensors = [SensorSpec("vec", (3,))]
    old = ObservationNormalizer(sensors).state_dict()
    old["clip"] = torch.tensor(float("inf"))  # as written before the bound was finite
    norm = ObservationNormalizer(sensors)
    norm.load_stats({"vec": {"count": 4, "mean": np.ones(3), "var": np.ones(3)}})  # then a checkpoint loads
    norm.load_state_dict(old)
    assert torch.equal(norm.clip, ObservationNormalizer(sensors).clip) and int(norm.count) == 0
    assert torch.equal(norm.mean_vec, torch.zeros(3))
    obs = [torch.tensor([[-1e30, 7.0, 1e30]])]
    assert torch.equal(norm(obs)[0], obs[0])
    assert torch.isfinite(norm.state_dict()["clip"])
    # a checkpoint with statistics keeps its bound of 5
    with_stats = ObservationNormalizer(sensors)
    with_stats.load_state_dict(norm.state_dict() | {"clip": torch.tensor(5.0), "count": torch.tensor(4)})
    assert float(with_stats.clip) == 5.0
