"""bench/eval_modes.py on a real run folder: a CartPole run trained briefly by main.py with a checkpoint
every 1,000 env steps, each checkpoint scored by its mode and by sampling, the critic read along the
mode's failed episodes, and the tables read back."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EPISODES = 4


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cwd = tmp_path_factory.mktemp("eval_modes")
    train = [sys.executable, str(ROOT / "main.py"), "gym/cartpole", "-n", "modes", "--no_progress",
             "--override", "base.max_step=2000", "--override", "sac.seed=0",
             "--override", "sac.save_model_per_step=1000", "--override", "sac.keep_checkpoints=5"]  # fmt: skip
    # updates start at 1,000 steps (the config's min_size_to_sample): checkpoint 1000 holds the untrained
    # policy, whose mode episodes fail within a few dozen steps, and checkpoint 2000 ~1,000 updates
    assert subprocess.run(train, cwd=cwd, capture_output=True, timeout=300).returncode == 0
    return cwd / "models/gym/cartpole/modes"


def eval_modes(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "bench.eval_modes", *args, "--episodes", str(EPISODES)],
                          cwd=ROOT, text=True, capture_output=True, timeout=300)  # fmt: skip


def scored_in_process(run: Path, step: int, seed: int = 12345) -> tuple[float, float]:
    from algorithm.config.load import config_from_file
    from algorithm.run.evaluation import evaluate
    from algorithm.run.folder import RunDir
    from bench.eval_modes import checkpoint_policy

    paths = RunDir(run)
    env, policy = checkpoint_policy(paths, config_from_file(paths.config), step, seed)
    mode = evaluate(env, policy, EPISODES, seed).mean
    return mode, evaluate(env, policy, EPISODES, seed, deterministic=False).mean


def test_every_checkpoint_gets_both_returns_and_its_mode_episodes_endings(run: Path) -> None:
    done = eval_modes(str(run))
    assert done.returncode == 0, done.stderr
    header, *rows = done.stdout.splitlines()
    assert header == "step,mode_return,sampled_return,time_limit,cart_edge,pole,other"
    assert [row.split(",")[0] for row in rows] == ["1000", "2000"]
    for row in rows:
        step, mode, sampled = int(row.split(",")[0]), *map(float, row.split(",")[1:3])
        ends = list(map(int, row.split(",")[3:]))
        # each row is its own checkpoint scored both ways from the same start states
        assert (mode, sampled) == pytest.approx(scored_in_process(run, step), abs=0.051)
        assert sum(ends) == EPISODES
        # The endings are counted on the mode's own episodes (same start states): every one at the time
        # limit is a return of 500, and a mean below 500 has at least one that fell.
        assert (ends[0] == EPISODES) == (mode == 500.0)


def test_the_critic_is_read_along_the_failed_episodes_against_the_steps_left(run: Path) -> None:
    done = eval_modes(str(run), "--critic", "1000")
    assert done.returncode == 0, done.stderr
    header, *rows = [line for line in done.stdout.splitlines() if not line.startswith("#")]
    assert header == "episode,ending,length,steps_before_end,q_chosen,discounted_steps_left,x"
    assert rows, "the untrained policy balances the pole: no mode episode failed"
    for row in rows:
        episode, ending, length, k, q, left, x = row.split(",")
        assert ending in ("cart edge", "pole") and 0 <= int(episode) < EPISODES
        assert int(k) <= int(length) < 500
        assert float(left) == pytest.approx((1 - 0.99 ** int(k)) / (1 - 0.99), abs=0.05)  # gym/cartpole's gamma
        assert abs(float(x)) <= 2.4
    follows = [line for line in done.stdout.splitlines() if line.startswith("# the mode is the action")]
    assert len(follows) == 1
    share = float(follows[0].split(" on ")[1].split(" of ")[0])
    assert 0.0 <= share <= 1.0


def test_a_missing_checkpoint_is_named(run: Path) -> None:
    done = eval_modes(str(run), "--critic", "1500")
    assert done.returncode != 0
    assert "--critic 1500: no such checkpoint" in done.stderr and "[1000, 2000]" in done.stderr


def test_a_folder_that_is_not_a_run_is_named(tmp_path: Path) -> None:
    done = eval_modes(str(tmp_path), "--critic-greedy")
    assert done.returncode != 0 and "Traceback" not in done.stderr
    assert f"{tmp_path}: not a run folder" in done.stderr and "config.yaml" in done.stderr


def test_bench_tasks_scores_the_runs_last_checkpoint_over_its_final_episodes(run: Path) -> None:
    """bench.tasks' final column: the last checkpoint (2000, not the untrained 1000) on its own episodes."""
    from bench.tasks import final_return

    first, _ = scored_in_process(run, 1000, seed=777)
    last, _ = scored_in_process(run, 2000, seed=777)
    assert first != pytest.approx(last, abs=1.0)  # the test can tell the checkpoints apart
    assert final_return(run, EPISODES, 777) == pytest.approx(last)


def test_steps_scores_only_the_checkpoints_asked_for_and_refuses_one_the_run_lacks(run: Path) -> None:
    done = eval_modes(str(run), "--steps", "2000")
    assert done.returncode == 0, done.stderr
    assert [row.split(",")[0] for row in done.stdout.splitlines()[1:]] == ["2000"]
    missing = eval_modes(str(run), "--steps", "1500")
    assert missing.returncode != 0 and "--steps [1500]: no such checkpoint" in missing.stderr


def test_critic_greedy_acts_by_the_critics_lower_value_and_adds_its_column(run: Path) -> None:
    import numpy as np
    import torch

    from algorithm.config.load import config_from_file
    from algorithm.run.evaluation import evaluate
    from algorithm.run.folder import RunDir
    from bench.eval_modes import CriticGreedy, checkpoint_policy

    paths = RunDir(run)
    env, policy = checkpoint_policy(paths, config_from_file(paths.config), 2000, 0)
    greedy = CriticGreedy(policy)
    obs, rng, min_and_max_differ = env.reset(seed=0), np.random.default_rng(0), 0
    for _ in range(300):  # states of a random walk: the critic's pick is the argmax of its heads' lower value
        with torch.no_grad():
            q = policy.models.q(policy.models.representation(policy.obs_tensors(obs)), None).numpy()[:, 0]
        actions, _ = greedy.act(obs)
        assert actions.tolist() == [np.eye(2)[int(np.argmax(q.min(axis=0)))].tolist()]
        min_and_max_differ += int(np.argmax(q.min(axis=0)) != np.argmax(q.max(axis=0)))
        obs = env.step(np.eye(2, dtype=np.float32)[rng.integers(2, size=1)]).obs
    assert min_and_max_differ > 0  # the states tell the lower value's pick from the higher one's
    done = eval_modes(str(run), "--steps", "1000", "2000", "--critic-greedy")
    assert done.returncode == 0, done.stderr
    header, *rows = done.stdout.splitlines()
    assert header.endswith(",critic_greedy_return")
    for row in rows:
        step, column = int(row.split(",")[0]), float(row.split(",")[-1])
        env, policy = checkpoint_policy(paths, config_from_file(paths.config), step, 12345)
        assert column == pytest.approx(evaluate(env, CriticGreedy(policy), EPISODES, 12345).mean, abs=0.051)  # type: ignore[arg-type]
