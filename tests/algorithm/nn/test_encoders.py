"""Conv encoders and the mixed image + vector representation with critic-only sensors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from algorithm.nn.encoders import NATURE_CNN, SMALL_CNN, ConvEncoder, MultiSensorRepresentation
from algorithm.spaces import SensorSpec

U8 = np.dtype(np.uint8)


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


def _images(*shape: int) -> torch.Tensor:
    return torch.randint(0, 256, shape, dtype=torch.uint8)


def _conv_layers(encoder: ConvEncoder) -> list[tuple[int, int, int]]:
    convs = [m for m in encoder.convs if isinstance(m, torch.nn.Conv2d)]
    return [(m.out_channels, m.kernel_size[0], m.stride[0]) for m in convs]


@pytest.mark.parametrize(
    ("hwc", "stack", "conv_dim"),
    [((84, 84, 3), NATURE_CNN, 64 * 7 * 7), ((24, 24, 3), SMALL_CNN, 32 * 7 * 7), ((16, 16, 3), SMALL_CNN, 32 * 3 * 3)],
)
@pytest.mark.parametrize("lead", [(5,), (2, 3)])
def test_conv_encoder_shapes(
    hwc: tuple[int, int, int], stack: tuple[tuple[int, int, int], ...], conv_dim: int, lead: tuple[int, ...]
) -> None:
    projected = ConvEncoder(hwc)
    raw = ConvEncoder(hwc, out_features=None)
    assert _conv_layers(projected) == list(stack)
    assert projected.conv_dim == raw.conv_dim == raw.features == conv_dim
    assert projected.features == 50
    x = _images(*lead, *hwc)
    out = projected(x)
    assert out.shape == (*lead, 50) and out.dtype == torch.float32
    assert out.abs().max() <= 1.0  # tanh head
    assert raw(x).shape == (*lead, conv_dim)
    # lead dims are only flattened around the convs: each image's features equal its own pass
    torch.testing.assert_close(out.reshape(-1, 50), projected(x.reshape(-1, *hwc)))


def test_conv_encoder_non_square_and_stacked_frames() -> None:
    encoder = ConvEncoder((64, 96, 12), out_features=8)  # shorter side 64 -> Nature stack
    assert _conv_layers(encoder) == list(NATURE_CNN)
    assert encoder(_images(2, 64, 96, 12)).shape == (2, 8)


def test_uint8_and_float_of_the_same_pixel_values_give_identical_features() -> None:
    # Documented choice: inputs are [0, 255] intensities in any dtype; the encoder always scales by 1/255.
    encoder = ConvEncoder((16, 16, 3), out_features=None)
    x = _images(4, 16, 16, 3)
    as_float = x.float()
    before = as_float.clone()
    torch.testing.assert_close(encoder(x), encoder(as_float), rtol=0, atol=0)
    torch.testing.assert_close(as_float, before)  # the caller's float tensor is not scaled in place
    # ... and it is the convs applied to x / 255 in NCHW
    expected = encoder.convs((x.float() / 255).permute(0, 3, 1, 2))
    torch.testing.assert_close(encoder(x), expected)


def test_gradients_reach_conv_weights() -> None:
    encoder = ConvEncoder((24, 24, 3))
    encoder(_images(3, 24, 24, 3)).square().sum().backward()
    for name, p in encoder.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_conv_encoder_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="too small"):
        ConvEncoder((8, 8, 3))
    with pytest.raises(ValueError, match="out_features"):
        ConvEncoder((16, 16, 3), out_features=0)
    with pytest.raises(ValueError, match=r"16, 16, 3"):
        ConvEncoder((16, 16, 3))(_images(2, 16, 16, 4))


def _mixed_sensors() -> list[SensorSpec]:
    return [
        SensorSpec("joints", (4,)),
        SensorSpec("cam", (16, 16, 3), U8),
        SensorSpec("grid", (2, 3)),  # rank-2 float: flattened like a vector
        SensorSpec("top", (24, 24, 1), U8),
    ]


def _mixed_obs(*lead: int) -> list[torch.Tensor]:
    return [torch.randn(*lead, 4), _images(*lead, 16, 16, 3), torch.randn(*lead, 2, 3), _images(*lead, 24, 24, 1)]


@pytest.mark.parametrize("lead", [(5,), (2, 3)])
def test_mixed_sensors_concatenate_in_sensor_order(lead: tuple[int, ...]) -> None:
    rep = MultiSensorRepresentation(_mixed_sensors(), conv_features=7)
    assert rep.state_dim == rep.policy_state_dim == 4 + 7 + 6 + 7
    assert rep.feature_slices == {
        "joints": slice(0, 4),
        "cam": slice(4, 11),
        "grid": slice(11, 17),
        "top": slice(17, 24),
    }
    obs = _mixed_obs(*lead)
    state = rep(obs)
    assert state.shape == (*lead, 24)
    torch.testing.assert_close(state[..., rep.feature_slices["joints"]], obs[0])
    torch.testing.assert_close(state[..., rep.feature_slices["cam"]], rep.encoders[0](obs[1]))
    torch.testing.assert_close(state[..., rep.feature_slices["grid"]], obs[2].flatten(-2))
    torch.testing.assert_close(state[..., rep.feature_slices["top"]], rep.encoders[1](obs[3]))


def test_vector_only_matches_plain_concatenation() -> None:
    rep = MultiSensorRepresentation([SensorSpec("a", (3,)), SensorSpec("b", (2, 2))])
    a, b = torch.randn(5, 3), torch.randn(5, 2, 2)
    assert len(rep.encoders) == 0
    torch.testing.assert_close(rep([a, b]), torch.cat([a, b.flatten(-2)], dim=-1))


def test_critic_only_features_come_last_and_the_policy_gets_the_rest() -> None:
    # "grid" and "top" are privileged; the policy sees joints and cam only
    rep = MultiSensorRepresentation(_mixed_sensors(), conv_features=7, critic_only=["top", "grid"])
    assert rep.policy_state_dim == 4 + 7 and rep.state_dim == 4 + 7 + 6 + 7
    assert list(rep.feature_slices) == ["joints", "cam", "grid", "top"]
    assert rep.feature_slices["grid"] == slice(11, 17) and rep.feature_slices["top"] == slice(17, 24)
    obs = _mixed_obs(2, 3)
    state = rep(obs)
    policy = rep.policy_state(state)
    assert policy.shape == (2, 3, 11)
    torch.testing.assert_close(policy, torch.cat([obs[0], rep.encoders[0](obs[1])], dim=-1))
    # actors skip the privileged sensors: they are neither read nor checked
    placeholders = [obs[0], obs[1], torch.empty(0), torch.empty(0)]
    torch.testing.assert_close(rep.forward_policy(placeholders), policy)


def _mixed_obs_two_cams() -> list[torch.Tensor]:
    return [_images(3, 16, 16, 3), _images(3, 16, 16, 3)]


def test_policy_loss_gives_no_gradient_to_critic_only_encoder() -> None:
    rep = MultiSensorRepresentation(
        [SensorSpec("cam", (16, 16, 3), U8), SensorSpec("privileged_cam", (16, 16, 3), U8)],
        conv_features=5,
        critic_only=["privileged_cam"],
    )
    policy_encoder, critic_encoder = rep.encoders
    rep.policy_state(rep(_mixed_obs_two_cams())).square().sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in policy_encoder.parameters())
    assert all(p.grad is None or torch.all(p.grad == 0) for p in critic_encoder.parameters())
    rep.zero_grad()
    rep(_mixed_obs_two_cams()).square().sum().backward()  # the critic's loss trains both
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in critic_encoder.parameters())


def test_constructor_errors_name_the_sensors() -> None:
    sensors = _mixed_sensors()
    with pytest.raises(ValueError, match=r"unknown sensors \['nope'\]"):
        MultiSensorRepresentation(sensors, critic_only=["cam", "nope"])
    with pytest.raises(ValueError, match="every sensor"):
        MultiSensorRepresentation(sensors, critic_only=[s.name for s in sensors])
    with pytest.raises(ValueError, match=r"duplicate sensor names \['a'\]"):
        MultiSensorRepresentation([SensorSpec("a", (1,)), SensorSpec("a", (2,))])
    with pytest.raises(ValueError, match="at least one"):
        MultiSensorRepresentation([])


def test_forward_errors_name_the_sensor() -> None:
    rep = MultiSensorRepresentation(_mixed_sensors(), conv_features=7)
    obs = _mixed_obs(2)
    with pytest.raises(ValueError, match="expected 4 sensors"):
        rep(obs[:3])
    with pytest.raises(ValueError, match=r"sensor 'cam': expected shape \[\*lead, 16, 16, 3\], got \(2, 16, 16, 4\)"):
        rep([obs[0], _images(2, 16, 16, 4), obs[2], obs[3]])
    with pytest.raises(ValueError, match="sensor 'grid'"):
        rep([obs[0], obs[1], torch.randn(2, 6), obs[3]])
    with pytest.raises(ValueError, match=r"sensor 'cam': leading dims \(3,\) differ from \(2,\) of sensor 'joints'"):
        rep([obs[0], _images(3, 16, 16, 3), obs[2], obs[3]])
