"""The role processes of distributed ASAC, composed from algorithm/ parts and ds/ transports.

Usage (``main_ds.py`` resolves the config and run directory, then calls exactly one of these)::

    role = RoleContext(config, run_dir, make_env, build, stop=stop_on_signals())
    code = run_replay(role)                 # serves the replay table until stopped
    code = run_learner(role, ckpt_step=None) # trains until replay has seen max_step env steps
    code = run_actor(role, noise=None)      # acts until the budget is spent
    code = run_local([python, "main_ds.py", "gym/pendulum"], child_args, actors=2)  # all as subprocesses

Each returns the process exit code: 0 done, 130 stopped by a signal (SIGINT/SIGTERM: the role
saves what it must first). Addresses come from ``net_config`` (``main_ds.py`` flags override it):
clients connect to ``<role>_host`` (null: this host), servers listen on ``bind_host``.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import TypeVar

import zmq
from grpc_health.v1 import health

from algorithm.actor import VectorEnvLike
from algorithm.config_schema import Config
from algorithm.logging import MetricsWriter
from algorithm.nn.user import ModelBuilder
from algorithm.replay import PrioritizedTable
from algorithm.sac import SAC
from algorithm.spaces import EnvSpec
from algorithm.trainer import EVAL_SEED_OFFSET, RunDir, seed_everything
from ds import learner_service, replay_service
from ds.actor import DistributedActor
from ds.learner import Learner
from ds.learner_service import (
    ActingPolicy,
    ActorRegistry,
    LearnerClient,
    LearnerServicer,
    ParamsStore,
    learner_message_limit,
    serve_learner,
)
from ds.params import ParamsPublisher
from ds.replay_codec import message_limit_bytes
from ds.replay_service import ReplayClient, serve_replay
from ds.rpc import set_serving, wait_until_serving

log = logging.getLogger("asac.roles")
LOCAL_HOST = "127.0.0.1"


_T = TypeVar("_T")


class RoleError(RuntimeError):
    """A role cannot start (e.g. its port is taken); the message says what to change."""


def _listen(what: str, address: str, flag: str, start: Callable[[], _T]) -> _T:
    try:
        return start()
    except (RuntimeError, zmq.ZMQError) as e:
        raise RoleError(
            f"{what} cannot listen on {address} ({e}); is the port in use? pick another with {flag}"
        ) from None


@dataclass
class RoleContext:
    """What every role needs: the resolved config, its run directory, an env factory
    ``make_env(num_envs, seed)``, the model builder of the run, the torch device, a stop event and
    the run's shared secret (``net_config.token_file``; None: parameters travel unsigned)."""

    config: Config
    run_dir: Path
    make_env: Callable[[int, int], VectorEnvLike]
    build: ModelBuilder
    device: str = "cpu"
    stop: threading.Event = field(default_factory=threading.Event)
    token: bytes | None = None

    @property
    def seed(self) -> int:
        return int(self.config.sac_config.seed or 0)

    def spec(self) -> EnvSpec:
        env = self.make_env(1, self.seed)
        try:
            return env.spec
        finally:
            env.close()

    def sac(self, spec: EnvSpec, device: str = "cpu") -> SAC:
        cfg = self.config
        return SAC(spec, cfg.sac_config, cfg.nn_config, cfg.replay_config, device=device, build=self.build)

    def address(self, role: str) -> str:
        net = self.config.net_config
        host, port = {"replay": (net.replay_host, net.replay_port), "learner": (net.learner_host, net.learner_port)}[
            role
        ]
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

    def replay_client(self, spec: EnvSpec, rnn_state_size: int) -> ReplayClient:
        limit = self.replay_limit(spec, rnn_state_size)
        return ReplayClient(
            self.address("replay"), spec.sensors, spec.action.size, rnn_state_size, max_message_bytes=limit
        )


