"""What a role process costs to start: CPU seconds until it is ready (a replay or an evolver logs
that it serves; an actor, pointed at a port where no replay listens, that it waits for the replay)
and its resident memory then, and whether torch is loaded (Linux: /proc/PID/maps).

Run: ``python -m bench.role_start [--rounds 3] [--baseline DIR]``. ``--baseline`` names another
checkout (e.g. ``git archive <commit>`` unpacked) whose ``main_ds.py`` is measured in the same run,
round by round alternating with this one, so that the two share the machine's load; the table gives
medians over rounds and each role's ratio to the baseline.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# role -> (its flags, the log line that says it is ready)
ROLES = {
    "replay": (["--replay_port", "0"], "serving on"),
    "evolver": (["--evolver_port", "0"], "serving on"),
    "actor": (["--replay_port", "1"], "waiting for replay"),
}
TICKS = os.sysconf("SC_CLK_TCK")


def start_cost(checkout: Path, role: str) -> tuple[float, float, bool]:
    """(CPU seconds, resident MB, torch loaded) of ``main_ds.py gym/pendulum ROLE`` once it is ready."""
    with tempfile.TemporaryDirectory() as cwd:
        log = Path(cwd) / "role.log"
        flags, ready = ROLES[role]
        command = [sys.executable, str(checkout / "main_ds.py"), "gym/pendulum", role, "-n", "start",
                   "--no_progress", *flags]  # fmt: skip
        env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
        with log.open("w") as out:
            proc = subprocess.Popen(command, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 120
            while ready not in log.read_text():
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"{role} did not get ready:\n{log.read_text()[-2000:]}")
                time.sleep(0.05)
            stat = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            cpu = (int(stat[11]) + int(stat[12])) / TICKS  # utime + stime (fields 14 and 15)
            rss = next(int(line.split()[1]) for line in Path(f"/proc/{proc.pid}/status").read_text().splitlines()
                       if line.startswith("VmRSS:")) / 1024  # fmt: skip
            torch = "libtorch" in Path(f"/proc/{proc.pid}/maps").read_text()
        finally:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=60)
    return cpu, rss, torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--baseline", type=Path, default=None, help="another checkout, measured alongside")
    args = parser.parse_args()
    checkouts = {"this": ROOT} | ({"baseline": args.baseline.resolve()} if args.baseline else {})
    got: dict[tuple[str, str], list[tuple[float, float, bool]]] = {}
    for _ in range(args.rounds):
        for role in ROLES:
            for name, checkout in checkouts.items():
                got.setdefault((name, role), []).append(start_cost(checkout, role))
    print("| role | checkout | CPU s until ready (median) | resident MB | torch loaded |")
    print("|---|---|---|---|---|")
    for (name, role), runs in got.items():
        cpu = statistics.median(r[0] for r in runs)
        rss = statistics.median(r[1] for r in runs)
        print(f"| {role} | {name} | {cpu:.2f} | {rss:.0f} | {'yes' if any(r[2] for r in runs) else 'no'} |")
    if args.baseline:
        for role in ROLES:
            ours = statistics.median(r[0] for r in got["this", role])
            base = statistics.median(r[0] for r in got["baseline", role])
            ours_mb = statistics.median(r[1] for r in got["this", role])
            base_mb = statistics.median(r[1] for r in got["baseline", role])
            print(f"{role}: CPU {ours / base:.2f}x of the baseline's, memory {ours_mb / base_mb:.2f}x")


if __name__ == "__main__":
    main()
