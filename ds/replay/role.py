"""The replay role, composed from algorithm/ parts and ds/ transports: :func:`run_replay` serves the run's
prioritized table (algorithm/replay/) over ds/replay/service.py, loading and saving its snapshot, until
stopped; with an evolver it first asks which learner it serves, and serves the one it is given next
when that learner is gone.

Usage (``main_ds.py replay``; what every role is given and the exit codes: ds/launch/role_context.py)::

    code = run_replay(role)  # 130 stopped; 0 its learner is gone and the next one needs another table layout
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from dataclasses import replace

from grpc_health.v1 import health

from algorithm.config.schema import Config
from algorithm.files import WriteFailures
from algorithm.replay import PrioritizedTable
from algorithm.replay.persistence import load_replay_snapshot, snapshot_kept
from algorithm.run.folder import RunDir
from algorithm.run.logging import MetricsWriter
from algorithm.seeding import seed_python_and_numpy
from ds.evolver.client import EvolverClient
from ds.evolver.state import Assignment
from ds.launch.role_context import RoleContext, fixed_port, listen, process_name
from ds.member.population import AssignmentKeeper, learner_dir, member_config, wait_for_assignment
from ds.net.rpc import set_serving
from ds.replay import service as replay_service
from ds.replay.service import serve_replay

log = logging.getLogger("asac.roles")


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
    seed_python_and_numpy(role.seed)  # no torch here: the table samples with numpy
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
    writer = MetricsWriter(RunDir(role.run_dir).role_log("replay"))
    snapshots = WriteFailures("replay snapshot", log, retry=f"trying again in {save_every_min:g} min",
                              kept=snapshot_kept)  # fmt: skip
    halt = keeper.tenure()[1] if keeper is not None else threading.Event()
    last_metrics = last_save = time.monotonic()
    finished = FinishedRunNotice(cfg.base_config.max_step, quiet_s=cfg.net_config.lease_s)
    code = 130
    try:
        while not role.stop.wait(1.0):
            now = time.monotonic()
            finished.check(table.rate_limiter.inserted, table.rate_limiter.sampled, now, saving_at_stop)
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
        set_serving(checker, replay_service.SERVICE_NAME, False)
        server.stop(grace=2.0).wait()
        if saving_at_stop and snapshots.attempt(path, lambda: table.save(path), final=True):
            info = table.info()
            log.info("replay saved to %s: %d env steps inserted over the run (%d of them stopping actors' last, "
                     "past the rate limiter)", path, info["inserted_steps"], info["stored_past_limiter"])  # fmt: skip
        writer.close()
    return code


class FinishedRunNotice:
    """Logs once when the run looks finished: ``max_step`` env steps are in and no learner has sampled
    for ``quiet_s`` (the replay role passes ``net.lease_s``, after which a learner drops a silent actor
    too). Roles started one by one stop the learner and actors at the budget, but nothing
    tells a replay that the learner will not come back (a resumed or second learner may), so it
    serves on and says so instead of sitting silent; ``local`` and Kubernetes stop it themselves."""

    def __init__(self, max_step: int, quiet_s: float) -> None:
        self.max_step, self.quiet_s = max_step, quiet_s
        self._sampled, self._since, self._told = -1, 0.0, False

    def check(self, inserted_steps: int, sampled_windows: int, now: float, saves_at_stop: bool) -> None:
        """Called about once a second with the table's counters; logs once per quiet spell (sampling
        again re-arms it)."""
        if self.max_step < 0 or inserted_steps < self.max_step:
            return
        if sampled_windows != self._sampled:
            self._sampled, self._since, self._told = sampled_windows, now, False
            return
        if self._told or now - self._since < self.quiet_s:
            return
        self._told = True
        log.info("the run's budget is in (%d+ env steps, base_config.max_step %d) and no learner has sampled for "
                 "%.0f s: the run looks finished, this replay serves on for a learner that resumes; Ctrl-C stops "
                 "it%s", inserted_steps, self.max_step, self.quiet_s,
                 " (and saves it)" if saves_at_stop else "")  # fmt: skip
