"""One metrics path: flat namespaced dicts -> TensorBoard, per-phase timers, a progress line.

Metric names are ``actor/*``, ``learner/*``, ``replay/*``, ``eval/*`` and ``time/*``; every write
goes through :meth:`MetricsWriter.write` with the env-step counter as the x axis.
"""

from __future__ import annotations

import sys
import time
from collections import defaultdict, deque
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import TextIO


class MetricsWriter:
    """TensorBoard event files under ``log_dir`` (one writer per role/process)."""

    def __init__(self, log_dir: Path) -> None:
        from torch.utils.tensorboard import SummaryWriter  # imported lazily: it pulls in tensorboard

        log_dir.mkdir(parents=True, exist_ok=True)
        self._writer = SummaryWriter(str(log_dir))

    def write(self, metrics: Mapping[str, float], step: int) -> None:
        for name, value in metrics.items():
            self._writer.add_scalar(name, float(value), step)

    def text(self, name: str, text: str, step: int = 0) -> None:
        # TensorBoard renders markdown; a fenced block keeps YAML indentation readable.
        self._writer.add_text(name, "```\n" + text + "\n```", step)

    def flush(self) -> None:
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()


class Timers:
    """Accumulates wall time per phase; :meth:`fractions` reports ``time/<phase>`` shares."""

    def __init__(self) -> None:
        self._total: dict[str, float] = defaultdict(float)

    @contextmanager
    def phase(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self._total[name] += time.perf_counter() - start

    def seconds(self) -> dict[str, float]:
        return {f"time/{k}_seconds": v for k, v in self._total.items()}

    def fractions(self) -> dict[str, float]:
        total = sum(self._total.values()) or 1.0
        return {f"time/{k}_fraction": v / total for k, v in self._total.items()}


class RateMeter:
    """Events per second over a sliding window of recent (time, count) marks."""

    def __init__(self, window_seconds: float = 10.0) -> None:
        self.window = window_seconds
        self._marks: deque[tuple[float, int]] = deque()

    def mark(self, count: int) -> float:
        now = time.perf_counter()
        self._marks.append((now, count))
        while len(self._marks) > 2 and now - self._marks[0][0] > self.window:
            self._marks.popleft()
        (t0, c0), (t1, c1) = self._marks[0], self._marks[-1]
        return (c1 - c0) / (t1 - t0) if t1 > t0 else 0.0


class ProgressLine:
    """A single refreshed terminal line: steps, rates, recent return, ETA (plain lines when not a tty)."""

    def __init__(self, total_steps: int, stream: TextIO = sys.stderr, min_interval: float = 1.0) -> None:
        self.total = total_steps
        self.stream = stream
        self.min_interval = min_interval if stream.isatty() else 10.0
        self._last = 0.0
        self._steps = RateMeter()

    def update(
        self, env_steps: int, updates: int, updates_per_s: float, recent_return: float | None, force: bool = False
    ) -> None:
        now = time.perf_counter()
        steps_per_s = self._steps.mark(env_steps)
        if not force and now - self._last < self.min_interval:
            return
        self._last = now
        ret = "   n/a" if recent_return is None else f"{recent_return:8.1f}"
        if self.total > 0:  # never past 100% or a negative ETA (a distributed run may end a chunk over)
            frac = min(env_steps / self.total, 1.0)
            left = max(self.total - env_steps, 0)
            eta = left / steps_per_s if steps_per_s > 0 else (0.0 if not left else float("inf"))
            bar = "#" * int(20 * frac) + "-" * (20 - int(20 * frac))
            head = f"[{bar}] {min(env_steps, self.total):>9,d}/{self.total:,d} steps"
            tail = f" | ETA {_fmt_seconds(eta)}"
        else:
            head, tail = f"{env_steps:>9,d} steps", ""
        line = (
            f"{head} | {steps_per_s:7.1f} steps/s | {updates:>8,d} updates {updates_per_s:6.1f}/s | return {ret}{tail}"
        )
        if self.stream.isatty():
            self.stream.write("\r" + line + "\033[K")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self.stream.isatty():
            self.stream.write("\n")
            self.stream.flush()


def _fmt_seconds(seconds: float) -> str:
    if seconds == float("inf"):
        return "--:--"
    seconds = int(seconds)
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m:02d}:{s:02d}"
