"""bench/modes.py's pure parts: the commands it runs, what it reads from evaluations.csv, its report."""

from __future__ import annotations

from pathlib import Path

from bench.modes import append, command, report, summarize


def evaluation(env_steps: float, updates: float, wall: float, ret: float) -> dict[str, float]:
    return {"env_steps": env_steps, "updates": updates, "wall_seconds": wall, "return_mean": ret, "return_std": 0.0}


def test_commands_are_the_users() -> None:
    main = command("gym/pendulum", "main", 3, 6000, 250, 2, ["sac.n_step=5"])
    assert main[1].endswith("main.py") and main[2:5] == ["gym/pendulum", "-n", "bench"]
    assert "--no_progress" in main
    sets = [main[i + 1] for i, a in enumerate(main) if a == "--override"]
    assert sets == ["sac.seed=3", "base_config.max_step=6000", "eval_config.eval_per_step=250", "sac.n_step=5"]
    local = command("gym/pendulum", "local", 3, 6000, 250, 2, [])
    assert local[1].endswith("main_ds.py") and local[2:6] == ["gym/pendulum", "local", "--actors", "2"]


def test_summarize_first_reach_and_rates() -> None:
    rows = [evaluation(1000, 0, 5, -1200), evaluation(2000, 4000, 20, -180), evaluation(3000, 8000, 35, -150),
            evaluation(4000, 12000, 50, -210)]  # fmt: skip
    out = summarize(rows, -200)
    assert (out["reached_at"], out["reached_wall_s"], out["best"], out["last"]) == (2000, 20, -150, -210)
    assert out["updates_per_step"] == 3.0 and out["late_updates_per_step"] == 4.0 and out["final_steps"] == 4000
    assert summarize(rows, 0)["reached_at"] is None
    assert summarize([], -200)["reached_at"] is None


def test_report_counts_failures_as_the_budget(tmp_path: Path) -> None:
    path = tmp_path / "modes.csv"
    base = {"task": "gym/pendulum", "steps": 6000, "threshold": -200.0, "reached_wall_s": 10, "best": -150,
            "last": -160, "updates_per_step": 3.3, "late_updates_per_step": 4.0, "age_median": 500, "age_p95": 900,
            "wall_s": 60, "commit": "abc", "final_steps": 6000, "rc": 0}  # fmt: skip
    for seed, (m, l) in enumerate([(1500, 2000), (1750, None), (2000, 2500)]):
        append({**base, "mode": "main", "actors": 0, "seed": seed, "reached_at": m}, path)
        append({**base, "mode": "local", "actors": 2, "seed": seed, "reached_at": l}, path)
    text = report(path)
    assert "| main | 3/3 | 1750 | 2000 |" in text
    assert "| local --actors 2 | 2/3 | 2500 | 6000 |" in text
    assert "local / main median steps to threshold: 1.43" in text
    assert text.count("\n| 0 ") == 1 and "not reached" in text
