"""README "Your own environment": a gymnasium env in the user's own package, a task folder outside the
checkout with a model file beside its config.yaml, trained and played through both launchers as a new
user runs them (real processes, from the user's own working directory)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from algorithm.run.evaluation import read_evaluations
from tests.role_runs import ENV

ROOT = Path(__file__).resolve().parents[1]


def readme_block(language: str) -> str:
    """The first ``language`` code block of README.md's "Your own environment": the test runs what a
    user copies from there."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Your own environment") :]
    return section.split(f"```{language}\n", 1)[1].split("```", 1)[0]


ENV_MODULE = readme_block("python")
MODEL_FILE = """
import torch
from torch import nn

from algorithm.nn.models import Representation


class Tanh(Representation):
    def __init__(self, spec):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(1, 16), nn.Tanh())
        self.state_dim = self.policy_state_dim = 16

    def forward(self, obs):
        return self.net(torch.cat(obs, dim=-1))


def build_representation(spec, nn_config):
    return Tanh(spec)
"""

CONFIG = yaml.safe_load(readme_block("yaml"))
# a short run of the README's task: its config, these overrides, and a model file of its own
SHORT = ["base.max_step=1200", "replay.min_size_to_sample=200", "replay.capacity=10000", "nn.hidden_units=[32,32]",
         "eval.eval_per_step=600", "eval.eval_episodes=2", "eval.eval_envs=1", "sac.seed=0"]  # fmt: skip
OVERRIDES = [a for o in SHORT for a in ("--override", o)] + ["--nn", "my_nn"]


def _project(tmp_path: Path) -> Path:
    """The user's project: their package (``mypkg/envs.py``) and a task folder (``tasks/reach``)."""
    project = tmp_path / "project"
    (project / "mypkg").mkdir(parents=True)
    (project / "mypkg" / "__init__.py").write_text("")
    (project / "mypkg" / "envs.py").write_text(ENV_MODULE)
    task = project / "tasks" / "reach"
    task.mkdir(parents=True)
    (task / "config.yaml").write_text(yaml.safe_dump(CONFIG))
    (task / "my_nn.py").write_text(MODEL_FILE)
    return project


def _run(cwd: Path, *argv: str) -> str:
    done = subprocess.run([sys.executable, *argv, "--no_progress"], cwd=cwd, env=ENV, text=True,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stdout[-4000:]
    return done.stdout


@pytest.mark.slow
@pytest.mark.grpc
def test_a_task_folder_of_ones_own_trains_and_plays_through_both_launchers(tmp_path: Path) -> None:
    project = _project(tmp_path)
    _run(project, str(ROOT / "main.py"), "tasks/reach", "-n", "first", *OVERRIDES)
    run = project / "models" / "reach" / "first"
    assert (run / "nn.py").read_text() == MODEL_FILE  # the model file beside config.yaml went with the run
    assert yaml.safe_load((run / "config.yaml").read_text())["base_config"]["build_path"] == "mypkg.envs:MyReach-v0"
    curve = read_evaluations(run / "evaluations.csv")
    assert [row["env_steps"] for row in curve][-1] == 1200
    assert all(-400.0 <= row["return_mean"] <= 0.0 for row in curve), curve  # 200 steps of -|x|, |x| <= 2

    played = _run(project, str(ROOT / "main.py"), "tasks/reach", "-n", "first", "--run", "--episodes", "1")
    assert "return" in played, played

    # the same folder by its absolute path, from elsewhere, in the distributed launcher
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "mypkg").symlink_to(project / "mypkg")  # the package importable from the working directory
    out = _run(elsewhere, str(ROOT / "main_ds.py"), str(project / "tasks" / "reach"), "local", "--actors", "1",
               "-n", "dist", *OVERRIDES)  # fmt: skip
    run = elsewhere / "models" / "reach" / "dist"
    assert (run / "nn.py").read_text() == MODEL_FILE, out[-4000:]
    assert [row["env_steps"] for row in read_evaluations(run / "evaluations.csv")][-1] >= 1200, out[-4000:]


def test_a_module_beside_config_yaml_is_importable_and_a_folder_without_one_is_refused(tmp_path: Path) -> None:
    """The env module may live in the task folder itself; a folder holding no config.yaml is one line,
    exit 2, naming the folder and what to give instead, and creates nothing."""
    task = tmp_path / "mytask"
    (task / "mypkg").mkdir(parents=True)
    (task / "mypkg" / "__init__.py").write_text("")
    (task / "mypkg" / "envs.py").write_text(ENV_MODULE)
    base = {**CONFIG["default"]["base_config"], "max_step": 300, "nn": "my_nn"}
    config = {"default": {**CONFIG["default"], "base_config": base}}
    config["default"]["replay_config"] = {"min_size_to_sample": 100, "capacity": 1000}
    config["default"]["eval_config"] = {"eval_per_step": 300, "eval_episodes": 1, "eval_envs": 1}
    (task / "config.yaml").write_text(yaml.safe_dump(config))
    (task / "my_nn.py").write_text(MODEL_FILE)
    _run(tmp_path, str(ROOT / "main.py"), str(task), "-n", "beside")
    assert read_evaluations(tmp_path / "models" / "mytask" / "beside" / "evaluations.csv")
    assert (tmp_path / "models" / "mytask" / "beside" / "nn.py").read_text() == MODEL_FILE

    empty = tmp_path / "notask"
    empty.mkdir()
    done = subprocess.run([sys.executable, str(ROOT / "main.py"), str(empty)], cwd=tmp_path, env=ENV, text=True,
                          capture_output=True, timeout=120)  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert f"the folder {empty} holds no config.yaml" in done.stderr and "own task folder" in done.stderr
    assert not (tmp_path / "models" / "notask").exists()

    (task / "config.yaml").write_text(yaml.safe_dump(config).replace("mypkg.envs:", "mypkg.nowhere:"))
    done = subprocess.run([sys.executable, str(ROOT / "main.py"), str(task), "-n", "typo"], cwd=tmp_path, env=ENV,
                          text=True, capture_output=True, timeout=120)  # fmt: skip
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert "cannot import 'mypkg.nowhere' for 'mypkg.nowhere:MyReach-v0'" in done.stderr, done.stderr
    assert not (tmp_path / "models" / "mytask" / "typo").exists()
