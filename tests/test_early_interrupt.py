"""A Ctrl-C while an entry point is still importing and setting up (before the run's own handlers are in
place) ends it with 130 and no traceback. Every role of a local run gets the terminal's Ctrl-C at once, and
each printed a KeyboardInterrupt traceback from wherever its imports stood (seen on a fresh clone's
``main_ds.py gym/pendulum local`` stopped 1.4 s after launch)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.role_runs import ENV, ROOT, TINY


@pytest.mark.parametrize("entry", ["main.py", "main_ds.py"])
def test_a_ctrl_c_while_starting_exits_130_without_a_traceback(tmp_path: Path, entry: str) -> None:
    role = ["replay"] if entry == "main_ds.py" else []
    outputs = []
    for delay_s in (0.4, 0.8, 1.2):  # inside the seconds of imports and set-up (torch alone takes ~1 s)
        command = [sys.executable, str(ROOT / entry), "gym/pendulum", *role, "-n", f"early_{delay_s}",
                   "--model_root", str(tmp_path), *TINY]  # fmt: skip
        proc = subprocess.Popen(command, cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        time.sleep(delay_s)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
        text = out.decode(errors="replace")
        outputs.append(text)
        assert proc.returncode == 130, f"after {delay_s} s: exit {proc.returncode}\n{text}"
        assert "Traceback" not in text, f"after {delay_s} s:\n{text}"
    assert any("SIGINT" not in text for text in outputs), "every signal came after the run's handlers: no test"
