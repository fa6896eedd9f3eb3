"""The learner role, composed from algorithm/ parts and ds/ transports: :func:`run_learner` opens the
parameter broadcast (ds/net/params.py), joins the evolver's population when there is one (its config
and its ``<run>/learner_<k>/`` folder come from there), waits for its replay, and trains
(ds/learner/learner.py) while serving the learner service (ds/learner/service.py).

Usage (``main_ds.py learner``; what every role is given and the exit codes: ds/launch/role_context.py)::

    code = run_learner(role, ckpt_step=None)  # trains until replay has seen max_step env steps
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import replace

from algorithm.config.load import config_to_yaml
from algorithm.files import WriteFailures, atomic_write
from algorithm.run.folder import EVAL_SEED_OFFSET, RunDir
from algorithm.sac.learner import SAC
from algorithm.seeding import seed_everything
from ds.evolver.client import EvolverClient
from ds.launch.role_context import RoleContext, RoleError, fixed_port, listen, process_name
from ds.learner import service as learner_service
from ds.learner.learner import Learner
from ds.learner.service import (
    ActorRegistry,
    LearnerServicer,
    ParamsStore,
    PublishedPolicy,
    learner_message_limit,
    serve_learner,
)
from ds.member.link import EvolverLink, Membership, WeightsSnapshot, exit_code, wait_for_replay
from ds.member.population import Joined, LearnerAddress, SlotTaken, join_population, member_config
from ds.net.params import ParamsPublisher, params_spec
from ds.net.rpc import set_serving, wait_until_serving
from ds.net.security import warn_if_exposed
from ds.net.stream_key import StreamKey
from ds.replay import service as replay_service
from ds.replay.client import ReplayClient

log = logging.getLogger("asac.roles")


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
              compile=cfg.sac_config.compile, build=role.models)  # fmt: skip
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
        replay_address = wait_for_replay(link, role.stop, net.peer_warn_s) if link is not None else None
        if link is not None and joined is not None and replay_address is None:
            return exit_code(link, joined)
        replay = connect(replay_address)
        if not wait_until_serving(replay.channel, replay_service.SERVICE_NAME, "replay", replay.address, role.stop,
                                  warn_after_s=net.peer_warn_s):  # fmt: skip
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
        eval_env, eval_policy = None, None
        if cfg.eval_config.eval_per_step > 0:  # evaluated beside training, with a copy of the acting weights
            eval_env = role.make_env(cfg.eval_config.eval_envs, role.seed + EVAL_SEED_OFFSET)
            eval_policy = role.policy(spec)
        try:
            learner = Learner(cfg, role.run_dir, sac, replay, publisher, store, acting=acting, registry=registry,
                              eval_env=eval_env, eval_policy=eval_policy, stop=role.stop, ckpt_step=ckpt_step,
                              progress=progress, member=member)  # fmt: skip
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
