"""Distributed ASAC: ``python main_ds.py gym/pendulum {replay,learner,actor,evolver,local} ...`` runs one role.

Thin by design, like main.py (whose flags it shares): parse, resolve the config and the run
directory, call the role's composition in ds/<role>/role.py (docs/architecture.md section 1). Exit codes:
0 done, 2 bad usage or config, 130 stopped by Ctrl-C / SIGTERM (``local``: 130 SIGINT, 143 SIGTERM;
ds/launch/local.py), 1 a role failed.
"""

from __future__ import annotations

import os

# Before torch and numpy are imported (see main.py).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from ds.net.grpc_env import read_replies_on_calling_thread

if __name__ == "__main__":  # a role process, not a test importing the parser
    read_replies_on_calling_thread()  # before grpc is imported (ds/net/grpc_env.py)

from algorithm.run.signals import exit_quietly_on_sigint

exit_quietly_on_sigint()  # a Ctrl-C while still importing: exit 130, no traceback

import argparse
import json
import logging
import random
import socket
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from algorithm.config.load import (
    DISTRIBUTED_TASK_FILE,
    ConfigError,
    apply_overrides,
    config_from_file,
    config_to_yaml,
    load_config,
    task_config_path,
)
from algorithm.config.original import CONFIG_LOGGER
from algorithm.config.random_params import draw_for_run
from algorithm.config.schema import MAX_EXPLORATION_NOISE, Config, NetConfig
from algorithm.errors import CheckpointError, RoleError
from algorithm.files import WriteFailures, atomic_write
from algorithm.run.folder import RunDir
from algorithm.run.folder_lock import FolderInUse, hold_folder
from algorithm.run.logging import LogFileHandler
from algorithm.run.signals import LAUNCHER_PID_ENV, StopRequest, stop_on_signals, stop_with_launcher
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
    positive,
    removed_if_not_started,
    run_directory,
    run_model_file_builder,
)
from cli import task_dir as resolve_task
from ds.evolver.state import EvolverStateError
from ds.launch import k8s
from ds.net import security

if TYPE_CHECKING:
    from ds.launch.role_context import RoleContext

ROLES = {"replay": "replay", "r": "replay", "learner": "learner", "l": "learner", "actor": "actor", "a": "actor",
         "evolver": "evolver", "e": "evolver", "local": "local"}  # fmt: skip
log = logging.getLogger("asac")
TLS_FLAGS = ("tls_cert", "tls_key", "tls_ca")


def port(text: str) -> int:
    value = int(text) if text.isascii() and text.isdigit() else -1
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number (0-65535)")
    return value


def noise_level(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0.0 <= value <= MAX_EXPLORATION_NOISE:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a noise level (a number in [0, {MAX_EXPLORATION_NOISE:.0f}])"
        )
    return value


