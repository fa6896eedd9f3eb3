"""bench/saturation.py on a real run folder: a Pendulum run trained briefly by main.py, probed along one
deterministic episode (Pendulum's time limit: 200 steps), and its numbers read back."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

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
