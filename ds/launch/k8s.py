"""The addresses a learner or replay derives from its Kubernetes pod name (``main_ds.py --in_k8s``).

k8s/ runs learners and replays as two StatefulSets of the same size, each behind a headless Service
named after it, so pod k of ``<app>-<role>`` is ``<app>-<role>-<k>`` and is reached as
``<app>-<role>-<k>.<app>-<role>`` from its namespace. Learner k trains from replay k::

    paired_hosts("asac-learner-2", "learner")
    # {"learner_host": "asac-learner-2.asac-learner", "replay_host": "asac-replay-2.asac-replay"}
    paired_hosts("asac-replay-2", "replay")
    # {"replay_host": "asac-replay-2.asac-replay"}
    paired_hosts("asac-actor-7d9f8-x2kq4", "actor")   # {}: the evolver places actors

The keys are ``net_config`` fields. A role's own entry is the address it gives the evolver: replay k
announces exactly the string learner k was started with, which is how the evolver pairs the two
(ds/evolver/assign.py), and a learner's stable name outlives its pod IP. Any other pod (an actor,
the evolver, a StatefulSet of another name) derives nothing and keeps its flags and config.
"""

from __future__ import annotations

import re
from typing import NamedTuple

# A DNS label (what Kubernetes allows in a StatefulSet's name) followed by the role and the ordinal.
_POD_NAME = re.compile(r"(?P<app>[a-z0-9](?:[-a-z0-9]*[a-z0-9])?)-(?P<role>learner|replay)-(?P<ordinal>0|[1-9][0-9]*)")


class PodName(NamedTuple):
    """A learner's or replay's StatefulSet pod name, ``<app>-<role>-<ordinal>``."""

    app: str
    role: str
    ordinal: int


def parse_pod_name(hostname: str) -> PodName | None:
    """``"asac-learner-2"`` -> ``PodName("asac", "learner", 2)``; a fully qualified name counts by its
    first label. None for any other name."""
    match = _POD_NAME.fullmatch(hostname.split(".", 1)[0])
    if match is None:
        return None
    return PodName(match["app"], match["role"], int(match["ordinal"]))


def stable_host(app: str, role: str, ordinal: int) -> str:
    """The DNS name of pod ``ordinal`` of StatefulSet ``<app>-<role>`` through its headless Service."""
    return f"{app}-{role}-{ordinal}.{app}-{role}"


def paired_hosts(hostname: str, role: str) -> dict[str, str]:
    """The ``net_config`` hosts that ``role`` (``"learner"``, ``"replay"``, ...) running in the pod
    named ``hostname`` derives from the pod's ordinal; ``{}`` unless the pod is that role's."""
    pod = parse_pod_name(hostname)
    if pod is None or pod.role != role:
        return {}
    replay = stable_host(pod.app, "replay", pod.ordinal)
    if role == "replay":
        return {"replay_host": replay}
    return {"learner_host": stable_host(pod.app, "learner", pod.ordinal), "replay_host": replay}


__all__ = ["PodName", "paired_hosts", "parse_pod_name", "stable_host"]
