"""``main_ds.py TASK local``'s launcher over stand-in roles (a few lines of Python each, that say when they
get a signal and when they are done), so the stop order is checked in seconds and exactly: learners
first, then actors, then replays, no kill in a normal finish, and the summary it ends with; the
actors' indices (ds/launch/local.py). The same journeys on real roles: tests/test_local_journeys.py.
"""

from __future__ import annotations

import shlex
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from algorithm.run.folder import python_command
from ds.actor.role import AsksForIndex
from ds.launch.local import plan
from ds.launch.local_summary import resume_argv
from ds.learner.client import LearnerClient
from tests.role_runs import ENV

ROOT = Path(__file__).resolve().parents[1]


STAND_IN = textwrap.dedent(
    """
    import signal, sys, time
    role = sys.argv[1]
    def stop(signum, frame):
        print(f"{role} got {signal.Signals(signum).name}", flush=True)
        time.sleep(0.5)  # saving
        print(f"{role} stopped", flush=True)
        sys.exit(130)
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    print(f"{role} up", flush=True)
    if "--finish" in sys.argv:
        time.sleep(1.5)
        print(f"{role} finished", flush=True)
        sys.exit(0)
    while True:
        time.sleep(0.05)
    """
)
LAUNCHER = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from ds.launch.local import run_local
    from ds.launch.local_summary import PlayableRun
    folder = Path(sys.argv[2])
    resume = ("main_ds.py", "gym/pendulum", "local", "-n", "standin")
    run = PlayableRun("gym/pendulum", "standin", folder, "models", Path("main.py"), resume)
    finish = {"learner": ["--finish"]} if sys.argv[3] == "finish" else {}
    sys.exit(run_local([sys.executable, sys.argv[1]], [], 2, finish, grace_s=10.0, run=run))
    """
)


def launch_stand_ins(tmp_path: Path, how: str) -> subprocess.Popen[str]:
    """``run_local`` (replay, learner, 2 actors) in a process of its own, over :data:`STAND_IN` roles;
    ``how``: "finish" (the learner exits 0 by itself after 1.5 s) or "wait" (until a signal)."""
    (tmp_path / "role.py").write_text(STAND_IN)
    folder = tmp_path / "run"
    (folder / "model").mkdir(parents=True)
    (folder / "model" / "1000.pt").write_bytes(b"")
    (folder / "evaluations.csv").write_text(
        "env_steps,updates,wall_seconds,return_mean,return_std\n500,1,1.0,-900.0,1.0\n1000,2,2.0,-321.5,1.0\n"
    )
    env = {**ENV, "PYTHONPATH": str(ROOT)}
    command = [sys.executable, "-c", LAUNCHER, str(tmp_path / "role.py"), str(folder), how]
    return subprocess.Popen(command, cwd=tmp_path, env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def at(lines: list[str], text: str) -> int:
    """The index of the first line containing ``text`` (fails naming it)."""
    found = [i for i, line in enumerate(lines) if text in line]
    assert found, f"no line with {text!r} in:\n" + "\n".join(lines)
    return found[0]


def test_a_normal_finish_stops_actors_then_the_replay_and_ends_with_the_summary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The learner exits 0 by itself: the actors are told to stop (SIGINT) and have stopped before
    the replay is told; nobody gets SIGTERM; exit 0; the summary, last, reads the run's files."""
    launcher = launch_stand_ins(tmp_path, "finish")
    out, _ = launcher.communicate(timeout=60)
    lines = out.splitlines()
    assert launcher.returncode == 0, out
    assert at(lines, "learner finished") < at(lines, "actor-0] actor got SIGINT")
    for k in (0, 1):
        assert at(lines, f"[actor-{k}] actor stopped") < at(lines, "[replay] replay got SIGINT"), out
    assert "SIGTERM" not in out and "SIGKILL" not in out, out
    monkeypatch.chdir(tmp_path)  # the launcher's working directory: how it shows the interpreter's path
    assert lines[-4:] == [
        "== local run finished ==",
        f"run folder: {tmp_path / 'run'}",
        "final evaluation return -321.5 (at 1000 env steps)",
        f"play it: {shlex.join([python_command(), 'main.py', 'gym/pendulum', '-n', 'standin', '--run'])}",
    ], out


