"""The role processes of distributed ASAC, composed from algorithm/ parts and ds/ transports.

Usage (``main_ds.py`` resolves the config and run directory, then calls exactly one of these)::

    role = RoleContext(config, run_dir, make_env, build, stop=stop_on_signals())
    code = run_replay(role)                 # serves the replay table until stopped
    code = run_learner(role, ckpt_step=None) # trains until replay has seen max_step env steps
    code = run_actor(role, noise=None, index=None)  # acts until the budget is spent
    code = run_evolver(role)                # keeps the population until stopped

(``ds/launch/local.py`` runs them all as subprocesses; :class:`RoleContext` and the helpers the loops
share live in ds/launch/role_context.py.) Each returns the process exit code: 0 done (or, a learner,
retired by the evolver), 130 stopped by a signal (SIGINT/SIGTERM: the role saves what it must
first), 1 the evolver forgot a learner. Addresses come from ``net_config`` (``main_ds.py``
flags override it): clients connect to ``<role>_host`` (null: this host), servers listen on
``bind_host``, every server and client with the role's credentials (ds/net/security.py: the token on
every rpc, TLS / mutual TLS; a server beyond loopback without them logs a warning).

With an evolver (``base_config.evolver_enabled``, or ``net_config.evolver_host`` set, e.g. by
``--evolver_host``) learners register with it and run with the config it gives them (their own
flags on top), replays and actors started without a learner ask it where to work, and every role of
learner k works in ``<run>/learner_<k>/`` (ds/evolver/population.py).
"""

from __future__ import annotations

import logging
import shutil
import socket
import threading
import time
from dataclasses import replace
from typing import Any

from grpc_health.v1 import health

from algorithm.config import config_to_yaml
from algorithm.config_schema import Config
from algorithm.files import WriteFailures, atomic_write
from algorithm.logging import MetricsWriter
from algorithm.replay import PrioritizedTable
from algorithm.replay.persistence import snapshot_kept
from algorithm.sac import SAC
from algorithm.signals import stop_on_signals
from algorithm.trainer import EVAL_SEED_OFFSET, RunDir, load_replay_snapshot, seed_everything
from ds.actor.actor import DistributedActor
from ds.evolver.evolver import Evolver
from ds.evolver.link import EvolverLink, Membership, WeightsSnapshot, exit_code, wait_for_replay
from ds.evolver.population import (
    AssignmentKeeper,
    Joined,
    LearnerAddress,
    SlotTaken,
    join_population,
    learner_dir,
    member_config,
    wait_for_assignment,
)
from ds.evolver.service import EvolverClient, serve_evolver
from ds.evolver.state import Assignment
from ds.launch.local import LOCAL_HOST
from ds.launch.role_context import RoleContext, RoleError, fixed_port, listen, process_name
from ds.learner import service as learner_service
from ds.learner.learner import Learner
from ds.learner.service import (
    ActorRegistry,
    LearnerClient,
    LearnerServicer,
    ParamsStore,
    PublishedPolicy,
    Registration,
    learner_message_limit,
    serve_learner,
)
from ds.net.params import ParamsPublisher, params_spec
from ds.net.rpc import set_serving, wait_until_serving
from ds.net.security import warn_if_exposed
from ds.net.stream_key import StreamKey
from ds.replay import service as replay_service
from ds.replay.service import ReplayClient, serve_replay

log = logging.getLogger("asac.roles")


# ---------------------------------------------------------------------- evolver


def run_evolver(role: RoleContext) -> int:
    """Keep the population (ds/evolver/evolver.py) on ``bind_host:evolver_port`` until stopped: its state lives
    in ``<run>/evolver/`` (a restarted evolver carries on from it), TensorBoard in ``<run>/log/evolver``."""
    cfg, net = role.config, role.config.net_config
    metrics = MetricsWriter(role.run_dir / "log" / "evolver")
    try:
        evolver = Evolver(cfg, role.run_dir / "evolver", cfg.base_config.name, token=role.token,
                          credentials=role.credentials, metrics=metrics)  # fmt: skip
    except BaseException:
        metrics.close()
        raise
    address = f"{net.bind_host}:{net.evolver_port}"
    server, port, _ = listen("evolver", address, "--evolver_port", lambda: serve_evolver(
        evolver, address, credentials=role.credentials, health_port=net.health_port))  # fmt: skip
    evolver.start()
    info = evolver.info()
    log.info("evolver of %r serving on %s:%d: %d learners known, %d CEM rounds so far", info.experiment,
             net.bind_host, port, len(info.learners), info.rounds)  # fmt: skip
    try:
        role.stop.wait()
    finally:
        server.stop(grace=2.0).wait()
        evolver.stop()
        metrics.close()
    return 130


