"""The command-line code both entry points share (``main.py`` and ``main_ds.py``): flags common
to both, task and run folders, config overrides, the checks made before anything starts, the env
factory, and playing a checkpoint (``--run``). The entry points stay thin: each parses its own
flags and composes its mode.

Bad input ends the process with one line ``error: ...`` on stderr and exit code 2 (the entry points
catch :class:`UsageError`, :class:`~algorithm.config.load.ConfigError` and
:class:`~algorithm.errors.CheckpointError`), before anything starts.

Nothing here imports torch at module level: the flags, the task, the config and the run folder are
checked before it is imported (a mistyped command is answered in a fraction of a second, not after
the ~3 s of CPU torch's import takes); the functions that build models or play a checkpoint import
what they need.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import shutil
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

import gymnasium
import numpy as np

from algorithm.config.load import ConfigError, apply_overrides, config_from_file
from algorithm.config.schema import BaseConfig, Config
from algorithm.run.folder import RunDir
from algorithm.run.folder_lock import FolderInUse
from algorithm.run.logging import LogFileHandler
from envs.make import VectorEnv, make_env, vector_env_factory

if TYPE_CHECKING:
    from algorithm.nn.user import ModelBuilder
    from algorithm.sac.policy import Policy

ROOT = Path(__file__).resolve().parent
ENVS_DIR = ROOT / "envs"
MODEL_ROOT_ENV = "ASAC_MODEL_ROOT"  # --model_root's default when set (the Dockerfiles set it to their /data volume)
log = logging.getLogger("asac")


class UsageError(Exception):
    """Bad task name, run name or flag combination; printed without a traceback."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse with its errors on one line (``main.py: error: ... (see --help)``, exit code 2)
    rather than after the whole usage block, like every other error of the command line."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {one_line(message)} (see --help)\n")


def one_line(text: object) -> str:
    """``text`` with its line breaks (a YAML mark, a torch size mismatch list) folded into spaces."""
    return " ".join(str(text).split())


def positive(text: str) -> int:
    value = int(text) if text.isascii() and text.isdigit() else 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive integer")
    return value


def step_number(text: str) -> int:
    if not (text.isascii() and text.isdigit()):
        raise argparse.ArgumentTypeError(f"{text!r} is not a checkpoint step (an integer >= 0)")
    return int(text)


# The torch device strings ASAC runs on (torch.device parses them once a run starts).
DEVICE = re.compile(r"(cpu|cuda|mps)(:(0|[1-9]\d*))?")


def torch_device(text: str) -> str:
    """``cpu``, ``cuda``, ``cuda:N`` or ``mps``; whether this machine has it is :func:`check_device`'s
    question (a command line may be written for another machine, as the k8s manifests are)."""
    if text == "gpu":  # the original's name for it
        raise argparse.ArgumentTypeError("'gpu' is the original's name: write --device cuda (or cuda:N)")
    if not DEVICE.fullmatch(text):
        raise argparse.ArgumentTypeError(f"{text!r} is not a torch device ASAC runs on (cpu, cuda, cuda:1, mps)")
    return text


def check_device(text: str) -> None:
    """:class:`UsageError` unless this machine has the ``--device``: before anything starts."""
    if text.split(":")[0] == "cpu":
        return  # every machine has one; torch need not be imported to say so
    import torch

    device = torch.device(text)
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if (device.index or 0) >= count:
            raise UsageError(f"--device {text}: this machine has {count} CUDA devices")
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise UsageError(f"--device {text}: MPS is not available on this machine")


UNITY_ONLY = "it sets up Unity, and ASAC runs gymnasium envs only (Unity is out of scope): delete it"
ORIGINAL_FLAGS: dict[tuple[str, ...], str] = {
    ("-p", "--port", "--build_port", "--unity_port"): UNITY_ONLY,
    ("--editor", "--additional_args", "--u_editor", "--u_port", "--u_quality_level", "--u_timescale"): UNITY_ONLY,
    ("--envs",): "parallel envs are --agents N here (base_config.n_agents)",
    ("--max_iter",): "write --override base.max_iter=N (episodes of env 0; -1 no limit)",
    ("--env_args",): "write --override 'base.env_kwargs={key: value}' (keyword arguments of gymnasium.make)",
    ("-o",): "write --override section.key=value (repeatable; e.g. --override sac.n_step=3)",
    ("--logger_file",): "write --logger_in_file (the log goes to the run folder)",
    ("--sac",): "model files are --nn NAME here (envs/<task>/NAME.py, in ASAC's form: README, model files)",
    ("--standalone",): "main_ds.py roles run without an evolver unless you start one (evolver role, local --learners "
    "N): delete it",
    ("--disable_sample", "--use_env_nn", "--copy_model", "--run_a"): "not an ASAC flag: delete it (python main.py -h "
    "lists ASAC's)",
}
"""Flags of the original's command lines: each is answered with what to write here, not argparse's
"unrecognized arguments"."""


