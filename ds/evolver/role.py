"""The evolver role, composed from its ds/evolver/ parts: :func:`run_evolver` keeps the population of
learners (ds/evolver/evolver.py) and serves it to learners, replays and actors (ds/evolver/service.py)
until stopped.

Usage (``main_ds.py evolver``; what every role is given and the exit codes: ds/launch/role_context.py)::

    code = run_evolver(role)  # 130: it keeps the population until a signal stops it
"""

from __future__ import annotations

import logging

from algorithm.run.folder import RunDir
from algorithm.run.logging import MetricsWriter
from ds.evolver.evolver import Evolver
from ds.evolver.service import serve_evolver
from ds.launch.role_context import RoleContext, listen

log = logging.getLogger("asac.roles")


def run_evolver(role: RoleContext) -> int:
    """Keep the population (ds/evolver/evolver.py) on ``bind_host:evolver_port`` until stopped: its state lives
    in ``<run>/evolver/`` (a restarted evolver carries on from it), TensorBoard in ``<run>/log/evolver``."""
    cfg, net = role.config, role.config.net_config
    metrics = MetricsWriter(RunDir(role.run_dir).role_log("evolver"))
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