def actor_index(text: str) -> int:
    value = int(text) if text.isascii() and text.isdigit() else -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not an actor index (an integer >= 0)")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = ArgumentParser(
        prog="main_ds.py",
        description="Run one role of distributed ASAC, or all of them as local subprocesses.",
        epilog="examples:\n  python main_ds.py gym/pendulum local --actors 2\n"
        "  python main_ds.py gym/pendulum local --learners 3 --actors 6   # a population with an evolver\n"
        "  python main_ds.py gym/pendulum replay -n myrun       # one role per host: the same -n on each\n"
        "  python main_ds.py gym/pendulum learner -n myrun --replay_host=10.0.0.2\n"
        "  python main_ds.py gym/pendulum actor -n myrun --learner_host=10.0.0.3 --replay_host=10.0.0.2 --noise 0.1",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_common_args(p)
    p.add_argument("role", choices=sorted(ROLES), help="replay (r), learner (l), actor (a), evolver (e) or local")
    for peer in ("evolver", "learner", "replay"):
        p.add_argument(f"--{peer}_host", help=f"address of the {peer} (net_config.{peer}_host)")
        p.add_argument(f"--{peer}_port", type=port, help=f"port of the {peer} (net_config.{peer}_port)")
    tls = {"cert": "this process's PEM certificate; its DNS SANs name its roles (replay, learner, evolver, actor)",
           "key": "the certificate's unencrypted PEM key",
           "ca": "PEM certificate of the run's CA: peers must hold a certificate it signed (mutual TLS)"}  # fmt: skip
    for name, what in tls.items():
        p.add_argument(f"--tls_{name}", metavar="FILE", help=f"{what} (net_config.tls_{name}; README Security)")
    p.add_argument("--noise", type=noise_level, help="this actor's exploration noise (default: from its index)")
    p.add_argument(
        "--index",
        type=actor_index,
        help="the index this actor asks its learner for (its seeds, noise and log/actor_<index>); default: the "
        "lowest free one; local gives actor k index k",
    )
    p.add_argument(
        "--in_k8s",
        action="store_true",
        help="servers listen on all interfaces (net_config.bind_host); learner k and replay k of the "
        "StatefulSets pair by pod ordinal (ds/launch/k8s.py)",
    )
    p.add_argument("--actors", type=positive, default=1, help="with local: how many actor processes")
    p.add_argument(
        "--no_token",
        action="store_true",
        help="with local: do not generate the run's token (<run>/token, mode 0600) when net_config.token_file "
        "names none; every local process may then call the roles",
    )
    p.add_argument(
        "--learners",
        type=positive,
        help="with local: run a population of N learners (each with its own replay) under an evolver",
    )
    return p


def resolve(args: argparse.Namespace) -> tuple[Config, Path, list[str]]:
    """The run's config (a resumed run's saved one wins; overrides and net flags still apply), its
    directory, with the seed resolved, as main.py does, and what to tell the user once everything is
    checked (bad input is one line); everything checked, nothing written."""
    task = resolve_task(args.env)
    check_device(args.device)
    overrides = cli_overrides(args)
    resolved = load_config(task, args.config, overrides, distributed=True)
    config, role = resolved.config, ROLES[args.role]
    template = args.name or config.base_config.name
    name = run_name(template, role)
    run_dir = run_directory(args.model_root, args.env, name)
    check_writable(run_dir, args.model_root)
    if role == "local":
        local_addresses(config.net_config, resolved.sources)  # what the task file or an override gives
    saved, drawn = RunDir(run_dir).config, dict[str, Any]()
    if saved.exists():
        config = apply_overrides(config_from_file(saved), overrides)
    else:
        if config.sac_config.seed is None:
            config.sac_config.seed = random.SystemRandom().randrange(2**31)
        if role == "local" and local_learners(args, config) is None:
            # no evolver to draw them: drawn once from the seed as main.py does, and recorded in the
            # run's config.yaml, which every role of the run then reads
            config, drawn = draw_for_run(config, config.sac_config.seed)
    config.base_config.name = name
    net = config.net_config
    if role == "local":  # a resumed run's config.yaml has the addresses its roles had: not said again
        net.evolver_host = net.learner_host = net.replay_host = None
    for peer in ("evolver", "learner", "replay"):
        if (host := getattr(args, f"{peer}_host")) is not None:
            setattr(net, f"{peer}_host", host)
        if (number := getattr(args, f"{peer}_port")) is not None:
            setattr(net, f"{peer}_port", number)
    if args.in_k8s:
        net.bind_host = "0.0.0.0"
        # Learner k and replay k of the StatefulSets find each other by ordinal (ds/launch/k8s.py); the pod
        # name is the hostname, or ASAC_POD_NAME (the Downward API's metadata.name) when set.
        pod = os.environ.get("ASAC_POD_NAME") or socket.gethostname()
        for key, value in k8s.paired_hosts(pod, ROLES[args.role]).items():
            if getattr(args, key) is None:  # an explicit --replay_host / --learner_host wins
                setattr(net, key, value)
    for name in TLS_FLAGS:
        if (path := getattr(args, name)) is not None:
            setattr(net, name, path)
    credentials(config, ROLES[args.role])  # a missing secret or a bad certificate stops here, before anything starts
    if ROLES[args.role] != "evolver":  # the one role without envs
        check_env(config)
    notes = []
    if (read := task_config_path(task, distributed=True)).name == DISTRIBUTED_TASK_FILE and not launched_by_local():
        notes.append(f"task file {read} (the distributed roles' file of this folder)")
    if drawn:
        notes.append(
            f"random_params drew {', '.join(f'{k}={v!r}' for k, v in drawn.items())} (recorded in config.yaml)"
        )
    if "{time}" in template and role != "local":
        notes.append(f"run {config.base_config.name!r}: roles started one by one without -n share this name "
                     f"('{{time}}' is {HAND_STARTED_TIME!r} for them), so their files go to one run folder and the "
                     "same commands resume it; -n NAME names it")  # fmt: skip
    return config, run_dir, notes


