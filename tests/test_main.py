"""The single-process CLI as a user runs it: a real subprocess per command."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

ROOT = Path(__file__).resolve().parents[1]
TINY_OVERRIDES = [
    "sac.seed=3",
    "replay.samples_per_insert=null",
    "nn.hidden_units=[16,16]",
    "replay.batch_size=16",
    "replay.min_size_to_sample=64",
    "base.max_step=250",
    "eval.eval_per_step=0",
    "eval.eval_episodes=2",
    "eval.eval_envs=2",
]
TINY = [arg for override in TINY_OVERRIDES for arg in ("--override", override)] + ["--no_progress"]


def run_main(
    *args: str, cwd: Path, timeout: float = 180, env_changes: dict[str, str | None] | None = None
) -> subprocess.CompletedProcess[str]:
    """``main.py ARGS`` without a display; ``env_changes`` sets (or, with None, removes) variables."""
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1", "MUJOCO_GL": "egl"}
    env.pop("DISPLAY", None)
    for key, value in (env_changes or {}).items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    return subprocess.run(
        [sys.executable, str(ROOT / "main.py"), *args],
        cwd=cwd,
        env=env,
        text=True,
        capture_output=True,
        timeout=timeout,
    )


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cwd = tmp_path_factory.mktemp("cli")
    done = run_main("gym/pendulum", "-n", "tiny", *TINY, cwd=cwd)
    assert done.returncode == 0, done.stderr
    return cwd


def test_training_writes_the_run_directory(trained: Path) -> None:
    run = trained / "models/gym/pendulum/tiny"
    assert (run / "config.yaml").is_file()
    assert (run / "model/250.pt").is_file()
    assert any((run / "log").iterdir())


def test_run_plays_the_checkpoint_and_reports_a_return(trained: Path) -> None:
    done = run_main("gym/pendulum", "-n", "tiny", "--run", "--episodes", "2", cwd=trained)
    assert done.returncode == 0, done.stderr
    assert "checkpoint 250: return" in done.stdout and "over 2 episodes" in done.stdout


def test_run_render_headless_writes_a_video(trained: Path) -> None:
    done = run_main(
        "gym/pendulum",
        "-n",
        "tiny",
        "--run",
        "--render",
        "--episodes",
        "1",
        "--override",
        "base.max_step_each_iter=20",
        cwd=trained,
    )
    assert done.returncode == 0, done.stderr
    video = trained / "models/gym/pendulum/tiny/play_250.mp4"
    assert video.is_file() and video.stat().st_size > 1000
    import imageio.v2 as imageio

    reader = imageio.get_reader(video)
    assert reader.get_data(0).shape == (500, 500, 3)  # Pendulum's frames as rendered, not rescaled
    reader.close()
    output = done.stdout + done.stderr  # no display and no sound card: nothing to complain about
    assert "XDG_RUNTIME_DIR" not in output and "ALSA" not in output and "WARNING" not in output, output


def test_render_of_a_mujoco_task_needs_no_setting_and_a_broken_renderer_is_one_line(tmp_path: Path) -> None:
    tiny = ["--override", "actor.random_steps=64", "--override", "base.max_step_each_iter=30"]
    done = run_main("mujoco/inverted_pendulum", "-n", "tiny", *TINY, *tiny, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    play = ["mujoco/inverted_pendulum", "-n", "tiny", "--run", "--render", "--episodes", "1"]

    shown = run_main(*play, cwd=tmp_path, env_changes={"MUJOCO_GL": None})  # a user's shell sets nothing
    assert shown.returncode == 0, shown.stderr
    assert (tmp_path / "models/mujoco/inverted_pendulum/tiny/play_250.mp4").stat().st_size > 1000
    assert "OpenGL" not in shown.stdout + shown.stderr, shown.stderr  # no INFO line from PyOpenGL

    broken = run_main(*play, cwd=tmp_path, env_changes={"MUJOCO_GL": "no-such-backend"})
    assert broken.returncode == 2, broken.stderr
    assert "Traceback" not in broken.stderr
    assert "--render: no display" in broken.stderr and "'no-such-backend'" in broken.stderr, broken.stderr
    assert "play without --render" in broken.stderr


def test_same_name_resumes(trained: Path) -> None:
    done = run_main("gym/pendulum", "-n", "tiny", *TINY, "--override", "base.max_step=300", cwd=trained)
    assert done.returncode == 0, done.stderr
    assert "resumed at 250 env steps" in done.stderr
    assert (trained / "models/gym/pendulum/tiny/model/300.pt").is_file()


def test_random_params_are_drawn_once_per_new_run_from_its_seed_and_kept_on_resume(tmp_path: Path) -> None:
    # Issue 15, defect 4: main.py ignored random_params, which the original drew for every
    # standalone run. Drawn from the run's seed (same seed, same draw), recorded in config.yaml.
    draws = ["--override", "random_params.sac_config={tau: {truncated: [0.001, 0.01]}, n_step: {in: [1, 2, 3, 4, 5]}}"]
    said = {}
    for name in ("a", "b"):
        done = run_main("gym/pendulum", "-n", name, *TINY, *draws, cwd=tmp_path)
        assert done.returncode == 0, done.stderr
        said[name] = next(line.split("random_params drew ")[1] for line in done.stderr.splitlines()
                          if "random_params drew " in line)  # fmt: skip
        saved = yaml.safe_load((tmp_path / f"models/gym/pendulum/{name}/config.yaml").read_text())
        assert saved["random_params"] in ({}, None)
        tau, n_step = saved["sac_config"]["tau"], saved["sac_config"]["n_step"]
        assert 0.001 <= tau <= 0.01 and tau != 0.005 and n_step in range(1, 6)
        assert f"sac_config.tau={tau!r}" in said[name] and f"sac_config.n_step={n_step!r}" in said[name]
    assert said["a"] == said["b"]  # both runs have seed 3
    before = (tmp_path / "models/gym/pendulum/a/config.yaml").read_text()
    done = run_main("gym/pendulum", "-n", "a", *TINY, *draws, "--override", "base.max_step=300", cwd=tmp_path)
    assert done.returncode == 0 and "resumed at 250 env steps" in done.stderr, done.stderr
    assert "random_params drew" not in done.stderr  # a resume runs with the values it drew
    after = (tmp_path / "models/gym/pendulum/a/config.yaml").read_text()
    assert yaml.safe_load(after)["sac_config"]["tau"] == yaml.safe_load(before)["sac_config"]["tau"]


def test_a_drawn_batch_size_sets_the_length_of_a_run_long_step_size_schedule(tmp_path: Path) -> None:
    # A schedule left at null spans the run's updates (updates per env step x env steps past the warm-up);
    # a drawn batch size changes the updates per env step, so the run anneals over its drawn length:
    # 64 samples per insert / batch 32 = 2 per step, over 250 - 64 steps (not 4 per step, batch 16's).
    draws = ["--override", "replay.samples_per_insert=64", "--override", "sac.learning_rate_final=0.0",
             "--override", "random_params.replay_config={batch_size: {in: [32]}}"]  # fmt: skip
    done = run_main("gym/pendulum", "-n", "drawn", *TINY, *draws, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    saved = yaml.safe_load((tmp_path / "models/gym/pendulum/drawn/config.yaml").read_text())
    assert saved["replay_config"]["batch_size"] == 32
    assert saved["sac_config"]["learning_rate_anneal_updates"] == 2 * (250 - 64)


def test_bad_task_name_is_a_clear_error(tmp_path: Path) -> None:
    done = run_main("gym/pendlum", cwd=tmp_path)
    assert done.returncode == 2
    assert "unknown task 'gym/pendlum'" in done.stderr and "gym/pendulum" in done.stderr
    assert "Traceback" not in done.stderr


def test_bad_override_is_a_clear_error(tmp_path: Path) -> None:
    done = run_main("gym/pendulum", "--override", "sac.gama=0.5", cwd=tmp_path)
    assert done.returncode == 2
    assert "sac_config.gama" in done.stderr and "did you mean 'gamma'" in done.stderr


def test_bad_checkpoint_is_a_clear_error(trained: Path) -> None:
    bad = trained / "models/gym/pendulum/tiny/model/999.pt"
    bad.write_bytes(b"this is not a checkpoint")
    try:
        done = run_main("gym/pendulum", "-n", "tiny", "--run", "--ckpt", "999", cwd=trained)
    finally:
        bad.unlink()
    assert done.returncode == 2
    assert "999.pt" in done.stderr and "not an ASAC checkpoint" in done.stderr
    assert "Traceback" not in done.stderr


def test_missing_checkpoint_step_lists_available(trained: Path) -> None:
    done = run_main("gym/pendulum", "-n", "tiny", "--run", "--ckpt", "12345", cwd=trained)
    assert done.returncode == 2
    assert "no checkpoint for step 12345" in done.stderr


def test_run_without_training_is_a_clear_error(tmp_path: Path) -> None:
    done = run_main("gym/pendulum", "--run", cwd=tmp_path)
    assert done.returncode == 2
    assert "no trained runs" in done.stderr


@pytest.mark.fault
def test_sigint_saves_and_says_how_to_resume_a_run_named_by_its_start_time(tmp_path: Path) -> None:
    """The default name is the start time ('{time}'), so the same command would start another run:
    the interrupted run names the command that resumes it, and that command does (a run with a fixed
    name says 'the same command resumes': tests/test_journeys.py)."""
    import re
    import signal
    import time

    args = [sys.executable, str(ROOT / "main.py"), "gym/pendulum", *TINY, "--override", "base.max_step=-1",
            "--override", "replay.save_replay=true"]  # fmt: skip
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(args, cwd=tmp_path, env=env, text=True, stderr=subprocess.PIPE)
    runs = tmp_path / "models/gym/pendulum"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not any(d.is_dir() and any(d.iterdir()) for d in runs.glob("*/log")):
        time.sleep(0.2)
    time.sleep(3)  # let it train for a while
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    said = re.search(r"saved; resume it with: \S+ \S*main\.py gym/pendulum -n (\d{14})$", stderr, re.M)
    assert said is not None, stderr
    name = said.group(1)
    assert [d.name for d in runs.iterdir()] == [name]
    model = runs / name / "model"
    steps = [int(p.stem) for p in model.glob("*.pt")]
    assert steps and max(steps) > 0
    assert (runs / name / "replay/replay.npz").is_file()

    done = run_main("gym/pendulum", "-n", name, *TINY, "--override", f"base.max_step={max(steps) + 50}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert f"resumed at {max(steps)} env steps" in done.stderr
    assert (model / f"{max(steps) + 50}.pt").is_file()


def test_a_task_model_file_is_copied_into_the_run_and_used_by_run(tmp_path: Path) -> None:
    source = ROOT / "envs/gym/pendulum/nn_layernorm.py"
    result = run_main("gym/pendulum", "--nn", "nn_layernorm", "-n", "custom", "--model_root", str(tmp_path),
                      "--no_progress", "--override", "base.max_step=300", "--override", "eval.eval_per_step=0",
                      "--override", "replay.min_size_to_sample=100", cwd=tmp_path)  # fmt: skip
    assert result.returncode == 0, result.stderr
    run_dir = tmp_path / "gym/pendulum/custom"
    assert (run_dir / "nn.py").read_text() == source.read_text()
    ckpt = sorted((run_dir / "model").glob("*.pt"))[-1]
    models = torch.load(ckpt, weights_only=True)["sac"]["models"]
    assert any(k.startswith("representation.net.") for k in models)  # the file's encoder was trained
    # --run builds from the run's copy: it keeps working when the task's file is gone or changed
    (run_dir / "nn.py").write_text((run_dir / "nn.py").read_text() + "\n# edited after training\n")
    played = run_main("gym/pendulum", "--run", "-n", "custom", "--model_root", str(tmp_path), "--episodes", "2",
                      cwd=tmp_path)  # fmt: skip
    assert played.returncode == 0, played.stderr
    assert "return" in played.stdout


def test_a_missing_or_broken_model_file_is_a_clear_error(tmp_path: Path) -> None:
    result = run_main("gym/pendulum", "--nn", "no_such_file", "--model_root", str(tmp_path), cwd=tmp_path)
    assert result.returncode == 2 and "no_such_file" in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "gym").exists()  # nothing started
