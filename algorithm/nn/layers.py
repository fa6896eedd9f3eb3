"""Small building blocks shared by the models: activations, MLPs, and the batched ensemble layer."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

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


def uses_bfloat16(compute_dtype: str, device: torch.device, cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """Resolve ``sac_config.compute_dtype``: ``auto`` means bfloat16 where the hardware computes it
    natively — a CUDA device that supports it, or a CPU whose flags list ``avx512_bf16`` or
    ``amx_bf16`` (elsewhere bf16 matmuls are emulated and slower than float32)."""
    if compute_dtype != "auto":
        return compute_dtype == "bfloat16"
    if device.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    if device.type != "cpu":
        return False
    try:
        flags = next((line for line in cpuinfo.read_text().splitlines() if line.startswith("flags")), "")
    except OSError:
        return False
    return bool({"avx512_bf16", "amx_bf16"} & set(flags.split()))


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

    def parameters_for(self, heads: Tensor | None = None, detach_params: bool = False) -> tuple[Tensor, Tensor]:
        """``(weight, bias)`` of the selected heads (all when None), detached with ``detach_params``."""
        weight: Tensor = self.weight
        bias: Tensor = self.bias
        if detach_params:
            weight, bias = weight.detach(), bias.detach()
        if heads is not None:
            weight, bias = weight[heads], bias[heads]
        return weight, bias

    def forward(self, x: Tensor, heads: Tensor | None = None, detach_params: bool = False) -> Tensor:
        weight, bias = self.parameters_for(heads, detach_params)
        if x.dim() == 2:
            x = x.expand(weight.shape[0], *x.shape)  # shared input: a stride-0 view, no copy
        # [E, out, in] weights used transposed: of the batched layouts measured (matmul broadcast,
        # einsum, [E, in, out]) this was the fastest forward + backward on CPU (bench/learner.py).
        return torch.baddbmm(bias, x, weight.mT)

    def extra_repr(self) -> str:
        return f"ensemble_size={self.ensemble_size}, in_features={self.in_features}, out_features={self.out_features}"


def relu_mlp_dtype(x: Tensor, params: Sequence[Tensor]) -> torch.dtype:
    """The dtype :func:`relu_mlp` runs its hidden layers in: the autocast dtype inside an autocast
    region of ``x``'s device, else the parameters' dtype."""
    if torch.is_autocast_enabled(x.device.type):
        return torch.get_autocast_dtype(x.device.type)
    return params[0].dtype


def relu_mlp(x: Tensor, params: Sequence[Tensor]) -> Tensor:
    """A stack of batched linear layers with ReLU between them, as one autograd node.

    ``params`` is ``(weight_1, bias_1, ..., weight_L, bias_L)`` with weights ``[E, out, in]`` and
    biases ``[E, 1, out]`` (:meth:`EnsembleLinear.parameters_for`); ``x`` is ``[E, N, in]`` and the
    result ``[E, N, out_L]``: ``layer_L(relu(... relu(layer_1(x))))`` as the layer-by-layer modules
    compute it, with the same precision (inside an autocast region the hidden layers run in its
    dtype, bfloat16 on CPU, and the output layer in the parameters' dtype, as :func:`in_float32`).
    Values and gradients equal the layer-by-layer ones (tests/algorithm/nn/test_nn.py).

    Why one node: outside its matmuls a SAC update at batch 256 on CPU is dispatch-bound. This saves
    the per-layer autograd, cast and transpose nodes, casts each weight once per call, applies ReLU in
    place, and computes each weight's gradient as ``g^T h`` in the weight's own layout (autograd's
    ``bmm(h^T, g)`` for the scalar Q output is a matrix-vector product that ran 12x slower here, 147
    vs 12 us). Measured on the Q ensemble: SAC updates/s +5% with bf16 hidden layers, +10% in float32
    (paired rounds, 256x256, batch 256); on the policy it gained nothing, so the policy stays modular.
    Parameters that do not require grad (detached, or in a no-grad region) get no gradient work.
    """
    return _ReluMLP.apply(x, relu_mlp_dtype(x, params), *params)


class _ReluMLP(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, x: Tensor, hidden_dtype: torch.dtype, *params: Tensor) -> Tensor:
        output_dtype = params[-2].dtype
        with torch.autocast(x.device.type, enabled=False):
            h = x.to(hidden_dtype) if len(params) > 2 else x  # without hidden layers x goes to the output layer
            inputs, hidden_weights = [h], []
            for i in range(0, len(params) - 2, 2):
                weight = params[i].to(hidden_dtype)
                h = torch.baddbmm(params[i + 1].to(hidden_dtype), h, weight.mT).relu_()
                inputs.append(h)
                hidden_weights.append(weight)
            last_input = h.to(output_dtype)
            out = torch.baddbmm(params[-1], last_input, params[-2].mT)
        ctx.save_for_backward(*inputs, last_input, *hidden_weights, params[-2])
        ctx.x_dtype = x.dtype
        return out

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        saved = ctx.saved_tensors
        layers = (len(saved) - 1) // 2  # inputs (L) + last_input + hidden weights (L - 1) + last weight
        inputs, last_input = saved[:layers], saved[layers]
        hidden_weights, last_weight = saved[layers + 1 : 2 * layers], saved[-1]
        needs = ctx.needs_input_grad  # (x, hidden_dtype, weight_1, bias_1, ...)
        grads: list[Tensor | None] = [None] * (2 * layers)

        def param_grads(i: int, g: Tensor, h: Tensor, dtype: torch.dtype) -> None:
            if needs[2 + 2 * i]:
                grads[2 * i] = torch.bmm(g.mT, h).to(dtype)  # [E, out, in], the weight's own layout
            if needs[3 + 2 * i]:
                grads[2 * i + 1] = g.sum(1, keepdim=True).to(dtype)

        params_dtype = last_weight.dtype
        param_grads(layers - 1, grad, last_input, params_dtype)
        # dL/dh for the last hidden output; a one-unit layer's is an outer product, done by broadcasting.
        g = grad * last_weight if last_weight.shape[1] == 1 else torch.bmm(grad, last_weight)
        g = g.to(inputs[-1].dtype)
        for i in range(layers - 2, -1, -1):
            g = torch.ops.aten.threshold_backward(g, inputs[i + 1], 0)  # through relu: 0 where it output 0
            param_grads(i, g, inputs[i], params_dtype)
            if i > 0 or needs[0]:
                g = torch.bmm(g, hidden_weights[i])
        grad_x = g.to(ctx.x_dtype) if needs[0] else None
        return (grad_x, None, *grads)
