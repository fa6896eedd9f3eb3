"""Helpers of the evolver tests on loopback: a config with sampled parameters, real learner servers that
serve fixed weights (optionally slowly), and :class:`Setup`, the evolvers of one state directory with their
servers and clients (the ``setup`` fixture of tests/ds/evolver/conftest.py stops them all)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from algorithm.config.schema import Config
from algorithm.spaces import ActionSpec, EnvSpec, SensorSpec
from ds.evolver.client import EvolverClient
from ds.evolver.evolver import Evolver
from ds.evolver.service import serve_evolver
from ds.learner.service import ActorRegistry, LearnerServicer, ParamsStore, serve_learner
from ds.net.params import encode_params
from ds.net.rpc import RetryPolicy

SPEC = EnvSpec((SensorSpec("state", (3,)),), ActionSpec(continuous_dim=1, low=(-2.0,), high=(2.0,)))
FAST_RETRY = RetryPolicy(attempts=2, initial_backoff_s=0.02, max_backoff_s=0.05)
LEASE_S = 10.0


def evolver_config(**base: Any) -> Config:
    settings = {"evolver_cem_length": 2, "evolver_cem_min_length": 1, "evolver_cem_best": 0.5,
                "evolver_cem_time": 60.0, "evolver_remove_worst": -1, "max_actors_each_learner": 2}  # fmt: skip
    return Config.model_validate(
        {
            "base_config": settings | base,
            "sac_config": {"seed": 0},
            "random_params": {"sac_config": {"n_step": {"in": [1, 3, 5]}, "gamma": {"truncated": [0.9, 0.99]}}},
        }
    )


def weights_of(value: float) -> dict[str, np.ndarray]:
    return {
        "q.weight": np.full((3, 4), value, np.float32),
        "policy.bias": np.full((2,), value, np.float64),
        "normalizer.count": np.array([7], np.int64),
    }


class FakeClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


class FakeLearner:
    """A real learner server whose GetWeights serves a fixed weight dict, optionally slowly."""

    def __init__(self, value: float, delay_s: float = 0.0) -> None:
        self.weights, self.delay_s = weights_of(value), delay_s
        self.fetching = threading.Event()
        servicer = LearnerServicer(SPEC, ActorRegistry(), ParamsStore(), params_port=0, weights=self.snapshot)
        self.server, self.port, _ = serve_learner(servicer)

    def snapshot(self) -> tuple[int, list[bytes]]:
        self.fetching.set()
        time.sleep(self.delay_s)
        return 5, encode_params(5, self.weights)


class Setup:
    """Evolvers (each with a server and a client) on one state directory; all stopped at the end."""

    def __init__(self, state_dir: Path) -> None:
        self.state_dir = state_dir
        self.clock = FakeClock()
        self._stops: list[Callable[[], None]] = []

    def evolver(self, config: Config, real_clock: bool = False, **kwargs: Any) -> tuple[Evolver, EvolverClient]:
        clock = time.monotonic if real_clock else self.clock
        evolver = Evolver(config, self.state_dir, "exp", lease_s=LEASE_S, clock=clock, **kwargs)
        server, port, _ = serve_evolver(evolver)
        client = EvolverClient(f"127.0.0.1:{port}", retry=FAST_RETRY, rpc_timeout_s=5.0)
        self._stops += [evolver.stop, lambda: server.stop(None), client.close]
        return evolver, client

    def learner(self, value: float, delay_s: float = 0.0) -> FakeLearner:
        fake = FakeLearner(value, delay_s)
        self._stops.append(lambda: fake.server.stop(None))
        return fake

    def close(self) -> None:
        while self._stops:
            self._stops.pop()()


def register(client: EvolverClient, fakes: list[FakeLearner]) -> list[int]:
    """Register each fake learner, each with its own replay; their ids."""
    return [
        client.register_learner(f"l{k}", "127.0.0.1", f.port, 0, f"replay-{k}:1").learner_id
        for k, f in enumerate(fakes)
    ]


def until(condition: Callable[[], bool], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.02)
