"""Sampled batches packed in one buffer (ds/replay/packed.py), and the learner's side of the transport:
several batches per call, large batches through a real server on loopback."""

from __future__ import annotations

import time

import numpy as np
import pytest

from algorithm.replay import PrioritizedTable, RateLimiter
from algorithm.spaces import SensorSpec
from algorithm.types import Batch, Chunk
from ds.learner.feeds import BatchPrefetcher
from ds.net.wire import WireError
from ds.replay.codec import ReplaySpecs, batches_per_reply, message_limit_bytes, sample_reply, split_sample_reply
from ds.replay.packed import ALIGN, BatchLayout, pack_batches, unpack_batches
from tests.ds.conftest import ServeOverGrpc

VECTOR = SensorSpec("state", (3,))
IMAGE = SensorSpec("pixels", (4, 4, 1), np.dtype(np.uint8))
WIDE = SensorSpec("wide", (2,), np.dtype(np.float64))


def random_batch(rng: np.random.Generator, sensors: tuple[SensorSpec, ...], b: int, length: int, rnn: int) -> Batch:
    def obs(s: SensorSpec) -> np.ndarray:
        shape = (b, length + 1, *s.shape)
        if np.dtype(s.dtype).kind == "u":
            return rng.integers(0, 256, shape, dtype=np.uint8)
        return rng.standard_normal(shape).astype(s.dtype)

    return Batch(
        keys=rng.integers(0, 2**40, b, dtype=np.uint64),
        probabilities=rng.uniform(0.0, 1.0, b),
        table_size=int(rng.integers(1, 1000)),
        obs=[obs(s) for s in sensors],
        actions=rng.standard_normal((b, length, 2), dtype=np.float32),
        prev_actions=rng.standard_normal((b, length, 2), dtype=np.float32),
        rewards=rng.standard_normal((b, length), dtype=np.float32),
        terminated=rng.random((b, length)) < 0.2,
        truncated=rng.random((b, length)) < 0.2,
        behaviour_logp=rng.standard_normal((b, length), dtype=np.float32),
        mask=rng.random((b, length)) < 0.8,
        rnn_state=rng.standard_normal((b, rnn), dtype=np.float32) if rnn else None,
    )


def assert_same(got: Batch, sent: Batch) -> None:
    assert got.table_size == sent.table_size
    for name in ("keys", "probabilities", "actions", "prev_actions", "rewards", "terminated", "truncated",
                 "behaviour_logp", "mask", "rnn_state"):  # fmt: skip
        a, b = getattr(got, name), getattr(sent, name)
        if b is None:
            assert a is None, name
            continue
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b), name
    assert len(got.obs) == len(sent.obs)
    for a, b in zip(got.obs, sent.obs, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)


@pytest.mark.parametrize(
    ("sensors", "b", "length", "rnn"),
    [((VECTOR,), 5, 1, 0), ((IMAGE, VECTOR, WIDE), 3, 4, 6), ((VECTOR, IMAGE), 1, 2, 0)],
)
def test_batches_come_back_exactly_as_packed_and_each_field_is_aligned(
    sensors: tuple[SensorSpec, ...], b: int, length: int, rnn: int
) -> None:
    rng = np.random.default_rng(0)
    layout = BatchLayout.of(sensors, 2, b, length, rnn)
    sent = [random_batch(rng, sensors, b, length, rnn) for _ in range(3)]
    data = pack_batches(layout, sent)
    assert len(data) == 3 * layout.batch_bytes and layout.batch_bytes % ALIGN == 0
    assert all(f.offset % ALIGN == 0 for f in layout.fields)
    got = unpack_batches(layout, data, [s.table_size for s in sent])
    for g, s in zip(got, sent, strict=True):
        assert_same(g, s)
        g.rewards[0, 0] = 7.0  # writable: the learner's memory, not the reply's bytes


