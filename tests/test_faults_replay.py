"""kill -9 in a real distributed run: replay, learner and actors are ``main_ds.py`` processes on
loopback, and the test kills them with SIGKILL while they work.

What the replay holds is read two ways: windows sampled through a replay client, and the table
saved through the Save rpc and read back as the plain arrays of its file (algorithm/replay/
persistence.py). "No partial chunk is visible" is checked on the data: every stored chunk has
``chunk_length`` steps or ends its episode, every row of it holds a real Pendulum observation
(cos^2 + sin^2 = 1; a row never written is zeros), and within it each step's ``prev_actions`` is the
previous step's action; every sampled window keeps to one chunk the same way.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from algorithm.spaces import EnvSpec
from ds.launch.local import free_port
from ds.replay.client import ReplayClient, ReplayRpcError
from envs.make import vector_env_factory

pytestmark = [pytest.mark.slow, pytest.mark.grpc, pytest.mark.fault]

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1", "MUJOCO_GL": "egl"}
CHUNK = 16  # Pendulum episodes are 200 steps: chunks of 16, and one of 8 that ends each episode
OVERRIDES = [
    "nn.hidden_units=[16,16]",
    "replay.batch_size=32",
    "replay.samples_per_insert=null",
    "replay.min_size_to_sample=200",
    "eval.eval_per_step=0",
    "sac.write_summary_per_step=50",
    f"actor.chunk_length={CHUNK}",
    "replay.capacity=20000",
    "base.max_step=-1",
]


class Run:
    """Roles of one run as separate ``main_ds.py`` processes, each logging to ``<tmp>/<name>.log``."""

    def __init__(self, tmp_path: Path, name: str, overrides: list[str]) -> None:
        self.tmp_path = tmp_path
        self.name = name
        self.replay_port, self.learner_port = free_port(), free_port()
        self.overrides = [*OVERRIDES, *overrides]
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.killed: set[int] = set()  # pids the test sent SIGKILL
        self.run_dir = tmp_path / "models/gym/pendulum" / name
        self.snapshots = self.run_dir / "replay"  # the replay's snapshot folder: its Save rpc names files in it

    def start(self, name: str) -> None:
        role = name.split("-")[0]
        args = [sys.executable, str(ROOT / "main_ds.py"), "gym/pendulum", role, "-n", self.name, "--no_progress",
                "--replay_host", "127.0.0.1", "--replay_port", str(self.replay_port), "--learner_host", "127.0.0.1",
                "--learner_port", str(self.learner_port), "--override", "net.params_port=0"]  # fmt: skip
        for override in self.overrides:
            args += ["--override", override]
        with self.log(name).open("ab") as out:
            self.procs[name] = subprocess.Popen(args, cwd=self.tmp_path, env=ENV, stdout=out, stderr=subprocess.STDOUT)

    def log(self, name: str) -> Path:
        return self.tmp_path / f"{name}.log"

    def signal(self, names: list[str], signum: int) -> None:
        for name in names:
            self.procs[name].send_signal(signum)
        if signum == signal.SIGKILL:
            for name in names:
                self.killed.add(self.procs[name].pid)
                assert self.procs[name].wait(timeout=30) == -signal.SIGKILL

    def check_alive(self) -> None:
        for name, proc in self.procs.items():
            if proc.poll() is None or proc.pid in self.killed:
                continue
            raise AssertionError(f"{name} exited with {proc.returncode}:\n{self.log(name).read_text()[-3000:]}")

    def stop(self) -> None:
        """SIGKILL to every process still running: what is left to check is checked, and an
        orderly shutdown (tests/test_main_ds.py) would only cost time here."""
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.kill()
        for proc in self.procs.values():
            proc.wait(timeout=30)

    def tails(self) -> str:
        return "\n".join(f"--- {n}\n{self.log(n).read_text()[-1500:]}" for n in self.procs)


@contextmanager
def running(tmp_path: Path, name: str, roles: list[str], overrides: list[str]) -> Iterator[Run]:
    run = Run(tmp_path, name, overrides)
    try:
        for role in roles:
            run.start(role)
        yield run
    finally:
        run.stop()


def pendulum() -> EnvSpec:
    env = vector_env_factory("Pendulum-v1")(1, 0)
    try:
        return env.spec
    finally:
        env.close()


def replay_client(run: Run) -> ReplayClient:
    spec = pendulum()
    return ReplayClient(f"127.0.0.1:{run.replay_port}", spec.sensors, spec.action.size, rpc_timeout_s=10.0)


def until(run: Run, what: str, condition: Callable[[], bool], timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        run.check_alive()
        assert time.monotonic() < deadline, f"timed out waiting until {what}\n{run.tails()}"
        time.sleep(0.25)


def info(client: ReplayClient) -> dict[str, Any]:
    """The replay's Info, or {} while it is unreachable."""
    try:
        return client.info()
    except ReplayRpcError:
        return {}