class _OriginalFlag(argparse.Action):
    """A flag of the original: using it is an error that says what to write instead."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: object,
                 option_string: str | None = None) -> None:  # fmt: skip
        parser.error(f"{option_string} is a flag of the original ASAC: {self.help_text}")

    help_text = ""


def add_original_flags(p: argparse.ArgumentParser) -> None:
    """Register :data:`ORIGINAL_FLAGS`, hidden from ``-h``."""
    for names, instead in ORIGINAL_FLAGS.items():
        action = type("OriginalFlag", (_OriginalFlag,), {"help_text": instead})
        p.add_argument(*names, nargs="?", action=action, help=argparse.SUPPRESS)


def add_common_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "env", help="a task under envs/ (gym/pendulum, mujoco/half_cheetah) or the path of your own task folder"
    )
    p.add_argument("-c", "--config", help="variant section of the task's config.yaml")
    p.add_argument("--run", action="store_true", help="play the latest (or --ckpt) checkpoint deterministically")
    p.add_argument("--render", action="store_true", help="with --run: show frames, or save an mp4 when headless")
    p.add_argument("--logger_in_file", action="store_true", help="also log to <run dir>/log.txt")
    p.add_argument("-n", "--name", help="run name ('{time}' becomes the start time); default base_config.name")
    p.add_argument("--nn", help="model file in the task folder (default base_config.nn)")
    p.add_argument("--ckpt", type=step_number, help="checkpoint step to resume from or play")
    p.add_argument("--agents", type=positive, help="parallel envs (base_config.n_agents)")
    p.add_argument(
        "--repeat", type=positive, default=1, help="train K runs one after another (seeds seed, seed+1, ...)"
    )
    p.add_argument("--device", type=torch_device, default="cpu", help="torch device for the learner, e.g. cpu or cuda")
    p.add_argument(
        "--override",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="set any config key, e.g. sac.n_step=5 (repeatable)",
    )
    p.add_argument(
        "--model_root",
        default=os.environ.get(MODEL_ROOT_ENV) or "models",
        help=f"where run folders go (default ${MODEL_ROOT_ENV}, else ./models; the images set /data/models)",
    )
    p.add_argument("--episodes", type=positive, help="with --run: episodes to play (default eval_config.eval_episodes)")
    p.add_argument("--no_progress", action="store_true", help="no progress line")
    add_original_flags(p)


def task_dir(task: str) -> Path:
    """The folder holding the task's ``config.yaml``: ``envs/<task>`` for ASAC's own tasks
    (``gym/pendulum``), else ``task`` read as the path of a folder of the user's own (absolute, ``~``,
    or relative to the working directory). Resolving a task also makes its modules importable (see
    :func:`import_from_task_folder`), so every launcher and role that reads a task can make its envs."""
    own = (ENVS_DIR / task).resolve()
    if ENVS_DIR.resolve() in own.parents and (own / "config.yaml").is_file():
        return own
    folder = Path(task).expanduser()
    if folder.is_dir() and (folder / "config.yaml").is_file() and folder.resolve().name:
        folder = folder.resolve()
        import_from_task_folder(folder)
        return folder
    known = sorted(str(p.parent.relative_to(ENVS_DIR)) for p in ENVS_DIR.glob("*/*/config.yaml"))
    found = f"the folder {folder} holds no config.yaml" if folder.is_dir() else f"no folder {folder}"
    raise UsageError(
        f"unknown task {task!r}: no envs/{task}/config.yaml, and {found}. Give one of ASAC's tasks "
        f"({', '.join(known)}) or the path of your own task folder holding a config.yaml (README: Your own environment)"
    )


def import_from_task_folder(folder: Path) -> None:
    """Let ``base_config.build_path: mymodule:MyEnv-v0`` import a module from the task's own folder or
    from the working directory (as ``python -m`` would), after everything installed: both go at the end
    of ``sys.path``, so a module of the user's never shadows one of ASAC's or an installed package's."""
    for path in (str(folder), os.getcwd()):
        if path not in sys.path:
            sys.path.append(path)


