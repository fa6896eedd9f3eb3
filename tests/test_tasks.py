"""Every task folder under envs/ resolves its config and trains a few steps with real envs."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from algorithm.config.load import load_config
from algorithm.run.evaluation import read_evaluations
from algorithm.run.trainer import EmbeddedTrainer
from envs.make import vector_env_factory
from tests.role_runs import ENV

ROOT = Path(__file__).resolve().parents[1]
TASKS = sorted(str(p.parent.relative_to(ROOT / "envs")) for p in (ROOT / "envs").glob("*/*/config.yaml"))
TINY = [
    "sac.seed=0",
    "nn.hidden_units=[8]",
    "replay.batch_size=8",
    "replay.samples_per_insert=null",
    "replay.capacity=1000",
    "replay.min_size_to_sample=20",
    "actor.random_steps=10",
    "actor.chunk_length=8",
    "base.max_step=40",
    "eval.eval_per_step=40",
    "eval.eval_episodes=1",
    "eval.eval_envs=1",
    "base.max_step_each_iter=15",
]


def sections(task: str) -> list[str | None]:
    """The task's config sections, ``None`` (the default) first."""
    named = yaml.safe_load((ROOT / "envs" / task / "config.yaml").read_text())
    return [None, *(k for k in named if k != "default")]


def test_the_documented_tasks_exist() -> None:
    expected = {
        "gym/pendulum",
        "gym/mountain_car",
        "mujoco/half_cheetah",
        "mujoco/hopper",
        "mujoco/walker2d",
        "mujoco/ant",
        "mujoco/humanoid",
        "mujoco/inverted_pendulum",
    }
    assert expected <= set(TASKS)


@pytest.mark.parametrize("task", TASKS)
def test_task_trains_a_few_steps(task: str, tmp_path: Path) -> None:
    for section in sections(task):
        config = load_config(ROOT / "envs" / task, section, TINY).config
        factory = vector_env_factory(config.base_config.build_path, max_episode_steps=15)
        trainer = EmbeddedTrainer(config, tmp_path / str(section), factory, progress=False)
        summary = trainer.run()
        assert summary.env_steps == 40 and summary.updates > 0
        assert summary.last_eval_mean is not None


@pytest.mark.parametrize("task", [t for t in TASKS if t.startswith("mujoco/")])
def test_mujoco_tasks_use_the_published_sac_setup(task: str) -> None:
    c = load_config(ROOT / "envs" / task).config
    assert c.nn_config.hidden_units == [256, 256]
    assert (c.replay_config.batch_size, c.sac_config.learning_rate, c.sac_config.gamma, c.sac_config.tau) == (
        256,
        3e-4,
        0.99,
        0.005,
    )
    assert c.sac_config.use_auto_alpha and c.replay_config.updates_per_step == 1.0
    assert c.replay_config.alpha == 0.0 and not c.sac_config.use_priority  # uniform replay


# (task, section) of every config section that anneals its step sizes (``sac.learning_rate_final``)
ANNEALING = [
    (task, section)
    for task in TASKS
    for section in sections(task)
    if load_config(ROOT / "envs" / task, section).config.sac_config.learning_rate_final is not None
]


def test_the_annealing_sections_are_found() -> None:
    """``gym/cartpole`` anneals to 0 over its run: the next test has at least that to check."""
    assert ("gym/cartpole", None) in ANNEALING


@pytest.mark.parametrize("task, section", ANNEALING)
def test_an_annealed_step_size_ends_with_its_run(task: str, section: str | None) -> None:
    """A section that anneals its step sizes anneals over its own run's updates, also when a user runs it
    longer or shorter: a shorter schedule leaves the rest of the run at the final step size (0: no
    learning), a longer one never gets there. ``gym/cartpole`` anneals to 0 over 30,000 env steps; a
    schedule of 58,000 updates written out in its config failed this with ``base.max_step=4000``."""
    own = load_config(ROOT / "envs" / task, section).config.base_config.max_step
    for max_step in (own, 4000, 2 * own):
        c = load_config(ROOT / "envs" / task, section, [f"base.max_step={max_step}"]).config
        updates = c.replay_config.updates_per_step * (max_step - c.replay_config.min_size_to_sample)
        assert c.sac_config.learning_rate_anneal_updates == updates, (task, section, max_step)


@pytest.mark.slow
@pytest.mark.grpc
def test_the_throughput_variant_trains_through_both_launchers(tmp_path: Path) -> None:
    """``-c throughput`` (README: for many actors) as a user runs it, on HalfCheetah with a small net:
    ``main_ds.py TASK local --actors 2 -c throughput`` finishes at its budget with each actor on 4 envs,
    the learner on batches of 1,024 with weights published by its 1% budget, every collected step
    stored; ``main.py TASK -c throughput`` trains the same section in one process."""
    small = ["nn.hidden_units=[16,16]", "replay.min_size_to_sample=1100", "base.max_step=1600",
             "eval.eval_per_step=800", "eval.eval_episodes=1", "eval.eval_envs=1", "sac.seed=0"]  # fmt: skip
    args = [a for o in small for a in ("--override", o)] + ["-c", "throughput", "--no_progress"]
    done = subprocess.run([sys.executable, str(ROOT / "main_ds.py"), "mujoco/half_cheetah", "local", "--actors", "2",
                           "-n", "wide", *args], cwd=tmp_path, env=ENV, text=True, stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, timeout=600)  # fmt: skip
    out = done.stdout
    assert done.returncode == 0, out[-4000:]
    assert len(re.findall(r"^\[actor-\d\] .*actor .*: index \d, noise .*, 4 envs$", out, re.M)) == 2, out[-4000:]
    collected = sum(int(n) for n in re.findall(r"^\[actor-\d\] .*actor \d finished after (\d+) env steps", out, re.M))
    ended = int(re.findall(r"^\[learner\] .*learner finished after (\d+) env steps", out, re.M)[0])
    assert ended == collected >= 1600, out[-4000:]
    run = tmp_path / "models/mujoco/half_cheetah/wide"
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved["replay_config"]["batch_size"] == 1024 and saved["base_config"]["n_agents"] == 4
    assert saved["sac_config"]["publish_budget"] == 0.01 and saved["sac_config"]["learning_rate"] == 1e-3
    assert read_evaluations(run / "evaluations.csv"), out[-4000:]

    done = subprocess.run([sys.executable, str(ROOT / "main.py"), "mujoco/half_cheetah", "-n", "one", *args],
                          cwd=tmp_path, env=ENV, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stdout[-4000:]
    one = tmp_path / "models/mujoco/half_cheetah/one"
    assert yaml.safe_load((one / "config.yaml").read_text())["replay_config"] == saved["replay_config"]
    last = read_evaluations(one / "evaluations.csv")[-1]
    assert last["env_steps"] >= 1600 and last["updates"] > 0, last