# ---------------------------------------------------------------------- replay


def run_replay(role: RoleContext, metrics_every_s: float = 10.0) -> int:
    """Serve the run's prioritized table (rate limiter enforced: actors and learner are separate
    processes) until stopped; with ``save_replay`` load it at start and save it every
    ``save_replay_per_minute`` (default ``save_model_per_minute``) minutes and at shutdown, with
    ``save_replay_on_stop`` (the default) only at shutdown and start. A
    replay killed without saving comes back with its last snapshot, including the ids of the chunks
    in it: actors send again what was not acknowledged, and what the snapshot holds is not stored
    twice. Its Save and Load rpcs may name files in ``<run>/replay/`` only (an empty name: the
    snapshot itself; ds/replay/files.py). With an evolver it first asks which learner it serves (announcing
    ``replay_host:replay_port``) and builds its table from that learner's config. A snapshot that
    cannot be written (a full disk) is logged once and tried again at the next interval, the previous
    one kept; the replay serves on, and a failed save at shutdown is logged, not raised."""
    client, keeper = None, None
    try:
        if role.uses_evolver:
            joined = _replay_assignment(role)
            if joined is None:
                return 130
            client, keeper, role = joined
        return _serve_replay(role, keeper, metrics_every_s)
    finally:
        if keeper is not None:
            keeper.close()
        if client is not None:
            client.close()


def _replay_assignment(role: RoleContext) -> tuple[EvolverClient, AssignmentKeeper, RoleContext] | None:
    net = role.config.net_config
    fixed_port("replay_port", net.replay_port)
    host = net.replay_host or (net.bind_host if net.bind_host not in ("0.0.0.0", "::", "") else socket.getfqdn())
    address, name = f"{host}:{net.replay_port}", process_name("replay")
    client = role.evolver_client()
    if client is None:
        return None

    def assign(previous: str) -> Assignment:
        return client.assign_replay(name, address, previous)

    job = wait_for_assignment(assign, f"replay at {address}", client.address, role.stop)
    if job is None:
        client.close()
        return None
    keeper = AssignmentKeeper(client, job, assign, role.stop, follow_gone=False)
    keeper.start()
    config = member_config(job.config_yaml, job.learner_id, role.config, role.overrides)
    log.info("replay at %s serves learner %d", address, job.learner_id)
    return client, keeper, replace(role, config=config, run_dir=learner_dir(role.run_dir, job.learner_id))


def _table_layout(config: Config) -> tuple[object, ...]:
    return config.replay_config, config.sac_config.burn_in_step, config.sac_config.n_step, config.nn_config