def test_sigterm_to_the_launcher_stops_learner_then_actors_then_replay_and_exits_143(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SIGTERM to the launcher: the learner is told first and has stopped (saved) before the actors
    are told, and they have before the replay is; exit 143; the summary says interrupted."""
    launcher = launch_stand_ins(tmp_path, "wait")
    assert launcher.stdout is not None
    seen: list[str] = []
    for line in launcher.stdout:  # every child up: then stop the launcher
        seen.append(line.rstrip("\n"))
        if sum(" up" in x for x in seen) == 4:
            break
    launcher.send_signal(signal.SIGTERM)
    out, _ = launcher.communicate(timeout=60)
    lines = seen + out.splitlines()
    assert launcher.returncode == 143, "\n".join(lines)
    assert at(lines, "[learner] learner stopped") < at(lines, "[actor-0] actor got SIGINT")
    assert at(lines, "[learner] learner stopped") < at(lines, "[actor-1] actor got SIGINT")
    for k in (0, 1):
        assert at(lines, f"[actor-{k}] actor stopped") < at(lines, "[replay] replay got SIGINT")
    assert "got SIGTERM" not in out, "a child got SIGTERM: " + out
    assert lines[-5] == "== local run interrupted (SIGTERM) ==", out
    monkeypatch.chdir(tmp_path)  # the launcher's working directory: how it shows the interpreter's path
    resume = shlex.join([python_command(), "main_ds.py", "gym/pendulum", "local", "-n", "standin"])
    assert lines[-1] == f"resume it: {resume}", out  # a finished run's summary has no such line (above)


def test_the_resume_command_names_the_run_and_restores_the_latest_checkpoint(tmp_path: Path) -> None:
    """Every way of giving ``-n`` is replaced by the run's name (a ``{time}`` name, the default, is
    the start time: the same words would start a new run); ``--ckpt`` (restore that checkpoint) is
    left out, so the resumed run continues from its latest; everything else is kept as typed."""
    script = tmp_path / "main_ds.py"
    for typed in (["-n", "{time}"], ["--name", "x"], ["--name=x"], ["-nx"], [], ["--ckpt", "500"], ["--ckpt=500"]):
        argv = ["gym/pendulum", "local", *typed, "--actors", "2", "--override", "sac.seed=3"]
        kept = ("gym/pendulum", "local", "--actors", "2", "--override", "sac.seed=3")
        assert resume_argv(script, argv, "20261128041500") == (str(script), *kept, "-n", "20261128041500"), typed


def test_actor_k_is_started_asking_for_index_k() -> None:
    """Both a one-learner run and a population give actor k ``--index k``, the index it asks for."""
    for learners in (None, 2):
        asked = {
            name: argv[argv.index("--index") + 1]
            for name, argv in plan(["main_ds.py", "gym/pendulum"], [], 3, learners=learners)
            if name.startswith("actor-")
        }
        assert asked == {"actor-0": "0", "actor-1": "1", "actor-2": "2"}, learners


def test_an_actor_asks_its_learner_for_its_index_first_and_its_own_index_after(monkeypatch: pytest.MonkeyPatch) -> None:
    """``--index k``: the first registration asks for k; one that names an index (the actor's own,
    registering again) asks for that one; without ``--index`` it asks for none, as before."""
    asked: list[int | None] = []
    monkeypatch.setattr(
        LearnerClient, "register", lambda self, name, preferred_index=None: asked.append(preferred_index)
    )
    for index, own in ((1, None), (1, 3), (None, None)):
        client = AsksForIndex("127.0.0.1:1", index=index)
        try:
            client.register("actor", own)
        finally:
            client.close()
    assert asked == [1, 3, None]
