"""Acting without torch: the policy's forward pass in NumPy, on the policy's own weights.

An actor calls the policy once per env step on a handful of observations. At that size a torch
forward is almost all dispatch: ~120 us for the 256x256 MuJoCo policy on one observation, against
~65 us for the HalfCheetah step itself, and the interleaving slows the env step that follows by
another ~50 us (torch's large code footprint evicts MuJoCo's from the caches; measured with
``bench/distributed.py actor``). The same forward in NumPy takes ~11 us (~23 us with the sample
and its log-probability) and leaves the env's speed alone.

:class:`NumpyGaussianActor` covers the common case exactly: vector sensors concatenated
(:class:`~algorithm.nn.models.VectorRepresentation`), optional observation normalization, and a
:class:`~algorithm.nn.models.TanhGaussianPolicy` whose trunk is ``Linear -> activation`` layers and
whose head is a plain ``Linear``, on the CPU. :func:`numpy_actor_for` returns None for anything else
(images, recurrent or user-defined models, noisy layers, discrete branches, RND action choice), and
:class:`~algorithm.sac.learner.SAC` then acts with torch as before.

The arrays are views of the torch parameters (``Tensor.numpy()`` shares memory), so optimizer steps
and ``load_state_dict`` (both in place) are seen without copying. The caller draws the noise
(``SAC`` from its own seeded and checkpointed ``numpy.random.Generator``); given the same noise,
both paths compute the same actions and log-probabilities up to float32 rounding
(tests/algorithm/nn/test_numpy_acting.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.special import log_ndtr
from torch import nn

from algorithm.nn.models import (
    _HALF_LOG_2PI,
    _LOG2,
    _SATURATED_PRE_TANH,
    SATURATED_ACTION,
    SacModels,
    TanhGaussianPolicy,
    VectorRepresentation,
)
from algorithm.nn.normalization import ObservationNormalizer

_Trunk = list[tuple[nn.Linear, Callable[[np.ndarray], np.ndarray]]]


def _silu(x: np.ndarray) -> np.ndarray:
    return x / (1.0 + np.exp(-x))


def _elu(x: np.ndarray) -> np.ndarray:  # torch's default alpha = 1
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0.0)))


_ACTIVATIONS: dict[type[nn.Module], Callable[[np.ndarray], np.ndarray]] = {
    nn.ReLU: lambda x: np.maximum(x, 0.0),
    nn.Tanh: np.tanh,
    nn.ELU: _elu,
    nn.SiLU: _silu,
}


def _plain_linear(module: nn.Module) -> bool:
    return type(module) is nn.Linear and module.bias is not None


class _Linear:
    """``weight @ x + bias`` on a torch ``nn.Linear``'s weights (views, not copies), for ``x`` laid
    out feature-major, ``[in, N]``. OpenBLAS (NumPy's BLAS) is slow with the row-major ``x @ W.T``
    from 8 rows on: the 17-256-256-12 policy took 56-151 us at 8-64 rows that way and 25-128 us
    feature-major, as fast as a contiguous copy of ``W.T`` (which would have to be refreshed after
    every optimizer step, and fused Adam does not bump the parameters' version counters)."""

    def __init__(self, linear: nn.Linear) -> None:
        assert linear.bias is not None
        self._weight = linear.weight.detach().numpy()
        self._bias = linear.bias.detach().numpy()[:, None]

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self._weight @ x + self._bias


def _trunk_layers(trunk: nn.Module) -> _Trunk | None:
    """``(linear, activation)`` per trunk layer, or None if the trunk is not exactly ``Linear ->
    activation`` pairs of known activations."""
    if type(trunk) is not nn.Sequential or len(trunk) % 2:
        return None
    layers = []
    modules = list(trunk)
    for linear, act in zip(modules[::2], modules[1::2], strict=True):
        fn = _ACTIVATIONS.get(type(act))
        if fn is None or not isinstance(linear, nn.Linear) or not _plain_linear(linear):
            return None
        if isinstance(act, nn.ELU) and act.alpha != 1.0:
            return None
        layers.append((linear, fn))
    return layers


class NumpyGaussianActor:
    """``tanh``-Gaussian actions and their log-probabilities from a policy's weights, in NumPy.

    Build with :func:`numpy_actor_for` (which checks the models and reads ``trunk`` from the policy);
    it mirrors :meth:`TanhGaussianPolicy.sample`, ``SAC._behaviour_sample`` (extra exploration noise)
    and the observation normalizer."""

    def __init__(self, models: SacModels, trunk: _Trunk) -> None:
        policy = models.policy
        assert isinstance(policy, TanhGaussianPolicy)
        self._trunk = [(_Linear(linear), activation) for linear, activation in trunk]
        assert isinstance(policy.head, nn.Linear)
        self._head = _Linear(policy.head)
        self._action_dim = policy.action_dim
        self._log_std_min, self._log_std_max = policy.log_std_min, policy.log_std_max
        rep = models.representation
        assert isinstance(rep, VectorRepresentation)
        self._flatten = [rank != 1 for rank in rep.sensor_ranks]
        self._normalizer: list[tuple[np.ndarray, np.ndarray] | None] = []
        self._clip: np.ndarray | None = None
        norm = models.normalizer
        if norm is not None:
            self._clip = norm.clip.numpy()
            for name, on in zip(norm.names, norm.normalized, strict=True):
                stats = (getattr(norm, f"mean_{name}").numpy(), getattr(norm, f"std_{name}").numpy()) if on else None
                self._normalizer.append(stats)

    def act(self, obs: list[np.ndarray], noise: np.ndarray | None, extra_noise: float) -> tuple[np.ndarray, np.ndarray]:
        """Actions ``[N, A]`` in ``[-1, 1]`` and log-probabilities ``[N]`` (float32) for ``obs`` (one
        ``[N, *shape]`` array per sensor). ``noise`` is standard normal ``[N, A]``, or None for the
        deterministic action ``tanh(mean)``; ``extra_noise > 0`` widens the pre-tanh std to
        ``sqrt(std^2 + extra^2)``."""
        x = self._state(obs).T  # feature-major through the layers (see _Linear)
        for linear, activation in self._trunk:
            x = activation(linear(x))
        out = self._head(x).T
        mean, log_std = out[:, : self._action_dim], out[:, self._action_dim :]
        log_std = np.clip(log_std, self._log_std_min, self._log_std_max)
        if noise is None:
            action = np.tanh(mean).astype(np.float32, copy=False)
            return action, _log_density(np.zeros_like(mean), log_std, mean).sum(axis=-1).astype(np.float32)
        if extra_noise > 0:
            log_std = 0.5 * np.logaddexp(2.0 * log_std, np.float32(2.0 * math.log(extra_noise)))
        action = np.tanh(mean + np.exp(log_std) * noise).astype(np.float32, copy=False)
        return action, stored_action_log_prob(mean, log_std, action)

    def _state(self, obs: list[np.ndarray]) -> np.ndarray:
        parts = []
        for i, o in enumerate(obs):
            o = o.astype(np.float32, copy=False)
            if self._normalizer and (stats := self._normalizer[i]) is not None:
                assert self._clip is not None
                o = np.clip((o - stats[0]) / stats[1], -self._clip, self._clip)
            parts.append(o.reshape(o.shape[0], -1) if self._flatten[i] else o)
        return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=-1)


def _log_density(noise: np.ndarray, log_std: np.ndarray, pre_tanh: np.ndarray) -> np.ndarray:
    """Per dimension, as algorithm/nn/models.py's ``_squashed_gaussian_log_density``."""
    gaussian = -0.5 * noise * noise - log_std - np.float32(_HALF_LOG_2PI)
    return gaussian - 2.0 * (np.float32(_LOG2) - pre_tanh - np.logaddexp(np.float32(0.0), -2.0 * pre_tanh))


def stored_action_log_prob(mean: np.ndarray, log_std: np.ndarray, action: np.ndarray) -> np.ndarray:
    """algorithm/nn/models.py's :func:`~algorithm.nn.models.stored_action_log_prob` in NumPy
    (float32 ``[N]``): the density inside ``|a| < SATURATED_ACTION``, the edge's probability beyond."""
    inside = np.abs(action) < SATURATED_ACTION
    pre_tanh = np.arctanh(np.clip(action, -SATURATED_ACTION, SATURATED_ACTION))
    density = _log_density((pre_tanh - mean) * np.exp(-log_std), log_std, pre_tanh)
    if inside.all():
        return density.sum(axis=-1).astype(np.float32, copy=False)
    std, edge = np.exp(log_std), np.float32(_SATURATED_PRE_TANH)
    edges = np.where(action > 0, log_ndtr((mean - edge) / std), log_ndtr((-edge - mean) / std))
    return np.where(inside, density, edges).sum(axis=-1).astype(np.float32, copy=False)


def numpy_actor_for(models: SacModels, device_type: str, rnn: bool, discrete: bool) -> NumpyGaussianActor | None:
    """A :class:`NumpyGaussianActor` for ``models`` when it computes exactly what torch acting does
    (see the module docstring), else None."""
    policy, rep, norm = models.policy, models.representation, models.normalizer
    if device_type != "cpu" or rnn or discrete or models.rnd is not None:
        return None
    if type(policy) is not TanhGaussianPolicy or not _plain_linear(policy.head):
        return None
    trunk = _trunk_layers(policy.trunk)
    if trunk is None:
        return None
    if type(rep) is not VectorRepresentation or rep.policy_state_dim != rep.state_dim:
        return None
    if norm is not None and type(norm) is not ObservationNormalizer:
        return None
    params = [*policy.parameters(), *(norm.buffers() if norm is not None else ())]
    if any(p.dtype.is_floating_point and p.dtype.itemsize != 4 for p in params):
        return None  # float32 only: what the arrays are computed in
    return NumpyGaussianActor(models, trunk)
