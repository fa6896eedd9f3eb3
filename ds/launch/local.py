"""``main_ds.py TASK local``: every role as a subprocess of one launcher on loopback, with free ports,
prefixed logs, an orderly stop and a summary; and the signal handling every role process shares.

Usage (``main_ds.py`` builds the command and the flags each child gets)::

    code = run_local([python, "main_ds.py", "gym/pendulum"], child_args, actors=2, run=playable)   # one learner
    code = run_local([python, "main_ds.py", "gym/pendulum"], child_args, actors=6, learners=3,     # a population
                     credentials=creds, run=playable)  # creds: the launcher's own (ds/net/security.py)

One learner: a replay, the learner and the actors, told each other's ports. A population: an evolver,
``learners`` replays and learners, told only the evolver's port (the evolver pairs replays with
learners, ds/member/population.py), and, once every learner has registered with a replay, the actors, so
that the evolver spreads them over all learners (it gives each actor the least-loaded learner there
is when it asks). Every child gets the same flags, so with TLS they share one certificate, which must
name every role (docs/security.md section 3); none opens a plaintext health port (``net_config.health_port`` is
for Kubernetes probes, and the children's would collide).

Names agree: actor k is started with ``--index k`` and asks its learner for index k (its seeds,
noise and ``log/actor_k``), so ``[actor-k]`` is the learner's index k. The evolver hands learner ids
out in the order learners register, so the launcher does not guess: it holds back a population
learner's lines until the evolver lists its pid, then prefixes them ``[learner-<id>]``, the folder
``learner_<id>/`` it writes; a replay becomes ``[replay-<id>]`` once it serves learner ``<id>``.

Stopping is ordered (:data:`STOP_ORDER`), at a normal finish (every learner exited 0: budget spent,
or retired) and on the launcher's first SIGINT/SIGTERM alike: the learners are told first (SIGINT:
they checkpoint), then the actors (they flush what they hold into the replays, still running), then
the replays (``save_replay``: they save) and the evolver last; each stage is waited for, and only a
child still running after ``grace_s`` gets SIGTERM, then SIGKILL. A second Ctrl-C forces: SIGKILL to
every child now. Last, the launcher prints a summary (ds/launch/local_summary.py): how the run ended, the
final evaluation return, the run folder and the ``main.py --run`` command that plays it.

Exit codes: 0 a normal finish, 130 stopped by SIGINT, 143 stopped by SIGTERM, 1 a child failed (or a
replay or the evolver exited on its own).
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import grpc

from algorithm.run.logging import Throttle
from algorithm.run.signals import LAUNCHER_PID_ENV, StopRequest, stop_on_signals
from ds.evolver.client import EvolverClient
from ds.evolver.state import LearnerInfo
from ds.launch.local_summary import PlayableRun, summary
from ds.net.rpc import LOCAL_HOST, RetryPolicy
from ds.net.security import NO_CREDENTIALS, Credentials

log = logging.getLogger("asac.local")
NO_HEALTH_PORT = ("--override", "net.health_port=null")
STOP_ORDER = ("learner", "actor", "replay", "evolver")
"""Who is told to stop first: a replay outlives the learner and actors it serves, the evolver all."""
HOLD_LINES_S = 60.0
"""How long after the evolver first answers a population learner's or replay's lines wait for its id
(then they show unnumbered): long enough for a slow start on a loaded machine, short enough that a
learner stuck before registering still shows why."""
_PID = re.compile(r"\(pid (\d+)\)")  # how a learner names itself to the evolver (ds/launch/role_context.py)


def free_port() -> int:
    """A TCP port that was free on loopback a moment ago."""
    with socket.socket() as s:
        s.bind((LOCAL_HOST, 0))
        return int(s.getsockname()[1])


class LocalProcesses:
    """Children of one ``local`` run in one process group (apart from the launcher's: a terminal's
    Ctrl-C reaches the launcher alone, which then stops them in order), their output streamed with
    a ``[label]`` prefix. A child started without a label has its lines held until :meth:`relabel`
    names it (or :meth:`release` shows them unnumbered)."""

    def __init__(self, stream: Callable[[str], None] = lambda line: print(line, end="", flush=True)) -> None:
        self.children: dict[str, subprocess.Popen[str]] = {}
        self.labels: dict[str, str] = {}
        self.pgid = 0
        self._stream = stream
        self._held: dict[str, list[str]] = {}
        self._lock = threading.Lock()
        self._readers: list[threading.Thread] = []
        self._stream_failed = False

    def start(self, name: str, command: list[str], labelled: bool = True) -> None:
        """Start ``command`` as ``name``; ``labelled``: its lines show as ``[name]`` at once."""
        proc = subprocess.Popen(
            command,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            text=True,
            process_group=self.pgid,  # the first child leads a new group; the others join it
            env={**os.environ, LAUNCHER_PID_ENV: str(os.getpid())},  # it stops if this launcher dies
        )
        if not self.pgid:
            self.pgid = proc.pid
        self.children[name] = proc
        if labelled:
            self.labels[name] = name
            log.info("started %s (pid %d)", name, proc.pid)
        else:
            self._held[name] = []
            log.info("started %s (pid %d); its lines show once the evolver gives it an id", _role(name), proc.pid)
        reader = threading.Thread(target=self._pump, args=(name, proc), daemon=True)
        reader.start()
        self._readers.append(reader)

    def _pump(self, name: str, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            with self._lock:
                if name in self._held:
                    self._held[name].append(line)
                    continue
                label = self.labels[name]
            self._show(f"[{label}] {line}")

    def _show(self, text: str) -> None:
        """Stream ``text``; once the stream fails (the terminal hung up: EIO; a closed pipe) stop
        showing lines but go on reading them: a reader that died would leave its child blocked on
        a full pipe, unable to log its stop or exit."""
        if self._stream_failed:
            return
        try:
            self._stream(text)
        except OSError:
            self._stream_failed = True

    def relabel(self, name: str, label: str) -> None:
        """Show ``name``'s lines as ``[label]`` from now on, the ones held back first."""
        with self._lock:
            if self.labels.get(name) == label:
                return
            self.labels[name] = label
            for line in self._held.pop(name, []):
                self._show(f"[{label}] {line}")
        log.info("%s (pid %d) is %s", _role(name), self.children[name].pid, label)

    def release(self) -> None:
        """Show the held lines of children still without an id, as ``[<role> pid <pid>]``."""
        for name in list(self._held):
            if name in self._held:
                self.relabel(name, f"{_role(name)} pid {self.children[name].pid}")

    def unlabelled(self) -> list[str]:
        with self._lock:
            return list(self._held)

    def names(self, role: str) -> list[str]:
        """The children of one role: ``learner`` names ``learner`` and ``learner-0``, ``learner-1``..."""
        return [n for n in self.children if _role(n) == role]

    def running(self, names: list[str]) -> list[str]:
        return [n for n in names if self.children[n].poll() is None]

    def signal(self, names: list[str], signum: int) -> None:
        for name in self.running(names):
            with contextlib.suppress(ProcessLookupError):
                self.children[name].send_signal(signum)

    def stop_in_order(self, grace_s: float) -> None:
        """SIGINT to each stage of :data:`STOP_ORDER` in turn, waiting up to ``grace_s`` for the stage
        to exit before the next one is told; a child still running then gets SIGTERM, then SIGKILL."""
        started = time.monotonic()
        for role in STOP_ORDER:
            names = self.running(self.names(role))
            if not names:
                continue
            log.info("stopping %s", ", ".join(self.labels.get(n, n) for n in names))
            self.signal(names, signal.SIGINT)
            if self.wait_all(grace_s, names):
                continue
            for signum in (signal.SIGTERM, signal.SIGKILL):
                late = self.running(names)
                if not late:
                    break
                log.warning("%s still running after %.0f s: sending %s", ", ".join(late), grace_s,
                            signal.Signals(signum).name)  # fmt: skip
                self.signal(late, signum)
                self.wait_all(5.0, late)
        log.info("every role has stopped (%.1f s)", time.monotonic() - started)

    def kill_all(self) -> None:
        """SIGKILL to every child still running (a forced stop)."""
        running = self.running(list(self.children))
        if running:
            log.warning("forced stop: sending SIGKILL to %s", ", ".join(running))
            self.signal(running, signal.SIGKILL)
        self.wait_all(5.0)

    def wait_all(self, timeout_s: float, names: list[str] | None = None) -> bool:
        deadline = time.monotonic() + timeout_s
        procs = [self.children[n] for n in names or list(self.children)]
        while any(p.poll() is None for p in procs):
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.1)
        return True

    def drain(self) -> None:
        """Wait (briefly) for the last lines of every child, showing any still held."""
        for reader in self._readers:
            reader.join(2.0)
        self.release()