def stop_on_signals() -> threading.Event:
    """An event set by the first SIGINT or SIGTERM (the role then finishes cleanly: saves, closes);
    a second signal raises KeyboardInterrupt to cut a stuck shutdown short."""
    stop = threading.Event()

    def handler(signum: int, frame: FrameType | None) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        log.info("%s: stopping (again to force)", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


# ---------------------------------------------------------------------- replay


def run_replay(role: RoleContext, metrics_every_s: float = 10.0) -> int:
    """Serve the run's prioritized table (rate limiter enforced: actors and learner are separate
    processes) until stopped; with ``save_replay`` load it at start and save it every
    ``save_model_per_minute`` minutes and at shutdown."""
    cfg = role.config
    seed_everything(role.seed)
    spec = role.spec()
    rnn = role.sac(spec).rnn_state_size
    sac_cfg = cfg.sac_config
    table = PrioritizedTable.from_config(
        cfg.replay_config,
        spec.sensors,
        spec.action.size,
        sac_cfg.burn_in_step + sac_cfg.n_step,
        rnn_state_size=rnn,
        enforce_ratio=True,
        seed=role.seed,
        burn_in=sac_cfg.burn_in_step,
    )
    path = RunDir(role.run_dir).replay
    saving = cfg.replay_config.save_replay
    if saving and path.exists():
        table.load(path)
        log.info("replay restored from %s: %d steps", path, table.info()["size"])
    checker = health.HealthServicer()
    address = f"{cfg.net_config.bind_host}:{cfg.net_config.replay_port}"
    server, port = _listen("replay", address, "--replay_port", lambda: serve_replay(
        table, address, max_message_bytes=role.replay_limit(spec, rnn), health_servicer=checker, max_workers=64
    ))  # fmt: skip
    log.info("replay serving on %s:%d (capacity %d steps)", cfg.net_config.bind_host, port, table.capacity)
    writer = MetricsWriter(role.run_dir / "log" / "replay")
    last_save = time.monotonic()
    try:
        while not role.stop.wait(metrics_every_s):
            info = table.info()
            writer.write(
                {f"replay/{k}": v for k, v in info.items() if isinstance(v, int | float)}, info["inserted_steps"]
            )
            if saving and (time.monotonic() - last_save) / 60 >= sac_cfg.save_model_per_minute:
                table.save(path)
                last_save = time.monotonic()
    finally:
        replay_service.set_serving(checker, False)
        server.stop(grace=2.0).wait()
        if saving:
            table.save(path)
            log.info("replay saved to %s", path)
        writer.close()
    return 130


# ---------------------------------------------------------------------- learner


def run_learner(role: RoleContext, ckpt_step: int | None = None, progress: bool = False) -> int:
    """Wait for the replay, then train (ds/learner.py), serving the learner service and
    broadcasting parameters, until the replay has seen ``max_step`` env steps or a signal."""
    cfg, net = role.config, role.config.net_config
    if cfg.base_config.torch_threads:
        import torch

        torch.set_num_threads(cfg.base_config.torch_threads)
    seed_everything(role.seed)
    spec = role.spec()
    sac = SAC(spec, cfg.sac_config, cfg.nn_config, cfg.replay_config, device=role.device,
              compile=cfg.sac_config.compile, build=role.build)  # fmt: skip
    replay = role.replay_client(spec, sac.rnn_state_size)
    if not wait_until_serving(replay.channel, replay_service.SERVICE_NAME, "replay", replay.address, role.stop):
        return 130
    params_address = f"tcp://{net.bind_host}:{net.params_port or '*'}"
    publisher = _listen("learner's parameter broadcast", params_address, "--override net.params_port=PORT",
                        lambda: ParamsPublisher(params_address, token=role.token))  # fmt: skip
    params_port = int(publisher.address.rsplit(":", 1)[1])
    store, registry = ParamsStore(), ActorRegistry()
    acting = None if cfg.actor_config.update_policy_mode else ActingPolicy(role.sac(spec))
    servicer = LearnerServicer(spec, registry, store, params_port, acting, sac.rnn_state_size)
    address = f"{net.bind_host}:{net.learner_port}"
    server, port, health = _listen("learner", address, "--learner_port", lambda: serve_learner(
        servicer, address, max_message_bytes=learner_message_limit(sac)))  # fmt: skip
    eval_env = None
    if cfg.eval_config.eval_per_step > 0:
        eval_env = role.make_env(cfg.eval_config.eval_envs, role.seed + EVAL_SEED_OFFSET)
    try:
        learner = Learner(cfg, role.run_dir, sac, replay, publisher, store, acting=acting, registry=registry,
                          eval_env=eval_env, stop=role.stop, ckpt_step=ckpt_step, progress=progress)  # fmt: skip
        learner.publish()
        set_serving(health, learner_service.SERVICE_NAME, True)
        log.info("learner serving on %s:%d, parameters on %s", net.bind_host, port, publisher.address)
        summary = learner.run()
    finally:
        server.stop(grace=1.0).wait()
        publisher.close()
        replay.close()
        if eval_env is not None:
            eval_env.close()
    log.info(
        "learner %s after %d env steps, %d updates, %.0f s; last eval return %s",
        "stopped" if summary.interrupted else "finished",
        summary.env_steps,
        summary.updates,
        summary.wall_seconds,
        "n/a" if summary.last_eval_mean is None else f"{summary.last_eval_mean:.1f}",
    )
    return 130 if summary.interrupted else 0


# ---------------------------------------------------------------------- actor


def run_actor(role: RoleContext, noise: float | None = None) -> int:
    """Act (ds/actor.py) until the replay has seen ``max_step`` env steps, ``max_iter`` iterations
    of this actor's env 0 end, or a signal."""
    import torch

    torch.set_num_threads(role.config.base_config.torch_threads or 1)  # acting is small: leave cores to the learner
    seed_everything(role.seed)
    spec = role.spec()
    sac = role.sac(spec)
    replay = role.replay_client(spec, sac.rnn_state_size)
    learner_host = role.config.net_config.learner_host or LOCAL_HOST
    learner = LearnerClient(
        role.address("learner"), spec, sac.rnn_state_size, max_message_bytes=learner_message_limit(sac)
    )
    try:
        actor = DistributedActor(role.config, role.run_dir, role.make_env, sac, replay, learner, learner_host,
                                 noise=noise, stop=role.stop, token=role.token)  # fmt: skip
        summary = actor.run()
    finally:
        replay.close()
        learner.close()
    log.info("actor %d %s after %d env steps, %d episodes", summary.index,
             "stopped" if summary.interrupted else "finished", summary.env_steps, summary.episodes)  # fmt: skip
    return 130 if summary.interrupted else 0


# ---------------------------------------------------------------------- local


def free_port() -> int:
    """A TCP port that was free on loopback a moment ago."""
    with socket.socket() as s:
        s.bind((LOCAL_HOST, 0))
        return int(s.getsockname()[1])


class LocalProcesses:
    """Children of one ``local`` run in one process group, their output streamed with role prefixes."""

    def __init__(self, stream: Callable[[str], None] = lambda line: print(line, end="", flush=True)) -> None:
        self.children: dict[str, subprocess.Popen[str]] = {}
        self.pgid = 0
        self._stream = stream
        self._readers: list[threading.Thread] = []

    def start(self, name: str, command: list[str], env: dict[str, str] | None = None) -> None:
        proc = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            env={**os.environ, **(env or {})},
            process_group=self.pgid,  # the first child leads a new group; the others join it
        )
        if not self.pgid:
            self.pgid = proc.pid
        self.children[name] = proc
        reader = threading.Thread(target=self._pump, args=(name, proc), daemon=True)
        reader.start()
        self._readers.append(reader)
        log.info("started %s (pid %d)", name, proc.pid)

    def _pump(self, name: str, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            self._stream(f"[{name}] {line}")

    def signal(self, names: list[str], signum: int) -> None:
        for name in names:
            proc = self.children[name]
            if proc.poll() is None:
                proc.send_signal(signum)

    def stop_all(self, grace_s: float) -> None:
        """SIGINT to the group, wait ``grace_s``; then SIGTERM, wait 5 s; then SIGKILL."""
        for signum, wait_s in ((signal.SIGINT, grace_s), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            if self.wait_all(0):
                break
            if signum != signal.SIGINT:
                log.warning("children still running after %.0f s: %s", wait_s, signal.Signals(signum).name)
            try:
                os.killpg(self.pgid, signum)
            except ProcessLookupError:
                break
            self.wait_all(wait_s)
        for reader in self._readers:
            reader.join(2.0)

    def wait_all(self, timeout_s: float, names: list[str] | None = None) -> bool:
        deadline = time.monotonic() + timeout_s
        procs = [self.children[n] for n in names or list(self.children)]
        while any(p.poll() is None for p in procs):
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.1)
        return True


def run_local(
    command: list[str],
    child_args: list[str],
    actors: int,
    role_args: dict[str, list[str]] | None = None,
    grace_s: float = 30.0,
) -> int:
    """Replay, learner and ``actors`` actors as subprocesses ``command + [role] + child_args`` (plus
    ``role_args[role]``) on loopback with free ports. Returns 0 when the learner finishes (then
    the actors and then the replay are stopped; the replay saves), 130 on SIGINT/SIGTERM (every
    child gets SIGINT, then SIGTERM and SIGKILL after ``grace_s``), 1 when a child fails (the others
    are stopped)."""
    ports = ["--replay_host", LOCAL_HOST, "--replay_port", str(free_port()), "--learner_host", LOCAL_HOST,
             "--learner_port", str(free_port()), "--override", "net.params_port=0"]  # fmt: skip
    children = LocalProcesses()
    stop = stop_on_signals()
    try:
        extra = role_args or {}
        children.start("replay", [*command, "replay", *child_args, *ports, *extra.get("replay", [])])
        children.start("learner", [*command, "learner", *child_args, *ports, *extra.get("learner", [])])
        for i in range(actors):
            children.start(f"actor-{i}", [*command, "actor", *child_args, *ports, *extra.get("actor", [])])
        code = _supervise(children, stop)
    except KeyboardInterrupt:
        code = 130
    if code == 0:  # the run's budget is spent: actors first (nothing left to learn from), then the replay
        actor_names = [n for n in children.children if n.startswith("actor")]
        children.signal(actor_names, signal.SIGINT)
        children.wait_all(grace_s, actor_names)
        children.signal(["replay"], signal.SIGINT)
    try:
        children.stop_all(grace_s)
    except KeyboardInterrupt:  # a second Ctrl-C: no more waiting
        os.killpg(children.pgid, signal.SIGKILL)
        children.wait_all(5.0)
        code = 130
    return code


def _supervise(children: LocalProcesses, stop: threading.Event) -> int:
    while not stop.wait(0.2):
        for name, proc in children.children.items():
            code = proc.poll()
            if code is None:
                continue
            if name == "learner" and code == 0:
                log.info("learner finished")
                return 0
            if code != 0 or name == "replay":
                log.error("%s exited with code %d: stopping the others", name, code)
                return 1
    return 130


__all__ = ["RoleContext", "RoleError", "run_actor", "run_learner", "run_local", "run_replay", "stop_on_signals"]
