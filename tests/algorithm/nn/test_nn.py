"""Model building blocks: the batched ensemble layer, the Q ensemble, the tanh-Gaussian policy."""

from __future__ import annotations

import copy
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.distributions import Normal, TanhTransform, TransformedDistribution

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.nn.builder import build_models
from algorithm.nn.layers import EnsembleLinear, activation, relu_mlp
from algorithm.nn.models import (
    QEnsemble,
    TanhGaussianPolicy,
    VectorRepresentation,
    squashed_gaussian_log_prob,
)
from algorithm.nn.user import model_builder, recurrent_state_size
from algorithm.sac.learner import SAC
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


def test_ensemble_linear_equals_one_linear_per_head() -> None:
    layer = EnsembleLinear(3, 5, 4)
    shared = torch.randn(7, 5)
    per_head = torch.randn(3, 7, 5)
    for i in range(3):
        torch.testing.assert_close(layer(shared)[i], shared @ layer.weight[i].T + layer.bias[i])
        torch.testing.assert_close(layer(per_head)[i], per_head[i] @ layer.weight[i].T + layer.bias[i])
    heads = torch.tensor([2, 0])
    torch.testing.assert_close(layer(shared, heads), layer(shared)[heads])
    torch.testing.assert_close(layer(per_head[heads], heads), layer(per_head)[heads])


def test_ensemble_linear_init_matches_torch_linear_per_head() -> None:
    fan_in = 64
    layer = EnsembleLinear(4, fan_in, 256)
    bound = 1 / math.sqrt(fan_in)
    reference = torch.nn.Linear(fan_in, 256)
    for p in (layer.weight, layer.bias):
        assert p.abs().max() <= bound
    # uniform(-b, b) has std b / sqrt(3), like nn.Linear's weights
    assert layer.weight.std().item() == pytest.approx(bound / math.sqrt(3), rel=0.05)
    assert reference.weight.std().item() == pytest.approx(bound / math.sqrt(3), rel=0.05)
    assert not torch.equal(layer.weight[0], layer.weight[1])  # heads are initialised independently


def test_ensemble_linear_rejects_bad_sizes() -> None:
    with pytest.raises(ValueError, match="ensemble_size=0"):
        EnsembleLinear(0, 3, 3)


def test_detached_params_pass_input_grads_but_not_weight_grads() -> None:
    layer = EnsembleLinear(2, 3, 1)
    x = torch.randn(4, 3, requires_grad=True)
    layer(x, detach_params=True).sum().backward()
    assert layer.weight.grad is None and layer.bias.grad is None
    torch.testing.assert_close(x.grad, layer.weight.detach().sum(0).squeeze(0).expand(4, 3))


def test_q_ensemble_heads_are_independent() -> None:
    q = QEnsemble(state_dim=3, action_dim=2, hidden_units=[8, 8], ensemble_size=3)
    out = q(torch.randn(5, 3), torch.randn(5, 2))
    assert out.shape == (3, 5)
    out[1].pow(2).sum().backward()
    for layer in q.layers:
        assert isinstance(layer, EnsembleLinear)
        for p in (layer.weight, layer.bias):
            assert p.grad is not None
            assert p.grad[1].abs().sum() > 0
            assert torch.all(p.grad[0] == 0) and torch.all(p.grad[2] == 0)


def test_q_ensemble_subset_equals_the_selected_rows() -> None:
    q = QEnsemble(3, 2, [8], ensemble_size=4)
    s, a = torch.randn(5, 3), torch.randn(5, 2)
    heads = torch.tensor([3, 1])
    torch.testing.assert_close(q(s, a, heads), q(s, a)[heads])


