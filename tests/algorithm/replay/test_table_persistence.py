"""save/load: identical sampling after a round trip; bad or mismatched files change nothing."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from algorithm.replay import PrioritizedTable, RateLimiter
from algorithm.spaces import SensorSpec
from algorithm.types import Batch

from .chunks import IMAGE, VECTOR, make_chunk
from .conftest import Connect

SENSORS = (VECTOR, IMAGE)


def build(seed: int, **kwargs: Any) -> PrioritizedTable:
    limiter = RateLimiter(samples_per_insert=8.0, min_size_to_sample=4, tolerance=1e9)
    kwargs = {"capacity": 50, "sensors": SENSORS, "rnn_state_size": 3, **kwargs}
    return PrioritizedTable(
        kwargs.pop("capacity"),
        kwargs.pop("sensors"),
        2,
        3,
        alpha=0.7,
        rate_limiter=limiter,
        seed=seed,
        **kwargs,
    )


def populated(connect: Connect, seed: int = 0) -> Any:
    tab = connect(build(seed))
    rng = np.random.default_rng(seed)
    for t in (5, 12, 20, 9, 17):  # wraps the ring and evicts
        tab.insert(make_chunk(t, tab.info()["next_key"], SENSORS, rnn_state_size=3))
        batch = tab.sample(16)
        tab.update_priorities(batch.keys, rng.uniform(0.0, 2.0, 16))
    return tab


def assert_same_batch(a: Batch, b: Batch) -> None:
    for field in dataclasses.fields(Batch):
        x, y = getattr(a, field.name), getattr(b, field.name)
        if field.name == "obs":
            for u, v in zip(x, y, strict=True):
                np.testing.assert_array_equal(u, v)
        else:
            np.testing.assert_array_equal(x, y)


def assert_same_info(a: dict[str, Any], b: dict[str, Any]) -> None:
    skip = {"normalizer", "insert_wait_seconds", "sample_wait_seconds", "insert_waits", "sample_waits"}
    assert {k: v for k, v in a.items() if k not in skip} == {k: v for k, v in b.items() if k not in skip}
    for name, stats in a["normalizer"].items():
        assert stats["count"] == b["normalizer"][name]["count"]
        np.testing.assert_array_equal(stats["mean"], b["normalizer"][name]["mean"])
        np.testing.assert_allclose(stats["var"], b["normalizer"][name]["var"], rtol=1e-14)


def test_round_trip_continues_sampling_identically(connect: Connect, tmp_path: Path) -> None:
    original = populated(connect)
    path = tmp_path / "replay.npz"
    original.save(path)
    assert [p.name for p in tmp_path.iterdir()] == ["replay.npz"]  # no temp file left behind
    restored = connect(build(seed=123))  # a different seed: the saved random state must win
    restored.load(path)
    assert_same_info(original.info(), restored.info())
    for step in range(5):
        assert_same_batch(original.sample(32), restored.sample(32))
        keys = np.arange(70, 110, dtype=np.uint64)
        td = np.linspace(0.0, 3.0, 40)
        original.update_priorities(keys, td)
        restored.update_priorities(keys, td)
        chunk = make_chunk(4 + step, original.info()["next_key"], SENSORS, rnn_state_size=3)
        np.testing.assert_array_equal(original.insert(chunk), restored.insert(chunk))
    assert_same_info(original.info(), restored.info())


def test_save_overwrites_atomically(connect: Connect, tmp_path: Path) -> None:
    path = tmp_path / "replay.npz"
    path.write_bytes(b"old contents")
    tab = populated(connect)
    tab.save(path)
    with np.load(path, allow_pickle=False) as f:  # plain arrays, no pickles
        assert json.loads(str(f["meta"]))["next_key"] == tab.info()["next_key"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["replay.npz"]


def corrupt(path: Path, tmp_path: Path, **changes: Any) -> Path:
    """A copy of the saved file with arrays or meta entries replaced (None: removed)."""
    with np.load(path, allow_pickle=False) as f:
        data = {name: f[name] for name in f.files}
    meta = json.loads(str(data["meta"]))
    for name, value in changes.items():
        target = meta if name in meta else data
        if value is None:
            del target[name]
        else:
            target[name] = value
    data["meta"] = np.array(json.dumps(meta))
    out = tmp_path / "corrupt.npz"
    np.savez(out, **data)
    return out


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("garbage", "not a readable replay file"),
        ("truncated", "not a readable replay file"),
        ("missing", "not a readable replay file"),
        ("capacity", "saved capacity is 51"),
        ("sensors", "saved sensors"),
        ("alpha", "saved alpha"),
        ("dtype", "array 'rewards' is float64"),
        ("shape", "array 'actions'"),
        ("missing array", "do not match"),
        ("negative priority", "priorities must be finite"),
        ("bootstrap priority", "0 on bootstrap"),
        ("counters", "rate limiter counters"),
        ("keys", "row keys"),
        ("rng", "inconsistent replay file"),
        ("compression method", "not a readable replay file"),
        ("counters of another type", "inconsistent replay file"),
        ("infinite next key", "inconsistent replay file"),
    ],
)
def test_bad_file_raises_and_leaves_the_table_intact(connect: Connect, tmp_path: Path, case: str, message: str) -> None:
    good = tmp_path / "good.npz"
    populated(connect, seed=1).save(good)
    with np.load(good, allow_pickle=False) as f:
        leaves, row_key, end_key = f["priorities"].copy(), f["row_key"].copy(), f["end_key"].copy()
        meta = json.loads(str(f["meta"]))
    bootstrap = int(np.flatnonzero((row_key == end_key) & (row_key >= 0))[0])
    if case == "garbage":
        path = tmp_path / "garbage.npz"
        path.write_bytes(b"\x00" * 100)
    elif case == "truncated":
        path = tmp_path / "truncated.npz"
        path.write_bytes(good.read_bytes()[:5000])
    elif case == "missing":
        path = tmp_path / "nope.npz"
    elif case == "capacity":
        path = corrupt(good, tmp_path, capacity=51)
    elif case == "sensors":
        path = corrupt(good, tmp_path, sensors=[["state", [4], "<f4"], ["pixels", [4, 4, 3], "|u1"]])
    elif case == "alpha":
        path = corrupt(good, tmp_path, alpha=0.5)
    elif case == "dtype":
        path = corrupt(good, tmp_path, rewards=np.zeros(50))
    elif case == "shape":
        path = corrupt(good, tmp_path, actions=np.zeros((50, 3), np.float32))
    elif case == "missing array":
        path = corrupt(good, tmp_path, rnn_state=None)
    elif case == "negative priority":
        path = corrupt(good, tmp_path, priorities=np.where(np.arange(50) == 7, -1.0, leaves))
    elif case == "bootstrap priority":
        path = corrupt(good, tmp_path, priorities=np.where(np.arange(50) == bootstrap, 1.0, leaves))
    elif case == "counters":
        path = corrupt(good, tmp_path, rate_limiter={**meta["rate_limiter"], "evicted": 0})
    elif case == "keys":
        path = corrupt(good, tmp_path, row_key=np.roll(row_key, 1))
    elif case == "rng":
        path = corrupt(good, tmp_path, rng={"bit_generator": "PCG64", "state": "nonsense"})
    elif case == "compression method":  # in the zip's central directory: numpy's reader cannot even start
        data = bytearray(good.read_bytes())
        data[data.find(b"PK\x01\x02") + 10] = 77
        path = tmp_path / "method.npz"
        path.write_bytes(bytes(data))
    elif case == "counters of another type":
        path = corrupt(good, tmp_path, counters=[1, 2])
    else:
        path = corrupt(good, tmp_path, next_key=float("inf"))

    tab, twin = populated(connect, seed=2), populated(connect, seed=2)
    with pytest.raises(ValueError, match=message):
        tab.load(path)
    assert_same_info(tab.info(), twin.info())
    assert_same_batch(tab.sample(16), twin.sample(16))


def test_mismatched_table_is_refused(connect: Connect, tmp_path: Path) -> None:
    path = tmp_path / "replay.npz"
    populated(connect).save(path)
    other = connect(build(seed=0, sensors=(VECTOR, SensorSpec("pixels", (4, 4, 1), np.dtype(np.uint8)))))
    with pytest.raises(ValueError, match="saved sensors"):
        other.load(path)
    with pytest.raises(ValueError, match="saved rnn_state_size is 3"):
        connect(build(seed=0, rnn_state_size=0)).load(path)
