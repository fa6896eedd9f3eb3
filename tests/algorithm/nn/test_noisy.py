"""Factorised Gaussian noisy layers (algorithm/nn/noisy.py): noise structure, statistics,
reproducibility, the noise-off path, gradients, head subsets, init, validation, checkpoints."""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import pytest
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from algorithm.nn.layers import EnsembleLinear
from algorithm.nn.noisy import NoisyEnsembleLinear, NoisyLayer, NoisyLinear, reset_noise, set_noise

LAYERS = ["linear", "ensemble"]


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


def make(
    kind: str, in_features: int = 5, out_features: int = 4, sigma0: float = 0.5
) -> NoisyLinear | NoisyEnsembleLinear:
    if kind == "linear":
        return NoisyLinear(in_features, out_features, sigma0)
    return NoisyEnsembleLinear(3, in_features, out_features, sigma0)


def f(x: Tensor) -> Tensor:
    """The paper's f(x) = sign(x) sqrt(|x|), written out here independently of the module."""
    return torch.where(x >= 0, x.abs().sqrt(), -x.abs().sqrt())


def noisy_params(layer: NoisyLayer) -> tuple[Tensor, Tensor]:
    weight, bias = layer.effective_params()
    return weight.detach(), bias.detach()


@pytest.mark.parametrize("kind", LAYERS)
def test_reset_noise_changes_noise_and_output(kind: str) -> None:
    layer = make(kind)
    x = torch.randn(6, 5)
    before, eps_in, eps_out = layer(x).detach(), layer.eps_in.clone(), layer.eps_out.clone()
    torch.testing.assert_close(layer(x), before)  # the noise is fixed between resets
    layer.reset_noise()
    assert not torch.equal(layer.eps_in, eps_in) and not torch.equal(layer.eps_out, eps_out)
    assert (layer(x) - before).abs().min() > 0


@pytest.mark.parametrize("kind", LAYERS)
def test_same_generator_seed_gives_identical_noise_and_output(kind: str) -> None:
    a, b = make(kind), make(kind)
    b.load_state_dict(a.state_dict())
    x = torch.randn(6, 5)
    a.reset_noise(torch.Generator().manual_seed(7))
    torch.manual_seed(123)  # the global RNG must not matter when a generator is given
    b.reset_noise(torch.Generator().manual_seed(7))
    assert torch.equal(a.eps_in, b.eps_in) and torch.equal(a.eps_out, b.eps_out)
    assert torch.equal(a(x), b(x))
    b.reset_noise(torch.Generator().manual_seed(8))
    assert not torch.equal(a.eps_in, b.eps_in) and not torch.equal(a(x), b(x))


def test_noise_off_linear_equals_torch_linear_exactly() -> None:
    layer = NoisyLinear(5, 4)
    reference = nn.Linear(5, 4)
    with torch.no_grad():
        reference.weight.copy_(layer.weight_mu)
        reference.bias.copy_(layer.bias_mu)
    x = torch.randn(2, 6, 5)
    assert not torch.equal(layer(x), reference(x))
    layer.noise_enabled = False
    assert torch.equal(layer(x), reference(x))
    layer.reset_noise()  # irrelevant while the noise is off
    assert torch.equal(layer(x), F.linear(x, layer.weight_mu, layer.bias_mu))


def test_noise_off_ensemble_equals_ensemble_linear_exactly() -> None:
    layer = NoisyEnsembleLinear(3, 5, 4)
    reference = EnsembleLinear(3, 5, 4)
    with torch.no_grad():
        reference.weight.copy_(layer.weight_mu)
        reference.bias.copy_(layer.bias_mu)
    shared, per_head, heads = torch.randn(6, 5), torch.randn(3, 6, 5), torch.tensor([2, 0])
    assert not torch.equal(layer(shared), reference(shared))
    layer.noise_enabled = False
    layer.reset_noise()
    assert torch.equal(layer(shared), reference(shared))
    assert torch.equal(layer(per_head), reference(per_head))
    assert torch.equal(layer(shared, heads), reference(shared, heads))


@pytest.mark.parametrize("kind", LAYERS)
def test_sigma0_zero_gives_the_mean_output_with_noise_on(kind: str) -> None:
    layer = make(kind, sigma0=0.0)
    x = torch.randn(6, 5)
    noisy = layer(x)
    layer.noise_enabled = False
    torch.testing.assert_close(noisy, layer(x), rtol=0, atol=0)


