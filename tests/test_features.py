"""docs/features.md's table (README: "Algorithm features") as a matrix: every row trains a short run through each
launcher, ``main.py`` (one process) and ``main_ds.py TASK local`` (replay, learner and an actor as
real processes, with the run's token), then plays it with ``main.py --run``.

A row is switched on by FEATURES below; a row added to docs/features.md without an entry here fails
test_every_documented_feature_has_a_matrix_entry. COMBINATIONS trains a few features together, the same ways.
Each test's failure message ends with the launcher's output."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from tests.role_runs import ENV, main_ds_command
from tests.test_main import run_main

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT_S = 240

# docs/features.md row -> (task, -c section or None, what switches the row's feature on). An item is a config
# override (SECTION.KEY=VALUE), or a launcher flag when it starts with "--" (passed as written).
FEATURES: dict[str, tuple[str, str | None, list[str]]] = {
    "Q ensemble": ("gym/pendulum", None, ["sac.ensemble_q_num=10", "sac.ensemble_q_sample=2"]),
    "n-step, V-trace": ("gym/pendulum", None, [
        "sac.n_step=3", "sac.use_n_step_is=true", "sac.v_lambda=0.9", "sac.v_rho=1.0", "sac.v_c=1.0",
    ]),
    # the task's default config: use_rnn, burn-in, train_every_step (R2D2); lstm and written-back states here
    "recurrent": ("gym/pendulum_novel", None, [
        "nn.rnn_type=lstm", "nn.rnn_units=8", "sac.burn_in_step=4", "sac.refresh_rnn_states=true",
    ]),
    "discrete / mixed actions": ("toy/mixed_target", None, ["sac.discrete_target_entropy_ratio=0.5"]),
    "action masks": ("toy/masked_grid", None, []),
    "dqn-like": ("gym/cartpole", "dqn", ["sac.discrete_dqn_like=true", "sac.discrete_dqn_epsilon=0.2"]),
    "images": ("toy/pixel_point", None, ["nn.conv_features=8"]),
    "asymmetric critic": ("toy/masked_grid", None, ["nn.critic_only=[position]"]),
    "prediction": ("gym/pendulum", None, ["sac.use_prediction=true", "sac.transition_kl=0.8"]),
    "curiosity": ("gym/mountain_car", "curiosity", ["sac.curiosity_inverse=true"]),
    "RND": ("gym/mountain_car", "rnd", [
        "sac.rnd_n_sample=8", "sac.rnd_choice_steps=100", "sac.rnd_strength=0.1", "sac.rnd_normalize=true",
    ]),
    "noisy layers": ("gym/pendulum", None, ["nn.noisy_q=true", "nn.noisy_policy=true", "nn.noisy_sigma0=0.5"]),
    "colored acting noise": ("gym/pendulum", None, ["sac.action_noise_color=1"]),
    "normalization": ("gym/pendulum", None, ["sac.use_normalization=true"]),
    "bfloat16": ("gym/pendulum", None, ["sac.compute_dtype=bfloat16"]),
    "NumPy acting": ("gym/pendulum", None, ["sac.numpy_acting=true"]),
    # discrete_entropy_penalty and munchausen_scale need a discrete-only task; tanh_log_det_epsilon, for
    # continuous actions, is accepted and unused here
    "update options": ("gym/cartpole", None, [
        "sac.update_order=critic_first", "sac.tanh_log_det_epsilon=1e-6", "sac.learning_rate_final=0.0",
        "sac.learning_rate_anneal_updates=100", "sac.clip_epsilon=5", "sac.discrete_entropy_penalty=0.5",
        "sac.discrete_target_entropy_start=0.98", "sac.munchausen_scale=0.9", "sac.munchausen_scale_start=0.0",
    ]),
    "stale actors": ("gym/pendulum", None, ["sac.update_policy_variables_per_step=5"]),
    "model files": ("gym/pendulum", None, ["--nn=nn_layernorm"]),
}  # fmt: skip
# Features together, beyond the one-row entries above (trained the same ways)
COMBINATIONS: dict[str, tuple[str, str | None, list[str]]] = {
    "every_extra": ("toy/masked_grid", None, [
        "sac.use_curiosity=true", "sac.curiosity_inverse=true", "sac.use_rnd=true", "nn.noisy_q=true",
        "nn.noisy_policy=true", "sac.use_normalization=true", "sac.use_prediction=true", "sac.use_n_step_is=true",
        "sac.n_step=3",
    ]),
    "rnd_mixed": ("toy/mixed_target", None, ["sac.use_rnd=true"]),
}  # fmt: skip
ENTRIES = {**FEATURES, **COMBINATIONS}

# A short run: a few dozen updates on tiny nets, no evaluation.
SMALL = [
    "base.max_step=120",
    "replay.min_size_to_sample=40",
    "actor.random_steps=20",
    "replay.batch_size=16",
    "replay.samples_per_insert=null",
    "eval.eval_per_step=0",
    "nn.hidden_units=[16]",
    "actor.chunk_length=16",
]


def documented_features() -> list[str]:
    """The first column of docs/features.md's table, row by row."""
    lines = (ROOT / "docs" / "features.md").read_text().splitlines()
    start = lines.index("# Algorithm features")
    rows: list[str] = []
    in_table = False
    for line in lines[start + 1 :]:
        if line.startswith("|"):
            in_table = True
            rows.append(line.split("|")[1].strip())
        elif in_table or line.startswith("#"):
            break
    assert len(rows) > 2 and rows[0] == "feature" and set(rows[1]) <= set("-: "), rows[:2]
    return rows[2:]


