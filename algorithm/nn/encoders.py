"""Image encoders and the mixed image + vector representation (docs/architecture.md section 3).

Images arrive as HWC ``uint8`` straight from replay (``algorithm/spaces.py``): a quarter of the
bytes of float32 on the host-to-device copy. The conversion to float, the ``1/255`` scaling and the
HWC -> CHW permute all happen inside :class:`ConvEncoder`, i.e. on whatever device the model lives.

:class:`MultiSensorRepresentation` is the :class:`~algorithm.nn.models.Representation` for any mix
of image and vector sensors, with optional critic-only (privileged) sensors for an asymmetric
critic: their features sit at the end of the state, so the policy's state is a prefix slice of the
critic's and the encoders run once per batch.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from algorithm.nn.layers import activation
from algorithm.nn.models import Representation
from algorithm.spaces import SensorSpec

# (out_channels, kernel, stride) per conv layer, each followed by the activation.
# Nature DQN (Mnih et al. 2015, "Human-level control through deep RL", Methods): 84x84 -> 20 -> 9 -> 7.
NATURE_CNN: tuple[tuple[int, int, int], ...] = ((32, 8, 4), (64, 4, 2), (64, 3, 1))
# Small images (< 64 px): the Nature stack's 8x8/4 first layer would leave 16 px as a 3x3 map and
# collapse to nothing in its last layer. 3x3 kernels with one stride-2 layer, 32 filters each, as in
# the SAC-AE encoder (Yarats et al. 2019, 1910.01741, appendix) cut to three layers: 24 -> 11 -> 9 -> 7,
# 16 -> 7 -> 5 -> 3; the smallest image it takes is 11 px per side.
SMALL_CNN: tuple[tuple[int, int, int], ...] = ((32, 3, 2), (32, 3, 1), (32, 3, 1))
# Images at least this many pixels on their shorter side get NATURE_CNN, smaller ones SMALL_CNN.
NATURE_MIN_SIDE = 64


def conv_stack_for(height: int, width: int) -> tuple[tuple[int, int, int], ...]:
    """The conv layers :class:`ConvEncoder` uses for an ``height x width`` image."""
    return NATURE_CNN if min(height, width) >= NATURE_MIN_SIDE else SMALL_CNN


class ConvEncoder(nn.Module):
    """``[*lead, H, W, C]`` pixel images -> ``[*lead, features]``.

    Input values are pixel intensities in ``[0, 255]`` *whatever the dtype*: ``uint8`` from replay,
    or a float tensor of the same values (e.g. after a float-valued augmentation such as DrQ's random
    shift, Kostrikov et al. 2020, 2004.13649, which DrQ-v2 also applies before its ``/255``). The
    encoder always scales by ``1/255``, so ``x`` and ``x.float()`` give identical features; a float
    input already in ``[0, 1]`` would be scaled twice. Deciding by value range instead would make
    the output depend on the batch's content, and deciding by dtype would make ``.float()`` a silent
    255x change of input scale.

    The conv stack is :data:`NATURE_CNN` for images whose shorter side is at least
    :data:`NATURE_MIN_SIDE` px, :data:`SMALL_CNN` otherwise; ``conv_dim`` (the flattened conv output)
    is found by a dry run at construction.

    ``out_features`` (default 50) adds ``Linear -> LayerNorm -> tanh`` on top, the SAC-AE encoder
    head (Yarats et al. 2019, 1910.01741) that DrQ reuses: it shrinks thousands of conv features
    (3136 for 84x84) to a state small enough that the Q heads' and policy's first layers stay cheap,
    and LayerNorm + tanh keep the state's scale fixed in ``[-1, 1]`` while the conv weights move
    under the critic's gradients (part of SAC-AE's recipe for stable SAC from pixels).
    ``out_features=None`` returns the raw flattened conv features (``features == conv_dim``).
    """

    def __init__(
        self,
        shape_hwc: tuple[int, int, int],
        out_features: int | None = 50,
        activation_name: str = "relu",
    ) -> None:
        super().__init__()
        if len(shape_hwc) != 3 or min(shape_hwc) < 1:
            raise ValueError(f"ConvEncoder: shape_hwc must be (H, W, C) with positive sizes, got {shape_hwc}")
        if out_features is not None and out_features < 1:
            raise ValueError(f"ConvEncoder: out_features must be >= 1 or None, got {out_features}")
        height, width, channels = (int(d) for d in shape_hwc)
        self.shape_hwc = (height, width, channels)
        stack = conv_stack_for(height, width)
        # Check sizes first so a too-small image names the layer, not a conv2d RuntimeError.
        h, w = height, width
        for i, (_, kernel, stride) in enumerate(stack):
            h, w = (h - kernel) // stride + 1, (w - kernel) // stride + 1
            if h < 1 or w < 1:
                raise ValueError(
                    f"ConvEncoder: a {height}x{width} image is too small for conv layer {i} "
                    f"(kernel {kernel}, stride {stride}) of {stack}"
                )
        layers: list[nn.Module] = []
        in_channels = channels
        for out_channels, kernel, stride in stack:
            layers += [nn.Conv2d(in_channels, out_channels, kernel, stride), activation(activation_name)]
            in_channels = out_channels
        layers.append(nn.Flatten())
        self.convs = nn.Sequential(*layers)
        with torch.no_grad():
            self.conv_dim = int(self.convs(torch.zeros(1, channels, height, width)).shape[-1])
        self.head: nn.Module
        if out_features is None:
            self.head = nn.Identity()
            self.features = self.conv_dim
        else:
            self.head = nn.Sequential(nn.Linear(self.conv_dim, out_features), nn.LayerNorm(out_features), nn.Tanh())
            self.features = out_features

    def forward(self, images: Tensor) -> Tensor:
        if tuple(images.shape[-3:]) != self.shape_hwc:
            raise ValueError(f"ConvEncoder: expected [*lead, {self.shape_hwc}], got {tuple(images.shape)}")
        lead = images.shape[:-3]
        x = images.reshape(-1, *self.shape_hwc)
        # Out of place: .to() returns an input already in the weights' dtype itself, which must not be
        # scaled in place. The permute is a view (NCHW with channels-last strides): no copy here, and
        # conv2d accepts that layout as is.
        x = (x.to(self.conv_dtype) * (1.0 / 255.0)).permute(0, 3, 1, 2)
        return self.head(self.convs(x)).reshape(*lead, self.features)

    @property
    def conv_dtype(self) -> torch.dtype:
        """The first conv's weight dtype, which images are converted to (float32 unless the model was cast)."""
        first = self.convs[0]
        assert isinstance(first, nn.Conv2d)
        return first.weight.dtype

    def extra_repr(self) -> str:
        return f"shape_hwc={self.shape_hwc}, conv_dim={self.conv_dim}, features={self.features}"


