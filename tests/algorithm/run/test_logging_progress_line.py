"""The progress line a user watches: never past 100%, never a negative ETA (issue 14 saw
``3,600/3,000 steps ... ETA -1:59:54`` when a distributed run ended a chunk past max_step)."""

from __future__ import annotations

import io
import time

from algorithm.run.logging import ProgressLine


def lines_for(total: int, steps: list[int]) -> list[str]:
    out = io.StringIO()
    bar = ProgressLine(total, stream=out)
    for step in steps:
        bar.update(step, step * 4, 10.0, -150.0, force=True)
        time.sleep(0.01)  # a step rate to compute the ETA from
    return out.getvalue().splitlines()


def test_a_run_that_ends_past_its_budget_shows_100_percent_and_no_negative_eta() -> None:
    lines = lines_for(3000, [2000, 2500, 3600])
    last = lines[-1]
    assert "3,000/3,000 steps" in last and "3,600" not in last
    assert "[" + "#" * 20 + "]" in last
    assert "ETA 00:00" in last and "-" not in last.split("ETA")[1]


def test_eta_counts_down_while_the_run_is_inside_its_budget() -> None:
    lines = lines_for(100_000_000, [100, 200, 300])  # ~10k steps/s: hours left
    assert "300/100,000,000 steps" in lines[-1]
    eta = lines[-1].split("ETA ")[1]
    assert eta != "00:00" and not eta.startswith("-")