def test_a_reply_of_the_wrong_length_or_with_a_bad_value_is_refused_naming_the_field() -> None:
    rng = np.random.default_rng(1)
    sensors = (VECTOR, IMAGE)
    layout = BatchLayout.of(sensors, 2, 4, 2, 0)
    good = [random_batch(rng, sensors, 4, 2, 0) for _ in range(2)]
    data = pack_batches(layout, good)
    with pytest.raises(WireError, match="data has .* bytes, but 3 batches of 4 windows of 2 steps take"):
        unpack_batches(layout, data, [1, 2, 3])
    with pytest.raises(WireError, match="data has"):
        unpack_batches(layout, data[:-8], [1, 2])

    for name, value, message in (
        ("actions", np.nan, "actions has non-finite values"),
        ("obs", np.inf, r"obs\[0\] has non-finite values"),
        ("behaviour_logp", -np.inf, "behaviour_logp has non-finite values"),
    ):
        bad = random_batch(rng, sensors, 4, 2, 0)
        (bad.obs[0] if name == "obs" else getattr(bad, name))[1, 0] = value
        with pytest.raises(WireError, match=message):
            unpack_batches(layout, pack_batches(layout, [good[0], bad]), [1, 2])

    raw = bytearray(data)
    mask = next(f for f in layout.fields if f.name == "mask")
    raw[layout.batch_bytes + mask.offset + 3] = 2  # a bool byte other than 0 or 1, in the second batch
    with pytest.raises(WireError, match="mask is bool but holds bytes other than 0 and 1"):
        unpack_batches(layout, bytes(raw), [1, 2])

    wide = (WIDE,)
    wide_layout = BatchLayout.of(wide, 2, 2, 1, 0)
    bad = random_batch(rng, wide, 2, 1, 0)
    bad.obs[0][0, 0, 0] = np.nan
    with pytest.raises(WireError, match=r"obs\[0\] has non-finite values"):
        unpack_batches(wide_layout, pack_batches(wide_layout, [bad]), [1])


def test_a_reply_that_is_not_the_batch_asked_for_is_refused() -> None:
    specs = ReplaySpecs((VECTOR,), 2)
    rng = np.random.default_rng(2)
    reply = sample_reply(specs.layout(4, 1), [random_batch(rng, (VECTOR,), 4, 1, 0)])
    assert len(specs.batches_from_reply(reply, 4)) == 1
    with pytest.raises(WireError, match="batch_size is 4, expected 8"):
        specs.batches_from_reply(reply, 8)
    with pytest.raises(WireError, match="window is 1, expected 3"):
        specs.batches_from_reply(reply, 4, window=3)


def chunk(rng: np.random.Generator, t: int, rnn: int = 0) -> Chunk:
    return Chunk(
        obs=[rng.standard_normal((t + 1, 3), dtype=np.float32)],
        actions=rng.uniform(-1, 1, (t, 2)).astype(np.float32),
        prev_actions=np.zeros((t, 2), dtype=np.float32),
        rewards=rng.standard_normal(t, dtype=np.float32),
        terminated=np.zeros(t, dtype=bool),
        truncated=np.zeros(t, dtype=bool),
        behaviour_logp=np.zeros(t, dtype=np.float32),
        rnn_state=rng.standard_normal((t, rnn), dtype=np.float32) if rnn else None,
    )


def test_one_call_carries_several_batches_each_its_own_sample(over_grpc: ServeOverGrpc) -> None:
    rng = np.random.default_rng(3)
    table = PrioritizedTable(5000, (VECTOR,), 2, 1, alpha=0.0, seed=0)
    for _ in range(40):
        table.insert(chunk(rng, 100))
    replay = over_grpc(table)
    batches = replay.sample_many(64, 5, timeout=5.0)
    assert [b.batch_size for b in batches] == [64] * 5
    assert len({tuple(b.keys) for b in batches}) == 5  # five draws, not one batch repeated

    prefetcher = BatchPrefetcher(replay, 64, depth=4, per_call=4)
    prefetcher.start()
    try:
        got = [prefetcher.get(timeout=10.0) for _ in range(12)]
    finally:
        prefetcher.stop()
    assert all(b is not None and b.batch_size == 64 for b in got)
    assert prefetcher.calls < prefetcher.sampled  # several batches per call


