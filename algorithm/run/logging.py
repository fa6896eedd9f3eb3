"""One metrics path: flat namespaced dicts -> TensorBoard, per-phase timers, a progress line.

Metric names are ``actor/*``, ``learner/*``, ``replay/*``, ``eval/*`` and ``time/*``; every write
goes through :meth:`MetricsWriter.write` with the env-step counter as the x axis.
"""

from __future__ import annotations

import io
import itertools
import logging
import math
import os
import socket
import sys
import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any, TextIO

from algorithm.files import WriteFailures, describe_os_error

log = logging.getLogger("asac.summaries")
_file_ids = itertools.count()


class MetricsWriter:
    """TensorBoard event files under ``log_dir`` (one writer per role/process): one file,
    ``events.out.tfevents.<time>.<host>.<pid>.<n>`` as TensorBoard names them, each :meth:`write` one
    event record appended to it at once by the calling thread (no writer thread).

    A write that fails (a full disk, an I/O error) never reaches the caller: it is logged once
    (:class:`~algorithm.files.WriteFailures`), the file is cut back to its last whole record, so
    everything written before stays readable, and the records not written are held, up to
    ``max_pending_bytes`` (the oldest dropped beyond it, counted), to be written at the next write or
    :meth:`flush` at least ``retry_s`` later; when one works again the held records follow in order.
    (torch's SummaryWriter, used before, stopped writing for good at the first failure, its thread
    dying with a traceback.)"""

    def __init__(
        self,
        log_dir: Path,
        *,
        retry_s: float = 10.0,
        max_pending_bytes: int = 4 << 20,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.log_dir = Path(log_dir)
        self.retry_s = float(retry_s)
        self.max_pending_bytes = int(max_pending_bytes)
        self.dropped = 0  # records dropped while writes failed (beyond max_pending_bytes)
        self._clock = clock
        self._lock = threading.Lock()
        self._fd: int | None = None
        self._size = 0  # bytes of whole records in the file
        self._pending: deque[bytes] = deque()
        self._pending_bytes = 0
        self._dropped_unreported = 0
        self._retry_at = -math.inf
        self.path = self._new_path()
        self._failures = WriteFailures(
            "TensorBoard summaries",
            log,
            retry=f"holding new ones (up to {self.max_pending_bytes >> 20} MiB) and trying again every {retry_s:g} s",
            kept=lambda path: f"{path} keeps the summaries written before, readable",
        )
        self._write_out()  # the folder and the file exist from the start, as they did with SummaryWriter

    def write(self, metrics: Mapping[str, float], step: int) -> None:
        """Scalars at ``step``, as one event."""
        summary_pb2 = _protos()[1]
        values = [summary_pb2.Summary.Value(tag=name, simple_value=float(value)) for name, value in metrics.items()]
        if values:
            self._add(summary_pb2.Summary(value=values), step)

    def text(self, name: str, text: str, step: int = 0) -> None:
        """``text`` under the tag ``<name>/text_summary`` in TensorBoard's text tab (the tag torch's
        SummaryWriter gave it before; written here without importing torch: the evolver writes text)."""
        summary_pb2 = _protos()[1]
        from tensorboard.compat.proto import tensor_pb2, tensor_shape_pb2, types_pb2

        # TensorBoard renders markdown; a fenced block keeps YAML indentation readable.
        fenced = ("```\n" + text + "\n```").encode()
        one = tensor_shape_pb2.TensorShapeProto(dim=[tensor_shape_pb2.TensorShapeProto.Dim(size=1)])
        tensor = tensor_pb2.TensorProto(dtype=types_pb2.DT_STRING, tensor_shape=one, string_val=[fenced])
        plugin = summary_pb2.SummaryMetadata(plugin_data=summary_pb2.SummaryMetadata.PluginData(plugin_name="text"))
        value = summary_pb2.Summary.Value(tag=f"{name}/text_summary", tensor=tensor, metadata=plugin)
        self._add(summary_pb2.Summary(value=[value]), step)

    def flush(self) -> None:
        """Write what is held now (the data is with the OS after each write already)."""
        with self._lock:
            self._write_out()

    def close(self) -> None:
        """A last try for what is held (logged as lost if it fails), then close the file."""
        with self._lock:
            self._write_out(final=True)
            if self._fd is not None:
                with suppress(OSError):
                    os.close(self._fd)
                self._fd = None

    # -- the file ---------------------------------------------------------------------------
    def _add(self, summary: Any, step: int) -> None:
        event = _protos()[0].Event(wall_time=time.time(), step=int(step), summary=summary)
        record = _record(event.SerializeToString())
        with self._lock:
            self._pending.append(record)
            self._pending_bytes += len(record)
            while self._pending_bytes > self.max_pending_bytes and len(self._pending) > 1:
                self._pending_bytes -= len(self._pending.popleft())
                self.dropped += 1
                self._dropped_unreported += 1
            self._write_out()

    def _write_out(self, final: bool = False) -> None:
        """Append the held records (the lock held); see the class for failures."""
        if not final and self._clock() < self._retry_at:
            return
        if not self._pending and (self._fd is not None or final):
            return  # nothing to write (the first call, from __init__, creates the file)
        data = b"".join(self._pending)
        try:
            if self._fd is None:
                self.log_dir.mkdir(parents=True, exist_ok=True)
                flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | getattr(os, "O_CLOEXEC", 0)
                self._fd = os.open(self.path, flags, 0o644)
                if self._size == 0:
                    version = _protos()[0].Event(wall_time=time.time(), file_version="brain.Event:2")
                    data = _record(version.SerializeToString()) + data
            view = memoryview(data)
            while view:
                view = view[os.write(self._fd, view) :]
        except OSError as e:
            self._cut_back()
            self._retry_at = self._clock() + self.retry_s
            self._failures.failed(self.path, e, final=final)
            if final and self._pending:
                log.error("the %d TensorBoard summaries held in memory for %s are lost", len(self._pending), self.path)
            return
        self._size += len(data)
        self._pending.clear()
        self._pending_bytes = 0
        self._retry_at = -math.inf
        self._failures.succeeded(self.path)
        if self._dropped_unreported:
            log.warning("%d TensorBoard summaries were dropped while %s could not be written (more than %d MiB "
                        "held)", self._dropped_unreported, self.path, self.max_pending_bytes >> 20)  # fmt: skip
            self._dropped_unreported = 0

    def _cut_back(self) -> None:
        """After a failed append: cut the file to its whole records (freeing space needs none); where
        even that fails, go on in a new file, so no record is ever written after a torn one."""
        if self._fd is None:
            return
        try:
            os.ftruncate(self._fd, self._size)
        except OSError:
            with suppress(OSError):
                os.close(self._fd)
            self._fd, self._size, self.path = None, 0, self._new_path()

    def _new_path(self) -> Path:
        name = f"events.out.tfevents.{int(time.time()):010d}.{socket.gethostname()}.{os.getpid()}.{next(_file_ids)}"
        return self.log_dir / name


class LogFileHandler(logging.FileHandler):
    """``--logger_in_file``'s handler (``<run>/log.txt``) for a disk that may fill up: a record it
    cannot write is not a ``--- Logging error ---`` traceback on stderr for each record (logging's
    default) but one line there, naming the file and the cause, until a record is written again; the
    file is cut back to its last whole line and reopened at each later record, and the first line
    written again says how many are missing (they are on stderr, which the other handler writes)."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, encoding="utf-8")
        self.missed = 0  # records not written since the last one that was
        self._good_size: int | None = None  # the file's size after the last record written whole

    def emit(self, record: logging.LogRecord) -> None:
        try:
            if self.stream is None:
                self.stream = self._open()
            if self._good_size is None:
                self._good_size = os.fstat(self.stream.fileno()).st_size
            line = self.format(record)
            if self.missed:
                line = f"({self.missed} log records before this one could not be written here; see stderr)\n{line}"
            self.stream.write(line + self.terminator)
            self.stream.flush()
            self._good_size = os.fstat(self.stream.fileno()).st_size
        except RecursionError:
            raise
        except OSError as e:
            self._failed(e)
            return
        except Exception:
            self.handleError(record)
            return
        self.missed = 0

    def _failed(self, error: OSError) -> None:
        stream, self.stream = self.stream, None
        if stream is not None:
            with suppress(Exception):
                stream.close()  # what its buffer held is lost with it; the record is on stderr
        if self._good_size is not None:
            with suppress(OSError):
                os.truncate(self.baseFilename, self._good_size)
        if not self.missed:
            sys.stderr.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} asac ERROR could not write the log file "
                             f"{self.baseFilename}: {describe_os_error(error)}; log records go to stderr only "
                             "until it can be written again (logged once)\n")  # fmt: skip
        self.missed += 1


def _protos() -> tuple[Any, Any]:
    """TensorBoard's event and summary protos, imported when first needed (they pull in tensorboard)."""
    from tensorboard.compat.proto import event_pb2, summary_pb2

    return event_pb2, summary_pb2


def _record(data: bytes) -> bytes:
    """``data`` framed as one TFRecord (length, data and their masked CRC32Cs), as event files hold them."""
    from tensorboard.summary.writer.record_writer import RecordWriter

    out = io.BytesIO()
    RecordWriter(out).write(data)
    return out.getvalue()


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
    """A single refreshed terminal line: steps, rates, recent return, ETA (plain lines when not a tty).

    A stream that cannot be written any more (a terminal that hung up: EIO) silences the line for
    good instead of raising: it raised out of the training loop and ended the run before the save
    that SIGHUP asks for (tests/test_journeys.py)."""

    def __init__(self, total_steps: int, stream: TextIO = sys.stderr, min_interval: float = 1.0) -> None:
        self.total = total_steps
        self.stream = stream
        self.min_interval = min_interval if stream.isatty() else 10.0
        self._last = 0.0
        self._steps = RateMeter()
        self._lost = False  # the stream failed once: nothing more is written

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
        self._write("\r" + line + "\033[K" if self.stream.isatty() else line + "\n")

    def close(self) -> None:
        if self.stream.isatty():
            self._write("\n")

    def _write(self, text: str) -> None:
        if self._lost:
            return
        try:
            self.stream.write(text)
            self.stream.flush()
        except OSError:
            self._lost = True


def _fmt_seconds(seconds: float) -> str:
    if seconds == float("inf"):
        return "--:--"
    seconds = int(seconds)
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m:02d}:{s:02d}"


REPEAT_LOG_S = 30.0  # a line about a state that persists (waiting, unreachable) is repeated at most this often


class Throttle:
    """True at most once every ``seconds`` (for log lines about a state that persists)."""

    def __init__(self, seconds: float = REPEAT_LOG_S) -> None:
        self.seconds = seconds
        self._last = -math.inf

    def __call__(self) -> bool:
        now = time.monotonic()
        if now - self._last < self.seconds:
            return False
        self._last = now
        return True