class MultiSensorRepresentation(Representation):
    """One :class:`ConvEncoder` per image sensor, concatenated with the flattened vector sensors.

    ``forward(obs)`` takes one tensor per sensor in ``sensors`` order, each ``[*lead, *shape]`` with
    the same ``lead`` (e.g. ``[B, L+1]`` for sequences: lead dims are flattened for the convs and
    restored after) and returns ``[*lead, state_dim]``. Image sensors (rank-3 ``uint8``, see
    :attr:`SensorSpec.is_image`) contribute ``conv_features`` each, vector sensors their flattened
    size. Images may be passed as ``uint8`` or as float with the same ``[0, 255]`` values.

    Asymmetric critic: sensors named in ``critic_only`` (privileged state the policy must not see,
    e.g. simulator ground truth) feed the critic only. Features are ordered policy sensors first,
    critic-only sensors last, each group in ``sensors`` order, so the critic computes the full state
    once and the policy takes the prefix ``policy_state(state) == state[..., :policy_state_dim]``
    (a view: no second encoder pass, and no gradient from the policy loss can reach the critic-only
    encoders). Actors that only need the policy's state call :meth:`forward_policy`, which skips
    the critic-only encoders. Whether the policy loss may train the shared encoders is the learner's
    choice; SAC-AE and DrQ detach them and train the encoder with the critic loss only.
    ``feature_slices`` maps each sensor name to its slice of the state.
    """

    def __init__(
        self,
        sensors: Sequence[SensorSpec],
        conv_features: int | None = 50,
        critic_only: Sequence[str] = (),
        activation_name: str = "relu",
    ) -> None:
        super().__init__()
        if not sensors:
            raise ValueError("MultiSensorRepresentation needs at least one sensor")
        names = [s.name for s in sensors]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise ValueError(f"MultiSensorRepresentation: duplicate sensor names {duplicates}")
        unknown = sorted(set(critic_only) - set(names))
        if unknown:
            raise ValueError(f"critic_only names unknown sensors {unknown}; sensors are {names}")
        privileged = set(critic_only)
        if privileged == set(names):
            raise ValueError(f"critic_only lists every sensor {names}: the policy would see nothing")
        self.sensors = tuple(sensors)
        # Sensor indices in feature order: the policy's first, the critic-only ones last.
        self.policy_order = [i for i, s in enumerate(sensors) if s.name not in privileged]
        self.critic_only_order = [i for i, s in enumerate(sensors) if s.name in privileged]
        # ModuleList, not ModuleDict: sensor names may contain '.', which ModuleDict rejects.
        self.encoders = nn.ModuleList()
        self._encoder_of: dict[int, int] = {}  # sensor index -> index into self.encoders
        widths: dict[int, int] = {}
        for i, s in enumerate(sensors):
            if s.is_image:
                encoder = ConvEncoder((s.shape[0], s.shape[1], s.shape[2]), conv_features, activation_name)
                self._encoder_of[i] = len(self.encoders)
                self.encoders.append(encoder)
                widths[i] = encoder.features
            else:
                widths[i] = math.prod(s.shape)
        self.feature_slices: dict[str, slice] = {}
        start = 0
        for i in self.policy_order + self.critic_only_order:
            self.feature_slices[sensors[i].name] = slice(start, start + widths[i])
            start += widths[i]
        self.policy_state_dim = sum(widths[i] for i in self.policy_order)
        self.state_dim = start

    def _check(self, obs: Sequence[Tensor], indices: Sequence[int]) -> None:
        """Count, trailing shapes and shared leading dims of ``obs`` for the sensors in ``indices``."""
        if len(obs) != len(self.sensors):
            raise ValueError(
                f"expected {len(self.sensors)} sensors {[s.name for s in self.sensors]}, got {len(obs)} tensors"
            )
        lead: tuple[int, ...] | None = None
        first = ""
        for i in indices:
            spec, o = self.sensors[i], obs[i]
            rank = len(spec.shape)
            if o.dim() < rank or tuple(o.shape[o.dim() - rank :]) != spec.shape:
                raise ValueError(
                    f"sensor {spec.name!r}: expected shape [*lead, {', '.join(map(str, spec.shape))}], "
                    f"got {tuple(o.shape)}"
                )
            this_lead = tuple(o.shape[: o.dim() - rank])
            if lead is None:
                lead, first = this_lead, spec.name
            elif this_lead != lead:
                raise ValueError(
                    f"sensor {spec.name!r}: leading dims {this_lead} differ from {lead} of sensor {first!r}"
                )

    def _features(self, obs: Sequence[Tensor], indices: Sequence[int]) -> Tensor:
        parts = []
        for i in indices:
            o, rank = obs[i], len(self.sensors[i].shape)
            if i in self._encoder_of:
                parts.append(self.encoders[self._encoder_of[i]](o))
            elif rank == 0:
                parts.append(o.unsqueeze(-1))
            else:
                parts.append(o.flatten(-rank) if rank > 1 else o)
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)

    def forward(self, obs: list[Tensor]) -> Tensor:
        """The critic's state ``[*lead, state_dim]``: policy features, then critic-only features."""
        order = self.policy_order + self.critic_only_order
        self._check(obs, order)
        return self._features(obs, order)

    def forward_policy(self, obs: list[Tensor]) -> Tensor:
        """``policy_state(forward(obs))`` without running the critic-only encoders.

        ``obs`` still has one entry per sensor, in ``sensors`` order; the critic-only entries are
        neither read nor checked, so an actor without privileged data can pass placeholders there.
        """
        self._check(obs, self.policy_order)
        return self._features(obs, self.policy_order)
