"""Observation normalization on the device, from the replay's exact running statistics.

``sac_config.use_normalization``: every vector sensor (not images, not the ``action_mask``) is
mapped to ``clip((x - mean) / sqrt(var + eps), -5, 5)`` before the representation, online and
target alike and on the acting side. The statistics are not estimated here: the replay table
keeps exact running mean/var over every inserted observation (:class:`algorithm.normalizer.
RunningMeanStd`) and the learner copies them in with :meth:`ObservationNormalizer.load_stats`
(docs/architecture.md section 4: in distributed mode the replay hands them to the learner). They live in
buffers, so checkpoints and the acting weights actors receive carry them.

Every buffer is finite, from the start: actors refuse weights with a non-finite value (ds/net/params.py).
Until statistics arrive the clip bound is float32's largest value, not +inf (the identity all the same
on finite inputs); a checkpoint written with the former +inf loads with that bound instead.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from algorithm.spaces import ACTION_MASK_SENSOR, SensorSpec

CLIP = 5.0  # as SB3's VecNormalize and Gymnasium's NormalizeObservation
NO_CLIP = torch.finfo(torch.float32).max  # the bound before statistics arrive: finite, clips no finite input


class ObservationNormalizer(nn.Module):
    """Per-sensor ``(x - mean) / std`` clipped to ``[-5, 5]``; identity until stats arrive."""

    count: Tensor
    clip: Tensor

    def __init__(self, sensors: Sequence[SensorSpec], epsilon: float = 1e-8) -> None:
        super().__init__()
        self.names = [s.name for s in sensors]
        self.normalized = [not s.is_image and s.name != ACTION_MASK_SENSOR for s in sensors]
        self.epsilon = epsilon
        for s, on in zip(sensors, self.normalized, strict=True):
            if on:
                self.register_buffer(f"mean_{s.name}", torch.zeros(s.shape))
                self.register_buffer(f"std_{s.name}", torch.ones(s.shape))
        self.register_buffer("count", torch.zeros((), dtype=torch.long))
        # NO_CLIP until statistics arrive, so the module starts as the exact identity (no clipping either);
        # not +inf, which actors refuse in published weights
        self.register_buffer("clip", torch.tensor(NO_CLIP))

    def forward(self, obs: list[Tensor]) -> list[Tensor]:
        out = []
        for name, on, o in zip(self.names, self.normalized, obs, strict=True):
            if on:
                o = ((o - getattr(self, f"mean_{name}")) / getattr(self, f"std_{name}")).clamp(-self.clip, self.clip)
            out.append(o)
        return out

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
        """A checkpoint from before NO_CLIP holds +inf as the bound of a normalizer without statistics:
        loaded as NO_CLIP (the same transform), so that the weights published next are finite."""
        key = prefix + "clip"
        clip = state_dict.get(key)
        if isinstance(clip, torch.Tensor) and bool(torch.isposinf(clip).all()):
            state_dict[key] = torch.full_like(clip, NO_CLIP)
        super()._load_from_state_dict(state_dict, prefix, *args)

    def load_stats(self, stats: Mapping[str, Mapping[str, Any]]) -> None:
        """Copy in ``{sensor: {"count", "mean", "var"}}`` (what the replay table reports); a sensor
        without data keeps the identity transform."""
        for name, on in zip(self.names, self.normalized, strict=True):
            if not on:
                continue
            if name not in stats:
                raise KeyError(f"normalizer stats lack sensor {name!r} (have {sorted(stats)})")
            entry = stats[name]
            if int(entry["count"]) == 0:
                continue
            mean = torch.as_tensor(np.asarray(entry["mean"]), dtype=torch.float32)
            std = torch.as_tensor(
                np.sqrt(np.asarray(entry["var"], dtype=np.float64) + self.epsilon), dtype=torch.float32
            )
            getattr(self, f"mean_{name}").copy_(mean)
            getattr(self, f"std_{name}").copy_(std)
        counts = [int(stats[n]["count"]) for n, on in zip(self.names, self.normalized, strict=True) if on]
        self.count.fill_(max(counts, default=0))
        if int(self.count) > 0:
            self.clip.fill_(CLIP)