def _serve_replay(role: RoleContext, keeper: AssignmentKeeper | None, metrics_every_s: float) -> int:
    cfg = role.config
    seed_everything(role.seed)
    spec = role.spec()
    rnn = role.rnn_state_size(spec)  # no SAC: a replay needs no models, target copies or optimizers
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
    saving = cfg.replay_config.save_replay  # periodic snapshots
    saving_at_stop = saving or cfg.replay_config.save_replay_on_stop  # a stopped run resumes with its data
    save_every_min = cfg.replay_config.save_replay_per_minute or sac_cfg.save_model_per_minute
    if saving_at_stop and path.exists():
        load_replay_snapshot(table, path)  # a bad file stops the role (exit 2) before it is saved over
        info = table.info()
        log.info("replay restored from %s: %d steps, the chunk ids of %d actors", path, info["size"], info["producers"])
    checker = health.HealthServicer()
    address = f"{cfg.net_config.bind_host}:{cfg.net_config.replay_port}"
    server, port = listen("replay", address, "--replay_port", lambda: serve_replay(
        table, address, max_message_bytes=role.replay_limit(spec, rnn), health_servicer=checker, max_workers=64,
        credentials=role.credentials, health_port=cfg.net_config.health_port, snapshot_dir=path.parent,
    ))  # fmt: skip
    log.info("replay serving on %s:%d (capacity %d steps)", cfg.net_config.bind_host, port, table.capacity)
    writer = MetricsWriter(role.run_dir / "log" / "replay")
    snapshots = WriteFailures("replay snapshot", log, retry=f"trying again in {save_every_min:g} min",
                              kept=snapshot_kept)  # fmt: skip
    halt = keeper.tenure()[1] if keeper is not None else threading.Event()
    last_metrics = last_save = time.monotonic()
    code = 130
    try:
        while not role.stop.wait(1.0):
            now = time.monotonic()
            if keeper is not None and halt.is_set() and not role.stop.is_set():
                job = keeper.job
                moved = member_config(job.config_yaml, job.learner_id, role.config, role.overrides)
                if _table_layout(moved) != _table_layout(cfg):
                    log.info("this replay's learner is gone and learner %d needs another table layout: exiting so "
                             "that a fresh replay serves it", job.learner_id)  # fmt: skip
                    code = 0
                    break
                log.info("this replay's learner is gone; it serves learner %d now", job.learner_id)
                halt = keeper.tenure()[1]
            if now - last_metrics >= metrics_every_s:
                info = table.info()
                metrics = {f"replay/{k}": v for k, v in info.items() if isinstance(v, int | float)}
                writer.write(metrics, info["inserted_steps"])
                last_metrics = now
            if saving and (now - last_save) / 60 >= save_every_min:
                snapshots.attempt(path, lambda: table.save(path))
                last_save = time.monotonic()
    finally:
        replay_service.set_serving(checker, False)
        server.stop(grace=2.0).wait()
        if saving_at_stop and snapshots.attempt(path, lambda: table.save(path), final=True):
            log.info("replay saved to %s", path)
        writer.close()
    return code


# ---------------------------------------------------------------------- learner


def run_learner(role: RoleContext, ckpt_step: int | None = None, progress: bool = False) -> int:
    """Wait for the replay, then train (ds/learner/learner.py), serving the learner service and
    broadcasting parameters, until the replay has seen ``max_step`` env steps or a signal. With an
    evolver it first registers (its config comes from the evolver, its own flags on top), works in
    ``<run>/learner_<id>/``, and exits 0, checkpointed, when the evolver retires it."""
    net = role.config.net_config
    params_address = f"tcp://{net.bind_host}:{net.params_port or '*'}"
    # Signed under this start's stream key (and the token: ds/net/stream_key.py), not encrypted (ZeroMQ carries
    # no TLS here): actors take parameters only from the learner they registered with.
    publisher = listen("learner's parameter broadcast", params_address, "--override net.params_port=PORT",
                       lambda: ParamsPublisher(params_address, token=role.token, stream=StreamKey.fresh()))  # fmt: skip
    warn_if_exposed(net.bind_host, f"learner's parameter broadcast on {publisher.address}", role.token is not None,
                    "net_config.token_file (actors then drop frames it did not sign)")  # fmt: skip
    client: EvolverClient | None = None
    joined: Joined | None = None
    try:
        if role.uses_evolver:
            fixed_port("learner_port", net.learner_port)
            if (client := role.evolver_client()) is None:
                return 130
            if (joined := _join(role, client, int(publisher.address.rsplit(":", 1)[1]))) is None:
                return 130
            role = _member_learner(role, joined)
        return _train(role, publisher, ckpt_step, progress, client, joined)
    finally:
        publisher.close()
        if client is not None:
            client.close()
        if joined is not None:
            joined.slot.release()


def _join(role: RoleContext, client: EvolverClient, params_port: int) -> Joined | None:
    net = role.config.net_config
    static_replay = f"{net.replay_host}:{net.replay_port}" if net.replay_host is not None else ""
    name, host = process_name("learner"), net.learner_host or ""
    address = LearnerAddress(name, host, net.learner_port, params_port, static_replay)
    try:
        return join_population(client, role.run_dir, address, role.stop)
    except SlotTaken as e:
        raise RoleError(str(e)) from None