def test_only_the_batches_the_rate_limiter_allows_at_once_come_back(over_grpc: ServeOverGrpc) -> None:
    """Five asked for, the ratio allows two: two come back at once, without waiting for the rest."""
    rng = np.random.default_rng(4)
    limiter = RateLimiter(samples_per_insert=2.0, min_size_to_sample=10, tolerance=0.0)
    table = PrioritizedTable(1000, (VECTOR,), 2, 1, alpha=0.0, rate_limiter=limiter, seed=0)
    table.insert(chunk(rng, 30))  # 20 steps past min_size_to_sample, x 2 samples each: two batches of 20
    replay = over_grpc(table)
    began = time.monotonic()
    batches = replay.sample_many(20, 5, timeout=5.0)
    assert len(batches) == 2 and time.monotonic() - began < 4.0


@pytest.mark.parametrize(("b", "length", "rnn"), [(4096, 1, 0), (16384, 1, 0), (4096, 6, 16)])
def test_large_batches_pass_with_the_limits_the_config_gives(over_grpc: ServeOverGrpc, b: int, length: int,
                                                             rnn: int) -> None:  # fmt: skip
    rng = np.random.default_rng(5)
    table = PrioritizedTable(40_000, (VECTOR,), 2, length, alpha=0.0, rnn_state_size=rnn, seed=0)
    for _ in range(60):
        table.insert(chunk(rng, 500, rnn))
    limit = message_limit_bytes((VECTOR,), 2, b, length, rnn, max_chunk_steps=500)
    replay = over_grpc(table, max_message_bytes=limit)
    batches = replay.sample_many(b, 8, timeout=10.0)
    fitting = batches_per_reply((VECTOR,), 2, b, length, rnn, limit)  # the table has no rate limiter: all that fit
    assert fitting >= 1 and len(batches) == min(8, fitting)  # as many as asked for, or as the limit lets through
    assert all(x.batch_size == b and x.window == length for x in batches)
    assert (batches[0].rnn_state is not None) == bool(rnn)


@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="pinned memory needs CUDA")
def test_on_cuda_batches_land_in_pinned_memory(over_grpc: ServeOverGrpc) -> None:
    import torch

    rng = np.random.default_rng(6)
    table = PrioritizedTable(2000, (VECTOR,), 2, 1, alpha=0.0, seed=0)
    table.insert(chunk(rng, 500))
    prefetcher = BatchPrefetcher(over_grpc(table), 32, pin_memory=True)
    prefetcher.start()
    try:
        batch = prefetcher.get(timeout=10.0)
    finally:
        prefetcher.stop()
    assert batch is not None and torch.from_numpy(batch.actions).is_pinned()


def test_a_reply_split_from_its_bytes_is_the_message_and_a_bad_one_is_refused() -> None:
    specs = ReplaySpecs((VECTOR,), 2)
    rng = np.random.default_rng(7)
    sent = [random_batch(rng, (VECTOR,), 4, 1, 0) for _ in range(2)]
    reply = sample_reply(specs.layout(4, 1), sent)
    header, data = split_sample_reply(reply.SerializeToString())
    assert (header.batch_size, header.window, list(header.table_size), header.data) == (
        4,
        1,
        [s.table_size for s in sent],
        b"",
    )
    assert bytes(data) == reply.data
    for got, batch in zip(specs.batches_from_reply(header, 4, data=data), sent, strict=True):
        assert_same(got, batch)
    raw = reply.SerializeToString()
    with pytest.raises(WireError, match="runs past the message's end"):
        split_sample_reply(raw[:-1])
    with pytest.raises(WireError, match="has field 9 of wire type 0"):
        split_sample_reply(raw + bytes([9 << 3, 1]))
    with pytest.raises(WireError, match="ends inside a number"):
        split_sample_reply(bytes([1 << 3, 0x80]))