def launched_by_local() -> bool:
    """Whether this process is a role a ``local`` launcher started (which has said what concerns the run)."""
    return bool(os.environ.get(LAUNCHER_PID_ENV))


HAND_STARTED_TIME = "ds"
"""What ``{time}`` in a run's name becomes for roles started one by one: each would otherwise name the
run by its own start time (their files in as many folders, and the same commands a new run each time)."""


def run_name(template: str, role: str) -> str:
    """The run's name from ``-n`` (or base_config.name): ``{time}`` is the start time under ``local`` (one
    launcher names the run for all its roles), :data:`HAND_STARTED_TIME` for a role started by hand."""
    return template.replace("{time}", time.strftime("%Y%m%d%H%M%S") if role == "local" else HAND_STARTED_TIME)


def local_learners(args: argparse.Namespace, config: Config) -> int | None:
    """How many learners a ``local`` run starts under an evolver; None: one learner, no evolver."""
    return args.learners or (2 if config.base_config.evolver_enabled else None)


def local_addresses(net: NetConfig, sources: dict[str, str]) -> None:
    """``local`` places every role on loopback at free ports and tells each where the others are; an
    address the task file (or an override) gives is for roles started one by one, so it is dropped here,
    with one WARNING naming it, rather than followed by roles waiting for a host that never answers."""
    for peer in ("evolver", "learner", "replay"):
        key = f"{peer}_host"
        if (host := getattr(net, key)) is not None:
            where = sources.get(f"net_config.{key}", "the run's config.yaml")
            evolver = (
                " (an evolver runs with --learners N, or base_config.evolver_enabled: true)"
                if peer == "evolver"
                else ""
            )
            log.warning("net_config.%s: %s (%s) is for roles started one by one; local runs every role on this "
                        "host at addresses it picks, so it is not used%s", key, host, where, evolver)  # fmt: skip
            setattr(net, key, None)


def credentials(config: Config, role: str) -> security.Credentials:
    """The role's token and TLS material (ds/net/security.py), checked: ConfigError naming the key and file."""
    loaded = security.load_credentials(config.net_config)
    if role != "actor":  # every other role serves gRPC (local runs them all)
        security.check_server_credentials(loaded, role)
    return loaded


def check_models(context: RoleContext, role: str) -> None:
    """Build the run's models once on the CPU: a config that fits the schema but not the task (an
    unknown ``critic_only`` sensor, say) is a :class:`ConfigError` before anything starts, as in
    main.py, not a traceback in a role that already runs. An actor builds what it acts with (no
    optimizers: creating one imports torch's compiler, ~2.5 s of CPU); the learner, and ``local``
    before it starts any role, the whole learner side."""
    try:
        spec = context.spec()
        if role == "actor":
            context.policy(spec)
        else:
            context.sac(spec)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"cannot build the models of this config: {type(e).__name__}: {e}") from None