def _q_values_and_grads(
    q: QEnsemble, per_head_state: bool, heads: torch.Tensor | None, detach_params: bool, autocast: bool
) -> dict[str, torch.Tensor | None]:
    """``q``'s output and the gradients of a fixed random projection of it: input's and parameters'."""
    gen = torch.Generator().manual_seed(1)
    e = q.ensemble_size if heads is None else len(heads)
    state = torch.randn((e, 5, 3) if per_head_state else (5, 3), generator=gen).requires_grad_()
    action = torch.randn(state.shape[:-1] + (2,), generator=gen).requires_grad_()
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        out = q(state, action, heads, detach_params)
    (out * torch.randn(out.shape, generator=gen)).sum().backward()
    named = {"out": out, "state": state.grad, "action": action.grad}
    return named | {name: p.grad for name, p in q.named_parameters()}


@pytest.mark.parametrize(
    ("hidden", "discrete_size", "per_head_state", "heads", "detach_params"),
    [
        ([8, 8], 0, False, None, False),
        ([8, 8], 0, False, None, True),  # the policy loss's call: input grads only
        ([8, 8], 0, False, [2, 0], False),  # a subset of heads (ensemble_q_sample)
        ([8], 4, False, None, False),  # discrete branches: 4 outputs per head
        ([], 0, False, None, False),  # no hidden layer
        ([6, 7, 8], 0, True, None, False),  # one input per head, three hidden layers
    ],
)
@pytest.mark.parametrize("autocast", [False, True], ids=["float32", "bf16-autocast"])
def test_q_ensemble_as_one_node_matches_the_layer_by_layer_modules(
    hidden: list[int], discrete_size: int, per_head_state: bool, heads: list[int] | None, detach_params: bool,
    autocast: bool,
) -> None:  # fmt: skip
    """``relu_mlp`` (one autograd node, hand-written backward) computes what the layers compute,
    values and every gradient, in float32 and with bf16 hidden layers under autocast."""
    fused = QEnsemble(3, 2, hidden, ensemble_size=3, discrete_size=discrete_size)
    assert fused.use_relu_mlp
    layered = copy.deepcopy(fused)
    layered.use_relu_mlp = False
    index = None if heads is None else torch.tensor(heads)
    expected = _q_values_and_grads(layered, per_head_state, index, detach_params, autocast)
    got = _q_values_and_grads(fused, per_head_state, index, detach_params, autocast)
    assert got["out"] is not None and got["out"].dtype == torch.float32  # the output layer stays float32
    # Float32 tolerances even under bf16 autocast: both paths round the same products to bf16 (found
    # equal to the bit at these sizes; at 256x256 within 2e-6 relative).
    for name, value in expected.items():
        if value is None:
            assert got[name] is None, name
        else:
            torch.testing.assert_close(got[name], value, msg=lambda m, name=name: f"{name}: {m}")
    assert (expected["layers.0.weight"] is None) == detach_params


def test_relu_mlp_backward_matches_finite_differences() -> None:
    gen = torch.Generator().manual_seed(2)
    sizes = [3, 4, 5, 2]
    params = []
    for i, o in itertools.pairwise(sizes):
        params += [torch.randn(2, o, i, dtype=torch.float64, generator=gen)]  # weight [E, out, in]
        params += [torch.randn(2, 1, o, dtype=torch.float64, generator=gen)]  # bias [E, 1, out]
    x = torch.randn(2, 6, 3, dtype=torch.float64, generator=gen)
    inputs = tuple(t.requires_grad_() for t in (x, *params))
    assert torch.autograd.gradcheck(lambda x, *p: relu_mlp(x, p), inputs)


def test_one_node_q_ensemble_builds_no_graph_under_no_grad_and_leaves_detached_params_alone() -> None:
    """The target's call (no_grad) and the policy loss's (detached parameters: input grads only)."""
    q = QEnsemble(3, 2, [8], ensemble_size=2)
    with torch.no_grad():
        assert not q(torch.randn(4, 3), torch.randn(4, 2)).requires_grad
    action = torch.randn(4, 2, requires_grad=True)
    q(torch.randn(4, 3), action, detach_params=True).sum().backward()
    assert action.grad is not None and all(p.grad is None for p in q.parameters())