def _role(name: str) -> str:
    return name.split("-")[0]


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

    # An address from the task file or an --override is for roles started one by one: each child is told
    # where its peers are, and a peer it asks the evolver for is unset (None) rather than the file's.
    if learners is None:
        ports = ["--replay_host", LOCAL_HOST, "--replay_port", str(free_port()), "--learner_host", LOCAL_HOST,
                 "--learner_port", str(free_port()), "--override", "net.params_port=0", *NO_HEALTH_PORT,
                 *unset("evolver")]  # fmt: skip
        return [("replay", child("replay", *ports)), ("learner", child("learner", *ports))] + [
            (f"actor-{i}", child("actor", *ports, "--index", str(i))) for i in range(actors)
        ]
    evolver = ["--evolver_host", LOCAL_HOST, "--evolver_port", str(free_port())]
    children = [("evolver", child("evolver", *evolver, *NO_HEALTH_PORT))]
    for k in range(learners):
        replay = ["--replay_host", LOCAL_HOST, "--replay_port", str(free_port()), *NO_HEALTH_PORT]
        children.append((f"replay-{k}", child("replay", *evolver, *replay)))
    for k in range(learners):
        learner = ["--learner_host", LOCAL_HOST, "--learner_port", str(free_port()), "--override", "net.params_port=0",
                   *NO_HEALTH_PORT]  # fmt: skip
        children.append((f"learner-{k}", child("learner", *evolver, *learner, *unset("replay"))))
    actor = [*evolver, *unset("replay", "learner")]
    return children + [(f"actor-{i}", child("actor", *actor, "--index", str(i))) for i in range(actors)]


