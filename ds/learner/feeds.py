"""The learner's background traffic with the replay: batches prefetched into a bounded queue,
priority updates sent back in merged batches. Neither ever drops data silently.

Usage (ds/learner/learner.py)::

    prefetcher, priorities = BatchPrefetcher(replay, batch_size=256), PriorityUpdater(replay)
    prefetcher.start(); priorities.start()
    while training:
        batch = prefetcher.get(timeout=0.5)           # None: nothing yet (replay short of data)
        ...
        priorities.put(batch.keys, td_abs)            # blocks (counted) while the queue is full
    prefetcher.stop(); priorities.close(timeout=5)   # close sends what is queued first

A replay that is short of data, unreachable (UNAVAILABLE) or not answering (a stalled process:
DEADLINE_EXCEEDED) is waited out and logged now and then;
any other replay error stops the thread and is raised in the learner's thread by the next
``get``/``put`` (errors surface, they are not swallowed).
"""

from __future__ import annotations

import collections
import logging
import queue
import threading
import time

import numpy as np

from algorithm.replay import ReplayTable, ReplayUnavailable, SampleTimeout
from algorithm.run.logging import Throttle
from algorithm.types import Batch
from ds.net.outage import BLIP_S, GRPC_DEADLINE_DETAILS, Outage, unanswered

log = logging.getLogger("asac.learner")
TRAINING_ON = "the learner trains on the batches it holds, then waits"


def replay_link(replay: ReplayTable) -> Outage:
    """The learner's link to ``replay``, told once down and once back (one for its three threads)."""
    return Outage(f"replay at {getattr(replay, 'address', 'in process')}", log, BLIP_S)


class _Worker:
    """A daemon thread running ``_run`` until :meth:`stop`; an exception it raises is kept and
    re-raised in the owner's thread by :meth:`check` (errors surface, they are not swallowed)."""

    name = "worker"

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._guarded, name=self.name, daemon=True)
        self.error: BaseException | None = None

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def check(self) -> None:
        if self.error is not None:
            raise RuntimeError(f"{self.name} thread failed: {self.error}") from self.error

    def _guarded(self) -> None:
        try:
            self._run()
        except BaseException as e:  # kept for check(): the owner decides
            self.error = e
            log.error("%s thread failed: %s", self.name, e)

    def _run(self) -> None:
        raise NotImplementedError