def test_squashed_log_prob_matches_a_transformed_distribution() -> None:
    mean, log_std = torch.randn(1000, 3), torch.rand(1000, 3) - 1.5
    noise = torch.randn(1000, 3)
    pre_tanh = mean + log_std.exp() * noise
    reference = TransformedDistribution(Normal(mean, log_std.exp()), [TanhTransform(cache_size=1)])
    action = reference.transforms[0](pre_tanh)  # caches pre_tanh, so log_prob does not invert tanh
    expected = reference.log_prob(action).sum(-1)
    torch.testing.assert_close(squashed_gaussian_log_prob(noise, log_std, pre_tanh), expected, rtol=1e-5, atol=1e-4)


def test_squashed_log_prob_is_finite_where_naive_formula_is_not() -> None:
    pre_tanh = torch.tensor([[30.0, -30.0]])
    naive = torch.log(1 - torch.tanh(pre_tanh).pow(2)).sum()
    assert not torch.isfinite(naive)
    out = squashed_gaussian_log_prob(torch.zeros(1, 2), torch.zeros(1, 2), pre_tanh)
    # log(1 - tanh(u)^2) ~ log 4 - 2|u| for large |u|
    expected = 2 * (-0.5 * math.log(2 * math.pi)) - 2 * (math.log(4) - 60.0)
    assert out.item() == pytest.approx(expected, rel=1e-5)


def test_policy_sample_shapes_range_and_determinism() -> None:
    policy = TanhGaussianPolicy(4, 3, [16], log_std_min=-5.0, log_std_max=1.0)
    state = torch.randn(6, 4) * 100  # large inputs push the mean far into tanh's flat region
    action, log_prob = policy.sample(state, torch.randn(6, 3))
    assert action.shape == (6, 3) and log_prob.shape == (6,)
    assert torch.all(action.abs() <= 1) and torch.all(torch.isfinite(log_prob))
    mean, log_std = policy(state)
    assert torch.all(log_std >= -5.0) and torch.all(log_std <= 1.0)
    deterministic, _ = policy.sample(state, None)
    torch.testing.assert_close(deterministic, torch.tanh(mean))


def test_policy_rejects_inverted_log_std_bounds() -> None:
    with pytest.raises(ValueError, match="log_std_min"):
        TanhGaussianPolicy(2, 2, [4], log_std_min=2.0, log_std_max=-2.0)


def test_vector_representation_concatenates_flattened_sensors() -> None:
    rep = VectorRepresentation([SensorSpec("a", (2,)), SensorSpec("b", (2, 3))])
    assert rep.state_dim == 8
    a, b = torch.randn(5, 4, 2), torch.randn(5, 4, 2, 3)
    torch.testing.assert_close(rep([a, b]), torch.cat([a, b.reshape(5, 4, 6)], -1))
    with pytest.raises(ValueError, match="expected 2 sensors"):
        rep([a])


def test_vector_representation_refuses_images() -> None:
    image = SensorSpec("camera", (8, 8, 3), np.dtype(np.uint8))
    with pytest.raises(NotImplementedError, match="camera"):
        VectorRepresentation([image])


@pytest.mark.parametrize(
    ("branches", "continuous", "dqn_like", "has_policy", "has_discrete_policy"),
    [((4,), 0, False, False, True), ((4,), 0, True, False, False), ((2, 3), 1, False, True, True),
     ((3,), 2, True, True, False), ((), 2, False, True, False)],
)  # fmt: skip
def test_build_models_builds_a_policy_per_action_part(
    branches: tuple[int, ...], continuous: int, dqn_like: bool, has_policy: bool, has_discrete_policy: bool
) -> None:
    spec = EnvSpec(
        (SensorSpec("obs", (3,)),), ActionSpec(branches, continuous, (-1.0,) * continuous, (1.0,) * continuous)
    )
    models = build_models(spec, SacConfig(discrete_dqn_like=dqn_like), NNConfig(hidden_units=[8]))
    assert (models.policy is not None) == has_policy
    assert (models.discrete_policy is not None) == has_discrete_policy
    q = models.q(torch.zeros(5, 3), torch.zeros(5, continuous) if continuous else None)
    assert q.shape == ((2, 5, sum(branches)) if branches else (2, 5))


