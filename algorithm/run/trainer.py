"""The embedded mode: actor loop + in-process replay + learner in one thread of one process.

Usage (``main.py`` does exactly this)::

    trainer = EmbeddedTrainer(config, run_dir, make_env)  # make_env(num_envs, seed) -> vector env
    summary = trainer.run(stop=event)   # until max_step / max_iter, ``stop`` set or Ctrl-C: then saves

The lifecycle (counters, evaluation, summaries, checkpoints, resume, budget) is the learner core's
(algorithm/run/learner_core.py); this module adds what is in-process: the actor loop stepping the envs,
the table it inserts into, and the :class:`~algorithm.run.learner_core.UpdateBudget` that pays, right
after each env step, the updates that step earned.

On a stop (``stop`` set, Ctrl-C, or the budget spent) open chunks are flushed into the table, and
with ``replay_config.save_replay`` (every checkpoint) or ``save_replay_on_stop`` (interrupted runs,
the default) the table is saved beside the checkpoint, so the same command resumes with the data the
run had collected.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from algorithm.config.schema import Config
from algorithm.files import WriteFailures
from algorithm.nn.user import model_builder
from algorithm.replay import PrioritizedTable
from algorithm.replay.persistence import load_replay_snapshot, snapshot_kept
from algorithm.run.actor import ActorLoop, StepStats, VectorEnvLike
from algorithm.run.folder import EVAL_SEED_OFFSET, RunDir
from algorithm.run.learner_core import LearnerCore, UpdateBudget, restore_env_rngs
from algorithm.run.progress import RunSummary
from algorithm.sac.learner import SAC
from algorithm.sac.policy import Policy
from algorithm.seeding import seed_everything

__all__ = ["EVAL_SEED_OFFSET", "EmbeddedTrainer", "RunDir", "RunSummary"]
log = logging.getLogger("asac")


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
        eval_env = make_env(config.eval_config.eval_envs, seed + EVAL_SEED_OFFSET) if evaluating else None
        self.eval_env = eval_env
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
        self.acting_policy: Policy = self.sac
        if sac_cfg.update_policy_variables_per_step > 1:
            self.acting_policy = Policy(spec, sac_cfg, config.nn_config, device=device, build=build)
            self.acting_policy.load_acting_state_dict(self.sac.acting_state_dict())
        self.actor = ActorLoop.from_config(self.env, self.acting_policy, self.table.insert, config, seed)
        self.core = LearnerCore(
            config, self.paths.root, self.sac, log_dir=self.paths.log, eval_env=eval_env, progress=progress,
            publish=self._publish, extra_state=self._extra_state,
            newest_key=lambda: int(self.table.info()["next_key"]),
        )  # fmt: skip
        self.budget = UpdateBudget(replay_cfg.updates_per_step, replay_cfg.min_size_to_sample)
        self.recent_returns: deque[float] = deque(maxlen=10)
        self._replay_saved_at: int | None = None  # inserted steps of the snapshot this run last wrote
        self.replay_writes = WriteFailures("replay snapshot", log, retry="trying again with the next checkpoint",
                                           kept=snapshot_kept)  # fmt: skip
        self._interrupted = False

        self.core.resume_then_open(self.restore, ckpt_step)

    # -- counters (the core's) --------------------------------------------------------------
    @property
    def env_steps(self) -> int:
        return self.core.counters.env_steps

    @property
    def updates(self) -> int:
        return self.core.counters.updates

    @property
    def last_eval_mean(self) -> float | None:
        return self.core.counters.last_eval_mean

    def done(self) -> bool:
        return self.core.done()

    # -- the loop ---------------------------------------------------------------------------
    def run(self, until_step: int | None = None, stop: threading.Event | None = None) -> RunSummary:
        """Train until max_step/max_iter, ``stop`` is set or Ctrl-C (then flush, save, close), or pause
        at ``until_step`` env steps with everything left open so a later ``run()`` continues."""
        core, c, table = self.core, self.core.counters, self.table
        normalize = self.config.sac_config.use_normalization
        batch_size = self.config.replay_config.batch_size
        core.start()
        interrupted = False
        try:
            while not core.done() and (until_step is None or c.env_steps < until_step):
                if stop is not None and stop.is_set():
                    interrupted = True
                    break
                with core.timers.phase("env"):
                    stats = self.actor.step()
                c.env_steps += stats.env_steps
                self._record_episodes(stats)
                c.iterations += stats.iteration_ended
                self.budget.earn(stats.env_steps, table.rate_limiter.size)
                if normalize and stats.chunks:  # new rows in replay: its exact running stats moved
                    self.sac.load_normalizer_stats(table.normalizer_stats())
                while self.budget.take(table.rate_limiter.size):
                    with core.timers.phase("sample"):
                        batch = table.sample(batch_size, timeout=0)
                    core.train_on(batch, table, self._metrics)
                core.tick(float(np.mean(self.recent_returns)) if self.recent_returns else None)
        except KeyboardInterrupt:
            interrupted = True
        if interrupted or core.done():
            self.actor.flush()  # open chunks go to replay before the final save: nothing collected is lost
            self._interrupted = interrupted
            core.finish()
        c = core.counters
        return RunSummary.of(c, interrupted)

    def _publish(self) -> None:
        if self.acting_policy is not self.sac:
            self.acting_policy.load_acting_state_dict(self.sac.acting_state_dict())

    def _record_episodes(self, stats: StepStats) -> None:
        for episode in stats.episode_metrics():
            self.core.counters.episodes += 1
            self.recent_returns.append(episode["actor/episode_return"])
            self.core.write(episode)

    def _metrics(self) -> dict[str, float]:
        info = self.table.info()
        replay = {f"replay/{k}": float(v) for k, v in info.items() if isinstance(v, int | float)}
        return {**replay, "actor/nonfinite_steps": float(self.actor.nonfinite_steps)}  # dropped, logged by the loop

    # -- checkpoints ------------------------------------------------------------------------
    def save(self) -> Path | None:
        """Checkpoint learner state, counters and RNGs (and replay first, when save_replay is on);
        None when the checkpoint could not be written (logged; the earlier ones are kept)."""
        return self.core.save()

    def _extra_state(self) -> dict[str, Any]:
        """What a checkpoint adds for the in-process mode, the table saved first beside it: with
        ``save_replay`` every time, with ``save_replay_on_stop`` when the run is interrupted."""
        cfg = self.config.replay_config
        if cfg.save_replay or (self._interrupted and cfg.save_replay_on_stop):
            path, inserted = self.paths.replay, int(self.table.rate_limiter.inserted)
            if self.replay_writes.attempt(path, lambda: self.table.save(path), final=self.core.finishing):
                self._replay_saved_at = inserted  # else the checkpoint names the snapshot still on disk
        self.core.counters.owed_updates = self.budget.owed
        return {
            "actor_rng": self.actor.rng.bit_generator.state,
            "env_rng": self.env.rng_states(),  # a resumed run's episodes go on with new starts
            "replay_inserted_steps": self._replay_saved_at,
            # what ends RND's choice (rnd_choice_until_return) holds across a resume
            "actor_best_episode_return": self.actor.progress.best_episode_return,
        }

    def restore(self, step: int | None = None) -> None:
        """Resume from checkpoint ``step`` (default: the latest) and the saved replay when it is the
        one written with that checkpoint. A damaged or foreign file is a :class:`CheckpointError`
        naming it, never a silent fallback to an older checkpoint: the caller stops and the user
        decides (``--ckpt``)."""
        path, state = self.core.restore(step)
        self.actor.rng.bit_generator.state = state["actor_rng"]
        if restore_env_rngs(self.env, state.get("env_rng"), "training", path):
            self.actor.obs = self.env.reset()  # new episodes from the restored streams, not the run's first starts
        self.actor.total_steps = self.env_steps  # random_steps counts from the run's start, not the resume
        self.actor.progress.best_episode_return = float(state.get("actor_best_episode_return", -math.inf))
        if not self.done():  # a finished run trains no more: its replay is not loaded (it can be gigabytes)
            self._restore_replay(path, state.get("replay_inserted_steps"))
        self.budget.owed = self.core.counters.owed_updates
        self.budget.forgive(self.table.rate_limiter.size)

    def _restore_replay(self, checkpoint: Path, saved_at: int | None) -> None:
        """Load the replay snapshot when it is the one written with ``checkpoint`` (``saved_at``: the
        inserted steps it was saved with; None: saved without it)."""
        if saved_at is not None and self.paths.replay.exists():
            load_replay_snapshot(self.table, self.paths.replay)
            info = self.table.info()
            inserted = int(info["inserted_steps"])
            log.info("replay restored from %s: %d steps", self.paths.replay, int(info["size"]))
            if inserted != saved_at:  # written at another moment (killed between the two saves): still data
                log.warning("replay snapshot %s holds %d inserted steps, checkpoint %s was saved with %d; using it",
                            self.paths.replay, inserted, checkpoint, saved_at)  # fmt: skip
        elif self.paths.replay.exists():
            log.info("not loading %s: checkpoint %s was saved without it", self.paths.replay, checkpoint)
