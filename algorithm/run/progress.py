"""What a run has done, as its checkpoints record it: the counters, whether they spend the config's
budget, and the summary a launcher reports at the end of a run, the same for both modes."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from algorithm.config.schema import BaseConfig
from algorithm.run.checkpoint import list_checkpoints, load_for_resume, restoring
from algorithm.run.folder import RunDir


@dataclass
class RunCounters:
    """What a checkpoint records about the run's progress (``counters``). ``owed_updates`` is the
    in-process :class:`UpdateBudget`'s balance; ``replay_inserted_seen`` the replay server's own
    count the distributed learner last saw (:class:`~ds.learner.learner.EnvSteps`); ``weights_round`` the
    CEM round whose sample the weights descend from (0: none)."""

    env_steps: int = 0
    updates: int = 0
    episodes: int = 0
    iterations: int = 0
    wall_seconds: float = 0.0
    next_eval: int = 0
    next_save: int = 0
    evaluations: int = 0
    last_eval_mean: float | None = None
    last_eval_step: int = -1
    owed_updates: float = 0.0
    replay_inserted_seen: int = 0
    weights_round: int = 0
    scored_below: int = 0

    @classmethod
    def from_checkpoint(cls, saved: dict[str, Any], defaults: RunCounters) -> RunCounters:
        """Counters written by any earlier version: keys it lacks keep ``defaults``; an unknown key
        (a checkpoint of a newer version, or damaged) is a KeyError, which ``restoring`` names."""
        known = {f.name for f in fields(cls)}
        unknown = set(saved) - known
        if unknown:
            raise KeyError(f"unknown counters {sorted(unknown)}")
        return cls(**{**asdict(defaults), **saved})


def budget_spent(base: BaseConfig, counters: RunCounters) -> bool:
    """Whether a run with these counters has spent its budget (``max_step`` env steps or
    ``max_iter`` iterations; -1: unbounded): a finished run, which a restart leaves as it is."""
    return (base.max_step >= 0 and counters.env_steps >= base.max_step) or (
        base.max_iter >= 0 and counters.iterations >= base.max_iter
    )


def finished_at(base: BaseConfig, run_dir: Path) -> int | None:
    """The env steps of a run whose latest checkpoint has spent the budget of ``base``; None for a new
    or unfinished run. Read from the checkpoint alone (nothing is built), so a launcher can tell a
    finished run before it starts anything; a damaged latest checkpoint is a CheckpointError naming it."""
    model = RunDir(run_dir).model
    if not list_checkpoints(model):
        return None
    path, state = load_for_resume(model)
    with restoring(path):
        counters = RunCounters.from_checkpoint(state["counters"], RunCounters())
    return counters.env_steps if budget_spent(base, counters) else None


@dataclass(frozen=True)
class RunSummary:
    """How a run (``main.py``'s, or a distributed learner's) ended: its counters then, whether a stop
    interrupted it, and for a population's learner whether its evolver retired it. ``episodes``:
    those the run's own actors finished (a distributed learner has none of its own: 0)."""

    env_steps: int
    updates: int
    episodes: int
    wall_seconds: float
    last_eval_mean: float | None
    interrupted: bool
    retired: bool = False

    @classmethod
    def of(cls, counters: RunCounters, interrupted: bool, retired: bool = False) -> RunSummary:
        c = counters
        return cls(c.env_steps, c.updates, c.episodes, c.wall_seconds, c.last_eval_mean, interrupted, retired)
