"""What every role process is given (:class:`RoleContext`) and the small helpers the four role
compositions share: how a server that cannot listen fails (:class:`RoleError`), and how a role names
itself to its peers. Each role is composed in its own package, beside its loop, server and client::

    role = RoleContext(config, run_dir, make_env, build, stop=stop_on_signals())
    code = run_replay(role)                 # ds/replay/role.py: serves the replay table until stopped
    code = run_learner(role, ckpt_step=None) # ds/learner/role.py: trains until replay has seen max_step env steps
    code = run_actor(role, noise=None, index=None)  # ds/actor/role.py: acts until the budget is spent
    code = run_evolver(role)                # ds/evolver/role.py: keeps the population until stopped

(``main_ds.py`` resolves the config and run directory, then calls exactly one of these;
``ds/launch/local.py`` runs them all as subprocesses.) Each returns the process exit code: 0 done (or, a
learner, retired by the evolver), 130 stopped by a signal (SIGINT/SIGTERM: the role saves what it must
first), 1 the evolver forgot a learner. Addresses come from ``net_config`` (``main_ds.py`` flags
override it): clients connect to ``<role>_host`` (null: this host), servers listen on ``bind_host``,
every server and client with the role's credentials (ds/net/security.py: the token on every rpc, TLS /
mutual TLS; a server beyond loopback without them logs a warning).

With an evolver (``base_config.evolver_enabled``, or ``net_config.evolver_host`` set, e.g. by
``--evolver_host``) learners register with it and run with the config it gives them (their own flags on
top), replays and actors started without a learner ask it where to work, and every role of learner k
works in ``<run>/learner_<k>/`` (ds/member/population.py).

Like the role compositions, this touches no envs itself (they arrive as the ``make_env`` factory).
"""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import zmq

from algorithm.config.load import ConfigError
from algorithm.config.schema import Config
from algorithm.errors import RoleError
from algorithm.nn.shapes import default_recurrent_state_size
from algorithm.run.actor import VectorEnvLike
from algorithm.spaces import EnvSpec
from ds.evolver import service as evolver_service
from ds.evolver.client import EvolverClient
from ds.net.credentials import NO_CREDENTIALS, Credentials, Keyring
from ds.net.rpc import LOCAL_HOST, wait_until_serving
from ds.replay.client import ReplayClient
from ds.replay.codec import message_limit_bytes

if TYPE_CHECKING:  # torch: imported by the roles that build models, never by the replay or the evolver
    from algorithm.nn.user import ModelBuilder
    from algorithm.sac.learner import SAC
    from algorithm.sac.policy import Policy

_T = TypeVar("_T")


def listen(what: str, address: str, flag: str, start: Callable[[], _T]) -> _T:
    try:
        return start()
    except (RuntimeError, zmq.ZMQError) as e:
        raise RoleError(
            f"{what} cannot listen on {address} ({e}); is the port in use? pick another with {flag}"
        ) from None


@dataclass
class RoleContext:
    """What every role needs: the resolved config, its run directory, an env factory
    ``make_env(num_envs, seed)``, the model builder of the run's model file (None: the default models,
    imported when first built, so that the replay of a run without a model file never imports torch),
    the torch device, a stop event, the role's credentials (ds/net/security.py: the run's shared secret
    of ``net_config.token_file``, which signs parameters and authenticates rpcs, and its TLS
    certificates; none: plaintext, unsigned) and this process's ``--override`` flags (applied again on
    top of the config an evolver gives)."""

    config: Config
    run_dir: Path
    make_env: Callable[[int, int], VectorEnvLike]
    build: ModelBuilder | None = None
    device: str = "cpu"
    stop: threading.Event = field(default_factory=threading.Event)
    credentials: Credentials = NO_CREDENTIALS
    overrides: tuple[str, ...] = ()

    @property
    def token(self) -> Keyring | None:
        """The run's token(s), read again when the token file changes (ds/net/credentials.py)."""
        return self.credentials.token

    @property
    def seed(self) -> int:
        return int(self.config.sac_config.seed or 0)

    @property
    def uses_evolver(self) -> bool:
        return self.config.base_config.evolver_enabled or self.config.net_config.evolver_host is not None

    def spec(self) -> EnvSpec:
        env = self.make_env(1, self.seed)
        try:
            return env.spec
        finally:
            env.close()

    def rnn_state_size(self, spec: EnvSpec) -> int:
        """The recurrent state width of this run's models, without building a SAC (a replay needs only this)."""
        cfg = self.config
        if self.build is None:
            return default_recurrent_state_size(cfg.sac_config, cfg.nn_config)
        from algorithm.nn.user import recurrent_state_size

        return recurrent_state_size(spec, cfg.sac_config, cfg.nn_config, self.build)

    @property
    def models(self) -> ModelBuilder:
        """The run's model builder: its model file's, else the default models'."""
        if self.build is not None:
            return self.build
        from algorithm.nn.builder import build_models

        return build_models

    def policy(self, spec: EnvSpec, device: str = "cpu") -> Policy:
        """The acting side alone (actors, the learner's GetAction copy): no optimizers, no targets."""
        from algorithm.sac.policy import Policy

        cfg = self.config
        return Policy(spec, cfg.sac_config, cfg.nn_config, device=device, build=self.models)

    def sac(self, spec: EnvSpec, device: str = "cpu") -> SAC:
        from algorithm.sac.learner import SAC

        cfg = self.config
        return SAC(spec, cfg.sac_config, cfg.nn_config, cfg.replay_config, device=device, build=self.models)

    def address(self, role: str) -> str:
        net = self.config.net_config
        host, port = {
            "replay": (net.replay_host, net.replay_port),
            "learner": (net.learner_host, net.learner_port),
            "evolver": (net.evolver_host, net.evolver_port),
        }[role]
        return f"{host or LOCAL_HOST}:{port}"

    def replay_limit(self, spec: EnvSpec, rnn_state_size: int) -> int:
        cfg = self.config
        window = cfg.sac_config.burn_in_step + cfg.sac_config.n_step
        return message_limit_bytes(
            spec.sensors,
            spec.action.size,
            cfg.replay_config.batch_size,
            window,
            rnn_state_size,
            max_chunk_steps=cfg.actor_config.chunk_length,
        )

    def replay_client(self, spec: EnvSpec, rnn_state_size: int, address: str | None = None) -> ReplayClient:
        limit = self.replay_limit(spec, rnn_state_size)
        return ReplayClient(
            address or self.address("replay"),
            spec.sensors,
            spec.action.size,
            rnn_state_size,
            max_message_bytes=limit,
            credentials=self.credentials,
            rpc_timeout_s=self.config.net_config.rpc_timeout_s,
            shared_memory=self.config.net_config.shared_memory,
        )

    def evolver_client(self) -> EvolverClient | None:
        """A client of the evolver once it serves; None if stopped while waiting for it."""
        client = EvolverClient(self.address("evolver"), token=self.token, credentials=self.credentials)
        service = evolver_service.SERVICE_NAME
        warn = self.config.net_config.peer_warn_s
        if wait_until_serving(client.channel, service, "evolver", client.address, self.stop, warn_after_s=warn):
            return client
        client.close()
        return None


def fixed_port(name: str, port: int) -> None:
    if port == 0:
        raise ConfigError(f"net_config.{name}: 0 (any free port) cannot be announced to the evolver; name a port")


def process_name(role: str) -> str:
    return f"{role} on {socket.gethostname()} (pid {os.getpid()})"


__all__ = ["RoleContext", "RoleError", "fixed_port", "listen", "process_name"]
