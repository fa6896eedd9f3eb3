"""Bad input to the command lines and to the files a run resumes from.

The contract (main.py's module docstring): wrong types, unknown keys, broken YAML, bad task names,
bad sections, bad flag values, missing files, damaged checkpoints and replay snapshots end the
process with one line ``error: ...`` naming the problem and exit code 2; nothing starts, no run
directory is created, and the files of an existing run are left exactly as they were.

Breadth comes in-process (hypothesis over the config parser; every case through ``main.main`` and
``main_ds.main``); real processes, started side by side to save time, hold the contract where it
counts: the exit code, stderr, and the run directory on disk.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, get_args

import pytest
import torch
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import cli
import main
import main_ds
from algorithm.config.load import ConfigError, config_from_yaml, config_to_yaml, load_config
from algorithm.config.schema import Config
from algorithm.run.checkpoint import load_checkpoint, save_checkpoint
from tests.damage import flip_in_largest_record, tree_digest, truncate

ROOT = Path(__file__).resolve().parents[1]
PENDULUM = ROOT / "envs/gym/pendulum"
ENV = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1", "MUJOCO_GL": "egl"}


# ---------------------------------------------------------------------- the config parser, in breadth

SECTIONS = [*Config.model_fields, "sac", "base", "nn", "replay", "actor", "eval", "net", "sacc", ""]
FIELDS = [(name, key) for name, f in Config.model_fields.items() for key in getattr(f.annotation, "model_fields", {})]
KEYS = sorted({key for _, key in FIELDS})
NUMERIC = [  # the keys that take a number
    (name, key)
    for name, f in Config.model_fields.items()
    for key, field in getattr(f.annotation, "model_fields", {}).items()
    if {int, float} & {field.annotation, *get_args(field.annotation)}
]
VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=6,
)


def yaml_value(value: Any) -> str:
    """``value`` as it is written after ``=`` in an override (flow style, no document end marker)."""
    return yaml.safe_dump(value, default_flow_style=True).removesuffix("...\n").strip()


@st.composite
def override(draw: st.DrawFn) -> str:
    """``section.key=value`` with any section, known or random keys and any YAML value; or any text."""
    if draw(st.integers(0, 9)) == 0:
        return draw(st.text(max_size=20))
    section, key = draw(
        st.sampled_from(FIELDS) | st.tuples(st.sampled_from(SECTIONS), st.sampled_from(KEYS) | st.text(max_size=8))
    )
    value = draw(VALUES.map(yaml_value) | st.text(max_size=12))
    return f"{section}.{key}={value}"


def numbers(value: Any) -> Iterator[float]:
    if isinstance(value, dict):
        value = list(value.values())
    if isinstance(value, list):
        for item in value:
            yield from numbers(item)
    elif isinstance(value, float):
        yield value


def assert_config_or_one_line_error(load: Callable[[], Config]) -> None:
    """``load()`` gives a config with finite numbers that survives the YAML round trip a run
    directory makes, or a :class:`ConfigError` of one non-empty line; never any other exception."""
    try:
        config = load()
    except ConfigError as e:
        assert str(e) and "\n" not in str(e), str(e)
    else:
        sections = config.model_dump(exclude={"base_config": {"env_kwargs"}, "reset_config": True})
        assert all(math.isfinite(x) for x in numbers(sections))
        assert config_from_yaml(config_to_yaml(config)) == config


@settings(max_examples=150, deadline=None)
@given(overrides=st.lists(override(), max_size=3))
def test_any_override_gives_a_config_or_a_one_line_error(overrides: list[str]) -> None:
    assert_config_or_one_line_error(lambda: load_config(PENDULUM, None, overrides).config)


@settings(max_examples=150, deadline=None)
@given(
    field=st.sampled_from(NUMERIC),
    number=st.sampled_from([math.nan, math.inf, -math.inf, 0, -1, 1e300]) | st.floats() | st.integers(),
)
def test_any_number_for_any_key_gives_a_config_or_a_one_line_error(field: tuple[str, str], number: float) -> None:
    """Plausible overrides (a key that takes a number, any number): NaN, infinities, zero, negatives, huge."""
    override = f"{field[0]}.{field[1]}={yaml_value(number)}"
    assert_config_or_one_line_error(lambda: load_config(PENDULUM, None, [override]).config)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    document=st.dictionaries(st.sampled_from(["default", "fast"]) | st.text(max_size=5), VALUES, max_size=3)
    | st.dictionaries(st.just("default"), st.dictionaries(st.sampled_from(SECTIONS), VALUES, max_size=3)),
    raw=st.none() | st.binary(max_size=40) | st.text(max_size=40).map(lambda t: t.encode("utf-8", "replace")),
    section=st.none() | st.sampled_from(["fast", "missing", "default"]),
)
@example(document={}, raw=b"1: {}\nfast: {}\n", section="missing")  # once a TypeError sorting the names for the error
@example(document={}, raw=b"0E0: {}\n", section=None)
def test_any_task_file_gives_a_config_or_a_one_line_error(
    tmp_path: Path, document: dict[str, Any], raw: bytes | None, section: str | None
) -> None:
    """A task's config.yaml with any structure, or any bytes at all (broken YAML, not UTF-8)."""
    task = tmp_path / "task"
    task.mkdir(exist_ok=True)
    (task / "config.yaml").write_bytes(yaml.safe_dump(document).encode() if raw is None else raw)
    assert_config_or_one_line_error(lambda: load_config(task, section).config)


