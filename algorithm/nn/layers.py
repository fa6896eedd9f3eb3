"""Small building blocks shared by the models: activations, MLPs, and the batched ensemble layer."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

ACTIVATIONS: dict[str, type[nn.Module]] = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU, "silu": nn.SiLU}


def activation(name: str) -> nn.Module:
    """A fresh activation module by config name (``nn_config.activation``)."""
    try:
        return ACTIVATIONS[name]()
    except KeyError:
        raise ValueError(
            f"nn_config.activation: unknown activation {name!r}, expected one of {sorted(ACTIVATIONS)}"
        ) from None


def in_float32(layer: nn.Module, x: Tensor, *args: object) -> Tensor:
    """``layer(x, *args)`` in float32 even inside a lower-precision ``torch.autocast`` region.

    Output layers run this way (``sac_config.compute_dtype``): a Q value of a few hundred has a
    bfloat16 step of 1-2, as large as the TD errors it is trained on, while the hidden layers'
    relative rounding (2^-8) is harmless. Outside autocast it is a plain call.
    """
    if not torch.is_autocast_enabled(x.device.type):
        return layer(x, *args)
    with torch.autocast(x.device.type, enabled=False):
        return layer(x.float(), *args)


def mlp(in_features: int, hidden_units: Sequence[int], activation_name: str) -> nn.Sequential:
    """``Linear -> activation`` for each hidden width; the caller adds its own output layer."""
    layers: list[nn.Module] = []
    for width in hidden_units:
        layers += [nn.Linear(in_features, width), activation(activation_name)]
        in_features = width
    return nn.Sequential(*layers)


class EnsembleLinear(nn.Module):
    """``E`` independent linear layers evaluated with one batched matmul.

    ``weight`` is ``[E, out, in]`` (each head laid out like ``nn.Linear.weight``) and ``bias``
    ``[E, 1, out]``; each head is initialised like a
    standalone :class:`torch.nn.Linear` (uniform in ``+-1/sqrt(in)`` for weight and bias, which is
    what ``kaiming_uniform_(a=sqrt(5))`` works out to), so an ensemble of ``E`` heads starts
    exactly as ``E`` separately built networks would.

    ``forward(x)`` takes ``x`` of shape ``[E, N, in]`` (one input per head) or ``[N, in]`` (the
    same input for every head) and returns ``[E, N, out]``. ``heads`` (a 1-D index tensor) runs
    only those heads; ``detach_params`` runs them with detached parameters so that a loss can
    backpropagate into the *input* without touching this layer's gradients.
    """

    def __init__(self, ensemble_size: int, in_features: int, out_features: int) -> None:
        super().__init__()
        if ensemble_size < 1 or in_features < 1 or out_features < 1:
            raise ValueError(
                f"EnsembleLinear: sizes must be >= 1, got ensemble_size={ensemble_size}, "
                f"in_features={in_features}, out_features={out_features}"
            )
        self.ensemble_size = ensemble_size
        self.in_features = in_features
        self.out_features = out_features
        self.weight = nn.Parameter(torch.empty(ensemble_size, out_features, in_features))
        self.bias = nn.Parameter(torch.empty(ensemble_size, 1, out_features))
        self.reset_parameters()

    def reset_parameters(self) -> None:
        bound = 1.0 / math.sqrt(self.in_features)
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: Tensor, heads: Tensor | None = None, detach_params: bool = False) -> Tensor:
        weight: Tensor = self.weight
        bias: Tensor = self.bias
        if detach_params:
            weight, bias = weight.detach(), bias.detach()
        if heads is not None:
            weight, bias = weight[heads], bias[heads]
        if x.dim() == 2:
            x = x.expand(weight.shape[0], *x.shape)  # shared input: a stride-0 view, no copy
        # [E, out, in] weights used transposed: of the batched layouts measured (matmul broadcast,
        # einsum, [E, in, out]) this was the fastest forward + backward on CPU (bench/learner.py).
        return torch.baddbmm(bias, x, weight.mT)

    def extra_repr(self) -> str:
        return f"ensemble_size={self.ensemble_size}, in_features={self.in_features}, out_features={self.out_features}"
