"""Temporally correlated acting noise with unchanged per-step marginals (``sac_config.action_noise_color``).

SAC explores with noise drawn afresh at every step ("white": independent across steps). Eberhard et
al. 2023 ("Pink Noise Is All You Need", ICLR) replace it with Gaussian noise whose power spectrum
falls as ``1/f**beta`` along an env's steps (beta 1: pink, 2: red/Brownian-like), which moves a
policy's samples in slow drifts as well as fast jitter: exploration that persists over many steps,
as a swing-up that needs pumping or a cart that must be walked back to the centre asks for, while
each step's noise stays a standard normal, so the action's distribution at every step is the
policy's own and the behaviour log-probabilities actors store stay exact.

:class:`ColoredNoise` keeps one sequence of ``horizon`` steps per (env, noise dimension) and hands
out one step of each per call; a used-up sequence is replaced by a fresh one. Sequences are drawn
with the spectral method (random Fourier coefficients scaled by ``f**(-beta/2)``, the lowest
frequency ``1/horizon`` standing in for zero, then an inverse real FFT) and divided by their exact
standard deviation, so every step is N(0, 1). Discrete branches use the same noise through its
normal CDF: a uniform draw, and the action the inverse CDF of the branch's probabilities gives.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

HORIZON = 1000  # steps per sequence: the episode length of most tasks, as in Eberhard et al. 2023


def colored_sequences(beta: float, count: int, horizon: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` independent sequences ``[count, horizon]`` float64 of power spectrum ~ ``1/f**beta``,
    each step distributed N(0, 1)."""
    if horizon < 2:
        raise ValueError(f"colored noise: horizon must be >= 2, got {horizon}")
    freqs = np.fft.rfftfreq(horizon)
    freqs[0] = 1.0 / horizon  # the zero frequency gets the lowest one's scale, not an infinite one
    scale = freqs ** (-beta / 2.0)
    real = rng.standard_normal((count, freqs.size)) * scale
    imag = rng.standard_normal((count, freqs.size)) * scale
    # The zero (and, for an even horizon, the Nyquist) coefficient of a real signal is real: its
    # variance is carried by the real part alone, twice as large.
    edges = [0, freqs.size - 1] if horizon % 2 == 0 else [0]
    imag[:, edges] = 0.0
    real[:, edges] *= math.sqrt(2.0)
    x = np.fft.irfft(real + 1j * imag, n=horizon, axis=-1)
    # Each step of the inverse transform sums 2 * scale_k**2 / horizon**2 of variance per interior
    # coefficient (real and imaginary parts, counted twice by symmetry) and 2 * scale_k**2 / horizon**2
    # for the edges: the same for every step, since the phases are uniformly random.
    interior = np.ones(freqs.size, dtype=bool)
    interior[edges] = False
    variance = (4.0 * np.sum(scale[interior] ** 2) + 2.0 * np.sum(scale[edges] ** 2)) / horizon**2
    return x / math.sqrt(variance)


class ColoredNoise:
    """Per-step standard-normal noise ``[n, dims]``, correlated across calls along each row's sequence."""

    def __init__(self, beta: float, rng: np.random.Generator, horizon: int = HORIZON) -> None:
        if not (math.isfinite(beta) and beta >= 0):
            raise ValueError(f"colored noise: beta must be finite and >= 0, got {beta!r}")
        self.beta, self.horizon, self.rng = float(beta), int(horizon), rng
        self._sequences = np.zeros((0, 0, self.horizon))  # [n, dims, horizon]
        self._position = self.horizon

    def draw(self, n: int, dims: int) -> np.ndarray:
        """The next step of each of ``n * dims`` sequences, ``[n, dims]`` float32. A call with another
        ``(n, dims)`` than the last starts new sequences."""
        if self._sequences.shape[:2] != (n, dims) or self._position >= self.horizon:
            self._sequences = colored_sequences(self.beta, n * dims, self.horizon, self.rng).reshape(n, dims, -1)
            self._position = 0
        step = self._sequences[:, :, self._position]
        self._position += 1
        return step.astype(np.float32)

    def state(self) -> dict[str, Any]:
        """What resumes the stream exactly (the sequences in use and the position in them)."""
        return {"sequences": self._sequences.copy(), "position": self._position}

    def load_state(self, state: dict[str, Any]) -> None:
        self._sequences = np.asarray(state["sequences"], dtype=np.float64)
        self._position = int(state["position"])


def inverse_cdf_choice(probs: Tensor, z: Tensor) -> Tensor:
    """One action per row of ``probs [N, K]`` from a standard normal ``z [N]``: the inverse CDF of the
    row's distribution at the uniform ``Phi(z)``, so a N(0, 1) ``z`` picks action k with probability
    ``probs[k]`` exactly, and correlated ``z`` give correlated choices. A uniform past the row's
    rounded total picks its last action of positive probability, never a masked one."""
    uniform = torch.special.ndtr(z.to(probs.dtype))[:, None]
    below = (probs.cumsum(dim=-1) <= uniform).sum(dim=-1)
    last = probs.shape[-1] - 1 - (probs > 0).flip(-1).int().argmax(dim=-1)
    return torch.minimum(below, last)