@settings(max_examples=60, deadline=None)
@given(edit=st.tuples(st.sampled_from(KEYS), VALUES) | st.text(max_size=60))
@example(edit="1")  # a number for the whole file: once a TypeError from the error formatting
@example(edit="- sac_config")
@example(edit="?")  # a key YAML reads as None: once an AttributeError from the error formatting
def test_any_saved_run_config_gives_a_config_or_a_one_line_error(edit: tuple[str, Any] | str) -> None:
    """A run directory's config.yaml (what a resume reads) with a key set to anything, or replaced by any text."""
    if isinstance(edit, str):
        text = edit
    else:
        data = Config().model_dump(mode="json")
        key, value = edit
        next(s for s in data.values() if isinstance(s, dict) and key in s)[key] = value
        text = yaml.safe_dump(data)
    assert_config_or_one_line_error(lambda: config_from_yaml(text, "models/x/config.yaml"))


# ---------------------------------------------------------------------- every case through main() in-process


@pytest.fixture
def in_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """Run in an empty folder (runs go to ./models), and leave logging as it was."""
    monkeypatch.chdir(tmp_path)
    handlers, level = logging.root.handlers[:], logging.root.level
    yield tmp_path
    logging.root.handlers[:], logging.root.level = handlers, level


def call(entry: Callable[[list[str]], int], argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    try:
        code = entry(argv)
    except SystemExit as e:  # argparse
        code = int(e.code or 0)
    return code, capsys.readouterr().err


def assert_refused(code: int, stderr: str, named: str, folder: Path) -> None:
    assert code == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "error: " in lines[0] and named in lines[0], stderr
    assert not (folder / "models").exists(), "a run directory was created"


PENDULUM_ARGS = ["gym/pendulum", "--no_progress"]
# (arguments after the task, what the line must name); main.py and main_ds.py (as a replay) share them.
SHARED_CASES = [
    (["--override", "sac.n_step=abc"], "sac_config.n_step (override 'sac.n_step=abc'): Input should be a valid"),
    (["--override", "sac.n_step"], "expected section.key=value"),
    (["--override", "sacc.n_step=1"], "unknown section 'sacc' (did you mean 'sac'?)"),
    (["--override", "nn.hidden_units=[16"], "not valid YAML at line 1, column 4"),
    (["--override", "replay.capacty=10", "--override", "sac.gama=1"], "capacty (override 'replay.capacty=10'): "
     "unknown key (did you mean 'capacity'?); sac_config.gama"),
    (["-c", "nosuch"], "no config section 'nosuch'; available: ['vanilla']"),
    (["--agents", "0"], "argument --agents: '0' is not a positive integer"),
    (["--ckpt", "-3"], "argument --ckpt: '-3' is not a checkpoint step"),
    (["--device", "banana"], "argument --device: 'banana' is not a torch device"),
    # the original's command lines: each flag answered with what to write here
    (["--device", "gpu"], "'gpu' is the original's name: write --device cuda"),
    (["-p", "5006"], "-p is a flag of the original ASAC: it sets up Unity"),
    (["--port", "5006"], "--port is a flag of the original ASAC: it sets up Unity"),
    (["--editor"], "--editor is a flag of the original ASAC: it sets up Unity"),
    (["--additional_args", "x"], "--additional_args is a flag of the original ASAC: it sets up Unity"),
    (["-o", "sac.n_step=3"], "-o is a flag of the original ASAC: write --override section.key=value"),
    (["--envs", "4"], "--envs is a flag of the original ASAC: parallel envs are --agents N here"),
    (["--max_iter", "100"], "--max_iter is a flag of the original ASAC: write --override base.max_iter=N"),
    (["--sac", "sac_hard"], "--sac is a flag of the original ASAC: model files are --nn NAME here"),
    (["--device", "cuda:99"], "--device cuda:99: this machine has"),
    (["-n", "../escape"], "run name '../escape' must be a relative path inside models/gym/pendulum/"),
    (["-n", " "], "run name ' '"),
    (["--override", "base.build_path=NoSuchEnv-v0"], "base_config.build_path 'NoSuchEnv-v0'"),
    (["--override", "base.env_kwargs={bogus: 1}"], "unexpected keyword argument 'bogus'"),
    (["--override", "replay.capacity=100"], "min_size_to_sample (1000) must be < capacity (100)"),
    (["--override", "sac.learning_rate=.inf"], "sac_config.learning_rate (override 'sac.learning_rate=.inf'): "
     "Input should be a finite number"),
    (["--override", "net.token_file=absent.key"], "net_config.token_file: cannot read 'absent.key'"),
]  # fmt: skip
MAIN_CASES = [
    *SHARED_CASES[:-1],  # main.py has no token
    (["--repeat", "0"], "argument --repeat: '0' is not a positive integer"),
    (["--run", "--episodes", "0"], "argument --episodes: '0' is not a positive integer"),
    # --logger_in_file makes the run directory (log.txt) before the models are built: it is removed again
    (["--logger_in_file", "--override", "nn.critic_only=[nope]"], "critic_only names unknown sensors ['nope']"),
    (["--logger_in_file", "-n", "fresh", "--ckpt", "5"], "no checkpoint for step 5 in models/gym/pendulum/fresh/model"),
]
MAIN_DS_CASES = [
    *[(["replay", *args], named) for args, named in SHARED_CASES],
    (["actor", "--noise", "1e9"], "argument --noise: '1e9' is not a noise level (a number in [0, 1000000])"),
    (["local", "--learners", "0"], "argument --learners: '0' is not a positive integer"),
    (["actor", "--override", "actor.noise_max=1e9"], "noise_max"),
    (["learner", "-n", "r", "--override", "nn.critic_only=[nope]"], "critic_only names unknown sensors ['nope']"),
    (["actor", "-n", "r", "--override", "nn.critic_only=[nope]"], "critic_only names unknown sensors ['nope']"),
    # local places every role itself: an address flag is for roles started one by one
    *[
        (["local", f"--{peer}_host", "10.0.0.9"], f"--{peer}_host is for roles started one by one")
        for peer in ("replay", "learner", "evolver")
    ],
    (["local", "--override", "nn.critic_only=[nope]"], "critic_only names unknown sensors ['nope']"),
]


@pytest.mark.parametrize("args, named", MAIN_CASES, ids=[" ".join(a) for a, _ in MAIN_CASES])
def test_main_refuses_bad_input_in_one_line(
    in_tmp: Path, capsys: pytest.CaptureFixture[str], args: list[str], named: str
) -> None:
    assert_refused(*call(main.main, [*PENDULUM_ARGS, *args], capsys), named, in_tmp)


@pytest.mark.parametrize("args, named", MAIN_DS_CASES, ids=[" ".join(a) for a, _ in MAIN_DS_CASES])
def test_main_ds_refuses_bad_input_in_one_line(
    in_tmp: Path, capsys: pytest.CaptureFixture[str], args: list[str], named: str
) -> None:
    assert_refused(*call(main_ds.main, [*PENDULUM_ARGS, *args], capsys), named, in_tmp)


# ---------------------------------------------------------------------- a run to damage


ORIGINAL_NN_FILE = """import torch
from torch import nn

import algorithm.nn_models as m

ModelRep = m.ModelSimpleRep


class ModelQ(m.ModelQ):
    def _build_model(self):
        return super()._build_model(c_dense_n=256, c_dense_depth=3)
"""


@pytest.mark.parametrize("entry", [main.main, main_ds.main], ids=["main", "main_ds"])
@pytest.mark.parametrize(
    "files, named",
    [
        ({"nn.py": ORIGINAL_NN_FILE}, "nn.py is a model file of the original ASAC (it imports algorithm.nn_models)"),
        ({}, "base_config.nn: nn_hard names a model file, but"),  # the section names a file that is not there
    ],
    ids=["original_model_file", "missing_model_file"],
)
def test_a_task_folder_of_the_original_with_its_model_files_is_answered_in_one_line(
    in_tmp: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
    entry: Callable[[list[str]], int],
    files: dict[str, str], named: str,
) -> None:  # fmt: skip
    """The original's model files cannot be loaded: one line says how to port them (not an ImportError from
    inside the file); a section naming a model file that is missing is refused, not the default models."""
    envs = in_tmp / "envs"
    task = envs / "bullet" / "walker"
    task.mkdir(parents=True)
    config = {"default": {"base_config": {"env_type": "GYM", "build_path": "Pendulum-v1"}},
              "hard": {"base_config": {"nn": "nn_hard"}}}  # fmt: skip
    (task / "config.yaml").write_text(yaml.safe_dump(config))
    for name, text in files.items():
        (task / name).write_text(text)
    monkeypatch.setattr(cli, "ENVS_DIR", envs)  # where tasks are looked up: this folder, not the checkout's
    role = ["replay"] if entry is main_ds.main else []
    section = [] if files else ["-c", "hard"]
    code, stderr = call(entry, ["bullet/walker", *role, *section, "--no_progress"], capsys)
    said = [line for line in stderr.splitlines() if " WARNING " not in line]  # what the original's keys became
    assert_refused(code, "\n".join(said), named, in_tmp)


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run with checkpoints at 20 and 40 env steps, a saved replay and its config (no updates: fast)."""
    root = tmp_path_factory.mktemp("trained")
    overrides = ["sac.seed=1", "base.max_step=40", "sac.save_model_per_step=20", "replay.save_replay=true",
                 "eval.eval_per_step=0", "nn.hidden_units=[16]"]  # fmt: skip
    args = [arg for o in overrides for arg in ("--override", o)]
    done = subprocess.run([sys.executable, str(ROOT / "main.py"), *PENDULUM_ARGS, "-n", "run", *args], cwd=root,
                          env=ENV, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    run = root / "models/gym/pendulum/run"
    assert sorted(p.name for p in (run / "model").glob("*.pt")) == ["20.pt", "40.pt"]
    assert (run / "replay/replay.npz").is_file()
    return root


def wrong_shapes(path: Path) -> None:
    """Rewrite a checkpoint (with a valid digest) whose first weight matrix is shaped for another task."""
    state = load_checkpoint(path)
    models = state["sac"]["models"]
    name = next(k for k, v in models.items() if v.ndim == 2)
    models[name] = torch.zeros(models[name].shape[0], models[name].shape[1] + 3)
    save_checkpoint(path.parent, int(path.stem), {k: v for k, v in state.items() if k != "format_version"}, keep=9)


def replace_in(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


RUN = "models/gym/pendulum/run"
# (name, damage to the copy of the run, command, what the error line names; " ... " separates fragments).
# The first case's override would change the saved config.yaml if anything were written before the
# checkpoint is read. DAMAGED_RUNS run as processes, DAMAGED_CONFIGS (which fail before anything is
# built) through main() in this process.
DAMAGED_RUNS: list[tuple[str, Callable[[Path], None], list[str], str]] = [
    ("latest checkpoint flipped", lambda r: flip_in_largest_record(r / "model/40.pt"),
     ["main.py", "--override", "eval.eval_episodes=3"],
     f"checkpoint {RUN}/model/40.pt is damaged: its contents do not match the digest written with them; nothing "
     "was overwritten: to use an older checkpoint, pass --ckpt 20"),
    ("latest checkpoint flipped, local", lambda r: flip_in_largest_record(r / "model/40.pt"),
     ["main_ds.py", "local"],  # the launcher reads it (is the run finished?) before it starts a role
     f"checkpoint {RUN}/model/40.pt is damaged: its contents do not match the digest written with them; nothing "
     "was overwritten: to use an older checkpoint, pass --ckpt 20"),
    ("latest checkpoint of another task", lambda r: wrong_shapes(r / "model/40.pt"), ["main.py"],
     f"checkpoint {RUN}/model/40.pt does not fit this run's models and state (RuntimeError: Error(s) in loading"),
    ("checkpoint truncated, played", lambda r: truncate(r / "model/40.pt"), ["main.py", "--run"],
     f"checkpoint {RUN}/model/40.pt is unreadable or not an ASAC checkpoint ... pass --ckpt 20"),
    # taken further: a finished run started again only reports, without reading its replay
    ("replay snapshot truncated", lambda r: truncate(r / "replay/replay.npz"),
     ["main.py", "--override", "base.max_step=80"],
     f"replay snapshot {RUN}/replay/replay.npz: not a readable replay file"),
    ("replay snapshot flipped", lambda r: flip_in_largest_record(r / "replay/replay.npz"), ["main_ds.py", "replay"],
     f"replay snapshot {RUN}/replay/replay.npz: not a readable replay file (BadZipFile: Bad CRC-32"),
]  # fmt: skip
DAMAGED_CONFIGS: list[tuple[str, Callable[[Path], None], list[str], str]] = [
    ("saved config broken", lambda r: replace_in(r / "config.yaml", "  n_step: 3", "  n_step: [3"), ["main.py"],
     f"{RUN}/config.yaml: not valid YAML at line"),
    ("saved config with an unknown key", lambda r: replace_in(r / "config.yaml", "  n_step:", "  n_stepz:"),
     ["main_ds.py", "learner"], f"sac_config.n_stepz ({RUN}/config.yaml): unknown key (did you mean 'n_step'?)"),
    ("saved config with a wrong type", lambda r: replace_in(r / "config.yaml", "  n_step: 3", "  n_step: three"),
     ["main.py"], f"sac_config.n_step ({RUN}/config.yaml): Input should be a valid integer"),
    ("saved config not UTF-8", lambda r: (r / "config.yaml").write_bytes(b"sac_config:\n  scene: caf\xe9\n"),
     ["main_ds.py", "replay"], f"{RUN}/config.yaml: not UTF-8 text (byte 0xe9 at offset 24)"),
]  # fmt: skip
# The same contract for bad command lines, on an empty folder: no run directory may appear. One case per
# stage a command line passes: flags, the task's env, building the models (after the run directory
# would have been made); every config error is on the in-process list above.
FRESH: list[tuple[str, list[str], str]] = [
    ("a bad flag", ["main.py", "--agents", "0"], "argument --agents: '0' is not a positive integer"),
    ("an env that cannot be made", ["main_ds.py", "replay", "--override", "base.build_path=NoSuchEnv-v0"],
     "base_config.build_path 'NoSuchEnv-v0'"),
    ("models that cannot be built", ["main.py", "--override", "nn.critic_only=[nope]"],
     "critic_only names unknown sensors ['nope']"),
]  # fmt: skip


@pytest.fixture(scope="module")
def processes(
    trained: Path, tmp_path_factory: pytest.TempPathFactory
) -> dict[str, tuple[Path, int, str, dict[str, str]]]:
    """Every case in its own folder (a copy of the damaged run, or empty), all processes started at
    once: ``{case: (folder, exit code, stderr, the run's files before)}``."""
    started = {}
    for name, damage, command, _ in DAMAGED_RUNS:
        folder = tmp_path_factory.mktemp("damaged")
        shutil.copytree(trained / "models", folder / "models")
        damage(folder / RUN)
        before = tree_digest(folder / "models")
        argv = [sys.executable, str(ROOT / command[0]), *PENDULUM_ARGS, *command[1:], "-n", "run"]
        process = subprocess.Popen(argv, cwd=folder, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        started[name] = (folder, process, before)
    for name, command, _ in FRESH:
        folder = tmp_path_factory.mktemp("fresh")
        argv = [sys.executable, str(ROOT / command[0]), *PENDULUM_ARGS, *command[1:]]
        process = subprocess.Popen(argv, cwd=folder, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        started[name] = (folder, process, {})
    finished = {}
    for name, (folder, process, before) in started.items():
        _, stderr = process.communicate(timeout=300)
        finished[name] = (folder, process.returncode, stderr, before)
    return finished


@pytest.mark.slow  # the processes fixture: ~15 processes of ~2 s CPU each, started side by side
@pytest.mark.parametrize("case, named", [(c[0], c[3]) for c in DAMAGED_RUNS], ids=[c[0] for c in DAMAGED_RUNS])
def test_a_damaged_run_is_refused_naming_the_file_and_left_as_it_was(
    processes: dict[str, tuple[Path, int, str, dict[str, str]]], case: str, named: str
) -> None:
    folder, returncode, stderr, before = processes[case]
    assert returncode == 2, stderr
    errors = [line for line in stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and all(part in errors[0] for part in named.split(" ... ")), stderr
    assert "Traceback" not in stderr
    assert tree_digest(folder / "models") == before  # nothing overwritten, deleted or added


@pytest.mark.slow
@pytest.mark.parametrize("case, named", [(c[0], c[2]) for c in FRESH], ids=[c[0] for c in FRESH])
def test_a_bad_command_line_is_one_line_exit_2_and_creates_nothing(
    processes: dict[str, tuple[Path, int, str, dict[str, str]]], case: str, named: str
) -> None:
    folder, returncode, stderr, _ = processes[case]
    assert returncode == 2, stderr
    assert stderr.strip().splitlines() == [stderr.strip()] and named in stderr, stderr  # one line, no traceback
    assert not any(folder.iterdir()), "something was created"


@pytest.mark.parametrize("case", DAMAGED_CONFIGS, ids=[c[0] for c in DAMAGED_CONFIGS])
def test_a_run_with_a_damaged_config_is_refused_naming_it_and_left_as_it_was(
    trained: Path, in_tmp: Path, capsys: pytest.CaptureFixture[str], case: tuple[Any, ...]
) -> None:
    _, damage, command, named = case
    shutil.copytree(trained / "models", in_tmp / "models")
    damage(in_tmp / RUN)
    before = tree_digest(in_tmp / "models")
    entry = main.main if command[0] == "main.py" else main_ds.main
    code, stderr = call(entry, [*PENDULUM_ARGS, *command[1:], "-n", "run"], capsys)
    lines = stderr.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and named in lines[0], stderr
    assert tree_digest(in_tmp / "models") == before