def task_label(task: str) -> str:
    """The ``<task>`` of ``<model_root>/<task>/<name>``: ASAC's task name (``gym/pendulum``, also when
    given as ``envs/gym/pendulum``), or the name of a user's own task folder (``~/work/mytask``: ``mytask``)."""
    folder, envs = task_dir(task), ENVS_DIR.resolve()
    return folder.relative_to(envs).as_posix() if envs in folder.parents else folder.name


def run_directory(model_root: str, task: str, name: str) -> Path:
    """``<model_root>/<task>/<name>`` (``<task>`` as :func:`task_label` names it); the name must stay
    inside the task's folder (it may have subfolders: ``-n myrun/learner_1`` plays one learner of a population)."""
    label = task_label(task)
    parts = Path(name).parts
    if not name.strip() or Path(name).is_absolute() or ".." in parts or "\0" in name:
        raise UsageError(f"run name {name!r} must be a relative path inside {model_root}/{label}/ (no '..')")
    return Path(model_root) / label / name


def check_writable(run_dir: Path, model_root: str) -> None:
    """The run folder can be written: it, or the nearest folder above it that exists, is a folder this
    user may write. Otherwise a :class:`UsageError` naming the path and what to do, before anything
    starts (a root-owned or read-only model root, a volume mounted for another user, a file in the
    way), rather than a PermissionError traceback from a role that already runs."""
    fix = f"pass --model_root a folder this user (uid {os.getuid()}) can write, or mount a writable volume there"
    for path in (run_dir, *run_dir.parents):
        try:
            if not path.exists():
                continue
            folder = path.is_dir()
        except OSError as e:
            raise UsageError(f"cannot write run folders under {model_root}: {path}: {e.strerror}; {fix}") from None
        if not folder:
            raise UsageError(f"cannot write run folders under {model_root}: {path} is not a folder; {fix}")
        if not os.access(path, os.W_OK | os.X_OK):
            raise UsageError(f"cannot write run folders under {model_root}: {path} is not writable; {fix}")
        return


@contextmanager
def removed_if_not_started(run_dir: Path) -> Iterator[None]:
    """Remove the folders this block creates on the way to ``run_dir`` if it raises: a run that
    could not start leaves no run directory behind. An existing one is never touched, nor a new one
    holding anything but what setting up a run writes (another role on a shared volume may have
    started meanwhile and written its own files)."""
    created = next((p for p in reversed((run_dir, *run_dir.parents)) if not p.exists()), None)
    try:
        yield
    except FolderInUse:
        raise  # the folder is another live process's run, made by it: never removed
    except BaseException:
        if created is not None and created.exists() and all(_written_by_setup(p) for p in created.rglob("*")):
            shutil.rmtree(created)
        raise


def _written_by_setup(path: Path) -> bool:
    """Folders, the copied model file, a log file (--logger_in_file), the resolved config."""
    name = path.name
    return path.is_dir() or name in ("nn.py", "config.yaml") or (name.startswith("log") and name.endswith(".txt"))


def cli_overrides(args: argparse.Namespace) -> list[str]:
    overrides = []
    if args.agents is not None:
        overrides.append(f"base_config.n_agents={args.agents}")
    if args.nn is not None:
        overrides.append(f"base_config.nn={args.nn}")
    return overrides + list(args.override)


DEFAULT_MODEL_FILE = BaseConfig.model_fields["nn"].default  # its absence means the default models


def copy_model_file(task: Path, config: Config, run_dir: Path, explicit: bool) -> None:
    """Copy the task's model file (``base_config.nn``, ``--nn``) into a new run directory; a run that
    already has one keeps it (resume). A file named by ``--nn`` or by the config (anything but the
    default name) that is missing is an error, not the default models in its place."""
    source = task / f"{config.base_config.nn}.py"
    target = RunDir(run_dir).model_file
    if not source.is_file():
        if explicit:
            raise UsageError(f"--nn {config.base_config.nn}: no model file {source}")
        if config.base_config.nn != DEFAULT_MODEL_FILE:
            raise UsageError(
                f"base_config.nn: {config.base_config.nn} names a model file, but {source} does not exist; add "
                f"it, or delete the key (or set it to {DEFAULT_MODEL_FILE}) to train the default models"
            )
        return
    if target.exists():
        return
    refuse_original_model_file(source)
    from algorithm.nn.user import model_builder

    try:
        model_builder(source)  # fail now, naming the file, rather than after the run directory exists
    except (ImportError, AttributeError) as e:
        raise UsageError(str(e)) from None
    run_dir.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(source, target)


ORIGINAL_MODEL_FILE = re.compile(
    r"^\s*(?:import\s+algorithm\.nn_models|from\s+algorithm(?:\.nn_models)?\s+import)", re.M
)