def _member_learner(role: RoleContext, joined: Joined) -> RoleContext:
    """Learner k's context: its config and its folder, with the config and model file it runs with."""
    r = joined.registration
    config = member_config(r.config_yaml, r.learner_id, role.config, role.overrides)
    folder = joined.slot.path
    path, text = RunDir(folder).config, config_to_yaml(config).encode()  # atomic: a full disk keeps the old one
    WriteFailures("run config", log).attempt(path, lambda: atomic_write(path, lambda f: f.write(text)))
    model_file = RunDir(role.run_dir).model_file
    if model_file.exists() and not RunDir(folder).model_file.exists():
        shutil.copyfile(model_file, RunDir(folder).model_file)  # main.py --run -n <run>/learner_<k> builds with it
    log.info("learner %d of %r in %s (seed %s, random_params %s)", r.learner_id, r.experiment, folder,
             config.sac_config.seed, r.params or "none")  # fmt: skip
    return replace(role, config=config, run_dir=folder)


def _train(
    role: RoleContext,
    publisher: ParamsPublisher,
    ckpt_step: int | None,
    progress: bool,
    client: EvolverClient | None,
    joined: Joined | None,
) -> int:
    cfg, net = role.config, role.config.net_config
    if cfg.base_config.torch_threads:
        import torch

        torch.set_num_threads(cfg.base_config.torch_threads)
    seed_everything(role.seed)
    spec = role.spec()
    sac = SAC(spec, cfg.sac_config, cfg.nn_config, cfg.replay_config, device=role.device,
              compile=cfg.sac_config.compile, build=role.build)  # fmt: skip
    replays: list[ReplayClient] = []

    def connect(address: str | None = None) -> ReplayClient:
        replays.append(role.replay_client(spec, sac.rnn_state_size, address))
        return replays[-1]

    member = link = None
    if client is not None and joined is not None:
        link = EvolverLink(client, joined, params_spec(sac.models.state_dict()))
        link.start()
        member = Membership(link, WeightsSnapshot(role.token), connect)
    try:
        replay_address = wait_for_replay(link, role.stop) if link is not None else None
        if link is not None and joined is not None and replay_address is None:
            return exit_code(link, joined)
        replay = connect(replay_address)
        if not wait_until_serving(replay.channel, replay_service.SERVICE_NAME, "replay", replay.address, role.stop):
            return 130
        store, registry = ParamsStore(), ActorRegistry(lease_s=net.lease_s)
        acting = None if cfg.actor_config.update_policy_mode else PublishedPolicy(role.policy(spec))
        weights = None if member is None else member.snapshot
        servicer = LearnerServicer(spec, registry, store, publisher_port(publisher), acting, sac.rnn_state_size,
                                   weights=weights, stream=publisher.stream)  # fmt: skip
        address = f"{net.bind_host}:{net.learner_port}"
        server, port, health_ = listen("learner", address, "--learner_port", lambda: serve_learner(
            servicer, address, max_message_bytes=learner_message_limit(sac), credentials=role.credentials,
            health_port=net.health_port))  # fmt: skip
        eval_env = None
        if cfg.eval_config.eval_per_step > 0:
            eval_env = role.make_env(cfg.eval_config.eval_envs, role.seed + EVAL_SEED_OFFSET)
        try:
            learner = Learner(cfg, role.run_dir, sac, replay, publisher, store, acting=acting, registry=registry,
                              eval_env=eval_env, stop=role.stop, ckpt_step=ckpt_step, progress=progress,
                              member=member)  # fmt: skip
            learner.replay_address = replay.address
            learner.publish()
            set_serving(health_, learner_service.SERVICE_NAME, True)
            log.info("learner serving on %s:%d, parameters on %s", net.bind_host, port, publisher.address)
            summary = learner.run()
        finally:
            server.stop(grace=1.0).wait()
            if eval_env is not None:
                eval_env.close()
    finally:
        if link is not None:
            link.close()
        for replay in replays:
            replay.close()
    log.info(
        "learner %s after %d env steps, %d updates, %.0f s; last eval return %s",
        "retired" if summary.retired else "stopped" if summary.interrupted else "finished",
        summary.env_steps,
        summary.updates,
        summary.wall_seconds,
        "n/a" if summary.last_eval_mean is None else f"{summary.last_eval_mean:.1f}",
    )
    if link is not None and joined is not None and (link.retired or link.lost):
        return exit_code(link, joined, summary.updates)
    return 130 if summary.interrupted else 0


