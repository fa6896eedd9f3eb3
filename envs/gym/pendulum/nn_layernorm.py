"""An example task model file (``python main.py gym/pendulum --nn nn_layernorm``).

It replaces the default encoder (plain concatenation) with a small LayerNorm MLP; Q heads and the
policy are still built from ``nn_config`` around it. See algorithm/nn/user.py for the contract.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from algorithm.config.schema import NNConfig
from algorithm.nn.models import Representation
from algorithm.spaces import EnvSpec


class LayerNormEncoder(Representation):
    """``state = tanh(LayerNorm(Linear(concat(vector sensors))))``."""

    def __init__(self, spec: EnvSpec, width: int = 32) -> None:
        super().__init__()
        in_features = sum(math.prod(s.shape) for s in spec.sensors)
        self.net = nn.Sequential(nn.Linear(in_features, width), nn.LayerNorm(width), nn.Tanh())
        self.state_dim = self.policy_state_dim = width

    def forward(self, obs: list[Tensor]) -> Tensor:
        return self.net(torch.cat([o.flatten(start_dim=o.dim() - 1) for o in obs], dim=-1))


def build_representation(spec: EnvSpec, nn_config: NNConfig) -> Representation:
    return LayerNormEncoder(spec)
