"""Seeding a process's random number generators from a run's seed.

The replay and the evolver roles never import torch (a Pendulum replay starts serving in ~1.5 s of CPU and
holds ~180 MB less than with it), so they seed Python's and numpy's generators only; every process
that builds models seeds torch's as well."""

from __future__ import annotations

import random

import numpy as np


def seed_python_and_numpy(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002 - user code and libraries may use the global RNG


def seed_everything(seed: int) -> None:
    """Python's, numpy's and torch's generators (torch is imported here)."""
    import torch

    seed_python_and_numpy(seed)
    torch.manual_seed(seed)
