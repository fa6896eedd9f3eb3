"""bench/tasks.py's pure parts: the first evaluation that reached the threshold, the lowest one from
there on (issue 15's "kept to 50k"), and rows appended to a results file written before a column."""

from __future__ import annotations

import csv
from pathlib import Path

from bench.tasks import FIELDS, append, final_cell, reached_and_kept, run


def rows(*returns: float) -> list[dict[str, float]]:
    return [{"env_steps": 5000.0 * (i + 1), "return_mean": r} for i, r in enumerate(returns)]


def test_kept_is_the_lowest_evaluation_from_the_first_that_reached_the_threshold() -> None:
    assert reached_and_kept(rows(-3.8, 92.0, 94.5, 91.0, 95.0), 90) == (10000, 91.0)
    assert reached_and_kept(rows(-3.8, 93.4, -37.3, 95.0), 90) == (10000, -37.3)  # found, then lost
    assert reached_and_kept(rows(-120.0, 85.0, 89.9), 90) == (None, None)  # never reached
    assert reached_and_kept(rows(10.0), None) == (None, None)  # no threshold given


def test_append_rewrites_an_older_header_and_keeps_its_rows(tmp_path: Path) -> None:
    path = tmp_path / "tasks.csv"
    older = [f for f in FIELDS if f != "kept"]
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, older)
        writer.writeheader()
        writer.writerow(dict.fromkeys(older, "1"))
    append(dict.fromkeys(FIELDS, "2"), path)
    append(dict.fromkeys(FIELDS, "3"), path)
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        assert reader.fieldnames == FIELDS
        got = list(reader)
    assert [r["seed"] for r in got] == ["1", "2", "3"] and [r["kept"] for r in got] == ["", "2", "3"]


def test_a_run_row_carries_the_final_policys_score_or_none_without_final_episodes() -> None:
    """A real CartPole run, briefly: the row's final score is a mean of CartPole returns (1-500 each)."""
    short = ["replay.min_size_to_sample=200", "nn.hidden_units=[16]", "eval.eval_envs=1"]
    row = run("gym/cartpole", None, 0, 400, 200, None, short, final_episodes=2)
    assert row["final_episodes"] == 2 and isinstance(row["final"], float) and 1.0 <= row["final"] <= 500.0
    assert set(row) == set(FIELDS)
    skipped = run("gym/cartpole", None, 0, 400, 200, None, short, final_episodes=0)
    assert skipped["final"] is None and skipped["final_episodes"] is None
    assert final_cell({k: "" if v is None else str(v) for k, v in skipped.items()}) == "-"
    assert final_cell({"final": "471.2", "final_episodes": "100"}) == "471.2 (100)"
