"""Factorised Gaussian noisy linear layers (NoisyNet) for parameter-space exploration.

Fortunato et al. 2018, "Noisy Networks for Exploration" (arXiv 1706.10295), section 3.2: every
weight is ``w = mu_w + sigma_w * eps_w`` and every bias ``b = mu_b + sigma_b * eps_b``, with
``mu`` and ``sigma`` learnt and the noise *factorised*: one standard normal per input
(``eps_in``) and one per output (``eps_out``), combined as

    eps_w[j, i] = f(eps_out[j]) * f(eps_in[i]),    eps_b[j] = f(eps_out[j]),    f(x) = sign(x) sqrt(|x|)

so a layer draws ``in + out`` normals per reset instead of ``in * out + out`` (the paper's
reason: cheaper sampling for big layers). The weight noise is a rank-one matrix per layer (per
head for the ensemble). Its entries have mean zero and, since ``E f(x)^2 = E|x| = sqrt(2/pi)``
for ``x ~ N(0, 1)``, variance ``E|a| E|b| = 2/pi`` for ``eps_w`` and ``sqrt(2/pi)`` for ``eps_b``
(not one: ``sigma`` absorbs the scale).

Initialisation follows the paper's factorised case: ``mu ~ U(-1/sqrt(in), 1/sqrt(in))`` (the
same as :class:`torch.nn.Linear` and :class:`~algorithm.nn.layers.EnsembleLinear`) and
``sigma = sigma0 / sqrt(in)`` with ``sigma0 = 0.5``.

The noise is *state*, not a parameter: it stays fixed between calls to ``reset_noise``, so one
sample serves a whole batch and the caller decides how often to resample (e.g. once per
environment step or per update); ``noise_enabled = False`` switches a layer to its mean weights
``mu`` for deterministic evaluation. The module-level :func:`reset_noise` and :func:`set_noise`
do either for every noisy layer inside a model.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def scale_noise(x: Tensor) -> Tensor:
    """``f(x) = sign(x) * sqrt(|x|)``, the paper's transform of each noise factor (section 3.2)."""
    return x.sign() * x.abs().sqrt()


def _check_args(layer: str, sizes: dict[str, int], sigma0: float) -> None:
    if any(size < 1 for size in sizes.values()):
        got = ", ".join(f"{name}={size}" for name, size in sizes.items())
        raise ValueError(f"{layer}: sizes must be >= 1, got {got}")
    # `not sigma0 >= 0` also rejects NaN, which compares False with everything.
    if not (math.isfinite(sigma0) and sigma0 >= 0):
        raise ValueError(f"{layer}: sigma0 must be finite and >= 0, got sigma0={sigma0!r}")


