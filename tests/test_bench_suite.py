"""bench/suite.py's ASAC runs outlast a working session: a run stopped (as SIGTERM to the suite does)
saves its folder and the same call resumes it to its budget, its curve whole (real Hopper-v5 envs
and trainer, tiny networks, a few hundred steps)."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from algorithm.run.folder import RunDir
from bench.suite import curve_mean, ratio_interval, report, run_folder
from bench.systems import RunResult, RunStopped, run_ours

TINY = ["nn.hidden_units=[16,16]", "replay.batch_size=16", "actor.random_steps=100", "replay.min_size_to_sample=100",
        "sac.compute_dtype=float32"]  # fmt: skip


def write_runs(out: Path, task: str, runs: list[tuple[str, int, float, list[tuple[int, float]]]]) -> None:
    """Finished runs as the suite leaves them in ``out``: a summary.csv row (return at 20k) and an evaluation
    curve per (system, seed, return, [(env steps, mean return), ...])."""
    summary = ["task,system,seed,steps,return,wall_s,eval_s,overrides,code,finished"]
    for system, seed, ret, curve in runs:
        summary.append(f"{task},{system},{seed},20000,{ret},10,1,,abc,today")
        (out / f"{task}_{system}_seed{seed}.csv").write_text(
            "env_steps,return_mean,return_std,wall_seconds\n" + "".join(f"{s},{r},0.0,1\n" for s, r in curve)
        )
    (out / "summary.csv").write_text("\n".join(summary) + "\n")


def test_a_stopped_run_is_saved_and_the_same_call_resumes_it_to_its_budget(tmp_path: Path) -> None:
    folder = run_folder(tmp_path, "hopper", 0, 600, " ".join(TINY))
    stop = threading.Event()
    evaluated: list[int] = []

    def after_the_first_evaluation(result: RunResult) -> None:
        evaluated.append(result.curve[-1][0])
        stop.set()  # as the suite's signal handler does

    with pytest.raises(RunStopped) as stopped:
        run_ours("hopper", 0, 600, TINY, every=200, on_eval=after_the_first_evaluation, run_dir=folder, stop=stop)
    assert evaluated == [200] and stopped.value.env_steps == 200
    saved = RunDir(folder)
    assert [int(p.stem) for p in saved.model.glob("*.pt")] == [200], list(saved.model.iterdir())
    assert saved.replay.is_file()  # what was collected comes back with the run

    result = run_ours("hopper", 0, 600, TINY, every=200, run_dir=folder)
    assert [at for at, *_ in result.curve] == [200, 400, 600]  # the first part's evaluation kept, none twice
    assert result.final == result.curve[-1][1]
    assert result.earlier_wall_s > 0  # the summary's wall time counts the first part too


def test_the_ratio_interval_widens_with_the_seeds_spread_and_holds_the_ratio_of_means() -> None:
    tight = ratio_interval([100.0, 101.0, 99.0], [100.0, 100.5, 99.5])
    spread = ratio_interval([300.0, 2600.0, 500.0], [350.0, 450.0, 2900.0])
    assert tight[0] <= 1.0 <= tight[1] and tight[1] - tight[0] < 0.05
    assert spread[0] < 0.5 and spread[1] > 2.0  # one seed far above the others on each side
    assert ratio_interval([200.0] * 3, [100.0] * 3) == (2.0, 2.0)


def test_the_curve_mean_averages_the_evaluations_past_the_random_warm_up_only(tmp_path: Path) -> None:
    curve = tmp_path / "walker2d_asac_seed0.csv"
    rows = [(5000, -1.0), (10000, 7.0), (15000, 200.0), (20000, 400.0), (100000, 900.0)]
    curve.write_text("env_steps,return_mean,return_std,wall_seconds\n" + "".join(f"{s},{r},0.0,1\n" for s, r in rows))
    assert curve_mean(curve) == pytest.approx(500.0)  # 15k, 20k and 100k: the untrained policy's scores left out


def test_the_report_counts_only_the_seeds_asked_for(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Extra seeds share the folder with the seeds a goal is judged on; the report of seeds 0-2 must not
    # fold them in.
    returns = {"asac": [100.0, 200.0, 300.0, 1000.0], "sb3": [200.0, 200.0, 200.0, 200.0]}
    runs = [(system, seed, ret, [(5000, 0.0), (15000, ret), (20000, ret)]) for system in returns
            for seed, ret in enumerate(returns[system])]  # fmt: skip
    write_runs(tmp_path, "walker2d", runs)
    report(tmp_path, "walker2d", [0, 1, 2])
    three = capsys.readouterr().out
    assert "asac: mean 200.0" in three and "over 3 seeds" in three and "ASAC / SB3 means: 1.00x" in three
    assert "| 3 |" not in three
    report(tmp_path, "walker2d")
    every = capsys.readouterr().out
    assert "asac: mean 400.0" in every and "over 4 seeds" in every and "ASAC / SB3 means: 2.00x" in every
    assert "How often a system meets 'mean of 3 seeds >= SB3's mean of 3 seeds'" in every
    from bench.suite import goal_chances  # the table's row is of the four seeds' pooled runs, both systems'

    chance = goal_chances({"Walker2d-v5": [100.0, 200.0, 300.0, 1000.0] + [200.0] * 4}, 0.0, 3)[1]
    assert f"| +0% | {chance:.0%} | {chance:.0%} |" in every


def test_the_figure_draws_only_the_seeds_asked_for_into_a_file_of_its_own(tmp_path: Path) -> None:
    # The goal's figure (seeds 0-2) and the five-seed one share a folder; neither may fold the other's runs in.
    from bench.curves import curves, figure_path

    write_runs(tmp_path, "ant", [(system, seed, seed, [(10000, 0.0), (20000, seed)]) for system in ("asac", "sb3")
                                 for seed in range(5)])  # fmt: skip
    assert sorted(curves(tmp_path, "ant", [0, 1, 2])["asac"]) == [0, 1, 2]
    assert sorted(curves(tmp_path, "ant")["sb3"]) == [0, 1, 2, 3, 4]
    assert curves(tmp_path, "ant", [0, 4])["sb3"][4] == {10000: 0.0, 20000: 4.0}
    assert figure_path(tmp_path, "ant") == tmp_path / "ant.png"
    assert figure_path(tmp_path, "ant", [0, 1, 2, 3, 4]) == tmp_path / "ant_seeds0_1_2_3_4.png"


def test_the_figure_of_the_seeds_asked_for_is_drawn_under_its_own_name(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib", reason="bench.curves draws with matplotlib, not a dependency of asac")
    from bench.curves import plot

    write_runs(tmp_path, "ant", [(system, seed, seed, [(10000, 0.0), (20000, seed)]) for system in ("asac", "sb3")
                                 for seed in range(5)])  # fmt: skip
    drawn = plot(tmp_path, "ant", [0, 1, 2])
    assert drawn == tmp_path / "ant_seeds0_1_2.png" and drawn.read_bytes()[:4] == b"\x89PNG"
    assert not (tmp_path / "ant.png").exists()  # the every-seed figure is not redrawn
    assert plot(tmp_path, "ant", [7]) is None  # no finished runs of that seed: nothing drawn


def test_the_figures_without_matplotlib_end_in_one_line_naming_it() -> None:
    # matplotlib is not a dependency: a fresh install that asks for figures gets an error saying what to install.
    blocked = (
        "import sys, runpy; sys.modules['matplotlib'] = None; sys.argv = ['bench.curves', '--tasks', 'ant'];"
        " runpy.run_module('bench.curves', run_name='__main__')"
    )
    done = subprocess.run([sys.executable, "-c", blocked], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("bench.curves: error: drawing needs matplotlib") and done.stderr.count("\n") == 1
    assert "pip install matplotlib" in done.stderr


def test_the_report_takes_runs_from_other_folders_with_their_curves(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Extra seeds run into a folder of their own (bench/results/walker2d_seeds5to9) are reported with the
    # goal's seeds; each run's curve is read from its own folder.
    for folder, seeds, asac in (("first", [1, 0], 100.0), ("extra", [6, 5], 300.0)):
        out = tmp_path / folder
        out.mkdir()
        # the last evaluation (return + seed) tells the seeds apart in the per-seed lists (in the table's order)
        runs = [(system, seed, ret, [(15000, ret / 2), (20000, ret + seed)])
                for system, ret in (("asac", asac), ("sb3", 200.0)) for seed in seeds]  # fmt: skip
        write_runs(out, "walker2d", runs)
    report(tmp_path / "first", "walker2d", [0, 1, 5, 6], also=[tmp_path / "extra"])
    said = capsys.readouterr().out
    assert "| 5 | 20000 | 300.0 |" in said and "asac: mean 200.0" in said and "over 4 seeds" in said
    assert "mean of all evaluations past 10000 steps 151.5 (75.0 / 75.5 / 227.5 / 228.0)" in said


def test_the_goal_chance_is_a_coin_per_task_for_alike_systems_and_grows_with_an_advantage() -> None:
    from bench.suite import goal_chances

    tight = [100.0, 101.0, 99.0, 100.5, 99.5, 100.2]
    spread = [300.0, 2600.0, 500.0, 350.0, 450.0, 2900.0]  # one seed far above the others on each side
    alike, every = goal_chances({"a": tight, "b": spread, "c": tight, "d": spread}, 0.0, 3)
    assert all(0.45 < chance < 0.6 for chance in alike.values()), alike  # a half, plus the share of ties
    assert every == pytest.approx(np.prod(list(alike.values()))) and 0.04 < every < 0.13  # about 1 / 16
    better, _ = goal_chances({"tight": tight, "spread": spread}, 0.2, 3)
    assert better["tight"] > 0.999  # 20% of 100 is far beyond the seeds' spread of 2
    assert alike["b"] < better["spread"] < 0.9  # helps, but the spread between seeds keeps it a gamble