def updates(stats: dict[str, Any]) -> int:
    """Learner updates whose priorities reached the replay (only the learner sends them)."""
    return (stats.get("priority_updates", 0) + stats.get("priority_updates_ignored", 0)) // 32


def stopped(pid: int) -> bool:
    """Every thread of ``pid`` is in the stopped state (``T`` in /proc's stat, after the command's ``)``)."""
    states = []
    for stat in Path(f"/proc/{pid}/task").glob("*/stat"):
        with contextlib.suppress(FileNotFoundError):  # a thread that ended meanwhile
            states.append(stat.read_text().rpartition(") ")[2][:1])
    return bool(states) and all(state == "T" for state in states)


def read_table(path: Path) -> dict[str, Any]:
    with np.load(path, allow_pickle=False) as f:
        return {name: f[name] for name in f.files}


def meta_of(path: Path) -> dict[str, Any]:
    """A replay file's JSON entry alone (np.load reads entries lazily)."""
    with np.load(path, allow_pickle=False) as f:
        return dict(json.loads(str(f["meta"])))


def newest_chunks(meta: dict[str, Any]) -> dict[int, int]:
    """From a replay file's dedup ledger: each producer (actor) that has stored a chunk, and the
    highest sequence number it is known to have stored."""
    newest = {producer: max([floor - 1] + [seq for seq, _ in stored]) for producer, floor, stored in meta["ledger"]}
    return {producer: seq for producer, seq in newest.items() if seq >= 0}


def stored_chunks(table: dict[str, Any]) -> list[np.ndarray]:
    """The rows of each stored chunk, first step to bootstrap row, in key order."""
    row_key, end_key, start_key = table["row_key"], table["end_key"], table["start_key"]
    capacity = row_key.shape[0]
    chunks = []
    for end in np.unique(end_key[row_key >= 0]):
        start = int(start_key[end % capacity])
        keys = np.arange(start, end + 1)
        rows = keys % capacity
        assert (row_key[rows] == keys).all(), f"chunk {start}..{end} is not stored whole"
        chunks.append(rows)
    return chunks


def assert_whole_chunks(table: dict[str, Any]) -> int:
    """Every stored chunk is whole (see the module docstring); returns how many there are."""
    obs, actions, prev = table["obs_0"], table["actions"], table["prev_actions"]
    ended = table["terminated"] | table["truncated"]
    chunks = stored_chunks(table)
    for rows in chunks:
        steps = rows[:-1]
        t = len(steps)
        assert t == CHUNK or (t < CHUNK and ended[steps[-1]]), f"a chunk of {t} steps that does not end an episode"
        assert not ended[steps[:-1]].any()
        np.testing.assert_allclose(obs[rows, 0] ** 2 + obs[rows, 1] ** 2, 1.0, atol=1e-5)  # every row written
        np.testing.assert_array_equal(prev[steps[1:]], actions[steps[:-1]])
    return len(chunks)


def assert_windows_keep_to_one_chunk(client: ReplayClient, batches: int) -> None:
    for _ in range(batches):
        batch = client.sample(32, timeout=60.0)
        mask = batch.mask
        assert mask[:, 0].all()
        assert (mask[:, 1:] <= mask[:, :-1]).all()  # valid steps are a prefix: the window's own chunk
        both = mask[:, 1:]
        np.testing.assert_array_equal(batch.prev_actions[:, 1:][both], batch.actions[:, :-1][both])
        ended = batch.terminated | batch.truncated
        assert not (ended[:, :-1] & mask[:, 1:]).any()  # an episode ends only at a window's last valid step
        assert not batch.actions[~mask].any() and not batch.rewards[~mask].any()
        cos, sin = batch.obs[0][..., 0], batch.obs[0][..., 1]
        np.testing.assert_allclose(cos**2 + sin**2, 1.0, atol=1e-5)