def test_build_models_uses_config_sizes() -> None:
    spec = EnvSpec((SensorSpec("obs", (3,)), SensorSpec("vel", (2,))), ActionSpec((), 2, (-1.0,) * 2, (1.0,) * 2))
    models = build_models(
        spec,
        SacConfig(ensemble_q_num=5, ensemble_q_sample=2),
        NNConfig(hidden_units=[32, 16], activation="tanh"),
    )
    assert models.q.layers[0].weight.shape == (5, 32, 5 + 2)
    assert models.q.layers[-1].weight.shape == (5, 1, 16)
    assert isinstance(models.q.act, torch.nn.Tanh)
    assert models.policy.head.out_features == 4


def test_unknown_activation_names_the_key() -> None:
    with pytest.raises(ValueError, match="nn_config.activation"):
        activation("gelu")


def test_model_files_build_what_they_define_and_errors_name_the_file(tmp_path: Path) -> None:
    spec = EnvSpec((SensorSpec("obs", (3,)),), ActionSpec((), 1, (-1.0,), (1.0,)))
    full = tmp_path / "full.py"
    full.write_text(
        "from algorithm.nn.builder import build_models as default\n"
        "def build_models(spec, sac, nn):\n"
        "    models = default(spec, sac, nn)\n"
        "    models.tag = 'mine'\n"
        "    return models\n"
    )
    assert model_builder(full)(spec, SacConfig(), NNConfig(hidden_units=[8])).tag == "mine"
    empty = tmp_path / "empty.py"
    empty.write_text("x = 1\n")
    with pytest.raises(AttributeError, match="empty.py"):
        model_builder(empty)
    broken = tmp_path / "broken.py"
    broken.write_text("raise RuntimeError('boom')\n")
    with pytest.raises(ImportError, match="broken.py.*boom"):
        model_builder(broken)
    assert model_builder(None) is build_models


@pytest.mark.parametrize(
    ("use_rnn", "rnn_type", "model_file"),
    [(False, "gru", None), (True, "gru", None), (True, "lstm", None), (True, "lstm", "build_representation"),
     (True, "gru", "build_models"), (False, "gru", "build_models")],
)  # fmt: skip
def test_the_recurrent_state_size_is_known_without_building_a_sac(
    tmp_path: Path, use_rnn: bool, rnn_type: str, model_file: str | None
) -> None:
    """Issue 16: the replay built a whole SAC (models, target copies, three optimizers) to read it."""
    spec = EnvSpec((SensorSpec("obs", (3,)),), ActionSpec((), 2, (-1.0, -1.0), (1.0, 1.0)))
    sac_cfg, nn_cfg = SacConfig(use_rnn=use_rnn), NNConfig(hidden_units=[8], rnn_units=5, rnn_type=rnn_type)
    build = build_models
    if model_file == "build_representation":
        path = tmp_path / "nn.py"
        path.write_text(
            "from algorithm.nn.models import VectorRepresentation\n"
            "def build_representation(spec, nn_config):\n    return VectorRepresentation(spec.sensors)\n"
        )
        build = model_builder(path)
    elif model_file == "build_models":  # its own recurrence, whatever the config says: 7 GRU units
        path = tmp_path / "nn.py"
        path.write_text(
            "from algorithm.nn.builder import build_models as default\n"
            "def build_models(spec, sac_config, nn_config):\n"
            "    return default(spec, sac_config.model_copy(update={'use_rnn': True}),\n"
            "                   nn_config.model_copy(update={'rnn_units': 7, 'rnn_type': 'gru'}))\n"
        )
        build = model_builder(path)
    expected = SAC(spec, sac_cfg, nn_cfg, ReplayConfig(), build=build).rnn_state_size
    assert recurrent_state_size(spec, sac_cfg, nn_cfg, build) == expected
    assert expected == {None: 5 * (2 if rnn_type == "lstm" else 1) if use_rnn else 0,
                        "build_representation": 10, "build_models": 7}[model_file]  # fmt: skip
