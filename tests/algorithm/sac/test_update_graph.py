"""Updates replayed from a recorded pass (algorithm/sac/update_graph.py) compute what eager updates compute.

Without a GPU the recorder is a stand-in that replays by running the pass again and copying its results
into the recorded tensors, as a CUDA graph's replay rewrites them: that checks the plumbing (batches
copied into the fixed input buffers, gradients pointed back at the recorded ones after an optimizer
let go of them, recording again when the batch's shapes change, falling back when recording fails).
On a machine with CUDA the same comparisons run against real CUDA graphs."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import torch
from torch import Tensor

from algorithm.config.schema import NNConfig, ReplayConfig, SacConfig
from algorithm.sac.learner import SAC
from algorithm.sac.update_graph import MAX_FAILED_RECORDINGS, UpdateGraph, why_not_graphed
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from tests.algorithm.sac.test_learner import SPEC, assert_same_state, make_batch

DISCRETE = EnvSpec((SensorSpec("obs", (3,)),), ActionSpec((2,), 0, (), ()))
NN = NNConfig(hidden_units=[16, 16])
CONFIGS: dict[str, tuple[EnvSpec, dict[str, Any]]] = {
    "continuous, prioritized": (SPEC, {"use_priority": True}),
    "discrete": (DISCRETE, {}),
    "head subsets, noisy Q, curiosity, RND": (
        SPEC,
        {
            "ensemble_q_num": 4,
            "ensemble_q_sample": 2,
            "use_curiosity": True,
            "use_rnd": True,
            "rnd_strength": 0.1,
            "noisy": True,
        },
    ),
}


def tensors_in(obj: Any) -> Iterator[Tensor]:
    """Every tensor of a pass's result (dataclasses, dicts, lists and tuples walked in order)."""
    if isinstance(obj, Tensor):
        yield obj
    elif hasattr(obj, "__dataclass_fields__"):
        for name in obj.__dataclass_fields__:
            yield from tensors_in(getattr(obj, name))
    elif isinstance(obj, dict):
        for value in obj.values():
            yield from tensors_in(value)
    elif isinstance(obj, list | tuple):
        for value in obj:
            yield from tensors_in(value)


class RerunRecorder:
    """Replays by running the recorded pass again and writing its results into the recorded tensors.
    Like a CUDA graph's replay it leaves Python's state alone: the parameters' ``.grad`` attributes are
    put back as they were (the pass sets them afresh)."""

    def __init__(self, params: list[Tensor]) -> None:
        self._params = params
        self._run: Callable[[], Any] | None = None
        self._out: Any = None

    def record(self, run: Callable[[], Any]) -> Any:
        self._run, self._out = run, run()
        return self._out

    def replay(self) -> None:
        assert self._run is not None
        attributes = [p.grad for p in self._params]
        fresh = list(tensors_in(self._run()))
        for p, grad in zip(self._params, attributes, strict=True):
            p.grad = grad
        recorded = list(tensors_in(self._out))
        assert len(fresh) == len(recorded)
        with torch.no_grad():
            for old, new in zip(recorded, fresh, strict=True):
                old.copy_(new)


class FailingRecorder:
    def record(self, run: Callable[[], Any]) -> Any:
        raise RuntimeError("operation not permitted when stream is capturing")

    def replay(self) -> None:
        raise AssertionError("never recorded")


def build(spec: EnvSpec, device: str = "cpu", **overrides: Any) -> SAC:
    nn = NN.model_copy(update={"noisy_q": True}) if overrides.pop("noisy", False) else NN
    return SAC(spec, SacConfig(**{"seed": 3, **overrides}), nn, ReplayConfig(beta=0.4), device=device)


def trained_params(sac: SAC) -> list[Tensor]:
    return [p for opt in sac._optimizers() for group in opt.param_groups for p in group["params"]]


def batches(spec: EnvSpec) -> list[Any]:
    """Thirty batches; one with a NaN reward (a skipped step) and two of another size (recorded again)."""
    out = []
    for i in range(30):
        b = 5 if i in (12, 13) else 8
        batch = make_batch(b=b, seed=i)
        if spec.action.discrete_branches:
            batch.actions = np.eye(2, dtype=np.float32)[np.random.default_rng(i).integers(0, 2, (b, 1))]
        if i == 7:
            batch.rewards[0, 0] = np.nan
        out.append(batch)
    return out