def refuse_original_model_file(source: Path) -> None:
    """A model file written for the original (it imports ``algorithm.nn_models``) is a :class:`UsageError`
    saying how to port it, rather than an ImportError from inside it."""
    try:
        text = source.read_text(errors="replace")
    except OSError:
        return  # model_builder names the file and what is wrong with it
    if ORIGINAL_MODEL_FILE.search(text) and "nn_models" in text:
        raise UsageError(
            f"{source} is a model file of the original ASAC (it imports algorithm.nn_models), which this ASAC "
            "cannot load: port it to define build_representation(spec, nn_config) or build_models(spec, sac_config, "
            "nn_config) (README, Algorithm features: model files; example envs/gym/pendulum/nn_layernorm.py), or "
            "move it out of the task folder to train the default MLPs, sized by nn_config.hidden_units (the "
            "original's c_dense_n: 256 with c_dense_depth: 3 is hidden_units: [256, 256, 256])"
        )


def run_model_builder(paths: RunDir) -> ModelBuilder:
    """Models as the run built them: from its copied model file when it has one."""
    from algorithm.nn.builder import build_models

    return run_model_file_builder(paths) or build_models


def run_model_file_builder(paths: RunDir) -> ModelBuilder | None:
    """The builder of the run's copied model file; None when it has none (the default models), in
    which case nothing is imported: a replay or an evolver of such a run never imports torch."""
    if not paths.model_file.exists():
        return None
    from algorithm.nn.user import model_builder

    try:
        return model_builder(paths.model_file)
    except (ImportError, AttributeError) as e:
        raise UsageError(str(e)) from None


def env_factory(config: Config) -> Callable[[int, int | None], VectorEnv]:
    """``factory(num_envs, seed)`` for the task's envs, with the config's kwargs and time limit."""
    base = config.base_config
    limit = base.max_step_each_iter if base.max_step_each_iter > 0 else None
    return vector_env_factory(base.build_path, env_kwargs=base.env_kwargs, max_episode_steps=limit,
                              reset_options=config.reset_config)  # fmt: skip


def check_env(config: Config) -> None:
    """Make one env of the config and close it: an unknown ``build_path`` or bad ``env_kwargs`` is a
    :class:`ConfigError` before anything starts, not an exception in a role that already runs."""
    base = config.base_config
    try:
        env_factory(config)(1, 0).close()
    except (ValueError, TypeError, gymnasium.error.Error) as e:
        raise ConfigError(
            f"base_config.build_path {base.build_path!r} with env_kwargs {base.env_kwargs}: "
            f"cannot make the env ({type(e).__name__}: {e})"
        ) from None


def setup_logging(run_dir: Path | None, in_file: bool) -> None:
    handlers: list[logging.Handler] = [logging.StreamHandler(sys.stderr)]
    if in_file and run_dir is not None:
        run_dir.mkdir(parents=True, exist_ok=True)
        handlers.append(LogFileHandler(run_dir / "log.txt"))
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s", handlers=handlers, force=True
    )


def play(args: argparse.Namespace) -> int:
    from algorithm.run.checkpoint import list_checkpoints, load_for_resume
    from algorithm.run.evaluation import evaluate
    from algorithm.sac.policy import Policy
    from algorithm.seeding import seed_everything

    check_device(args.device)
    run_root = Path(args.model_root) / task_label(args.env)
    if args.name is None or "{time}" in args.name:
        runs = sorted((p for p in run_root.glob("*") if RunDir(p).config.exists()), key=lambda p: p.stat().st_mtime)
        if not runs:
            raise UsageError(f"--run: no trained runs under {run_root}; train first or give -n NAME")
        run_dir = runs[-1]
    else:
        run_dir = run_directory(args.model_root, args.env, args.name)
    paths = RunDir(run_dir)
    if not paths.config.exists():
        raise UsageError(f"--run: {run_dir} is not a run folder (no config.yaml)")
    learners = sorted(p.name for p in run_dir.glob("learner_*") if RunDir(p).config.exists())
    if learners and not list_checkpoints(paths.model):  # an evolver's population: each learner has its folder
        name = run_dir.relative_to(run_root)
        raise UsageError(f"--run: {run_dir} holds a population; play one learner with -n {name}/<learner>, "
                         f"one of: {', '.join(learners)}")  # fmt: skip
    config = apply_overrides(config_from_file(paths.config), cli_overrides(args))
    setup_logging(run_dir, args.logger_in_file)
    ckpt, state = load_for_resume(paths.model, args.ckpt)
    seed = int(config.sac_config.seed or 0)
    seed_everything(seed)
    episodes = args.episodes or config.eval_config.eval_episodes
    base = config.base_config
    limit = base.max_step_each_iter if base.max_step_each_iter > 0 else None
    if args.render:
        return _play_rendered(config, state, run_dir, ckpt.stem, episodes, limit, args.device)
    env = env_factory(config)(min(episodes, config.eval_config.eval_envs), seed)
    sac = Policy(env.spec, config.sac_config, config.nn_config, device=args.device, build=run_model_builder(paths))
    _load_policy(sac, state, ckpt)
    result = evaluate(env, sac, episodes, seed)
    print(f"{run_dir} checkpoint {ckpt.stem}: return {result.mean:.1f} +- {result.std:.1f} over {episodes} episodes")
    return 0


