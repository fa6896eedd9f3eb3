"""bench/saturation.py on a real run folder: a Pendulum run trained briefly by main.py, probed along one
deterministic episode (Pendulum's time limit: 200 steps), and its numbers read back."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def test_the_probe_reports_the_pre_tanh_spread_of_a_trained_run(tmp_path: Path) -> None:
    train = [sys.executable, str(ROOT / "main.py"), "gym/pendulum", "-n", "probe", "--no_progress",
             "--override", "base.max_step=300", "--override", "replay.min_size_to_sample=100"]  # fmt: skip
    assert subprocess.run(train, cwd=tmp_path, capture_output=True, timeout=300).returncode == 0
    run = tmp_path / "models/gym/pendulum/probe"
    done = subprocess.run([sys.executable, "-m", "bench.saturation", str(run)], cwd=ROOT, text=True,
                          capture_output=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    said = re.fullmatch(
        r".*probe \(300\): 200 steps, return -?\d+; \|mean u\| median ([\d.]+), p90 ([\d.]+), max ([\d.]+); "
        r"share > 4: ([\d.]+), > 6.5: ([\d.]+); std median ([\d.]+)\n",
        done.stdout,
    )
    assert said, done.stdout
    median, p90, top, over4, over_edge, std = map(float, said.groups())
    assert median <= p90 <= top and over_edge <= over4 <= 1 and std > 0


def test_an_sb3_model_the_suite_saved_is_probed_on_the_same_env(tmp_path: Path) -> None:
    pytest.importorskip("stable_baselines3")  # the optional peer (pip install -e '.[bench]')
    from stable_baselines3 import SAC as SB3SAC

    from bench.suite import sb3_model_path
    from bench.systems import run_sb3

    saved = sb3_model_path(tmp_path, "hopper", 0, 300)
    run_sb3("hopper", 0, 300, save_to=saved)  # inside the 10,000 random steps: an untrained policy
    assert saved.is_file()
    # Its means sit near 0, where the pre-tanh mean and the action agree: pushed to ~5 past the edge
    # (the action is then tanh(5) ~ 1), a probe that read the action instead would report under 1.
    model = SB3SAC.load(saved, device="cpu")
    with torch.no_grad():
        model.actor.mu.weight.zero_()
        model.actor.mu.bias.fill_(5.0)
    model.save(saved)
    done = subprocess.run([sys.executable, "-m", "bench.saturation", str(saved)], cwd=ROOT, text=True,
                          capture_output=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    said = re.fullmatch(
        r".*sb3_s0_0k\.zip \(SB3\): \d+ steps, return -?\d+; \|mean u\| median ([\d.]+), p90 [\d.]+, "
        r"max ([\d.]+); share > 4: ([\d.]+), .*\n",
        done.stdout,
    )
    assert said, done.stdout
    median, top, over4 = map(float, said.groups())
    assert median == pytest.approx(5.0, abs=1e-3) and top == pytest.approx(5.0, abs=1e-3) and over4 == 1.0


def test_a_model_outside_a_task_folder_is_refused_by_name(tmp_path: Path) -> None:
    stray = tmp_path / "elsewhere" / "model.zip"
    stray.parent.mkdir()
    stray.write_bytes(b"")
    done = subprocess.run([sys.executable, "-m", "bench.saturation", str(stray)], cwd=ROOT, text=True,
                          capture_output=True, timeout=300)  # fmt: skip
    assert done.returncode == 1
    assert f"{stray}: its folder names no task of" in done.stderr and "mujoco_suite/<task>/" in done.stderr