def setup_logging(run_dir: Path | None, role: str, in_file: bool) -> None:
    """Log lines tagged with time, role and level on stderr (and in ``log_<role>.txt`` with ``in_file``).
    Set before the config is read, so its warnings carry their tag too; a role ``local`` started has
    its config's warnings said once, by the launcher (they would repeat in every child)."""
    handlers: list[logging.Handler] = [logging.StreamHandler(sys.stderr)]
    if in_file and run_dir is not None:
        run_dir.mkdir(parents=True, exist_ok=True)
        handlers.append(LogFileHandler(run_dir / f"log_{role}.txt"))
    logging.basicConfig(
        level=logging.INFO, format=f"%(asctime)s {role} %(levelname)s %(message)s", handlers=handlers, force=True
    )
    if launched_by_local():
        logging.getLogger(CONFIG_LOGGER).setLevel(logging.ERROR)


def child_args(args: argparse.Namespace, config: Config) -> list[str]:
    """What ``local`` passes on to each role: the run name and seed it resolved, and the user's flags."""
    out = ["-n", config.base_config.name, "--model_root", args.model_root, "--device", args.device]
    out += ["--override", f"sac.seed={config.sac_config.seed}"]
    for flag in ("config", "nn", "agents"):
        if (value := getattr(args, flag)) is not None:
            out += [f"--{flag}", str(value)]
    for override in args.override:
        out += ["--override", override]
    for name in TLS_FLAGS:
        if (path := getattr(args, name)) is not None:
            out += [f"--{name}", path]
    out += ["--logger_in_file"] * args.logger_in_file + ["--no_progress"] * args.no_progress
    return out


def run(args: argparse.Namespace) -> int:
    role = ROLES[args.role]
    if args.run:
        return play(args)
    setup_logging(None, role, False)
    if args.repeat != 1:
        raise UsageError("--repeat is for main.py; start one distributed run per name")
    for flag, given in (("--actors", args.actors != 1), ("--learners", args.learners is not None),
                        ("--no_token", args.no_token)):  # fmt: skip
        if given and role != "local":
            raise UsageError(f"{flag} is for the local role")
    if args.index is not None and role != "actor":
        raise UsageError("--index is for the actor role (local gives each actor its own)")
    if args.ckpt is not None and role not in ("learner", "local"):
        raise UsageError("--ckpt is for the learner (it resumes from that checkpoint)")
    for peer in ("evolver", "learner", "replay"):
        if role == "local" and getattr(args, f"{peer}_host") is not None:
            raise UsageError(f"local runs every role on this host at addresses it picks; --{peer}_host is for "
                             "roles started one by one")  # fmt: skip
    config, run_dir, notes = resolve(args)
    # torch and the roles' code, imported once the flags, the task, the config and the credentials
    # are known to be good (cli.py); each role process imports its own role's composition only
    from ds.launch.role_context import RoleContext

    with removed_if_not_started(run_dir):
        # local drives the whole run, as main.py does: a second launcher on it stops here (the roles
        # started one by one are kept apart by their ports, which only one process can serve)
        if role == "local":
            hold_folder(run_dir, "run")  # held until this process ends (the kernel drops it then)
        copy_model_file(resolve_task(args.env), config, run_dir, explicit=args.nn is not None)
        setup_logging(run_dir, role, args.logger_in_file)
        context = RoleContext(
            config,
            run_dir,
            env_factory(config),
            None if role == "evolver" else run_model_file_builder(RunDir(run_dir)),  # it builds no model
            args.device,
            stop_on_signals("stopping"),
            credentials=credentials(config, role),
            overrides=tuple(cli_overrides(args)),
        )
        if role not in ("evolver", "replay"):  # the roles without models (a replay needs only a state width)
            check_models(context, role)
        for note in notes:
            log.info("%s", note)
        if role in ("local", "evolver") or (role == "learner" and not context.uses_evolver):
            run_dir.mkdir(parents=True, exist_ok=True)  # a population's learners write learner_<id>/config.yaml
            path, text = RunDir(run_dir).config, config_to_yaml(config).encode()  # a full disk keeps the old file
            WriteFailures("run config", log).attempt(path, lambda: atomic_write(path, lambda f: f.write(text)))
    if role == "local":
        return local(args, config, run_dir, context.credentials)
    if isinstance(context.stop, StopRequest):
        stop_with_launcher(context.stop)  # a role of local: it stops if the launcher dies
    log.info("%s of run %s (seed %s)", role, run_dir, config.sac_config.seed)
    security.warn_without_token(role, context.credentials)
    code = run_role(role, context, args)
    stop = context.stop
    return stop.exit_code if code == 130 and isinstance(stop, StopRequest) else code  # 143 after SIGTERM