def run_both(plain: SAC, replayed: SAC, spec: EnvSpec) -> None:
    for i, batch in enumerate(batches(spec)):
        a = plain.update(batch, with_metrics=i % 5 == 0)
        b = replayed.update(batch, with_metrics=i % 5 == 0)
        assert a.skipped == b.skipped == (i == 7)
        np.testing.assert_array_equal(a.td_abs, b.td_abs)
        assert a.metrics == b.metrics


@pytest.mark.parametrize("name", CONFIGS)
def test_replayed_updates_compute_what_eager_updates_compute(name: str) -> None:
    spec, overrides = CONFIGS[name]
    plain, replayed = build(spec, **overrides), build(spec, **overrides)
    assert plain.update_graph is None  # no graphs on the CPU
    params = trained_params(replayed)
    graph = UpdateGraph(lambda: RerunRecorder(params), params)
    replayed.update_graph = graph
    run_both(plain, replayed, spec)
    assert graph.recordings == 3  # the first batch, the smaller one, the usual size again
    assert_same_state(plain.state_dict(), replayed.state_dict())


def test_a_recording_that_fails_falls_back_to_eager_updates(caplog: pytest.LogCaptureFixture) -> None:
    plain, replayed = build(SPEC), build(SPEC)
    graph = UpdateGraph(FailingRecorder, trained_params(replayed))
    replayed.update_graph = graph
    with caplog.at_level(logging.WARNING, logger="asac.update_graph"):
        run_both(plain, replayed, SPEC)
    assert_same_state(plain.state_dict(), replayed.state_dict())
    assert graph.failed == MAX_FAILED_RECORDINGS and not graph.usable
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == MAX_FAILED_RECORDINGS
    assert "operation not permitted when stream is capturing" in warnings[0]
    assert "updates run without it from now on" in warnings[-1]


def test_which_configs_are_recorded() -> None:
    cuda, default = torch.device("cuda"), SacConfig()
    assert why_not_graphed(default, torch.device("cpu"), False, False, False) == "not a CUDA device"
    assert why_not_graphed(default, cuda, False, False, False) is None
    assert "cuda_graph is false" in str(why_not_graphed(SacConfig(cuda_graph=False), cuda, False, False, False))
    assert "compile" in str(why_not_graphed(default, cuda, True, False, False))
    assert "use_rnn" in str(why_not_graphed(default, cuda, False, True, False))
    assert "V-trace" in str(why_not_graphed(SacConfig(use_n_step_is=True), cuda, False, False, False))
    assert "prediction" in str(why_not_graphed(default, cuda, False, False, True))
    rnd = SacConfig(use_rnd=True, rnd_strength=0.1, rnd_normalize=True)
    assert "rnd_normalize" in str(why_not_graphed(rnd, cuda, False, False, False))


needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


@needs_cuda
@pytest.mark.parametrize("name", CONFIGS)
@pytest.mark.parametrize("dtype", ["float32", "bfloat16"])
def test_cuda_graph_updates_match_eager_updates_on_the_gpu(name: str, dtype: str) -> None:
    spec, overrides = CONFIGS[name]
    plain = build(spec, "cuda", cuda_graph=False, compute_dtype=dtype, **overrides)
    graphed = build(spec, "cuda", compute_dtype=dtype, **overrides)
    assert plain.update_graph is None and graphed.update_graph is not None
    for i, batch in enumerate(batches(spec)):
        a, b = plain.update(batch), graphed.update(batch)
        assert a.skipped == b.skipped == (i == 7)
        np.testing.assert_allclose(a.td_abs, b.td_abs, rtol=1e-4, atol=1e-5)
    assert graphed.update_graph.recordings == 3 and graphed.update_graph.failed == 0
    for (key, x), y in zip(plain.models.state_dict().items(), graphed.models.state_dict().values(), strict=True):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5, msg=key)