def learner_threads(actors: int, learners: int | None, cores: int | None = None) -> int:
    """Torch threads for each learner of a ``local`` run whose config leaves them to torch (0): the
    cores less one per actor process and one for the replay, shared by the learners, at least 1.
    Torch alone would give every learner every core, and the learner's threads would then wait on
    the actors' and the replay's; small batches gain little from a second thread anyway (on a 2-core
    machine, alone, HalfCheetah's default update of 256 took 9.1 ms with 1 thread, 14.6 ms with 2;
    one of 1,024 28.0 and 24.7: bench/results/throughput_variant/)."""
    cores = cores or os.cpu_count() or 1
    return max(1, (cores - actors - 1) // (learners or 1))


def unset(*peers: str) -> list[str]:
    """Overrides that clear the addresses of ``peers``, so that a child asks for them (or has none)."""
    return [arg for peer in peers for arg in ("--override", f"net.{peer}_host=null")]


@dataclass
class Outcome:
    """How a ``local`` run ended: its exit code and the words the summary starts with."""

    code: int
    words: str


def run_local(
    command: list[str],
    child_args: list[str],
    actors: int,
    role_args: dict[str, list[str]] | None = None,
    grace_s: float = 30.0,
    learners: int | None = None,
    credentials: Credentials = NO_CREDENTIALS,
    run: PlayableRun | None = None,
) -> int:
    """Run :func:`plan`'s children (``command + [role] + child_args`` plus their ports and
    ``role_args[role]``) until every learner has exited 0, a child fails, or a signal; stop them in
    order; print ``run``'s summary. Returns the exit code (the module docstring). ``credentials``
    are the launcher's own, for asking the evolver who registered."""
    children = LocalProcesses()
    signals = stop_on_signals("stopping every role in order")
    population = learners is not None
    learner_ids: dict[str, int] = {}
    try:
        try:
            outcome = _run(children, signals, plan(command, child_args, actors, role_args, learners), credentials,
                           learner_ids, population)  # fmt: skip
            children.stop_in_order(grace_s)
        except KeyboardInterrupt:  # a second signal: no more waiting
            children.kill_all()
            outcome = Outcome(signals.exit_code, f"stopped by force ({_signal_name(signals.signum)} twice)")
    except KeyboardInterrupt:  # a third, while killing: the children are SIGKILLed already or soon gone
        children.kill_all()
        outcome = Outcome(signals.exit_code, "stopped by force")
    children.drain()
    if run is not None:
        ids = sorted(learner_ids.values()) if population else None
        print("\n".join(summary(run, outcome.words, ids)), flush=True)
    return outcome.code


def _signal_name(signum: int | None) -> str:
    return signal.Signals(signum or signal.SIGINT).name


def _run(
    children: LocalProcesses,
    signals: StopRequest,
    planned: list[tuple[str, list[str]]],
    credentials: Credentials,
    learner_ids: dict[str, int],
    population: bool,
) -> Outcome:
    """Start the children and supervise them: the outcome that ends the run (nothing stopped yet)."""
    for name, argv in planned:
        if _role(name) != "actor":
            children.start(name, argv, labelled=not population or name == "evolver")
    if population:
        evolver = planned[0][1]
        address = f"{LOCAL_HOST}:{evolver[evolver.index('--evolver_port') + 1]}"
        ports = {n: argv[argv.index("--replay_port") + 1] for n, argv in planned if _role(n) == "replay"}
        failed = _wait_for_learners(children, signals, address, credentials, learner_ids, ports)
        if failed is not None:
            return failed
    for name, argv in planned:
        if _role(name) == "actor" and not signals.is_set():
            children.start(name, argv)
    return _supervise(children, signals)


def _supervise(children: LocalProcesses, signals: StopRequest) -> Outcome:
    learners = children.names("learner")
    while not signals.wait(0.2):
        if (failed := _failed(children)) is not None:
            return failed
        if all(children.children[n].poll() == 0 for n in learners):
            log.info("%s finished", "learner" if len(learners) == 1 else f"all {len(learners)} learners")
            return Outcome(0, "finished")
    return _interrupted(signals)


def _interrupted(signals: StopRequest) -> Outcome:
    return Outcome(signals.exit_code, f"interrupted ({_signal_name(signals.signum)})")


def _failed(children: LocalProcesses) -> Outcome | None:
    """Exit code 1 when a child failed, or a replay or the evolver exited (logged); learners and
    actors exit 0 when done."""
    for name, proc in children.children.items():
        code = proc.poll()
        if code is not None and (code != 0 or _role(name) in ("replay", "evolver")):
            label = children.labels.get(name, f"{_role(name)} pid {proc.pid}")
            log.error("%s exited with code %d: stopping the others", label, code)
            return Outcome(1, f"failed ({label} exited with code {code})")
    return None


def _wait_for_learners(
    children: LocalProcesses,
    stop: threading.Event,
    evolver: str,
    credentials: Credentials,
    learner_ids: dict[str, int],
    replay_ports: dict[str, str],
) -> Outcome | None:
    """Wait until every learner child is registered with the evolver at ``evolver`` and has a replay,
    labelling each learner (and replay) with the id the evolver gave it (``learner_ids``: child name
    -> id): None; or the outcome when a child failed or a signal came first."""
    count, waiting, answered_at = len(children.names("learner")), Throttle(), None
    with EvolverClient(evolver, rpc_timeout_s=2.0, retry=RetryPolicy(attempts=1), credentials=credentials) as client:
        while not stop.wait(1.0):
            if (failed := _failed(children)) is not None:
                return failed
            try:
                live = [x for x in client.info().learners if x.live]
                answered_at = answered_at or time.monotonic()
            except grpc.RpcError:
                live = []
            _label_members(children, live, learner_ids, replay_ports)
            if sum(1 for x in live if x.replay_address) >= count and not children.unlabelled():
                return None
            if answered_at is not None and time.monotonic() - answered_at > HOLD_LINES_S:
                children.release()
            if waiting():
                log.info("actors start once %d learners have registered with a replay each (%d so far)", count,
                         sum(1 for x in live if x.replay_address))  # fmt: skip
    return None


def _label_members(
    children: LocalProcesses, live: list[LearnerInfo], learner_ids: dict[str, int], replay_ports: dict[str, str]
) -> None:
    """Name each learner child after the id the evolver lists for its pid, each replay child after the
    learner it serves (the evolver lists that learner's replay at ``127.0.0.1:<port>``)."""
    pids = {children.children[n].pid: n for n in children.names("learner")}
    replays = {f"{LOCAL_HOST}:{port}": name for name, port in replay_ports.items()}
    for x in live:
        if (m := _PID.search(x.name)) is not None and (name := pids.get(int(m.group(1)))) is not None:
            learner_ids[name] = x.learner_id
            children.relabel(name, f"learner-{x.learner_id}")
        if (name := replays.get(x.replay_address)) is not None:
            children.relabel(name, f"replay-{x.learner_id}")


__all__ = ["LOCAL_HOST", "STOP_ORDER", "LocalProcesses", "free_port", "plan", "run_local"]
