"""RunningMeanStd: exact under any batching and merging, stable far from zero, checkpointable."""

from __future__ import annotations

import numpy as np
import pytest

from algorithm.normalizer import RunningMeanStd


def test_batched_updates_and_merges_equal_a_single_pass() -> None:
    rng = np.random.default_rng(0)
    data = rng.normal(1e6, 3.0, size=(5000, 4, 2))  # far from zero: naive sum-of-squares would lose digits
    cuts = np.sort(rng.choice(np.arange(1, 5000), 40, replace=False))
    pieces = np.split(data, cuts)

    streamed = RunningMeanStd((4, 2))
    for piece in pieces:
        streamed.update(piece)
    merged = RunningMeanStd((4, 2))
    for part in (pieces[:10], pieces[10:11], pieces[11:]):
        worker = RunningMeanStd((4, 2))
        for piece in part:
            worker.update(piece)
        merged.merge(worker)

    for rms in (streamed, merged):
        assert rms.count == 5000
        np.testing.assert_allclose(rms.mean, data.mean(axis=0), rtol=1e-14)
        np.testing.assert_allclose(rms.var, data.var(axis=0), rtol=1e-9)


def test_empty_inputs_change_nothing() -> None:
    rms = RunningMeanStd((3,))
    rms.update(np.zeros((0, 3)))
    rms.merge(RunningMeanStd((3,)))
    assert rms.count == 0 and not rms.var.any()
    rms.update(np.array([[1.0, 2.0, 3.0]]))
    empty = RunningMeanStd((3,))
    empty.merge(rms)
    np.testing.assert_array_equal(empty.mean, [1.0, 2.0, 3.0])


def test_normalize_standardises_and_clips() -> None:
    rms = RunningMeanStd((2,))
    rms.update(np.array([[0.0, 10.0], [2.0, 10.0], [4.0, 10.0]]))
    out = rms.normalize(np.array([[2.0, 10.0], [100.0, 1e9], [-100.0, 10.0]]), clip=5.0)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out[0], [0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(out[1], [5.0, 5.0])  # constant feature: epsilon keeps it finite, then clipped
    np.testing.assert_allclose(out[2, 0], -5.0)


def test_state_dict_round_trip_and_validation() -> None:
    rms = RunningMeanStd((2,))
    rms.update(np.random.default_rng(1).normal(size=(100, 2)))
    copy = rms.copy()
    np.testing.assert_array_equal(copy.mean, rms.mean)
    np.testing.assert_allclose(copy.var, rms.var, rtol=1e-15)
    copy.update(np.ones((1, 2)))
    assert rms.count == 100  # the copy is independent
    with pytest.raises(ValueError, match="expected shape"):
        RunningMeanStd((3,)).load_state_dict(rms.state_dict())
    with pytest.raises(ValueError, match="var >= 0"):
        RunningMeanStd((2,)).load_state_dict({"count": 1, "mean": np.zeros(2), "var": -np.ones(2)})


def test_bad_batches_are_named() -> None:
    rms = RunningMeanStd((2,))
    with pytest.raises(ValueError, match=r"expected \[N, \*\(2,\)\]"):
        rms.update(np.zeros((5, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        rms.update(np.array([[0.0, np.nan]]))
    with pytest.raises(ValueError, match="shapes differ"):
        rms.merge(RunningMeanStd((3,)))
    assert rms.count == 0
