"""The learner's background threads against a real loopback replay server, and the learner loop:
batches are prefetched without loss, full queues block and are counted, priority updates arrive
(merged, newest wins), an unreachable replay is waited out, and a stopped learner resumes."""

from __future__ import annotations

import logging
import re
import shutil
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch

from algorithm.config.load import load_config
from algorithm.replay import PrioritizedTable
from algorithm.run.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from algorithm.run.evaluation import read_evaluations
from algorithm.sac.learner import SAC
from ds.learner.feeds import BatchPrefetcher, PriorityUpdater, merge_priorities
from ds.learner.learner import EnvSteps, Learner
from ds.learner.service import ParamsStore
from ds.net.params import ParamsPublisher, decode_params, params_spec
from ds.net.rpc import RetryPolicy
from ds.replay.client import ReplayClient
from ds.replay.service import serve_replay
from envs.make import make_vector_env
from tests.algorithm.replay.chunks import VECTOR, make_chunk
from tests.damage import flip_in_largest_record, tree_digest
from tests.ds.conftest import ServeOverGrpc

pytestmark = pytest.mark.grpc
ROOT = Path(__file__).resolve().parents[3]


def until(condition: Callable[[], bool], timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out waiting for the condition"
        time.sleep(0.02)


def filled(capacity: int = 400, chunks: int = 5, t: int = 20) -> PrioritizedTable:
    table = PrioritizedTable(capacity, (VECTOR,), 2, window=2, alpha=0.6, seed=0)
    for i in range(chunks):
        table.insert(make_chunk(t, i * (t + 1)))
    return table


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_prefetcher_draws_only_with_room_and_counts(over_grpc: ServeOverGrpc) -> None:
    """Three batches per call, at most six ahead: the thread draws a call only while a whole one fits,
    and waits (counted) meanwhile; it never drops a batch."""
    client = over_grpc(filled())
    prefetcher = BatchPrefetcher(client, batch_size=8, depth=2, per_call=3)
    prefetcher.start()
    try:
        until(lambda: prefetcher.full_waits >= 1)  # two calls drawn, no room for a third: it waits
        assert prefetcher.sampled == 6 and prefetcher.metrics()["learner/prefetch_queue"] == 6
        batches = [prefetcher.get(timeout=5) for _ in range(4)]
        assert all(b is not None and b.batch_size == 8 for b in batches)
        # 4 handed out left 2 ahead: room for one more call, and only one (3 + 2 + 3 > 6)
        until(lambda: prefetcher.sampled == 9 and prefetcher.metrics()["learner/prefetch_queue"] == 5)
        time.sleep(0.7)  # waiting, not drawing, past its 0.5 s look again
        assert prefetcher.sampled == 9 and prefetcher.calls == 3
        assert prefetcher.max_ahead == 6
        assert prefetcher.full_waits >= 2
        rest = [prefetcher.get(timeout=5) for _ in range(5)]  # every batch drawn is handed out
        assert all(b is not None for b in rest) and prefetcher.delivered == 9
    finally:
        prefetcher.stop()


def test_prefetcher_draws_again_at_once_when_calls_come_back_short(over_grpc: ServeOverGrpc) -> None:
    """A rate limiter that lets one batch through per call (calls cut short) leaves room ahead: the
    thread draws the next call without waiting for the last one to be taken."""
    client = over_grpc(filled())
    real = client.sample_many
    client.sample_many = lambda b, n, t, a=None: real(b, 1, t, a)  # type: ignore[method-assign]
    prefetcher = BatchPrefetcher(client, batch_size=8, depth=2, per_call=3)
    prefetcher.start()
    try:
        until(lambda: prefetcher.sampled == 4)  # 1 + 1 + 1 + 1: four short calls fill the six, no get
        assert prefetcher.delivered == 0 and prefetcher.ahead == 4
    finally:
        prefetcher.stop()


def test_prefetcher_waits_for_data_and_for_an_unreachable_replay() -> None:
    port = free_port()
    client = ReplayClient(f"127.0.0.1:{port}", (VECTOR,), 2, retry=RetryPolicy(attempts=2, initial_backoff_s=0.05))
    prefetcher = BatchPrefetcher(client, batch_size=4, depth=2, sample_timeout_s=0.2)
    prefetcher.start()
    try:
        until(lambda: prefetcher.unavailable >= 1)  # no server yet: waited out, not fatal
        assert prefetcher.get(timeout=0.1) is None
        table = PrioritizedTable(400, (VECTOR,), 2, window=2, seed=0)
        server, _ = serve_replay(table, f"127.0.0.1:{port}")
        try:
            until(lambda: prefetcher.sample_waits >= 1)  # up but empty: SampleTimeout, waited out
            table.insert(make_chunk(10))
            assert prefetcher.get(timeout=20) is not None
            prefetcher.check()
        finally:
            server.stop(None)
    finally:
        prefetcher.stop()
        client.close()


def test_prefetcher_surfaces_other_replay_errors(over_grpc: ServeOverGrpc) -> None:
    client = over_grpc(filled())
    prefetcher = BatchPrefetcher(client, batch_size=0)  # INVALID_ARGUMENT from the server
    prefetcher.start()
    until(lambda: prefetcher.error is not None)
    with pytest.raises(RuntimeError, match="prefetch thread failed"):
        prefetcher.get(timeout=0.1)


def test_priority_updates_reach_the_replay_merged(over_grpc: ServeOverGrpc) -> None:
    table = filled()
    client = over_grpc(table)
    updater = PriorityUpdater(client, depth=16, merge=4)
    batches = [client.sample(16) for _ in range(10)]
    for b in batches:
        updater.put(b.keys, np.full(16, 0.5))  # queued before the thread starts: merged 4 + 4 + 2
    updater.start()
    updater.close(timeout=20)
    assert updater.unsent == 0 and updater.sent_calls == 3
    groups = [batches[:4], batches[4:8], batches[8:]]
    expected = sum(len(np.unique(np.concatenate([b.keys for b in g]))) for g in groups)
    assert table.info()["priority_updates"] == updater.sent_keys == expected


def test_merged_priorities_keep_the_newest_value_per_key() -> None:
    keys, priorities = merge_priorities(
        [
            (np.array([3, 5, 7], np.uint64), np.array([1.0, 1.0, 1.0])),
            (np.array([5, 9], np.uint64), np.array([2.0, 2.0])),
        ]
    )
    assert dict(zip(keys.tolist(), priorities.tolist(), strict=True)) == {3: 1.0, 5: 2.0, 7: 1.0, 9: 2.0}


class BlockingReplay:
    """A replay whose update_priorities blocks until released (a slow or stuck server)."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.calls = 0

    def update_priorities(self, keys: np.ndarray, priorities: np.ndarray) -> None:
        self.release.wait()
        self.calls += 1


def test_full_priority_queue_blocks_the_learner_and_counts() -> None:
    replay = BlockingReplay()
    updater = PriorityUpdater(replay, depth=1, merge=1)  # type: ignore[arg-type]
    updater.start()
    keys = np.arange(4, dtype=np.uint64)
    updater.put(keys, np.ones(4))  # taken by the thread, which blocks in the call
    until(lambda: updater.pending() == 0)
    updater.put(keys, np.ones(4))  # fills the queue
    done = threading.Event()
    threading.Thread(target=lambda: (updater.put(keys, np.ones(4)), done.set()), daemon=True).start()
    until(lambda: updater.full_waits == 1)
    assert not done.wait(0.3)  # blocked, not dropped
    replay.release.set()
    assert done.wait(10)
    updater.close(timeout=10)
    assert replay.calls == 3 and updater.unsent == 0


def test_priority_updates_wait_for_an_unreachable_replay() -> None:
    port = free_port()
    client = ReplayClient(f"127.0.0.1:{port}", (VECTOR,), 2, retry=RetryPolicy(attempts=2, initial_backoff_s=0.05))
    updater = PriorityUpdater(client)
    updater.start()
    table = filled()
    keys = table.sample(8).keys
    updater.put(keys, np.full(8, 0.7))
    until(lambda: updater.unavailable >= 1)
    server, _ = serve_replay(table, f"127.0.0.1:{port}")
    try:
        until(lambda: updater.sent_calls == 1)
        updater.close()
        assert table.info()["priority_updates"] == len(np.unique(keys))
    finally:
        server.stop(None)
        client.close()


def test_env_steps_survive_a_replay_restart() -> None:
    steps = EnvSteps()
    assert [steps.observe(n) for n in (100, 250, 30, 80)] == [100, 250, 280, 330]


SMALL = [
    "sac.seed=0",
    "nn.hidden_units=[16,16]",
    "replay.batch_size=16",
    "replay.samples_per_insert=null",
    "replay.min_size_to_sample=50",
    "eval.eval_per_step=0",
    "base.max_step=-1",
    "sac.write_summary_per_step=5",
]


def make_learner(
    tmp_path: Path, client: ReplayClient, stop: threading.Event, overrides: tuple[str, ...] = (), **kwargs: object
) -> Learner:
    config = load_config(ROOT / "envs/gym/pendulum", None, [*SMALL, *overrides]).config
    spec = make_vector_env("Pendulum-v1", 1, seed=0).spec
    sac = SAC(spec, config.sac_config, config.nn_config, config.replay_config)
    publisher = ParamsPublisher("tcp://127.0.0.1:*")
    return Learner(config, tmp_path, sac, client, publisher, ParamsStore(), stop=stop, **kwargs)  # type: ignore[arg-type]


def pendulum_table(steps: int) -> PrioritizedTable:
    env = make_vector_env("Pendulum-v1", 1, seed=0)
    sensors, a = env.spec.sensors, env.spec.action.size
    table = PrioritizedTable(10_000, sensors, a, window=3, seed=0)  # n_step 3
    rng = np.random.default_rng(0)
    for _ in range(steps // 50):
        chunk = make_chunk(50, 0, sensors, a)
        chunk.obs[0] = rng.normal(size=chunk.obs[0].shape).astype(np.float32)
        chunk.actions = rng.uniform(-1, 1, chunk.actions.shape).astype(np.float32)
        chunk.prev_actions = np.zeros_like(chunk.actions)
        chunk.behaviour_logp = np.zeros_like(chunk.behaviour_logp)
        table.insert(chunk)
    return table


def test_learner_trains_publishes_checkpoints_and_resumes(over_grpc: ServeOverGrpc, tmp_path: Path) -> None:
    client = over_grpc(pendulum_table(300))
    stop = threading.Event()
    learner = make_learner(tmp_path, client, stop, ("sac.publish_budget=0",))  # no budget: every update
    result: list = []
    thread = threading.Thread(target=lambda: result.append(learner.run()))
    thread.start()
    until(lambda: learner.updates >= 30, timeout_s=60)
    stop.set()
    thread.join(30)
    summary = result[0]
    assert summary.interrupted and summary.updates >= 30 and summary.env_steps == 300
    assert learner.store.version == learner.publisher.version == summary.updates  # published every update
    assert learner.publish_deferred == 0
    assert sorted((tmp_path / "model").glob("*.pt")) == [tmp_path / "model/300.pt"]
    assert any((tmp_path / "log/learner").iterdir())
    learner.publisher.close()

    again = make_learner(tmp_path, client, threading.Event())
    assert again.updates == summary.updates and again.env_steps.total == 300
    torch_state = again.sac.state_dict()["models"]
    for name, value in learner.sac.state_dict()["models"].items():
        assert (torch_state[name] == value).all(), name
    again.publisher.close()


class SlowEnv:
    """A vector env whose every step takes ``delay_s`` more: an evaluation that takes a while."""

    def __init__(self, env: object, delay_s: float) -> None:
        self.env, self.delay_s = env, delay_s

    def __getattr__(self, name: str) -> object:
        return getattr(self.env, name)

    def step(self, actions: np.ndarray) -> object:
        time.sleep(self.delay_s)
        return self.env.step(actions)  # type: ignore[attr-defined]


def test_an_evaluation_runs_beside_training_and_records_the_weights_it_scored(
    over_grpc: ServeOverGrpc, tmp_path: Path
) -> None:
    """With a copy of the acting weights to act with, the learner evaluates on a thread of its own:
    it goes on updating while an evaluation runs, and the row it writes names the updates and env
    steps of the weights it scored (those when it started), not those when it ended."""
    client = over_grpc(pendulum_table(300))
    stop = threading.Event()
    config = load_config(ROOT / "envs/gym/pendulum", None, [*SMALL, "eval.eval_per_step=100"]).config
    eval_env = SlowEnv(make_vector_env("Pendulum-v1", 1, seed=5), delay_s=0.01)  # 200 steps: >= 2 s an episode
    learner = make_learner(tmp_path, client, stop, ("eval.eval_per_step=100", "eval.eval_episodes=1"),
                           eval_env=eval_env, eval_policy=SAC(eval_env.spec, config.sac_config, config.nn_config,
                                                               config.replay_config))  # fmt: skip
    thread = threading.Thread(target=learner.run)
    thread.start()
    try:
        background = learner.core.background
        assert background is not None
        until(background.busy, timeout_s=60)
        started_at = learner.updates
        until(lambda: (tmp_path / "evaluations.csv").exists(), timeout_s=60)
        ended_at = learner.updates
    finally:
        stop.set()
        thread.join(30)
        learner.publisher.close()
    rows = read_evaluations(tmp_path / "evaluations.csv")
    assert ended_at - started_at >= 20, (started_at, ended_at)  # updates went on during the ~2 s evaluation
    assert rows[0]["env_steps"] == 300 and rows[0]["updates"] <= started_at  # the weights it was given


def test_publishing_keeps_to_its_budget_and_the_latest_weights_go_out_after_it(tmp_path: Path) -> None:
    """``publish_budget``: after a publish that took t seconds, none before t / budget seconds have passed
    (counted as deferred), the next update's after; ``force`` (new weights loaded) publishes at once.
    The cost here is made large (a slow copy of the acting weights) so that the wait is long."""
    learner = make_learner(tmp_path, pendulum_table(0), threading.Event(), ("sac.publish_budget=0.25",))  # type: ignore[arg-type]
    acting_state = learner.sac.acting_state_dict

    def slow_copy() -> dict:
        time.sleep(0.05)
        return acting_state()

    learner.sac.acting_state_dict = slow_copy  # type: ignore[method-assign]
    started = time.perf_counter()
    learner.core.counters.updates = 1
    learner.publish()
    assert learner.publisher.version == 1
    assert learner._next_publish >= started + 0.05 / 0.25  # its own cost / the budget: >= 0.2 s on
    learner.core.counters.updates = 2
    learner.publish()  # within the wait: deferred
    assert learner.publisher.version == 1 and learner.publish_deferred == 1
    learner.publish(force=True)  # a CEM sample loaded: at once
    assert learner.publisher.version == 2
    while time.perf_counter() < learner._next_publish:
        time.sleep(0.01)
    learner.core.counters.updates = 3
    learner.publish()  # the wait is over: the latest weights go out
    assert learner.publisher.version == learner.store.version == 3
    learner.publisher.close()


def test_learner_takes_the_replays_normalizer_stats_and_publishes_them(
    over_grpc: ServeOverGrpc, tmp_path: Path
) -> None:
    table = pendulum_table(300)
    client = over_grpc(table)
    stop = threading.Event()
    config = load_config(ROOT / "envs/gym/pendulum", None, [*SMALL, "sac.use_normalization=true"]).config
    spec = make_vector_env("Pendulum-v1", 1, seed=0).spec
    sac = SAC(spec, config.sac_config, config.nn_config, config.replay_config)
    publisher = ParamsPublisher("tcp://127.0.0.1:*")
    learner = Learner(config, tmp_path, sac, client, publisher, ParamsStore(), stop=stop)
    thread = threading.Thread(target=learner.run)
    thread.start()
    until(lambda: learner.updates >= 3, timeout_s=60)
    stop.set()
    thread.join(30)
    publisher.close()
    stats = table.normalizer_stats()["obs"]
    latest = learner.store.get()
    assert latest is not None
    _, params = decode_params(latest[1], params_spec(sac.acting_state_dict()))
    np.testing.assert_allclose(params["normalizer.mean_obs"], stats["mean"], rtol=1e-6)
    assert int(params["normalizer.count"]) == stats["count"]


def test_a_recurrent_learner_refreshes_the_stored_states_over_grpc(over_grpc: ServeOverGrpc, tmp_path: Path) -> None:
    rnn = ["sac.use_rnn=true", "sac.burn_in_step=2", "nn.rnn_units=8", "sac.refresh_rnn_states=true"]
    config = load_config(ROOT / "envs/gym/pendulum", None, [*SMALL, *rnn]).config
    spec = make_vector_env("Pendulum-v1", 1, seed=0).spec
    sac = SAC(spec, config.sac_config, config.nn_config, config.replay_config)
    table = PrioritizedTable(10_000, spec.sensors, spec.action.size, window=5, rnn_state_size=8, seed=0, burn_in=2)
    for i in range(6):
        table.insert(make_chunk(50, 51 * i, spec.sensors, spec.action.size, rnn_state_size=8))
    client = over_grpc(table)
    stop = threading.Event()
    publisher = ParamsPublisher("tcp://127.0.0.1:*")
    learner = Learner(config, tmp_path, sac, client, publisher, ParamsStore(), stop=stop)
    thread = threading.Thread(target=learner.run)
    thread.start()
    try:
        until(lambda: learner.updates >= 10, timeout_s=60)
    finally:
        stop.set()
        thread.join(30)
        publisher.close()
    assert table.info()["rnn_state_updates"] > 0 and learner.rnn_refreshes_skipped == 0


@pytest.mark.parametrize("damage", ["flipped byte", "another task's weights"])
def test_a_damaged_latest_checkpoint_stops_the_learner_naming_it(tmp_path: Path, damage: str) -> None:
    """No silent fallback to the older checkpoint: the error names the file and the --ckpt to pass."""
    table = pendulum_table(0)
    first = make_learner(tmp_path, table, threading.Event())  # type: ignore[arg-type]
    first.publisher.close()
    good = first.save()  # model/0.pt
    latest = tmp_path / "model/10.pt"
    if damage == "flipped byte":
        shutil.copyfile(good, latest)
        flip_in_largest_record(latest)
    else:  # a valid checkpoint whose first layer is shaped for another observation size
        state = load_checkpoint(good)
        models = state["sac"]["models"]
        name = next(k for k, v in models.items() if v.ndim == 2)
        models[name] = torch.zeros(models[name].shape[0], models[name].shape[1] + 5)
        save_checkpoint(tmp_path / "model", 10, {k: v for k, v in state.items() if k != "format_version"}, keep=5)
    before = tree_digest(tmp_path)
    with pytest.raises(CheckpointError, match=re.escape(f"checkpoint {latest} ")) as e:
        make_learner(tmp_path, table, threading.Event())  # type: ignore[arg-type]
    message = str(e.value)
    if damage == "flipped byte":
        assert "is damaged: its contents do not match the digest" in message and "--ckpt 0" in message
    else:
        assert "does not fit this run's models" in message and "size mismatch" in message
    assert tree_digest(tmp_path) == before


class PoisonedReplay:
    """A loopback replay client whose sampled batches number ``poisoned`` (1-based) get a NaN
    reward on their way into the learner: a batch corrupted inside the learner's process, where no
    wire check sees it."""

    def __init__(self, client: ReplayClient, poisoned: set[int]) -> None:
        self.client, self.poisoned, self.sampled = client, poisoned, 0

    def sample_many(self, batch_size: int, count: int, timeout: float | None = None, allocate: object = None) -> object:
        batches = self.client.sample_many(batch_size, count, timeout, allocate)  # type: ignore[arg-type]
        for batch in batches:
            self.sampled += 1
            if self.sampled in self.poisoned:
                batch.rewards[0, 0] = np.nan
        return batches

    def __getattr__(self, name: str) -> object:
        return getattr(self.client, name)


def test_a_nan_in_a_batch_never_reaches_the_weights_and_is_counted_and_logged(
    over_grpc: ServeOverGrpc, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    replay = PoisonedReplay(over_grpc(pendulum_table(300)), poisoned={3, 7})
    stop = threading.Event()
    learner = make_learner(tmp_path, replay, stop)  # type: ignore[arg-type]
    thread = threading.Thread(target=learner.run)
    with caplog.at_level(logging.WARNING, logger="asac.learner"):
        thread.start()
        try:
            until(lambda: learner.updates >= 20, timeout_s=60)
        finally:
            stop.set()
            thread.join(30)
            learner.publisher.close()
    assert learner.sac.nonfinite_skipped == 2 and learner.sac.updates == learner.updates - 2
    state = learner.sac.state_dict()
    for part in (state["models"], state["target_q"]):
        assert all(bool(torch.isfinite(v).all()) for v in part.values() if v.is_floating_point())
    assert all(
        bool(torch.isfinite(s).all())
        for opt in state["optimizers"].values()
        for param in opt["state"].values()
        for s in param.values()
    )
    assert bool(torch.isfinite(state["log_alpha"]))
    assert "update skipped: non-finite loss or gradient (1 skipped so far" in caplog.text  # then once per 30 s
