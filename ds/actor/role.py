"""The actor role, composed from algorithm/ parts and ds/ transports: :func:`run_actor` acts
(ds/actor/actor.py) for the learner named by ``--learner_host`` or, with an evolver, for the one the
evolver assigns, moving to another when that learner retires or stays away past its lease.

Usage (``main_ds.py actor``; what every role is given and the exit codes: ds/launch/role_context.py)::

    code = run_actor(role, noise=None, index=None)  # acts until the budget is spent
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Any

from algorithm.seeding import seed_everything
from ds.actor.actor import DistributedActor
from ds.evolver.state import Assignment
from ds.launch.role_context import RoleContext, process_name
from ds.learner.client import LearnerClient, Registration
from ds.learner.service import learner_message_limit
from ds.member.population import AssignmentKeeper, learner_dir, member_config, wait_for_assignment
from ds.net.rpc import LOCAL_HOST

log = logging.getLogger("asac.roles")


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
    who = "actor (stopped before a learner gave it an index)" if summary.index < 0 else f"actor {summary.index}"
    log.info("%s %s after %d env steps, %d episodes", who, "stopped" if summary.interrupted else "finished",
             summary.env_steps, summary.episodes)  # fmt: skip
    return 130 if summary.interrupted else 0