def test_every_documented_feature_has_a_matrix_entry() -> None:
    rows = documented_features()
    assert len(rows) == len(set(rows)), rows
    assert set(FEATURES) == set(rows), (
        f"docs/features.md rows without a matrix entry: {sorted(set(rows) - set(FEATURES))}; "
        f"entries without a docs/features.md row: {sorted(set(FEATURES) - set(rows))}"
    )


def slug(feature: str) -> str:
    return re.sub(r"\W+", "_", feature).strip("_").lower()


ROWS = [pytest.param(feature, id=slug(feature)) for feature in ENTRIES]


def tail(done: subprocess.CompletedProcess[str], chars: int = 4000) -> str:
    return f"exit {done.returncode}\n--- stdout\n{done.stdout[-chars:]}\n--- stderr\n{done.stderr[-chars:]}"


def train_args(feature: str, model_root: Path) -> tuple[str, list[str]]:
    """The task, and the arguments after it that train ``feature``'s row into ``model_root``."""
    task, section, switches = ENTRIES[feature]
    args = ["-n", slug(feature), "--model_root", str(model_root), "--no_progress"]
    if section:
        args += ["-c", section]
    for item in SMALL + switches:
        args += [item] if item.startswith("--") else ["--override", item]
    return task, args


def play_and_check(feature: str, model_root: Path) -> Path:
    """Plays the trained row's run for one episode; its run folder."""
    task = ENTRIES[feature][0]
    run_dir = model_root / task / slug(feature)
    assert sorted((run_dir / "model").glob("*.pt")), f"no checkpoint in {run_dir / 'model'}"
    played = run_main(task, "-n", slug(feature), "--run", "--episodes", "1", "--model_root", str(model_root),
                      cwd=model_root, timeout=TIMEOUT_S)  # fmt: skip
    assert played.returncode == 0, tail(played)
    assert re.search(r"checkpoint \d+: return -?\d", played.stdout), tail(played)
    return run_dir


@pytest.mark.parametrize("feature", ROWS)
def test_feature_trains_and_plays_through_main(feature: str, tmp_path: Path) -> None:
    task, args = train_args(feature, tmp_path)
    trained = run_main(task, *args, cwd=tmp_path, timeout=TIMEOUT_S)
    assert trained.returncode == 0, tail(trained)
    play_and_check(feature, tmp_path)


@pytest.mark.parametrize("feature", ROWS)
def test_feature_trains_and_plays_through_main_ds_local(feature: str, tmp_path: Path) -> None:
    task, args = train_args(feature, tmp_path)
    trained = subprocess.run(main_ds_command(task, "local", "--actors", "1", *args), cwd=tmp_path, env=ENV,
                             text=True, capture_output=True, timeout=TIMEOUT_S)  # fmt: skip
    assert trained.returncode == 0, tail(trained)
    run_dir = play_and_check(feature, tmp_path)
    assert (run_dir / "token").is_file()  # local made the run's token: every role ran authenticated
