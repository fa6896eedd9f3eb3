"""The few lines ``main_ds.py TASK local`` prints last: how the run ended, its final evaluation
return, where it lies and the command that plays it (``main.py --run``, which finds a run as
``<model_root>/<task>/<name>/``, a population's learner k as ``-n <name>/learner_<k>``); a run that
did not finish also gets the command that resumes it (the launcher's own, naming the run: a name made
from the start time, ``{time}``, the default, would start a new run).

Usage (ds/launch/local.py, once every child has stopped)::

    run = PlayableRun("gym/pendulum", "base", Path("models/gym/pendulum/base"), "models", main_py)
    print("\\n".join(summary(run, "finished", learner_ids=None)))   # learner_ids=[0, 1]: a population

Read from what the learners wrote (``evaluations.csv``: its last row's ``return_mean``; ``model/``:
a checkpoint to play), so it says the same whether the run finished or was interrupted.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from pathlib import Path

from algorithm.run.checkpoint import list_checkpoints
from algorithm.run.folder import RunDir, python_command, shown_path
from algorithm.run.learner_core import last_evaluation

DEFAULT_MODEL_ROOT = "models"  # main.py's --model_root default: the play command leaves it out


@dataclass(frozen=True)
class PlayableRun:
    """A run as ``main.py --run`` finds it: ``task``, ``name`` (``-n``), its ``folder``
    (``<model_root>/<task>/<name>``), ``model_root`` and the path of ``main.py``."""

    task: str
    name: str
    folder: Path
    model_root: str
    main_py: Path
    resume: tuple[str, ...] = ()  # the launcher's command line that continues this run (resume_argv)


def summary(run: PlayableRun, outcome: str, learner_ids: list[int] | None) -> list[str]:
    """The lines to print: ``outcome`` (e.g. "finished", "interrupted (SIGINT)"), then the run folder
    and, for the run or each of ``learner_ids`` (a population), its final return and play command."""
    lines = [f"== local run {outcome} ==", f"run folder: {run.folder}"]
    if learner_ids is None:
        lines += _member_lines(run, run.folder, run.name, "")
    elif not learner_ids:
        lines += ["no learner registered with the evolver: nothing to play"]
    for k in sorted(learner_ids or ()):
        lines += _member_lines(run, run.folder / f"learner_{k}", f"{run.name}/learner_{k}", f"learner {k}: ")
    if outcome != "finished" and run.resume:
        lines.append(f"resume it: {shlex.join([python_command(), *run.resume])}")
    return lines


def resume_argv(script: Path, argv: list[str], name: str) -> tuple[str, ...]:
    """The launcher's command line (``script`` and its arguments ``argv``) that continues the run
    called ``name``: ``-n``/``--name`` set to it (a ``{time}`` name is the start time, so the same
    words would start a new run), ``--ckpt`` left out (it restores that checkpoint, not the latest)."""
    kept: list[str] = []
    skip = False
    for arg in argv:
        if skip:
            skip = False
        elif arg in ("-n", "--name", "--ckpt"):
            skip = True
        elif not arg.startswith(("--name=", "--ckpt=")) and not (arg.startswith("-n") and not arg.startswith("--")):
            kept.append(arg)
    return (shown_path(script), *kept, "-n", name)


def _member_lines(run: PlayableRun, folder: Path, name: str, who: str) -> list[str]:
    paths = RunDir(folder)
    last = last_evaluation(paths.evaluations)
    if last is not None:
        result = f"final evaluation return {last[1]:.1f} (at {last[0]} env steps)"
    else:
        result = f"no evaluation yet ({paths.evaluations} is missing or empty)"
    if not list_checkpoints(paths.model):
        return [f"{who}{result}", f"{who}nothing to play yet: no checkpoint in {paths.model}"]
    command = [python_command(), shown_path(run.main_py), run.task, "-n", name, "--run"]
    if run.model_root != DEFAULT_MODEL_ROOT:
        command += ["--model_root", run.model_root]
    return [f"{who}{result}", f"{who}play it: {shlex.join(command)}"]


__all__ = ["PlayableRun", "resume_argv", "summary"]
