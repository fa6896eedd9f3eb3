"""``main_ds.py TASK local``: every role as a subprocess of one launcher on loopback, with free ports,
prefixed logs, and one Ctrl-C for all; and the signal handling every role process shares.

Usage (``main_ds.py`` builds the command and the flags each child gets)::

    code = run_local([python, "main_ds.py", "gym/pendulum"], child_args, actors=2)              # one learner
    code = run_local([python, "main_ds.py", "gym/pendulum"], child_args, actors=6, learners=3,  # a population
                     credentials=creds)   # what the launcher itself needs to ask the evolver (ds/security.py)

One learner: a replay, the learner and the actors, told each other's ports. A population: an evolver,
``learners`` replays and learners, told only the evolver's port (the evolver pairs replays with
learners, ds/population.py), and, once every learner has registered with a replay, the actors, so
that the evolver spreads them over all learners (it gives each actor the least-loaded learner there
is when it asks). Every child gets the same flags, so with TLS they share one certificate, which must
name every role (README Security); none opens a plaintext health port (``net_config.health_port`` is
for Kubernetes probes, and the children's would collide).
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
from types import FrameType

import grpc

from ds.evolver_service import EvolverClient
from ds.replay_feeds import Throttle
from ds.rpc import RetryPolicy
from ds.security import NO_CREDENTIALS, Credentials

log = logging.getLogger("asac.local")
LOCAL_HOST = "127.0.0.1"
NO_HEALTH_PORT = ("--override", "net.health_port=null")


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

    def names(self, role: str) -> list[str]:
        """The children of one role: ``learner`` names ``learner`` and ``learner-0``, ``learner-1``..."""
        return [n for n in self.children if n.split("-")[0] == role]

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
                running = [n for n, p in self.children.items() if p.poll() is None]
                log.warning("still running: %s; sending %s", ", ".join(running), signal.Signals(signum).name)
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


def plan(
    command: list[str],
    child_args: list[str],
    actors: int,
    role_args: dict[str, list[str]] | None = None,
    learners: int | None = None,
) -> list[tuple[str, list[str]]]:
    """The children of a ``local`` run as ``(name, argv)``, in start order (see the module docstring)."""
    extra = role_args or {}

    def child(role: str, *flags: str) -> list[str]:
        return [*command, role, *child_args, *flags, *extra.get(role, [])]

    if learners is None:
        ports = ["--replay_host", LOCAL_HOST, "--replay_port", str(free_port()), "--learner_host", LOCAL_HOST,
                 "--learner_port", str(free_port()), "--override", "net.params_port=0", *NO_HEALTH_PORT]  # fmt: skip
        return [("replay", child("replay", *ports)), ("learner", child("learner", *ports))] + [
            (f"actor-{i}", child("actor", *ports)) for i in range(actors)
        ]
    evolver = ["--evolver_host", LOCAL_HOST, "--evolver_port", str(free_port())]
    children = [("evolver", child("evolver", *evolver, *NO_HEALTH_PORT))]
    for k in range(learners):
        replay = ["--replay_host", LOCAL_HOST, "--replay_port", str(free_port()), *NO_HEALTH_PORT]
        children.append((f"replay-{k}", child("replay", *evolver, *replay)))
    for k in range(learners):
        learner = ["--learner_host", LOCAL_HOST, "--learner_port", str(free_port()), "--override", "net.params_port=0",
                   *NO_HEALTH_PORT]  # fmt: skip
        children.append((f"learner-{k}", child("learner", *evolver, *learner)))
    return children + [(f"actor-{i}", child("actor", *evolver)) for i in range(actors)]


def run_local(
    command: list[str],
    child_args: list[str],
    actors: int,
    role_args: dict[str, list[str]] | None = None,
    grace_s: float = 30.0,
    learners: int | None = None,
    credentials: Credentials = NO_CREDENTIALS,
) -> int:
    """Run :func:`plan`'s children (``command + [role] + child_args`` plus their ports and
    ``role_args[role]``). Returns 0 when every learner has exited 0 (finished its budget, or retired
    by the evolver; then the actors and then the replays and the evolver are stopped; replays save),
    130 on SIGINT/SIGTERM (every child gets SIGINT, then SIGTERM and SIGKILL after ``grace_s``), 1
    when a child fails or a replay or the evolver exits (the others are stopped). ``credentials``
    are the launcher's own, for asking the evolver whether the learners have registered."""
    children = LocalProcesses()
    stop = stop_on_signals()
    try:
        planned = plan(command, child_args, actors, role_args, learners)
        for name, argv in planned:
            if not name.startswith("actor"):
                children.start(name, argv)
        code = None
        if learners is not None:
            evolver = planned[0][1]
            address = f"{LOCAL_HOST}:{evolver[evolver.index('--evolver_port') + 1]}"
            code = _wait_for_learners(children, stop, address, credentials)
        if code is None:
            for name, argv in planned:
                if name.startswith("actor"):
                    children.start(name, argv)
            code = _supervise(children, stop)
    except KeyboardInterrupt:
        code = 130
    if code == 0:  # the budget is spent: actors first (nothing left to learn from), then replays and evolver
        actor_names = children.names("actor")
        children.signal(actor_names, signal.SIGINT)
        children.wait_all(grace_s, actor_names)
        rest = children.names("replay") + children.names("evolver")
        children.signal(rest, signal.SIGINT)
        children.wait_all(grace_s, rest)  # a second SIGINT (stop_all's) would cut their shutdown short
    try:
        children.stop_all(grace_s)
    except KeyboardInterrupt:  # a second Ctrl-C: no more waiting
        os.killpg(children.pgid, signal.SIGKILL)
        children.wait_all(5.0)
        code = 130
    return code


def _supervise(children: LocalProcesses, stop: threading.Event) -> int:
    learners = children.names("learner")
    while not stop.wait(0.2):
        if _failed(children):
            return 1
        if all(children.children[n].poll() == 0 for n in learners):
            log.info("%s finished", "learner" if len(learners) == 1 else f"all {len(learners)} learners")
            return 0
    return 130


def _failed(children: LocalProcesses) -> bool:
    """Whether a child failed, or a replay or the evolver exited (logged); learners and actors exit 0 when done."""
    for name, proc in children.children.items():
        code = proc.poll()
        if code is not None and (code != 0 or name.split("-")[0] in ("replay", "evolver")):
            log.error("%s exited with code %d: stopping the others", name, code)
            return True
    return False


def _wait_for_learners(
    children: LocalProcesses, stop: threading.Event, evolver: str, credentials: Credentials
) -> int | None:
    """Wait until every learner child is registered with the evolver at ``evolver`` and has a replay:
    None; or the exit code when a child failed (1) or a signal came (130) first."""
    count, waiting = len(children.names("learner")), Throttle(30.0)
    with EvolverClient(evolver, rpc_timeout_s=2.0, retry=RetryPolicy(attempts=1), credentials=credentials) as client:
        while not stop.wait(1.0):
            if _failed(children):
                return 1
            try:
                ready = sum(1 for x in client.info().learners if x.live and x.replay_address)
            except grpc.RpcError:
                ready = 0
            if ready >= count:
                return None
            if waiting():
                log.info("actors start once %d learners have registered with a replay each (%d so far)", count, ready)
    return 130


__all__ = ["LOCAL_HOST", "LocalProcesses", "free_port", "plan", "run_local", "stop_on_signals"]
