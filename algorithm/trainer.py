"""The embedded mode: actor loop + in-process replay + learner in one thread of one process.

Usage (``main.py`` does exactly this)::

    trainer = EmbeddedTrainer(config, run_dir, make_env)  # make_env(num_envs, seed) -> vector env
    summary = trainer.run()        # trains until max_step / max_iter; Ctrl-C saves and returns

The update-to-data ratio is explicit (SPEC.md A): once replay holds ``min_size_to_sample`` steps,
every env step owes ``samples_per_insert / batch_size`` updates, paid right after the step that
earned them — independent of how many envs run in parallel.
"""

from __future__ import annotations

import math
import random
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from algorithm.actor import ActorLoop, VectorEnvLike
from algorithm.checkpoint import (
    CheckpointError,
    capture_rng,
    list_checkpoints,
    load_for_resume,
    restore_rng,
    restoring,
    save_checkpoint,
)
from algorithm.config import config_to_yaml
from algorithm.config_schema import Config
from algorithm.evaluation import append_evaluation, evaluate
from algorithm.logging import MetricsWriter, ProgressLine, RateMeter, Timers
from algorithm.nn.user import model_builder
from algorithm.replay import PrioritizedTable
from algorithm.sac import SAC

EVAL_SEED_OFFSET = 100_000  # eval envs never share seeds with training envs (env i gets seed + i)


@dataclass(frozen=True)
class RunDir:
    """``models/<task>/<name>/`` and what lives in it (ARCHITECTURE.md 9)."""

    root: Path

    @property
    def config(self) -> Path:
        return self.root / "config.yaml"

    @property
    def log(self) -> Path:
        return self.root / "log"

    @property
    def model(self) -> Path:
        return self.root / "model"

    @property
    def replay(self) -> Path:
        return self.root / "replay" / "replay.npz"

    @property
    def evaluations(self) -> Path:
        return self.root / "evaluations.csv"

    @property
    def model_file(self) -> Path:
        """The run's copy of the task's model file (nn/user.py), when the task has one."""
        return self.root / "nn.py"


def load_replay_snapshot(table: PrioritizedTable, path: Path) -> None:
    """``table.load(path)``, with a file that cannot be loaded (damaged, truncated, another task's)
    as a :class:`CheckpointError`: the table and the file stay as they are."""
    try:
        table.load(path)
    except ValueError as e:
        raise CheckpointError(
            f"replay snapshot {e}; nothing was overwritten: repair it, or move it away to start with an empty replay"
        ) from None


@dataclass
class TrainSummary:
    env_steps: int
    updates: int
    episodes: int
    wall_seconds: float
    last_eval_mean: float | None
    interrupted: bool


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002 - user code and libraries may use the global RNG
    torch.manual_seed(seed)


