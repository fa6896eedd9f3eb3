"""Single-process ASAC: ``python main.py gym/pendulum`` trains; ``--run`` plays a checkpoint.

Thin by design: parse flags, resolve the config, wire env factories into algorithm/ (docs/architecture.md
section 1); what it shares with main_ds.py is in cli.py.

Bad input (flags, task names, config files, overrides, checkpoints) ends the process with one line
``error: ...`` on stderr naming the problem, exit code 2, before anything starts; a run directory
this process made for a run that then could not start is removed again.
"""

from __future__ import annotations

import os

# Before torch is imported: with OpenMP's active waiting, multi-threaded torch slowed ~200x when
# another process held a core (bench/learner.py); passive waiting costs nothing measurable.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# Before numpy is imported: NumPy's OpenBLAS runs the actors' policy (sac_config.numpy_acting) on
# a few rows at a time; its worker threads only contend with the env and the learner there (one
# actor with 64 envs acted 3.5x slower with a second core busy: 516 vs 149 us).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from algorithm.run.signals import exit_quietly_on_sigint

exit_quietly_on_sigint()  # a Ctrl-C while still importing: exit 130, no traceback

import argparse
import logging
import random
import shlex
import sys
import time
from pathlib import Path
from typing import Any

import gymnasium

from algorithm.config.load import ConfigError, apply_overrides, config_from_file, load_config
from algorithm.config.random_params import draw_for_run
from algorithm.errors import CheckpointError
from algorithm.run.folder import RunDir, python_command, shown_path
from algorithm.run.folder_lock import FolderInUse, hold_folder
from algorithm.run.signals import stop_on_signals
from cli import (
    ArgumentParser,
    UsageError,
    add_common_args,
    check_device,
    check_env,
    check_writable,
    cli_overrides,
    copy_model_file,
    env_factory,
    one_line,
    play,
    removed_if_not_started,
    run_directory,
    setup_logging,
    task_dir,
    task_label,
)

log = logging.getLogger("asac")


def build_parser(prog: str = "main.py") -> argparse.ArgumentParser:
    p = ArgumentParser(
        prog=prog,
        description="Train or play ASAC (Soft Actor-Critic) on a task from envs/ or your own task folder.",
        epilog="examples:\n  python main.py gym/pendulum\n"
        "  python main.py mujoco/half_cheetah -n 'test_{time}' --agents 2 --override sac.n_step=3\n"
        "  python main.py gym/pendulum -n myrun --run --render",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_common_args(p)
    return p


def train(args: argparse.Namespace) -> int:
    setup_logging(None, False)  # the config's own warnings (a key of the original's layout) carry their tag
    task = task_dir(args.env)
    check_device(args.device)
    resolved = load_config(task, args.config, cli_overrides(args))
    config = resolved.config
    check_env(config)
    # torch comes with the trainer, imported once the flags, the task and the config are known to be good
    from algorithm.run.trainer import EmbeddedTrainer

    name_template = args.name or config.base_config.name
    stop = stop_on_signals()  # Ctrl-C and SIGTERM: finish the step, save, exit 130 / 143
    for repeat in range(args.repeat):
        run_config, drawn = config.model_copy(deep=True), dict[str, Any]()
        name = name_template.replace("{time}", time.strftime("%Y%m%d%H%M%S"))
        if args.repeat > 1:
            name = f"{name}_{repeat}"
        run_dir = run_directory(args.model_root, args.env, name)
        check_writable(run_dir, args.model_root)
        saved_config = RunDir(run_dir).config
        with removed_if_not_started(run_dir):
            lock = hold_folder(run_dir, "run")  # one process trains a run: a second one stops here
            if saved_config.exists():
                # Resuming: the run's own resolved config (seed included) wins; command-line overrides still apply.
                run_config = apply_overrides(config_from_file(saved_config), cli_overrides(args))
            else:
                if run_config.sac_config.seed is None:
                    run_config.sac_config.seed = random.SystemRandom().randrange(2**31)  # recorded in config.yaml
                elif args.repeat > 1:
                    run_config.sac_config.seed = int(run_config.sac_config.seed) + repeat
                # As the original did for every standalone run; the values land in config.yaml, so a
                # resume runs with them (random_params emptied) instead of drawing again.
                run_config, drawn = draw_for_run(run_config, run_config.sac_config.seed)
            run_config.base_config.name = name
            copy_model_file(task, run_config, run_dir, explicit=args.nn is not None)
            setup_logging(run_dir, args.logger_in_file)
            try:
                trainer = EmbeddedTrainer(
                    run_config,
                    run_dir,
                    env_factory(run_config),
                    device=args.device,
                    progress=not args.no_progress,
                    ckpt_step=args.ckpt,
                )
            except ConfigError:
                raise
            except (ValueError, TypeError, gymnasium.error.Error) as e:  # the config does not fit the task
                raise ConfigError(f"cannot start {run_dir} with this config: {type(e).__name__}: {e}") from None
        log.info("run %s (seed %s)", run_dir, run_config.sac_config.seed)
        if drawn:
            values = ", ".join(f"{k}={v!r}" for k, v in drawn.items())
            log.info("random_params drew %s (recorded in config.yaml)", values)
        if trainer.done():
            report_finished(run_dir, args, trainer.env_steps, trainer.last_eval_mean, already=True)
            lock.release()
            continue
        if trainer.env_steps:
            log.info("resumed at %d env steps, %d updates", trainer.env_steps, trainer.updates)
        summary = trainer.run(stop=stop)
        if summary.interrupted:
            # a name made from the start time ('{time}', the default) is a new run next time: name it
            how = (
                f"resume it with: {run_command(args, run_dir)}"
                if "{time}" in name_template
                else "the same command resumes"
            )
            log.info("interrupted after %d env steps, %d updates, %.0f s: saved; %s",
                     summary.env_steps, summary.updates, summary.wall_seconds, how)  # fmt: skip
            return stop.exit_code
        report_finished(run_dir, args, summary.env_steps, summary.last_eval_mean, already=False)
        lock.release()
    return 0


def run_command(args: argparse.Namespace, run_dir: Path) -> str:
    """The command that trains ``run_dir`` on (resumes it), as the user would type it here."""
    name = run_dir.relative_to(Path(args.model_root) / task_label(args.env))
    root = [] if args.model_root == "models" else ["--model_root", args.model_root]
    return shlex.join([python_command(), shown_path(Path(__file__)), args.env, "-n", str(name), *root])


def play_command(args: argparse.Namespace, run_dir: Path) -> str:
    """The command that plays ``run_dir``'s latest checkpoint, as the user would type it here."""
    return f"{run_command(args, run_dir)} --run"


def report_finished(
    run_dir: Path, args: argparse.Namespace, env_steps: int, last_eval: float | None, already: bool
) -> None:
    """The end of a finished run (or of re-running one): its last evaluation, its folder, how to play it."""
    if last_eval is None:  # checkpoints from before the counters kept it
        from algorithm.run.learner_core import last_evaluation

        row = last_evaluation(RunDir(run_dir).evaluations)
        last_eval = None if row is None else row[1]
    result = "n/a (no evaluation)" if last_eval is None else f"{last_eval:.1f}"
    state = "already finished" if already else "finished"
    log.info("%s at %d env steps; last eval return %s", state, env_steps, result)
    log.info("run folder %s; play it with: %s", run_dir, play_command(args, run_dir))


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return play(args) if args.run else train(args)
    except (UsageError, ConfigError, CheckpointError, FolderInUse) as e:
        print(f"error: {one_line(e)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