class BatchPrefetcher(_Worker):
    """Samples ``batch_size`` windows from ``replay`` on a background thread, up to ``per_call``
    batches per call where the replay can (a client's ``sample_many``: a call's fixed cost, ~0.5-1 ms
    of CPU after the thread sat idle, shared by its batches; 32 take the learner's CPU per sampled
    step from ~0.41 to ~0.33 us against 16, bench/results/transport/). Each call's batches go into a
    queue as one item; :meth:`get` hands them out one by one, so the thread is woken once per call,
    not per batch (waking a thread costs ~0.1 ms of CPU on a virtual machine). The thread draws a call
    only while :attr:`ahead` (batches drawn and not yet handed out, which PER sampled by priorities
    older than the learner's) leaves room for a whole one below :attr:`max_ahead`, ``per_call`` times
    ``ceil(depth / per_call) + 1``: calls the rate limiter cut short leave room for the next at once.
    The replay being short of data (SampleTimeout) or unreachable (UNAVAILABLE) is waited out, logged
    now and then; waiting for room is counted (``full_waits``, ``full_wait_seconds``); any other
    replay error stops it and :meth:`get` raises it. ``pin_memory`` (a learner on CUDA): batches land
    in page-locked memory, so their copies to the device do not block."""

    name = "prefetch"

    def __init__(
        self,
        replay: ReplayTable,
        batch_size: int,
        depth: int = 16,
        sample_timeout_s: float = 1.0,
        pin_memory: bool = False,
        per_call: int = 32,
        link: Outage | None = None,
    ) -> None:
        super().__init__()
        self.replay = replay
        self.link = link or replay_link(replay)
        self.batch_size = int(batch_size)
        self.per_call = max(1, int(per_call))
        self.sample_timeout_s = float(sample_timeout_s)
        self._allocate = _pinned if pin_memory else None
        self._max_ahead = (max(1, -(-int(depth) // self.per_call)) + 1) * self.per_call
        self._room = threading.Condition()  # notified when get() takes a call: room may have come
        self._queue: queue.SimpleQueue[list[Batch]] = queue.SimpleQueue()
        self._ready: collections.deque[Batch] = collections.deque()  # the taken call's batches, for get()
        self.sampled = 0
        self.delivered = 0
        self.calls = 0
        self.sample_waits = 0
        self.unavailable = 0
        self.full_waits = 0
        self.full_wait_seconds = 0.0
        self._log_wait = Throttle()

    @property
    def ahead(self) -> int:
        """Batches drawn and not yet handed out (queued or being handed out)."""
        return self.sampled - self.delivered

    @property
    def max_ahead(self) -> int:
        """The most batches :attr:`ahead` can reach."""
        return self._max_ahead

    def get(self, timeout: float) -> Batch | None:
        """The next batch, or None if none came within ``timeout`` seconds."""
        self.check()
        if not self._ready:
            try:
                self._ready.extend(self._queue.get(timeout=timeout))
            except queue.Empty:
                self.check()
                return None
            with self._room:  # its batches are being handed out: room for the next call, maybe
                self._room.notify()
        self.delivered += 1
        return self._ready.popleft()

    def _run(self) -> None:
        backoff = 0.1
        while self._wait_for_room():
            try:
                batches = self._draw()
            except SampleTimeout as e:  # too little data yet, the learner ahead of the actors, or no answer
                self.sample_waits += 1
                if unanswered(e):
                    self.link.failed(GRPC_DEADLINE_DETAILS, TRAINING_ON)
                elif self._log_wait():
                    log.info("waiting for data in replay: %s", e)
                continue
            except ReplayUnavailable as e:
                self.unavailable += 1
                self.link.failed(str(e), TRAINING_ON)
                self._stop.wait(backoff)
                backoff = min(2 * backoff, 5.0)
                continue
            self.link.ok()
            backoff = 0.1
            self.calls += 1
            self.sampled += len(batches)
            self._queue.put(batches)

    def _wait_for_room(self) -> bool:
        """Block until a whole call fits below :attr:`max_ahead` (counted when it had to wait); False
        once stopped. While it waits a call is queued, so get() takes one and says so."""
        if self.ahead + self.per_call <= self._max_ahead:
            return not self._stop.is_set()
        self.full_waits += 1
        start = time.monotonic()
        with self._room:
            while not self._stop.is_set() and self.ahead + self.per_call > self._max_ahead:
                self._room.wait(0.5)
        self.full_wait_seconds += time.monotonic() - start
        return not self._stop.is_set()

    def _draw(self) -> list[Batch]:
        sample_many = getattr(self.replay, "sample_many", None)  # a client has it; the in-process table need not
        if sample_many is None:
            return [self.replay.sample(self.batch_size, timeout=self.sample_timeout_s)]
        batches: list[Batch] = sample_many(self.batch_size, self.per_call, self.sample_timeout_s, self._allocate)
        return batches

    def metrics(self) -> dict[str, float]:
        return {
            "learner/prefetch_queue": float(self.ahead),
            "learner/prefetch_batches_per_call": self.sampled / max(self.calls, 1),
            "learner/prefetch_full_waits": float(self.full_waits),
            "learner/prefetch_full_wait_seconds": self.full_wait_seconds,
            "learner/sample_waits": float(self.sample_waits),
            "learner/replay_unavailable": float(self.unavailable),
        }


class PriorityUpdater(_Worker):
    """Sends priority updates to ``replay`` from a background thread.

    :meth:`put` queues ``(keys, |TD|)`` of one batch (a full queue of ``depth`` blocks the caller
    with a timeout loop, counted in ``full_waits``); the thread merges everything queued (up to
    ``merge`` batches; a key updated twice keeps its newest priority) into one call. UNAVAILABLE is
    retried with backoff, keeping the payload; :meth:`close` flushes what is left within its timeout
    and logs how many updates it could not send."""

    name = "priorities"

    def __init__(self, replay: ReplayTable, depth: int = 64, merge: int = 16, link: Outage | None = None) -> None:
        super().__init__()
        self.replay = replay
        self.link = link or replay_link(replay)
        self.merge = int(merge)
        self._queue: queue.Queue[tuple[np.ndarray, np.ndarray]] = queue.Queue(maxsize=depth)
        self.sent_calls = 0
        self.sent_keys = 0
        self.full_waits = 0
        self.full_wait_seconds = 0.0
        self.unavailable = 0
        self.unsent = 0
        self._closing = threading.Event()
        self._log_wait = Throttle()

    def put(self, keys: np.ndarray, priorities: np.ndarray) -> None:
        self.check()
        item = (np.asarray(keys), np.asarray(priorities, dtype=np.float64))
        try:
            self._queue.put_nowait(item)
            return
        except queue.Full:
            self.full_waits += 1
        start = time.monotonic()
        while True:
            self.check()
            try:
                self._queue.put(item, timeout=0.5)
                break
            except queue.Full:
                if self._log_wait():
                    log.warning("priority updates are backing up (replay slow or unreachable); learner waits")
        self.full_wait_seconds += time.monotonic() - start

    def close(self, timeout: float = 5.0) -> None:
        """Send what is queued (for at most ``timeout`` seconds), then stop the thread."""
        self._closing.set()
        if self._thread.is_alive():
            self._thread.join(timeout)
        self.stop(0.1)
        while True:
            try:
                keys, _ = self._queue.get_nowait()
            except queue.Empty:
                break
            self.unsent += len(keys)
        if self.unsent:
            log.warning("%d priority updates were not sent before shutdown", self.unsent)

    def pending(self) -> int:
        return self._queue.qsize()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                first = self._queue.get(timeout=0.2)
            except queue.Empty:
                if self._closing.is_set():
                    return
                continue
            items = [first]
            while len(items) < self.merge:
                try:
                    items.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            keys, priorities = merge_priorities(items)
            self._send(keys, priorities)

    def _send(self, keys: np.ndarray, priorities: np.ndarray) -> None:
        backoff = 0.1
        while not self._stop.is_set():
            try:
                self.replay.update_priorities(keys, priorities)
                self.link.ok()
                self.sent_calls += 1
                self.sent_keys += len(keys)
                return
            except ReplayUnavailable as e:
                self.unavailable += 1
                self.link.failed(str(e), "the learner keeps the priority updates and sends them again")
                self._stop.wait(backoff)
                backoff = min(2 * backoff, 5.0)
        self.unsent += len(keys)

    def metrics(self) -> dict[str, float]:
        return {
            "learner/priority_queue": float(self._queue.qsize()),
            "learner/priority_calls": float(self.sent_calls),
            "learner/priority_full_waits": float(self.full_waits),
            "learner/priority_full_wait_seconds": self.full_wait_seconds,
        }


def _pinned(nbytes: int) -> np.ndarray:
    """``nbytes`` of page-locked host memory (torch's caching host allocator) as a numpy array."""
    import torch

    return torch.empty(nbytes, dtype=torch.uint8, pin_memory=True).numpy()


def merge_priorities(items: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """One ``(keys, priorities)`` from several, in order; a key present twice keeps its last value."""
    keys = np.concatenate([k for k, _ in items])
    priorities = np.concatenate([p for _, p in items])
    _, last_first = np.unique(keys[::-1], return_index=True)
    keep = np.sort(len(keys) - 1 - last_first)
    return keys[keep], priorities[keep]