def _load_policy(sac: Policy, state: dict, ckpt: Path) -> None:
    from algorithm.run.checkpoint import restoring

    with restoring(ckpt):
        sac.load_state_dict(state["sac"])


def _play_rendered(
    config: Config, state: dict, run_dir: Path, step: str, episodes: int, limit: int | None, device: str
) -> int:
    from algorithm.sac.policy import Policy

    base = config.base_config
    headless = not os.environ.get("DISPLAY")
    if headless:  # pygame's init (classic-control renderers) would look for a display and a sound card and
        # print errors about both (XDG_RUNTIME_DIR, ALSA); rgb_array frames need neither
        os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
        os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
        # MuJoCo renders off-screen through EGL (libEGL, with or without a GPU) unless told otherwise;
        # read when mujoco is first imported, which making the env does
        os.environ.setdefault("MUJOCO_GL", "egl")
        logging.getLogger("OpenGL").setLevel(logging.WARNING)  # PyOpenGL's INFO line about its C accelerator
    with _off_screen_rendering(headless):  # an off-screen GL library is loaded here, when the env is made
        env = make_env(
            base.build_path,
            seed=int(config.sac_config.seed or 0),
            env_kwargs=base.env_kwargs,
            max_episode_steps=limit,
            render_mode="rgb_array" if headless else "human",
        )
    venv = VectorEnv([env])  # sensors split and actions mapped exactly as in training
    spec = venv.spec
    sac = Policy(spec, config.sac_config, config.nn_config, device=device, build=run_model_builder(RunDir(run_dir)))
    _load_policy(sac, state, run_dir / "model" / f"{step}.pt")
    frames: list[np.ndarray] = []
    returns = []
    for ep in range(episodes):
        obs = venv.reset(seed=int(config.sac_config.seed or 0) + ep)
        prev_action = np.zeros((1, spec.action.size), dtype=np.float32)
        rnn_state = sac.initial_rnn_state(1)
        total, done = 0.0, False
        while not done:
            if sac.rnn_state_size:
                action, _, rnn_state = sac.act_recurrent(obs, prev_action, rnn_state, deterministic=True)
            else:
                action, _ = sac.act(obs, deterministic=True)
            result = venv.step(action)
            obs, prev_action = result.obs, action
            total += float(result.rewards[0])
            done = bool(result.terminated[0] or result.truncated[0])
            if headless:
                with _off_screen_rendering(headless):  # and a context is made at the first frame
                    frames.append(np.asarray(env.render()))
        returns.append(total)
    env.close()
    mean, std = float(np.mean(returns)), float(np.std(returns))
    print(f"{run_dir} checkpoint {step}: return {mean:.1f} +- {std:.1f} over {episodes} episodes")
    if headless and frames:
        import imageio.v2 as imageio

        video = run_dir / f"play_{step}.mp4"
        # H.264 in yuv420p (imageio-ffmpeg's default) needs even sizes; its default block of 16 would
        # rescale e.g. Pendulum's 500x500 frames to 512x512 and warn about it on every play.
        fps = int(env.metadata.get("render_fps", 30))
        imageio.mimwrite(video, list(frames), fps=fps, macro_block_size=2)
        print(f"no display: frames saved to {video}")
    return 0


@contextmanager
def _off_screen_rendering(headless: bool) -> Iterator[None]:
    """Without a display, a renderer that cannot start becomes a UsageError saying what it needs."""
    try:
        yield
    except Exception as e:  # the renderers raise their own types (mujoco.FatalError, AttributeError, ...)
        if not headless:
            raise
        raise UsageError(
            f"--render: no display (DISPLAY unset) and off-screen rendering failed: {one_line(e)}. MuJoCo renders "
            "off-screen with MUJOCO_GL=egl (needs libEGL; Debian: libegl1) or osmesa (libOSMesa; Debian: "
            f"libosmesa6), here {os.environ.get('MUJOCO_GL')!r}; or play without --render"
        ) from e