class NoisyLayer(nn.Module):
    """Shared state and noise handling of the factorised noisy layers.

    Subclasses register ``eps_in`` (``[..., in]``) and ``eps_out`` (``[..., out]``) buffers of
    raw standard normals; ``f`` is applied when the noise is used, so the buffers hold exactly
    what was drawn. :func:`reset_noise` and :func:`set_noise` find layers by this class.

    The buffers are registered with ``persistent=False``: the noise is sampling state like an
    RNG's, not something learnt. Left out of ``state_dict``, it is not published with the
    acting weights (``SAC.acting_state_dict``), so each actor keeps drawing its own noise
    instead of receiving the learner's, and checkpoints hold the same keys as a layer's learnt
    parameters (they load with ``strict=True``). A caller that needs bit-exact resumption owns a
    ``torch.Generator``, saves its state, and calls ``reset_noise(generator)`` after loading.
    """

    eps_in: Tensor
    eps_out: Tensor
    in_features: int
    weight_mu: nn.Parameter
    weight_sigma: nn.Parameter
    bias_mu: nn.Parameter
    bias_sigma: nn.Parameter

    def __init__(self, sigma0: float) -> None:
        super().__init__()
        self.sigma0 = float(sigma0)
        # A plain flag, independent of train()/eval(): acting with the mean weights is the
        # caller's explicit choice (deterministic evaluation), not a side effect of a mode that
        # other modules read too.
        self.noise_enabled = True

    def reset_parameters(self) -> None:
        """mu ~ U(+-1/sqrt(in)), sigma = sigma0 / sqrt(in) (1706.10295, section 3.2, factorised case)."""
        bound = 1.0 / math.sqrt(self.in_features)
        nn.init.uniform_(self.weight_mu, -bound, bound)
        nn.init.uniform_(self.bias_mu, -bound, bound)
        nn.init.constant_(self.weight_sigma, self.sigma0 * bound)
        nn.init.constant_(self.bias_sigma, self.sigma0 * bound)

    def reset_noise(self, generator: torch.Generator | None = None) -> None:
        """Draw fresh standard-normal ``eps_in`` then ``eps_out``.

        With ``generator`` the draws come from it (on the generator's device, then copied to
        the buffers' device), so a caller that owns its RNG gets the same noise on any device;
        without it they come from torch's global RNG for the buffers' device.
        """
        device = self.eps_in.device if generator is None else generator.device
        with torch.no_grad():
            for buffer in (self.eps_in, self.eps_out):
                buffer.copy_(torch.randn(buffer.shape, generator=generator, device=device, dtype=buffer.dtype))

    def epsilon(self) -> tuple[Tensor, Tensor]:
        """The current weight and bias noise as :meth:`effective_params` applies it."""
        raise NotImplementedError

    def effective_params(self) -> tuple[Tensor, Tensor]:
        """The weight and bias that ``forward`` uses now."""
        raise NotImplementedError

    def _factors(self, heads: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``f(eps_out), f(eps_in)``, of the selected heads when ``heads`` is given.

        In-place ``reset_noise`` between a forward and its backward is safe: the raw buffers
        are never saved for backward (no op on them requires grad), only tensors derived here.
        """
        eps_out, eps_in = self.eps_out, self.eps_in
        if heads is not None:
            eps_out, eps_in = eps_out[heads], eps_in[heads]
        return scale_noise(eps_out), scale_noise(eps_in)


class NoisyLinear(NoisyLayer):
    """Drop-in for :class:`torch.nn.Linear` with factorised Gaussian weight and bias noise.

    Parameters ``weight_mu``/``weight_sigma`` are ``[out, in]`` and ``bias_mu``/``bias_sigma``
    ``[out]``; ``forward(x)`` takes ``x`` of shape ``[..., in]`` and returns ``[..., out]``,
    with the current noise (the same for the whole batch) or, with ``noise_enabled = False``,
    exactly ``F.linear(x, weight_mu, bias_mu)``.
    """

    def __init__(self, in_features: int, out_features: int, sigma0: float = 0.5) -> None:
        _check_args("NoisyLinear", {"in_features": in_features, "out_features": out_features}, sigma0)
        super().__init__(sigma0)
        self.in_features = in_features
        self.out_features = out_features
        self.weight_mu = nn.Parameter(torch.empty(out_features, in_features))
        self.weight_sigma = nn.Parameter(torch.empty(out_features, in_features))
        self.bias_mu = nn.Parameter(torch.empty(out_features))
        self.bias_sigma = nn.Parameter(torch.empty(out_features))
        self.register_buffer("eps_in", torch.empty(in_features), persistent=False)
        self.register_buffer("eps_out", torch.empty(out_features), persistent=False)
        self.reset_parameters()
        self.reset_noise()

    def epsilon(self) -> tuple[Tensor, Tensor]:
        """The current noise as applied: ``eps_w = outer(f(eps_out), f(eps_in))`` ``[out, in]``
        and ``eps_b = f(eps_out)`` ``[out]`` (materialised; for inspection and tests)."""
        f_out, f_in = self._factors()
        return torch.outer(f_out, f_in), f_out

    def effective_params(self) -> tuple[Tensor, Tensor]:
        """The weight ``[out, in]`` and bias ``[out]`` that :meth:`forward` uses now: ``mu``
        themselves with the noise off, ``mu + sigma * eps`` otherwise."""
        if not self.noise_enabled:
            return self.weight_mu, self.bias_mu
        f_out, f_in = self._factors()
        # The noisy weight is formed once and used in one matmul. The alternative that never
        # builds an [out, in] tensor, x @ mu.T + f_out * ((x * f_in) @ sigma.T), costs a second
        # N x in x out matmul: for in = out = 256, forward + backward on one CPU thread, it was
        # 15% faster at N = 1 (187 vs 220 us) but 1.9x slower at a learner batch of N = 256
        # (2.5 vs 1.35 ms), and the learner is where the time goes.
        weight = torch.addcmul(self.weight_mu, self.weight_sigma, torch.outer(f_out, f_in))
        bias = torch.addcmul(self.bias_mu, self.bias_sigma, f_out)
        return weight, bias

    def forward(self, x: Tensor) -> Tensor:
        weight, bias = self.effective_params()
        return F.linear(x, weight, bias)

    def extra_repr(self) -> str:
        return (
            f"in_features={self.in_features}, out_features={self.out_features}, sigma0={self.sigma0}, "
            f"noise_enabled={self.noise_enabled}"
        )


class NoisyEnsembleLinear(NoisyLayer):
    """:class:`~algorithm.nn.layers.EnsembleLinear` with independent factorised noise per head.

    Same interface, shapes and computation (``torch.baddbmm(bias, x, weight.mT)``):
    ``weight_mu``/``weight_sigma`` are ``[E, out, in]``, ``bias_mu``/``bias_sigma``
    ``[E, 1, out]``, and ``forward(x, heads=None, detach_params=False)`` takes ``x`` of shape
    ``[E, N, in]`` (``[len(heads), N, in]`` with ``heads``) or ``[N, in]`` (shared by every
    head) and returns ``[E, N, out]``. Each head has its own noise vectors (``eps_in`` is
    ``[E, in]``, ``eps_out`` ``[E, out]``), so the heads explore independently, as ``E``
    separately built noisy networks would; ``heads`` selects those heads' parameters *and*
    noise. ``detach_params`` detaches ``mu`` and ``sigma``: gradients reach the input only.
    """

    def __init__(self, ensemble_size: int, in_features: int, out_features: int, sigma0: float = 0.5) -> None:
        sizes = {"ensemble_size": ensemble_size, "in_features": in_features, "out_features": out_features}
        _check_args("NoisyEnsembleLinear", sizes, sigma0)
        super().__init__(sigma0)
        self.ensemble_size = ensemble_size
        self.in_features = in_features
        self.out_features = out_features
        self.weight_mu = nn.Parameter(torch.empty(ensemble_size, out_features, in_features))
        self.weight_sigma = nn.Parameter(torch.empty(ensemble_size, out_features, in_features))
        self.bias_mu = nn.Parameter(torch.empty(ensemble_size, 1, out_features))
        self.bias_sigma = nn.Parameter(torch.empty(ensemble_size, 1, out_features))
        self.register_buffer("eps_in", torch.empty(ensemble_size, in_features), persistent=False)
        self.register_buffer("eps_out", torch.empty(ensemble_size, out_features), persistent=False)
        self.reset_parameters()
        self.reset_noise()

    def epsilon(self, heads: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The current noise as applied, per head: ``eps_w`` ``[E, out, in]`` (one rank-one
        outer product per head) and ``eps_b`` ``[E, 1, out]`` (materialised; for inspection)."""
        f_out, f_in = self._factors(heads)
        return f_out.unsqueeze(-1) * f_in.unsqueeze(-2), f_out.unsqueeze(-2)

    def effective_params(self, heads: Tensor | None = None, detach_params: bool = False) -> tuple[Tensor, Tensor]:
        """The weight ``[E, out, in]`` and bias ``[E, 1, out]`` that :meth:`forward` uses now,
        of the selected heads with ``heads`` and detached from ``mu``/``sigma`` with
        ``detach_params``."""
        weight_mu: Tensor = self.weight_mu
        bias_mu: Tensor = self.bias_mu
        weight_sigma: Tensor = self.weight_sigma
        bias_sigma: Tensor = self.bias_sigma
        if detach_params:
            weight_mu, bias_mu = weight_mu.detach(), bias_mu.detach()
            weight_sigma, bias_sigma = weight_sigma.detach(), bias_sigma.detach()
        if heads is not None:
            weight_mu, bias_mu = weight_mu[heads], bias_mu[heads]
        if not self.noise_enabled:
            return weight_mu, bias_mu
        if heads is not None:
            weight_sigma, bias_sigma = weight_sigma[heads], bias_sigma[heads]
        f_out, f_in = self._factors(heads)
        # One batched outer product per head and one baddbmm, for the reason given in
        # NoisyLinear.effective_params (the noisy weight costs E * out * in elementwise work,
        # the input-side alternative an extra E * N * in * out matmul).
        weight = torch.addcmul(weight_mu, weight_sigma, f_out.unsqueeze(-1) * f_in.unsqueeze(-2))
        bias = torch.addcmul(bias_mu, bias_sigma, f_out.unsqueeze(-2))
        return weight, bias

    def forward(self, x: Tensor, heads: Tensor | None = None, detach_params: bool = False) -> Tensor:
        weight, bias = self.effective_params(heads, detach_params)
        if x.dim() == 2:
            x = x.expand(weight.shape[0], *x.shape)  # shared input: a stride-0 view, no copy
        return torch.baddbmm(bias, x, weight.mT)

    def extra_repr(self) -> str:
        return (
            f"ensemble_size={self.ensemble_size}, in_features={self.in_features}, "
            f"out_features={self.out_features}, sigma0={self.sigma0}, noise_enabled={self.noise_enabled}"
        )


def reset_noise(module: nn.Module, generator: torch.Generator | None = None) -> int:
    """Call ``reset_noise(generator)`` on every :class:`NoisyLayer` in ``module`` (itself
    included); returns how many. Layers draw in ``module.modules()`` order (registration order),
    so a seeded generator reproduces the noise of the whole model."""
    count = 0
    for layer in module.modules():
        if isinstance(layer, NoisyLayer):
            layer.reset_noise(generator)
            count += 1
    return count


def set_noise(module: nn.Module, enabled: bool) -> int:
    """Set ``noise_enabled`` on every :class:`NoisyLayer` in ``module`` (itself included);
    returns how many. ``False`` makes them use their mean weights ``mu`` only."""
    count = 0
    for layer in module.modules():
        if isinstance(layer, NoisyLayer):
            layer.noise_enabled = enabled
            count += 1
    return count