class EmbeddedTrainer:
    def __init__(
        self,
        config: Config,
        run_dir: Path,
        make_env: Callable[[int, int], VectorEnvLike],
        evaluate: bool = True,
        device: str = "cpu",
        progress: bool = True,
        ckpt_step: int | None = None,
    ) -> None:
        """``make_env(num_envs, seed)`` builds the training envs (``n_agents``) and, with ``evaluate``
        and ``eval_per_step > 0``, separate evaluation envs (``eval_envs``); ``config.sac_config.seed``
        must be resolved (not None). Models come from ``run_dir/nn.py`` when the run has one
        (main.py copies the task's model file there)."""
        if config.sac_config.seed is None:
            raise ValueError("EmbeddedTrainer needs a resolved sac_config.seed (main.py picks one)")
        self.config = config
        self.paths = RunDir(Path(run_dir))
        base, sac_cfg, replay_cfg = config.base_config, config.sac_config, config.replay_config
        seed = int(sac_cfg.seed)  # type: ignore[arg-type]
        if base.torch_threads:
            torch.set_num_threads(base.torch_threads)
        seed_everything(seed)

        self.env = make_env(base.n_agents, seed)
        evaluating = evaluate and config.eval_config.eval_per_step > 0
        self.eval_env = make_env(config.eval_config.eval_envs, seed + EVAL_SEED_OFFSET) if evaluating else None
        self.eval_seed = seed + EVAL_SEED_OFFSET
        spec = self.env.spec
        model_file = self.paths.model_file if self.paths.model_file.exists() else None
        build = model_builder(model_file)
        self.sac = SAC(spec, sac_cfg, config.nn_config, replay_cfg, device=device, compile=sac_cfg.compile, build=build)
        window = sac_cfg.burn_in_step + sac_cfg.n_step
        self.table = PrioritizedTable.from_config(
            replay_cfg,
            spec.sensors,
            spec.action.size,
            window,
            rnn_state_size=self.sac.rnn_state_size,
            seed=seed,
            burn_in=sac_cfg.burn_in_step,
        )
        # Actors act with the learner's weights as of the last publication, every
        # update_policy_variables_per_step updates (1: always current), as distributed actors do.
        self.acting_policy = self.sac
        if sac_cfg.update_policy_variables_per_step > 1:
            self.acting_policy = SAC(spec, sac_cfg, config.nn_config, replay_cfg, device=device, build=build)
            self.acting_policy.load_acting_state_dict(self.sac.acting_state_dict())
        self.actor = ActorLoop(
            self.env,
            self.acting_policy,
            self.table.insert,
            chunk_length=config.actor_config.chunk_length,
            random_steps=config.actor_config.random_steps,
            reset_on_iteration=base.reset_on_iteration,
            seed=seed,
        )
        self.updates_per_step = replay_cfg.updates_per_step
        self.env_steps = 0
        self.updates = 0
        self.episodes = 0
        self.iterations = 0
        self.owed_updates = 0.0
        self.wall_seconds = 0.0
        self.next_eval = config.eval_config.eval_per_step
        self.next_save = sac_cfg.save_model_per_step
        self.last_eval_mean: float | None = None
        self.evaluations = 0
        self.recent_returns: deque[float] = deque(maxlen=10)
        self.timers = Timers()
        self.progress = progress

        # Restored before anything is written: a run whose checkpoint cannot be read keeps its files.
        if list_checkpoints(self.paths.model) or ckpt_step is not None:  # --ckpt on a new run: say so
            self.restore(ckpt_step)
        self.paths.root.mkdir(parents=True, exist_ok=True)
        self.paths.config.write_text(config_to_yaml(config))
        self.writer = MetricsWriter(self.paths.log)
        self.writer.text("config", config_to_yaml(config), self.env_steps)

    # -- the loop ---------------------------------------------------------------------------
    def run(self, until_step: int | None = None) -> TrainSummary:
        """Train until max_step/max_iter (then flush, save, close) or Ctrl-C (same), or pause at
        ``until_step`` env steps with everything left open so a later ``run()`` continues."""
        cfg = self.config
        base, replay_cfg = cfg.base_config, cfg.replay_config
        summary_every = cfg.sac_config.write_summary_per_step
        bar = ProgressLine(base.max_step) if self.progress else None
        update_rate = RateMeter()
        priorities_matter = replay_cfg.alpha > 0
        normalize = cfg.sac_config.use_normalization
        publish_every = cfg.sac_config.update_policy_variables_per_step
        sampling = self.table.rate_limiter.size >= replay_cfg.min_size_to_sample
        started = time.perf_counter() - self.wall_seconds
        last_save_time = time.perf_counter()
        interrupted = False
        try:
            while not self._done() and (until_step is None or self.env_steps < until_step):
                with self.timers.phase("env"):
                    stats = self.actor.step()
                self.env_steps += stats.env_steps
                self._record_episodes(stats.finished)
                self.iterations += stats.iteration_ended
                if not sampling:
                    sampling = self.table.rate_limiter.size >= replay_cfg.min_size_to_sample
                if sampling:
                    self.owed_updates += stats.env_steps * self.updates_per_step
                if normalize and stats.chunks:  # new rows in replay: its exact running stats moved
                    self.sac.load_normalizer_stats(self.table.normalizer_stats())
                while self.owed_updates >= 1.0:
                    with_metrics = self.updates % summary_every == 0
                    with self.timers.phase("sample"):
                        batch = self.table.sample(replay_cfg.batch_size)
                    with self.timers.phase("update"):
                        result = self.sac.update(batch, with_metrics=with_metrics)
                    if priorities_matter and not result.skipped:
                        with self.timers.phase("priorities"):
                            self.table.update_priorities(batch.keys, result.td_abs)
                    if result.refreshed_rnn_states is not None:
                        self.table.update_rnn_states(*result.refreshed_rnn_states)
                    self.owed_updates -= 1.0
                    self.updates += 1
                    if self.acting_policy is not self.sac and self.updates % publish_every == 0:
                        self.acting_policy.load_acting_state_dict(self.sac.acting_state_dict())
                    if with_metrics:
                        self._write_summary(result.metrics, update_rate.mark(self.updates))
                self.wall_seconds = time.perf_counter() - started
                if self.eval_env is not None and self.env_steps >= self.next_eval:
                    with self.timers.phase("eval"):
                        self._evaluate()
                    self.next_eval += cfg.eval_config.eval_per_step * math.ceil(
                        (self.env_steps - self.next_eval + 1) / cfg.eval_config.eval_per_step
                    )
                minutes = (time.perf_counter() - last_save_time) / 60
                if self.env_steps >= self.next_save or minutes >= cfg.sac_config.save_model_per_minute:
                    self.save()
                    last_save_time = time.perf_counter()
                if bar is not None:
                    recent = float(np.mean(self.recent_returns)) if self.recent_returns else None
                    bar.update(self.env_steps, self.updates, update_rate.mark(self.updates), recent)
        except KeyboardInterrupt:
            interrupted = True
        finally:
            if bar is not None:
                bar.close()
        if interrupted or self._done():
            self.actor.flush()  # open chunks go to replay before the final save: nothing collected is lost
            self.save()
            self.writer.close()
        return TrainSummary(
            self.env_steps, self.updates, self.episodes, self.wall_seconds, self.last_eval_mean, interrupted
        )

    def _done(self) -> bool:
        base = self.config.base_config
        return (base.max_step >= 0 and self.env_steps >= base.max_step) or (
            base.max_iter >= 0 and self.iterations >= base.max_iter
        )

    def _record_episodes(self, finished: list[tuple[float, int]]) -> None:
        for ret, length in finished:
            self.episodes += 1
            self.recent_returns.append(ret)
            self.writer.write({"actor/episode_return": ret, "actor/episode_length": length}, self.env_steps)

    def _write_summary(self, learner_metrics: dict[str, float], updates_per_s: float) -> None:
        info = self.table.info()
        replay = {f"replay/{k}": float(v) for k, v in info.items() if isinstance(v, int | float)}
        metrics = {
            **learner_metrics,
            **replay,
            **self.timers.fractions(),
            "time/updates_per_second": updates_per_s,
            "time/wall_seconds": self.wall_seconds,
            "learner/updates": float(self.updates),
            "actor/nonfinite_steps": float(self.actor.nonfinite_steps),  # dropped, logged by the ActorLoop
        }
        self.writer.write(metrics, self.env_steps)

    def _evaluate(self) -> None:
        assert self.eval_env is not None
        seed = self.eval_seed if not self.evaluations else None  # one seeded stream per process
        result = evaluate(self.eval_env, self.sac, self.config.eval_config.eval_episodes, seed)
        self.evaluations += 1
        self.last_eval_mean = result.mean
        append_evaluation(self.paths.evaluations, self.env_steps, self.updates, self.wall_seconds, result)
        self.writer.write(
            {
                "eval/return_mean": result.mean,
                "eval/return_std": result.std,
                "eval/episode_length": float(result.lengths.mean()),
            },
            self.env_steps,
        )

    # -- checkpoints ------------------------------------------------------------------------
    def counters(self) -> dict[str, Any]:
        return {
            "env_steps": self.env_steps,
            "updates": self.updates,
            "episodes": self.episodes,
            "iterations": self.iterations,
            "owed_updates": self.owed_updates,
            "wall_seconds": self.wall_seconds,
            "next_eval": self.next_eval,
            "next_save": self.next_save,
        }

    def save(self) -> Path:
        """Checkpoint learner state, counters and RNGs (and replay first, when save_replay is on)."""
        cfg = self.config.sac_config
        replay_inserted = None
        if self.config.replay_config.save_replay:
            self.table.save(self.paths.replay)
            replay_inserted = int(self.table.info()["inserted_steps"])
        while self.next_save <= self.env_steps:
            self.next_save += cfg.save_model_per_step
        state = {
            "sac": self.sac.state_dict(),
            "counters": self.counters(),
            "rng": capture_rng(),
            "actor_rng": self.actor.rng.bit_generator.state,
            "replay_inserted_steps": replay_inserted,
        }
        return save_checkpoint(self.paths.model, self.env_steps, state, keep=cfg.keep_checkpoints)

    def restore(self, step: int | None = None) -> None:
        """Resume from checkpoint ``step`` (default: the latest) and, with save_replay, the saved
        replay. A damaged or foreign file is a :class:`CheckpointError` naming it, never a silent
        fallback to an older checkpoint: the caller stops and the user decides (``--ckpt``)."""
        path, state = load_for_resume(self.paths.model, step)
        with restoring(path):
            self.sac.load_state_dict(state["sac"])
            for key, value in state["counters"].items():
                if key not in self.counters():
                    raise KeyError(f"unknown counter {key!r}")
                setattr(self, key, value)
            restore_rng(state["rng"])
            self.actor.rng.bit_generator.state = state["actor_rng"]
        self.actor.total_steps = self.env_steps  # random_steps counts from the run's start, not the resume
        if self.config.replay_config.save_replay and self.paths.replay.exists():
            load_replay_snapshot(self.table, self.paths.replay)
