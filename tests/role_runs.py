"""A distributed run as an operator starts it by hand, for the fault tests: every role a real
``main_ds.py`` process on loopback, started one by one with fixed ports, so that a role killed or
stopped can be started again with the same command and its peers find it where it was.

Usage::

    run = RoleRun(tmp_path, "name", flags("sac.seed=0", "base.max_step=5000"))
    run.start("replay", "replay"); run.start("learner", "learner")
    run.start("actor-0", "actor"); run.start("actor-1", "actor")
    run.wait_for_line("learner", r"checkpoint \\S+/(\\d+)\\.pt", 120)
    os.kill(run.procs["learner"].pid, signal.SIGKILL)
    ...
    run.stop_all()          # SIGINT in the order ``main_ds.py local`` uses, then SIGKILL

The pattern is tests/test_population.py's (which runs a population under an evolver); here there is
no evolver, and the replay and learner ports are fixed for the whole run.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from ds.launch.local import free_port
from ds.net.rpc import LOCAL_HOST, RetryPolicy
from ds.replay.client import ReplayClient

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1", "MUJOCO_GL": "egl"}
# A Pendulum run small enough for a test: tiny nets and batches, 1 update per env step from 200 steps.
TINY_OVERRIDES = [
    "nn.hidden_units=[16,16]",
    "replay.batch_size=32",
    "replay.samples_per_insert=null",
    "replay.min_size_to_sample=200",
    "eval.eval_per_step=300",
    "eval.eval_episodes=2",
    "eval.eval_envs=2",
    "sac.write_summary_per_step=50",
]
TINY = [arg for override in TINY_OVERRIDES for arg in ("--override", override)] + ["--no_progress"]


def flags(*overrides: str) -> list[str]:
    return [arg for override in overrides for arg in ("--override", override)] + ["--no_progress"]


def main_ds_command(*args: str) -> list[str]:
    """``python main_ds.py ARGS`` with this interpreter."""
    return [sys.executable, str(ROOT / "main_ds.py"), *args]


_SIGHUP_DEFAULT = (
    "import os, signal, sys; signal.signal(signal.SIGHUP, signal.SIG_DFL); "
    "os.execv(sys.executable, [sys.executable, *sys.argv[1:]])"
)


def as_a_shell_starts_it(command: list[str]) -> list[str]:
    """``command`` (``python ARGS`` with this interpreter) started with SIGHUP at its default, as a
    shell starts a job, even when the tests run under ``nohup``: an ignored SIGHUP is inherited, and
    ``main.py`` and ``local`` rightly keep ignoring it (a terminal test then waits for a stop that
    never comes)."""
    assert command[0] == sys.executable, command
    return [sys.executable, "-c", _SIGHUP_DEFAULT, *command[1:]]


def child_pids(output: str) -> dict[str, int]:
    """The pid of every role a ``local`` launcher logged as started, by its label."""
    return {name: int(pid) for name, pid in re.findall(r"started (\S+) \(pid (\d+)\)", output)}


def no_process_mentions(name: str) -> bool:
    """No process on the machine has ``-n NAME `` in its command line (a run's roles all do)."""
    found = subprocess.run(["pgrep", "-f", f"-n {name} "], capture_output=True, text=True)
    return found.stdout.strip() == ""


def event_files(run: Path, role: str) -> list[Path]:
    """The TensorBoard event files of one role of a run (``log/<role>``)."""
    folder = run / "log" / role
    return sorted(folder.glob("events.out.tfevents.*")) if folder.is_dir() else []


def running(pid: int) -> bool:
    """Whether ``pid`` exists and is not a zombie (a stopped process, state T, is running)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


def torch_is_loaded(pid: int) -> bool:
    """Whether process ``pid`` has torch's library mapped (Linux: /proc/PID/maps)."""
    return "libtorch" in Path(f"/proc/{pid}/maps").read_text()


def rss_mb(pid: int) -> float | None:
    """Resident set size of ``pid`` in MiB (``VmRSS`` of /proc/<pid>/status); None once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def scalars(folder: Path, tag: str) -> list[tuple[float, int, float]]:
    """``(wall_time, step, value)`` of every ``tag`` scalar in the TensorBoard event files under
    ``folder`` (all of them: a restarted role adds a file), in wall-time order."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = []
    for events in sorted(folder.glob("events.out.tfevents.*")):
        acc = EventAccumulator(str(events), size_guidance={"scalars": 0})
        acc.Reload()
        if tag in acc.Tags()["scalars"]:
            out += [(e.wall_time, e.step, e.value) for e in acc.Scalars(tag)]
    return sorted(out)


class RoleRun:
    """The role processes of one run, each in a process group of its own, its output in ``<label>.log``.

    Every run is remembered until :meth:`kill_all_left` (tests/conftest.py calls it after each test),
    so a test that fails before its ``stop_all`` leaves no role running (a run with ``max_step=-1``
    would go on for the rest of the suite, taking its cores)."""

    _all: list[RoleRun] = []

    def __init__(self, cwd: Path, name: str | None, common: list[str], task: str = "gym/pendulum") -> None:
        """``name`` None: the roles are started without ``-n`` (their run is then ``models/TASK/ds``)."""
        self.cwd, self.name, self.common, self.task = cwd, name, common, task
        self.replay_port, self.learner_port = free_port(), free_port()
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.ended: set[str] = set()  # roles the test ended with a signal: their exit is no failure
        self.run = cwd / "models" / task / (name or "ds")
        RoleRun._all.append(self)

    @classmethod
    def kill_all_left(cls) -> None:
        """SIGKILL the process group of every role still running, of every run so far."""
        for run in cls._all:
            for proc in run.procs.values():
                if proc.poll() is None:
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait(timeout=10)
        cls._all.clear()

    def start(self, label: str, role: str, *extra: str) -> subprocess.Popen[bytes]:
        """``main_ds.py TASK ROLE -n NAME`` with the run's ports, the common flags and ``extra``, as
        ``label`` (its log is appended to: a restarted role's lines follow the killed one's)."""
        ports = ["--replay_host", LOCAL_HOST, "--replay_port", str(self.replay_port), "--learner_host", LOCAL_HOST,
                 "--learner_port", str(self.learner_port), "--override", "net.params_port=0"]  # fmt: skip
        named = ["-n", self.name] if self.name else []
        command = [sys.executable, str(ROOT / "main_ds.py"), self.task, role, *named, *ports]
        with self.log(label).open("ab") as out:
            proc = subprocess.Popen([*command, *self.common, *extra], cwd=self.cwd, env=ENV, stdout=out,
                                    stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, process_group=0)  # fmt: skip
        self.procs[label] = proc
        self.ended.discard(label)
        return proc

    def log(self, label: str) -> Path:
        return self.cwd / f"{label}.log"

    def text(self, label: str) -> str:
        path = self.log(label)
        return path.read_text() if path.exists() else ""

    def logs(self) -> str:
        """The tail of every role's log, for assertion messages."""
        return "\n".join(f"--- {label}\n{self.text(label)[-2500:]}" for label in self.procs)

    def wait_for(self, what: str, ready: Callable[[], bool], timeout_s: float) -> None:
        """Poll ``ready`` until it holds; fail naming ``what`` when a role exits (one not ended by
        :meth:`signal`) or time is up."""
        deadline = time.monotonic() + timeout_s
        while not ready():
            exited = {x: p.returncode for x, p in self.procs.items() if p.poll() is not None and x not in self.ended}
            assert not exited, f"{exited} exited while waiting for {what}\n{self.logs()}"
            assert time.monotonic() < deadline, f"no {what} within {timeout_s:.0f} s\n{self.logs()}"
            time.sleep(0.5)

    def wait_for_line(self, label: str, pattern: str, timeout_s: float, start: int = 0) -> re.Match[str]:
        """The first match of ``pattern`` in ``label``'s log at or after character ``start``, waiting for it."""
        regex = re.compile(pattern)
        found: list[re.Match[str]] = []

        def ready() -> bool:
            match = regex.search(self.text(label), start)
            found[:] = [match] if match else []
            return bool(found)

        self.wait_for(f"{pattern!r} in {label}'s log", ready, timeout_s)
        return found[0]

    def replay_client(self, sensors: tuple, action_size: int) -> ReplayClient:
        """A client of the run's replay that tries once per call (the test asks; it does not wait)."""
        return ReplayClient(f"{LOCAL_HOST}:{self.replay_port}", sensors, action_size, rpc_timeout_s=5.0,
                            retry=RetryPolicy(attempts=1))  # fmt: skip

    def signal(self, label: str, signum: int) -> None:
        """Send ``signum`` to ``label``'s process group; after SIGKILL, SIGINT or SIGTERM its exit is expected."""
        if signum in (signal.SIGKILL, signal.SIGINT, signal.SIGTERM):
            self.ended.add(label)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.procs[label].pid, signum)

    def stop_all(self, grace_s: float = 30.0) -> dict[str, int]:
        """Stop every role as ``main_ds.py local`` does: SIGCONT (a stopped one must see the signal),
        then SIGINT to the learner (it saves first), then the actors, then the replay, each stage
        waited for up to ``grace_s``; then SIGKILL. Returns each role's exit code."""
        for label in self.procs:
            self.signal(label, signal.SIGCONT)
        stages = [[x for x in self.procs if x.startswith(r)] for r in ("learner", "actor")]
        stages.append([x for x in self.procs if not x.startswith(("actor", "learner"))])
        for labels, signum in [(s, signal.SIGINT) for s in stages] + [(list(self.procs), signal.SIGKILL)]:
            for label in labels:
                if self.procs[label].poll() is None:
                    self.signal(label, signum)
            deadline = time.monotonic() + grace_s
            while any(self.procs[x].poll() is None for x in labels) and time.monotonic() < deadline:
                time.sleep(0.2)
        return {label: proc.wait(timeout=10) for label, proc in self.procs.items()}
