"""The two systems the bench compares, run the same way: ASAC (its trainer, in process) and
Stable-Baselines3 SAC (an optional peer: pip install -e '.[bench]'), with the same hyper-parameters
and warm-up, evaluated by the same code (algorithm/run/evaluation.py) on the same seeded envs.

    result = run_ours("hopper", seed=0, steps=100_000, overrides=[], every=5000)   # a RunResult
    result = run_sb3("hopper", seed=0, steps=100_000, every=5000)

``run_ours`` with a ``run_dir`` trains in that folder: a run stopped by ``stop`` (set by a signal:
it saves, as main.py does on Ctrl-C) raises :class:`RunStopped`, and the same call later resumes it.
"""

from __future__ import annotations

import contextlib
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from algorithm.config.load import load_config
from algorithm.config.schema import Config
from algorithm.run.evaluation import evaluate, read_evaluations
from algorithm.run.trainer import EmbeddedTrainer
from algorithm.types import ActingProgress
from envs.make import make_vector_env, vector_env_factory

ROOT = Path(__file__).resolve().parents[1]
MUJOCO_TASKS = {
    "half_cheetah": "HalfCheetah-v5",
    "hopper": "Hopper-v5",
    "walker2d": "Walker2d-v5",
    "ant": "Ant-v5",
    "inverted_pendulum": "InvertedPendulum-v5",
    "humanoid": "Humanoid-v5",
}
EVAL_EPISODES = 10
EVAL_ENVS = 5


# -- ours ---------------------------------------------------------------------------------------
def our_config(task: str, overrides: list[str]) -> Config:
    return load_config(ROOT / "envs" / task, None, overrides).config


def our_trainer(config: Config, run_dir: Path, with_eval: bool = False) -> EmbeddedTrainer:
    base = config.base_config
    return EmbeddedTrainer(
        config,
        run_dir,
        vector_env_factory(base.build_path, env_kwargs=base.env_kwargs),
        evaluate=with_eval,
        progress=False,
    )


# -- SB3 ----------------------------------------------------------------------------------------
def sb3_model(env_id: str, seed: int, learning_starts: int, buffer_size: int = 1_000_000):  # noqa: ANN201
    import gymnasium as gym
    from stable_baselines3 import SAC as SB3SAC
    from stable_baselines3.common.logger import Logger

    env = gym.make(env_id)
    model = SB3SAC(
        "MlpPolicy",
        env,
        learning_rate=3e-4,
        buffer_size=buffer_size,
        learning_starts=learning_starts,
        batch_size=256,
        tau=0.005,
        gamma=0.99,
        train_freq=1,
        gradient_steps=1,
        ent_coef="auto_1.0",
        policy_kwargs={"net_arch": [256, 256]},
        seed=seed,
        device="cpu",
        verbose=0,
    )
    # A logger with no outputs and no folder: the one learn() makes at verbose 0 writes nothing but leaves an
    # empty SB3-<date> folder in the temporary directory on every call.
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


