"""Bench drivers that start one child process after another and outlast a working session.

    children = Children()               # from now on SIGINT and SIGTERM stop the driver, as below
    code = children.run([sys.executable, "main.py", ...], cwd=ROOT)
    if code != 0 or children.stopping: ...   # stop here; the same driver command resumes later

A terminal's Ctrl-C reaches the child too (one process group). SIGTERM (a background driver's stop:
``kill PID``) reaches only the driver, which passes it on to the child in progress as one SIGINT, the
signal main.py and the resumable bench runs answer by saving; never a second one, which main.py reads
as "stop without saving". Either way the driver starts no other child.
"""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path


def default_runs() -> Path:
    """Where run folders that outlast a session go: ``$ASAC_BENCH_RUNS``, else ``~/asac_long_runs``."""
    return Path(os.environ.get("ASAC_BENCH_RUNS", str(Path.home() / "asac_long_runs")))


class Children:
    def __init__(self) -> None:
        self._running: subprocess.Popen[bytes] | None = None
        self._stopping = False
        signal.signal(signal.SIGINT, self._stop)
        signal.signal(signal.SIGTERM, self._stop)

    @property
    def stopping(self) -> bool:
        return self._stopping

    def run(self, args: list[str], cwd: Path) -> int:
        """Run ``args`` to its end; its exit code."""
        self._running = subprocess.Popen(args, cwd=cwd)
        try:
            return self._running.wait()
        finally:
            self._running = None

    def _stop(self, signum: int, _frame: object) -> None:
        if signum == signal.SIGTERM and self._running is not None and not self._stopping:
            self._running.send_signal(signal.SIGINT)
        self._stopping = True