@pytest.mark.parametrize("kind", LAYERS)
def test_weight_noise_is_the_factorised_outer_product(kind: str) -> None:
    layer = make(kind, in_features=6, out_features=5)
    layer.reset_noise(torch.Generator().manual_seed(3))
    weight, bias = noisy_params(layer)
    eps_w = (weight - layer.weight_mu.detach()) / layer.weight_sigma.detach()
    eps_b = (bias - layer.bias_mu.detach()) / layer.bias_sigma.detach()
    # eps_w[..., j, i] = f(eps_out[j]) f(eps_in[i]) per head, eps_b[..., j] = f(eps_out[j])
    expected_w = f(layer.eps_out).unsqueeze(-1) * f(layer.eps_in).unsqueeze(-2)
    torch.testing.assert_close(eps_w, expected_w, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(eps_b, f(layer.eps_out).reshape(eps_b.shape), rtol=1e-4, atol=1e-5)
    assert torch.all(torch.linalg.matrix_rank(expected_w) == 1)  # one rank-one matrix per head
    reported_w, reported_b = layer.epsilon()
    torch.testing.assert_close(reported_w, expected_w)
    torch.testing.assert_close(reported_b, eps_b, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("kind", LAYERS)
def test_noise_statistics_over_many_resets(kind: str) -> None:
    """Mean of the noisy weights -> mu; std -> sigma * sqrt(2/pi) for weights (Var f(a) f(b) =
    E|a| E|b| = 2/pi) and sigma * (2/pi)^(1/4) for biases (Var f(a) = E|a|); heads independent."""
    layer = make(kind, in_features=4, out_features=3)
    generator = torch.Generator().manual_seed(11)
    n = 2000
    weights, biases = [], []
    for _ in range(n):
        layer.reset_noise(generator)
        weight, bias = noisy_params(layer)
        weights.append(weight)
        biases.append(bias)
    for samples, mu, sigma, std in (
        (torch.stack(weights), layer.weight_mu.detach(), layer.weight_sigma.detach(), math.sqrt(2 / math.pi)),
        (torch.stack(biases), layer.bias_mu.detach(), layer.bias_sigma.detach(), (2 / math.pi) ** 0.25),
    ):
        # mean within 5 standard errors of mu, entry by entry
        assert torch.all((samples.mean(0) - mu).abs() <= 5 * sigma * std / math.sqrt(n))
        # std within ~5 standard errors (a few % at n = 2000 for these kurtoses)
        torch.testing.assert_close(samples.std(0), sigma * std, rtol=0.08, atol=0)
        torch.testing.assert_close((samples.std(0) / sigma).mean(), torch.tensor(std), rtol=0.03, atol=0)
    if kind == "ensemble":
        eps = (torch.stack(weights) - layer.weight_mu.detach()) / layer.weight_sigma.detach()
        corr = torch.corrcoef(torch.stack([eps[:, 0, 0, 0], eps[:, 1, 0, 0]]))[0, 1]
        assert corr.abs() < 5 / math.sqrt(n)


def test_ensemble_heads_get_independent_noise() -> None:
    layer = NoisyEnsembleLinear(3, 5, 4)
    with torch.no_grad():  # identical heads: any difference in output comes from the noise
        for p in (layer.weight_mu, layer.weight_sigma, layer.bias_mu, layer.bias_sigma):
            p.copy_(p[0].expand_as(p))
    out = layer(torch.randn(6, 5))
    eps_w, _ = layer.epsilon()
    for i in range(3):
        for j in range(i):
            assert not torch.equal(layer.eps_in[i], layer.eps_in[j])
            assert not torch.equal(layer.eps_out[i], layer.eps_out[j])
            assert not torch.allclose(eps_w[i], eps_w[j])
            assert not torch.allclose(out[i], out[j])


def test_ensemble_heads_select_their_parameters_and_noise() -> None:
    layer = NoisyEnsembleLinear(4, 5, 3)
    with torch.no_grad():  # sigma starts equal in every head; make it tell the heads apart
        layer.weight_sigma.uniform_(0.1, 1.0)
        layer.bias_sigma.uniform_(0.1, 1.0)
    shared, per_head = torch.randn(6, 5), torch.randn(4, 6, 5)
    heads = torch.tensor([3, 1])
    torch.testing.assert_close(layer(shared, heads), layer(shared)[heads])
    torch.testing.assert_close(layer(per_head[heads], heads), layer(per_head)[heads])
    for row, h in enumerate(heads.tolist()):
        # written out per head from the raw buffers: mu + sigma * outer(f(eps_out), f(eps_in))
        weight = layer.weight_mu[h] + layer.weight_sigma[h] * torch.outer(f(layer.eps_out[h]), f(layer.eps_in[h]))
        bias = layer.bias_mu[h, 0] + layer.bias_sigma[h, 0] * f(layer.eps_out[h])
        torch.testing.assert_close(layer(shared, heads)[row], shared @ weight.T + bias)
        torch.testing.assert_close(layer(per_head[heads], heads)[row], per_head[h] @ weight.T + bias)


def test_linear_accepts_any_leading_shape() -> None:
    layer = NoisyLinear(5, 4)
    x = torch.randn(2, 3, 5)
    weight, bias = noisy_params(layer)
    assert layer(x).shape == (2, 3, 4)
    torch.testing.assert_close(layer(x), x @ weight.T + bias)
    torch.testing.assert_close(layer(x[0, 0]), x[0, 0] @ weight.T + bias)


@pytest.mark.parametrize("kind", LAYERS)
def test_gradients_reach_mu_sigma_and_input(kind: str) -> None:
    layer = make(kind)
    x = torch.randn(6, 5, requires_grad=True)
    out = layer(x)
    upstream = torch.randn_like(out)
    (out * upstream).sum().backward()
    eps_w, eps_b = layer.epsilon()
    for p in (layer.weight_mu, layer.weight_sigma, layer.bias_mu, layer.bias_sigma):
        assert p.grad is not None and p.grad.abs().sum() > 0
    assert layer.weight_mu.grad is not None and layer.bias_mu.grad is not None
    # d/dsigma = d/dw * eps: the gradient of sigma is the weight's gradient times the noise used
    torch.testing.assert_close(layer.weight_sigma.grad, layer.weight_mu.grad * eps_w)
    torch.testing.assert_close(layer.bias_sigma.grad, layer.bias_mu.grad * eps_b)
    weight, _ = noisy_params(layer)
    expected_x_grad = (upstream @ weight).sum(0) if kind == "ensemble" else upstream @ weight
    torch.testing.assert_close(x.grad, expected_x_grad)


@pytest.mark.parametrize("kind", LAYERS)
def test_noise_off_trains_mu_only(kind: str) -> None:
    layer = make(kind)
    layer.noise_enabled = False
    layer(torch.randn(6, 5)).sum().backward()
    assert layer.weight_mu.grad is not None and layer.bias_mu.grad is not None
    assert layer.weight_sigma.grad is None and layer.bias_sigma.grad is None


@pytest.mark.parametrize("noise_enabled", [True, False])
def test_detach_params_passes_input_grads_but_not_parameter_grads(noise_enabled: bool) -> None:
    layer = NoisyEnsembleLinear(3, 5, 2)
    layer.noise_enabled = noise_enabled
    x = torch.randn(6, 5, requires_grad=True)
    layer(x, detach_params=True).sum().backward()
    assert all(p.grad is None for p in layer.parameters())
    assert x.grad is not None
    detached_grad = x.grad.clone()
    x.grad = None
    layer(x).sum().backward()
    torch.testing.assert_close(x.grad, detached_grad)
    trained = list(layer.parameters()) if noise_enabled else [layer.weight_mu, layer.bias_mu]
    assert all(p.grad is not None for p in trained)


@pytest.mark.parametrize("kind", LAYERS)
def test_reset_noise_between_forward_and_backward_keeps_the_forward_noise(kind: str) -> None:
    layer = make(kind)
    out = layer(torch.randn(6, 5))
    eps_w, _ = layer.epsilon()
    layer.reset_noise()  # in place on the buffers; backward must neither fail nor see the new noise
    out.sum().backward()
    assert layer.weight_mu.grad is not None
    torch.testing.assert_close(layer.weight_sigma.grad, layer.weight_mu.grad * eps_w)


@pytest.mark.parametrize("kind", LAYERS)
@pytest.mark.parametrize("sigma0", [0.5, 0.1])
def test_init_ranges(kind: str, sigma0: float) -> None:
    fan_in = 64
    layer = make(kind, in_features=fan_in, out_features=128, sigma0=sigma0)
    bound = 1 / math.sqrt(fan_in)
    for mu in (layer.weight_mu, layer.bias_mu):
        assert mu.abs().max() <= bound
    # uniform(-b, b) has std b / sqrt(3), like nn.Linear's weights
    assert layer.weight_mu.std().item() == pytest.approx(bound / math.sqrt(3), rel=0.05)
    for sigma in (layer.weight_sigma, layer.bias_sigma):
        assert torch.all(sigma == sigma0 / math.sqrt(fan_in))
    if kind == "ensemble":
        assert not torch.equal(layer.weight_mu[0], layer.weight_mu[1])  # heads initialised independently


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: NoisyLinear(0, 3), "NoisyLinear: sizes must be >= 1, got in_features=0, out_features=3"),
        (lambda: NoisyLinear(3, -1), "out_features=-1"),
        (lambda: NoisyEnsembleLinear(0, 3, 3), "NoisyEnsembleLinear: sizes must be >= 1, got ensemble_size=0"),
        (lambda: NoisyEnsembleLinear(2, 0, 3), "in_features=0"),
        (lambda: NoisyEnsembleLinear(2, 3, 0), "out_features=0"),
        (lambda: NoisyLinear(3, 3, sigma0=-0.1), "NoisyLinear: sigma0 must be finite and >= 0, got sigma0=-0.1"),
        (lambda: NoisyEnsembleLinear(2, 3, 3, sigma0=-1.0), "sigma0=-1.0"),
        (lambda: NoisyLinear(3, 3, sigma0=math.nan), "sigma0=nan"),
        (lambda: NoisyLinear(3, 3, sigma0=math.inf), "sigma0=inf"),
    ],
)
def test_rejects_bad_arguments(build: Callable[[], NoisyLayer], message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        build()


@pytest.mark.parametrize("kind", LAYERS)
def test_checkpoint_holds_the_learnt_parameters_only_and_loads_strictly(kind: str) -> None:
    source, target = make(kind), make(kind)
    state = source.state_dict()
    assert set(state) == {"weight_mu", "weight_sigma", "bias_mu", "bias_sigma"}
    noise_before = target.eps_in.clone(), target.eps_out.clone()
    target.load_state_dict(state, strict=True)
    for name, p in target.named_parameters():
        assert torch.equal(p, state[name])
    # the receiver keeps drawing its own noise: loading weights does not copy the sender's
    assert torch.equal(target.eps_in, noise_before[0]) and torch.equal(target.eps_out, noise_before[1])
    target.noise_enabled = source.noise_enabled = False
    x = torch.randn(6, 5)
    assert torch.equal(target(x), source(x))


def test_module_helpers_reach_every_noisy_layer() -> None:
    def build() -> nn.Sequential:
        return nn.Sequential(NoisyLinear(5, 4), nn.ReLU(), nn.Linear(4, 4), NoisyEnsembleLinear(2, 4, 3))

    a, b = build(), build()
    b.load_state_dict(a.state_dict())
    x = torch.randn(6, 5)
    assert reset_noise(a, torch.Generator().manual_seed(5)) == 2
    assert reset_noise(b, torch.Generator().manual_seed(5)) == 2
    assert torch.equal(a(x), b(x))  # one seeded generator reproduces the whole model's noise
    before = a(x)
    assert reset_noise(a) == 2
    assert not torch.equal(a(x), before)
    assert set_noise(a, False) == 2
    assert all(not m.noise_enabled for m in a.modules() if isinstance(m, NoisyLayer))
    mean_only = a(x)
    reset_noise(a)
    assert torch.equal(a(x), mean_only)
    assert set_noise(a, True) == 2
    assert not torch.equal(a(x), mean_only)
    assert reset_noise(nn.Linear(2, 2)) == 0 and set_noise(nn.Linear(2, 2), False) == 0
    assert reset_noise(NoisyLinear(2, 2)) == 1  # the module itself counts


@pytest.mark.parametrize("kind", LAYERS)
def test_noise_follows_dtype_and_a_cpu_generator_is_device_independent(kind: str) -> None:
    layer = make(kind).double()
    layer.reset_noise(torch.Generator().manual_seed(1))
    assert layer.eps_in.dtype == torch.float64 and layer(torch.randn(6, 5, dtype=torch.float64)).dtype == torch.float64
    if not torch.cuda.is_available():
        return
    cpu = make(kind)
    gpu = make(kind).cuda()
    cpu.reset_noise(torch.Generator().manual_seed(2))
    gpu.reset_noise(torch.Generator().manual_seed(2))  # drawn on the CPU, copied to the GPU
    assert torch.equal(gpu.eps_in.cpu(), cpu.eps_in) and torch.equal(gpu.eps_out.cpu(), cpu.eps_out)
    gpu.reset_noise(torch.Generator("cuda").manual_seed(2))
    gpu.reset_noise()
    assert gpu.eps_in.device.type == "cuda"
