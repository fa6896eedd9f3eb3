"""bench/eval_modes.py on a real run folder: a CartPole run trained briefly by main.py with a checkpoint
every 1,000 env steps, each checkpoint scored by its mode and by sampling, and the table read back."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EPISODES = 4


def test_every_checkpoint_gets_both_returns_and_its_mode_episodes_endings(tmp_path: Path) -> None:
    train = [sys.executable, str(ROOT / "main.py"), "gym/cartpole", "-n", "modes", "--no_progress",
             "--override", "base.max_step=2000", "--override", "replay.min_size_to_sample=200",
             "--override", "sac.save_model_per_step=1000", "--override", "sac.keep_checkpoints=5"]  # fmt: skip
    assert subprocess.run(train, cwd=tmp_path, capture_output=True, timeout=300).returncode == 0
    run = tmp_path / "models/gym/cartpole/modes"
    done = subprocess.run([sys.executable, "-m", "bench.eval_modes", str(run), "--episodes", str(EPISODES)],
                          cwd=ROOT, text=True, capture_output=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    header, *rows = done.stdout.splitlines()
    assert header == "step,mode_return,sampled_return,time_limit,cart_edge,pole,other"
    assert [row.split(",")[0] for row in rows] == ["1000", "2000"]
    for row in rows:
        mode, sampled = map(float, row.split(",")[1:3])
        ends = list(map(int, row.split(",")[3:]))
        assert 1 <= mode <= 500 and 1 <= sampled <= 500
        assert sum(ends) == EPISODES
        # The endings are counted on the mode's own episodes (same start states): every one at the time
        # limit is a return of 500, and a mean below 500 has at least one that fell.
        assert (ends[0] == EPISODES) == (mode == 500.0)
