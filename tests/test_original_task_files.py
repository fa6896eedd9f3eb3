"""Task folders as a user of the original ASAC brings them: ``config.yaml`` and ``config_ds.yaml``,
written here with the keys and values the original's gym and bullet files set (its walker and
cart_pole folders, of the era with a replay process), trained for a short budget and played through
``main.py`` and through ``main_ds.py TASK local`` on real processes, as they are.

What each key became is tests/algorithm/config/test_original.py's; here: the files load and train in both
modes, ``main_ds.py`` reads ``config_ds.yaml`` and ``main.py`` ``config.yaml``, the bullet id runs as
its MuJoCo counterpart, the file's hosts (every original ``config_ds.yaml`` names an evolver) do not
keep ``local`` waiting, and what differs from the original is said in WARNING lines, once per run.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from tests.role_runs import ENV, main_ds_command
from tests.test_main import ROOT, run_main

# The original's walker folder: config.yaml for main.py, config_ds.yaml for its distributed roles.
WALKER = {
    "default": {
        "base_config": {"env_type": "GYM", "scene": "Walker2D", "build_path": "Walker2DBulletEnv-v0", "max_iter": -1,
                        "max_step": 1000000, "n_agents": 10},
        "sac_config": {"write_summary_per_step": 100, "save_model_per_step": 10000, "save_model_per_minute": 5,
                       "n_step": 5, "v_lambda": 0.99, "use_normalization": True},
    },
}  # fmt: skip
WALKER_DS = {
    "default": {
        "base_config": {"env_type": "GYM", "scene": "Walker2D", "build_path": "Walker2DBulletEnv-v0",
                        "update_policy_variables_per_step": 20, "noise_increasing_rate": 0.01, "n_agents": 10,
                        "evolver_cem_time": 8, "evolver_enabled": False},
        "net_config": {"evolver_host": "walker-ds-evolver"},
        "sac_config": {"write_summary_per_step": 100, "save_model_per_step": 10000, "save_model_per_minute": 20,
                       "n_step": 5, "v_lambda": 0.9},
        "replay_config": {"batch_size": 16},
    },
}  # fmt: skip
# The original's cart_pole folder (gym; it has no config_ds.yaml: main_ds.py reads config.yaml too).
CART_POLE = {
    "default": {
        "base_config": {"env_type": "GYM", "scene": "CartPole", "build_path": "CartPole-v1", "max_step": -1,
                        "max_iter": 1000, "n_agents": 10},
        "replay_config": {"batch_size": 128, "capacity": 100000, "alpha": 0.0, "beta_increment_per_sampling": 0},
        "sac_config": {"save_model_per_step": 1000, "save_model_per_minute": 1, "n_step": 3, "clip_epsilon": -1,
                       "use_n_step_is": True},
    },
}  # fmt: skip
FOLDERS = {"walker": {"config.yaml": WALKER, "config_ds.yaml": WALKER_DS}, "cart_pole": {"config.yaml": CART_POLE}}
# A short budget; the file's own values otherwise (its batch sizes are what tell the two files apart).
SHORT = ["base.max_step=400", "replay.min_size_to_sample=100", "eval.eval_per_step=0", "nn.hidden_units=[16]",
         "actor.chunk_length=16", "eval.eval_episodes=1", "eval.eval_envs=1"]  # fmt: skip
HANG_S = 300  # a guard, not a timing: each run takes 20-60 s on 2 cores


@pytest.fixture
def originals() -> Iterator[str]:
    """A folder under the checkout's envs/ (where tasks are looked up) holding the original's task
    folders, removed afterwards; yields its name."""
    folder = ROOT / "envs" / f"_test_original_{uuid.uuid4().hex[:8]}"
    for name, files in FOLDERS.items():
        (folder / name).mkdir(parents=True)
        for file, content in files.items():
            (folder / name / file).write_text(yaml.safe_dump(content, sort_keys=False))
    try:
        yield folder.name
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def overrides() -> list[str]:
    return [arg for override in SHORT for arg in ("--override", override)] + ["--no_progress"]


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["main", "local"])
@pytest.mark.parametrize("name", sorted(FOLDERS))
def test_the_originals_task_files_train_and_play_as_they_are(originals: str, name: str, mode: str,
                                                              tmp_path: Path) -> None:  # fmt: skip
    task = f"{originals}/{name}"
    args = [task, *(["local", "--actors", "1"] if mode == "local" else []), "-n", "moved", "--model_root",
            str(tmp_path), *overrides()]  # fmt: skip
    if mode == "local":
        done = subprocess.run(main_ds_command(*args), cwd=tmp_path, env=ENV, text=True, capture_output=True,
                              timeout=HANG_S)  # fmt: skip
    else:
        done = run_main(*args, cwd=tmp_path, timeout=HANG_S)
    out = done.stdout + done.stderr
    assert done.returncode == 0, out[-5000:]
    run = tmp_path / task / "moved"
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert sorted(run.glob("model/*.pt")), out[-5000:]
    warnings = re.findall(r"^\S+ \S+ \S+ WARNING (.*)$", out, re.M)
    assert len(warnings) == len(set(warnings)), warnings  # each said once, not once per role process
    assert any("is read as the original's" in w for w in warnings), warnings
    if name == "walker":  # main.py reads config.yaml, main_ds.py config_ds.yaml
        assert saved["replay_config"]["batch_size"] == (16 if mode == "local" else 256), saved["replay_config"]
        assert saved["base_config"]["build_path"] == "Walker2d-v5"
        assert any("Walker2DBulletEnv-v0" in w and "Walker2d-v5" in w for w in warnings), warnings
    else:  # the original's meanings: -1 turns the clip off, V-trace as the file says
        assert saved["replay_config"]["batch_size"] == 128 and saved["sac_config"]["clip_epsilon"] is None
        assert saved["sac_config"]["use_n_step_is"] is True
    if mode == "local" and name == "walker":
        assert any("net_config.evolver_host: walker-ds-evolver" in w for w in warnings), warnings
        assert "waiting for evolver" not in out
        assert (run / "token").is_file()
    played = run_main(task, "--run", "-n", "moved", "--model_root", str(tmp_path), "--episodes", "1", cwd=tmp_path)
    assert played.returncode == 0 and "return" in played.stdout, played.stderr[-3000:]