def test_training_goes_on_when_one_actor_and_then_two_at_once_are_killed(tmp_path: Path) -> None:
    actors = [f"actor-{i}" for i in range(4)]
    with running(tmp_path, "kill_actors", ["replay", "learner", *actors], []) as run:
        client = replay_client(run)
        try:
            until(run, "all four actors send chunks and the learner trains",
                  lambda: info(client).get("producers", 0) == 4 and updates(info(client)) > 0,
                  timeout_s=240)  # fmt: skip
            for victims in (actors[:1], actors[1:3]):
                before = client.info()
                run.signal(victims, signal.SIGKILL)
                until(run, f"the run goes on without {victims}",
                      lambda b=before: client.info()["inserted_steps"] >= b["inserted_steps"] + 10 * CHUNK
                      and updates(client.info()) >= updates(b) + 50)  # fmt: skip
                assert_windows_keep_to_one_chunk(client, batches=5)
            assert run.procs["actor-3"].poll() is None and run.procs["learner"].poll() is None
            client.save("after_kills.npz")
            table = read_table(run.snapshots / "after_kills.npz")
            assert assert_whole_chunks(table) >= 20
        finally:
            client.close()


def test_a_killed_replay_comes_back_from_its_snapshot_and_the_actors_carry_on(tmp_path: Path) -> None:
    peers, actors = ["learner", "actor-0", "actor-1"], ["actor-0", "actor-1"]
    snapshot_every = ["replay.save_replay=true", "replay.save_replay_per_minute=0.05"]  # every 3 s
    with running(tmp_path, "kill_replay", ["replay", *peers], snapshot_every) as run:
        snapshot = run.run_dir / "replay/replay.npz"
        client = replay_client(run)
        try:
            until(run, "a snapshot holds chunks of both actors and the learner trains",
                  lambda: snapshot.exists() and len(newest_chunks(meta_of(snapshot))) == 2
                  and updates(info(client)) > 0, timeout_s=240)  # fmt: skip
            run.signal(["replay"], signal.SIGKILL)
            saved, meta = read_table(snapshot), meta_of(snapshot)
            until(run, "both actors find the replay gone and keep their chunks",
                  lambda: all("the actor keeps its chunks" in run.log(a).read_text() for a in actors))  # fmt: skip
            # Freeze the peers so that nothing changes the restored table before the test has read it: every
            # thread stopped, as a thread inside a system call stops only when the call returns.
            run.signal(peers, signal.SIGSTOP)
            until(
                run,
                "every thread of the peers is stopped",
                lambda: all(stopped(run.procs[p].pid) for p in peers),
                timeout_s=30,
            )
            run.start("replay")
            until(run, "the replay serves again", lambda: bool(info(client)), timeout_s=90)
            restored = client.info()
            client.save("restored.npz")
            run.signal(peers, signal.SIGCONT)
            limiter = meta["rate_limiter"]
            assert (restored["inserted_steps"], restored["size"], restored["sampled_windows"]) == (
                limiter["inserted"], limiter["inserted"] - limiter["evicted"], limiter["sampled"])  # fmt: skip
            assert (restored["next_key"], restored["producers"]) == (meta["next_key"], 2)
            assert restored["inserted_chunks"] == meta["counters"]["inserted_chunks"]
            again = read_table(run.snapshots / "restored.npz")
            for name in ("priorities", "row_key", "end_key", "start_key", "obs_0", "actions", "rewards"):
                np.testing.assert_array_equal(again[name], saved[name], err_msg=name)
            assert meta_of(run.snapshots / "restored.npz")["ledger"] == meta["ledger"]
            assert "replay restored from" in run.log("replay").read_text()

            # Both actors, the same processes (producer ids), store chunks numbered past the snapshot's.
            before, final = newest_chunks(meta), run.snapshots / "final.npz"

            def both_actors_carry_on() -> bool:
                client.save(final.name)
                now = newest_chunks(meta_of(final))
                return now.keys() == before.keys() and all(now[p] > before[p] for p in now)

            until(run, "both actors insert into the restarted replay", both_actors_carry_on)
            until(run, "the learner trains on", lambda: updates(client.info()) >= updates(restored) + 20)
            client.save(final.name)
            final_table = read_table(final)
            count = assert_whole_chunks(final_table)
            # No chunk is stored twice: real env data never repeats a chunk's actions by chance.
            contents = {final_table["actions"][rows[:-1]].tobytes() for rows in stored_chunks(final_table)}
            assert len(contents) == count
        finally:
            client.close()