def run_role(role: str, context: RoleContext, args: argparse.Namespace) -> int:
    from ds.net.heap import keep_freed_memory

    keep_freed_memory()  # every role moves messages of hundreds of KB
    if role == "evolver":
        from ds.evolver.role import run_evolver

        return run_evolver(context)
    if role == "replay":
        from ds.replay.role import run_replay

        return run_replay(context)
    if role == "learner":
        from ds.learner.role import run_learner

        return run_learner(context, args.ckpt, progress=not args.no_progress)
    from ds.actor.role import run_actor

    return run_actor(context, args.noise, args.index)


def local(args: argparse.Namespace, config: Config, run_dir: Path, creds: security.Credentials) -> int:
    """All roles as subprocesses: a replay, a learner and the actors; or, with ``--learners N`` (or
    ``base_config.evolver_enabled``: N defaults to 2), an evolver, N replays, N learners and the actors.
    Without ``net_config.token_file`` (nor ``--no_token``) the run gets a fresh token in ``<run>/token``
    (mode 0600), handed to every child as an explicit one is: ``--override net.token_file=<run>/token``."""
    from algorithm.run.progress import finished_at
    from ds.launch.local import learner_threads, run_local
    from ds.launch.local_summary import PlayableRun, resume_argv, summary

    learners = local_learners(args, config)
    here = Path(__file__).resolve()
    name = config.base_config.name
    playable = PlayableRun(args.env, name, run_dir, args.model_root, here.with_name("main.py"),
                           resume=resume_argv(here, args.command_line, name))  # fmt: skip
    if learners is None and args.ckpt is None and (done := finished_at(config.base_config, run_dir)) is not None:
        # started again on a finished run: say so without starting the roles (the learner would only
        # find the same and stop; a population's learners each decide for themselves)
        log.info("already finished at %d env steps; nothing to train, no role started", done)
        print("\n".join(summary(playable, "finished", None)), flush=True)
        return 0
    token_flags: list[str] = []
    if config.net_config.token_file is None and not args.no_token:
        security.write_token_file(run_dir / "token")
        config.net_config.token_file = str(run_dir / "token")
        creds = credentials(config, "local")
        token_flags = ["--override", f"net.token_file={json.dumps(config.net_config.token_file)}"]  # a YAML string
        log.info("every role of this run authenticates with the token in %s (mode 0600)", run_dir / "token")
    seed = config.sac_config.seed
    if learners is None:
        log.info("run %s (seed %s): replay, learner and %d actors", run_dir, seed, args.actors)
    else:
        log.info("run %s (seed %s): evolver, %d replays, %d learners and %d actors", run_dir, seed, learners,
                 learners, args.actors)  # fmt: skip
    extra = {
        "learner": [] if args.ckpt is None else ["--ckpt", str(args.ckpt)],
        "actor": [] if args.noise is None else ["--noise", str(args.noise)],
    }
    if not config.base_config.torch_threads:  # torch would give each learner every core the actors use too
        threads = learner_threads(args.actors, learners)
        extra["learner"] += ["--override", f"base.torch_threads={threads}"]
    command = [sys.executable, str(here), args.env]
    return run_local(command, child_args(args, config) + token_flags, args.actors, extra, learners=learners,
                     credentials=creds, run=playable)  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.command_line = list(sys.argv[1:] if argv is None else argv)  # what local's summary says resumes it
    try:
        return run(args)
    except (UsageError, ConfigError, CheckpointError, EvolverStateError, FolderInUse) as e:
        print(f"error: {one_line(e)}", file=sys.stderr)
        return 2
    except RoleError as e:
        print(f"error: {one_line(e)}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