class SB3Policy:
    """Adapts an SB3 model to our Policy protocol so both are evaluated by the same code."""

    rnn_state_size = 0  # SB3's SAC is feedforward: evaluation calls act only
    progress = ActingProgress()  # the acting loop's (ASAC's exploration schedules read it; SB3 acts on its own)

    def __init__(self, model) -> None:  # noqa: ANN001
        self.model = model
        space = model.action_space
        self.low, self.high = space.low, space.high

    def act(self, obs: list[np.ndarray], deterministic: bool = False) -> tuple[np.ndarray, np.ndarray]:
        env_action, _ = self.model.predict(obs[0], deterministic=deterministic)
        unit = 2.0 * (env_action - self.low) / (self.high - self.low) - 1.0
        return unit.astype(np.float32), np.zeros(len(unit), np.float32)

    def act_recurrent(
        self, obs: list[np.ndarray], prev_actions: np.ndarray, rnn_state: np.ndarray, deterministic: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError("SB3's SAC has no recurrent policy")


@dataclass
class RunResult:
    final: float  # mean deterministic return of the last evaluation (after `steps` env steps)
    curve: list[tuple[int, float, float, float]] = field(default_factory=list)  # env steps, mean, std, wall s
    eval_seconds: float = 0.0
    earlier_wall_s: float = 0.0  # a resumed run: the wall seconds its earlier processes trained


class RunStopped(Exception):
    """``run_ours`` was stopped (``stop`` set) and saved its run folder at ``env_steps``."""

    def __init__(self, env_steps: int) -> None:
        super().__init__(f"stopped at {env_steps} env steps, saved")
        self.env_steps = env_steps


def warmup_steps(task: str) -> int:
    """The uniformly random steps the task's config asks for; SB3's learning_starts is set to them."""
    return our_config(f"mujoco/{task}", []).actor_config.random_steps


def run_ours(
    task: str,
    seed: int,
    steps: int,
    overrides: list[str],
    every: int = 0,
    on_eval: Callable[[RunResult], None] | None = None,
    run_dir: Path | None = None,
    stop: threading.Event | None = None,
) -> RunResult:
    """ASAC with the task's config. ``every`` > 0: the trainer's own evaluations every ``every`` env
    steps (its evaluations.csv: EVAL_EPISODES deterministic episodes on EVAL_ENVS envs seeded
    seed + 100000 at the first evaluation only), the last at ``steps``. ``every`` == 0: none during
    training, one at the end on fresh envs seeded the same way. ``run_dir``: train there (resuming
    what is saved there) instead of in a temporary folder; ``stop`` set: save and raise RunStopped."""
    config = our_config(
        f"mujoco/{task}",
        [
            f"sac.seed={seed}",
            f"base.max_step={steps}",
            f"eval.eval_per_step={every}",
            f"eval.eval_episodes={EVAL_EPISODES}",
            f"eval.eval_envs={EVAL_ENVS}",
            *overrides,
        ],
    )
    result = RunResult(float("nan"))
    with contextlib.ExitStack() as folders:
        folder = run_dir if run_dir is not None else Path(folders.enter_context(tempfile.TemporaryDirectory()))
        trainer = our_trainer(config, folder, with_eval=every > 0)
        result.earlier_wall_s = trainer.core.counters.wall_seconds
        if every == 0:
            if trainer.run(stop=stop).interrupted:
                raise RunStopped(trainer.env_steps)
            env = make_vector_env(MUJOCO_TASKS[task], EVAL_ENVS, seed=seed + 100_000)
            result.final = evaluate(env, trainer.sac, EVAL_EPISODES, seed + 100_000).mean
            return result
        while not trainer.done():
            interrupted = trainer.run(until_step=trainer.env_steps + every, stop=stop).interrupted
            rows = read_evaluations(trainer.paths.evaluations) if trainer.paths.evaluations.exists() else []
            curve = [(int(r["env_steps"]), r["return_mean"], r["return_std"], r["wall_seconds"]) for r in rows]
            result.eval_seconds = trainer.core.timers.seconds().get("time/eval_seconds", 0.0)
            if on_eval is not None and curve != result.curve:
                result.curve = curve
                on_eval(result)
            result.curve = curve
            if interrupted:
                raise RunStopped(trainer.env_steps)
    if not result.curve or result.curve[-1][0] != steps:
        raise RuntimeError(f"ASAC {task} seed {seed}: last evaluation at {result.curve[-1:]} rather than {steps} steps")
    result.final = result.curve[-1][1]
    return result


def run_sb3(
    task: str,
    seed: int,
    steps: int,
    every: int = 0,
    on_eval: Callable[[RunResult], None] | None = None,
    stop: threading.Event | None = None,
    save_to: Path | None = None,
) -> RunResult:
    """SB3 SAC with the same hyper-parameters and warm-up, evaluated by the same code on the same
    envs at the same cadence as :func:`run_ours` (``every`` == 0: once at the end). ``stop`` set:
    RunStopped between two evaluations (nothing saved: SB3's runs start again). ``save_to``: the
    trained model is saved there at the end (SB3's zip, without its replay buffer), for
    ``python -m bench.saturation``."""
    env_id = MUJOCO_TASKS[task]
    model = sb3_model(env_id, seed, learning_starts=warmup_steps(task))
    env = make_vector_env(env_id, EVAL_ENVS, seed=seed + 100_000)
    policy = SB3Policy(model)
    result = RunResult(float("nan"))
    start = time.perf_counter()
    while model.num_timesteps < steps:
        if stop is not None and stop.is_set():
            raise RunStopped(model.num_timesteps)
        model.learn(total_timesteps=min(every or steps, steps - model.num_timesteps), reset_num_timesteps=False)
        if every == 0 and model.num_timesteps < steps:
            continue
        eval_start = time.perf_counter()
        r = evaluate(env, policy, EVAL_EPISODES, seed + 100_000 if not result.curve else None)
        result.eval_seconds += time.perf_counter() - eval_start
        result.curve.append((model.num_timesteps, r.mean, r.std, time.perf_counter() - start))
        if on_eval is not None:
            on_eval(result)
    if save_to is not None:
        save_to.parent.mkdir(parents=True, exist_ok=True)
        model.save(save_to)
    result.final = result.curve[-1][1]
    return result