def publisher_port(publisher: ParamsPublisher) -> int:
    return int(publisher.address.rsplit(":", 1)[1])


# ---------------------------------------------------------------------- actor


def run_actor(role: RoleContext, noise: float | None = None, index: int | None = None) -> int:
    """Act (ds/actor/actor.py) until the replay has seen ``max_step`` env steps, ``max_iter`` iterations
    of this actor's env 0 end, or a signal. With an evolver and no ``--learner_host`` it asks the
    evolver for a learner (and its replay and config), and moves to another one when its learner
    retires or stays away longer than its lease. ``index`` (``--index``): the index it asks each
    learner for (:class:`AsksForIndex`); None: the lowest free one."""
    import torch

    torch.set_num_threads(role.config.base_config.torch_threads or 1)  # acting is small: leave cores to the learner
    net = role.config.net_config
    if not role.uses_evolver or net.learner_host is not None:
        host = net.learner_host or LOCAL_HOST
        return _act(role, role.address("learner"), host, role.address("replay"), noise, index=index)
    name = process_name("actor")
    client = role.evolver_client()
    if client is None:
        return 130

    def assign(previous: str) -> Assignment:
        return client.assign_actor(name, previous)

    try:
        job = wait_for_assignment(assign, "actor", client.address, role.stop)
        if job is None:
            return 130
        keeper = AssignmentKeeper(client, job, assign, role.stop, follow_gone=True)
        keeper.start()
        try:
            while True:
                job, halt = keeper.tenure()
                config = member_config(job.config_yaml, job.learner_id, role.config, role.overrides)
                member = replace(role, config=config, run_dir=learner_dir(role.run_dir, job.learner_id), stop=halt)
                log.info("actor works for learner %d at %s:%d (replay %s)", job.learner_id, job.learner_host,
                         job.learner_port, job.replay_address)  # fmt: skip
                learner = f"{job.learner_host}:{job.learner_port}"
                code = _act(member, learner, job.learner_host, job.replay_address, noise, name, index)
                if role.stop.is_set():
                    return 130
                if not halt.is_set():
                    return code
        finally:
            keeper.close()
    finally:
        client.close()


class AsksForIndex(LearnerClient):
    """A learner client whose registrations ask for ``index`` when the actor names none of its own
    (its first one: an actor registering again asks for the index it had), so that ``local``'s
    ``[actor-k]`` is the learner's index k (ds/launch/local.py). Taken by another live actor: the learner
    gives the lowest free one, as without."""

    def __init__(self, *args: Any, index: int | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.index = index

    def register(self, name: str, preferred_index: int | None = None) -> Registration:
        return super().register(name, self.index if preferred_index is None else preferred_index)


def _act(
    role: RoleContext,
    learner_address: str,
    learner_host: str,
    replay_address: str,
    noise: float | None,
    name: str | None = None,
    index: int | None = None,
) -> int:
    seed_everything(role.seed)
    spec = role.spec()
    sac = role.policy(spec)
    replay = role.replay_client(spec, sac.rnn_state_size, replay_address)
    learner = AsksForIndex(learner_address, spec, sac.rnn_state_size, max_message_bytes=learner_message_limit(sac),
                           credentials=role.credentials, rpc_timeout_s=role.config.net_config.rpc_timeout_s,
                           index=index)  # fmt: skip
    try:
        actor = DistributedActor(role.config, role.run_dir, role.make_env, sac, replay, learner, learner_host,
                                 noise=noise, stop=role.stop, token=role.token, name=name)  # fmt: skip
        summary = actor.run()
    finally:
        replay.close()
        learner.close()
    log.info("actor %d %s after %d env steps, %d episodes", summary.index,
             "stopped" if summary.interrupted else "finished", summary.env_steps, summary.episodes)  # fmt: skip
    return 130 if summary.interrupted else 0


__all__ = [
    "RoleContext",
    "RoleError",
    "run_actor",
    "run_evolver",
    "run_learner",
    "run_replay",
    "stop_on_signals",
]
