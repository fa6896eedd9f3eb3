"""Statistical and adversarial tests of the float64 sum tree."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chisquare

from algorithm.replay.sum_tree import SumTree


def draw(tree: SumTree, n: int, rng: np.random.Generator, batch: int = 256) -> np.ndarray:
    return np.concatenate([tree.sample_stratified(batch, rng) for _ in range(n // batch)])


@pytest.mark.parametrize("capacity", [7, 1000])
def test_sampled_frequencies_match_leaf_values(capacity: int) -> None:
    rng = np.random.default_rng(0)
    values = rng.uniform(0.0, 1.0, capacity) ** 3  # skewed, like priorities ** alpha
    values[rng.choice(capacity, capacity // 5, replace=False)] = 0.0
    tree = SumTree(capacity)
    tree.set(np.arange(capacity), values)
    n = 256 * 2000
    counts = np.bincount(draw(tree, n, rng), minlength=capacity)
    assert counts[values == 0].sum() == 0
    live = values > 0
    expected = n * values[live] / values[live].sum()
    assert chisquare(counts[live], expected).pvalue > 0.001


def test_skewed_batch_of_one_is_unbiased() -> None:
    """With one segment per draw, frequencies follow the values exactly (no stratification help)."""
    rng = np.random.default_rng(1)
    values = np.array([1e-3, 0.0, 5.0, 1.0, 0.0, 0.25, 3.0])
    tree = SumTree(7)
    tree.set(np.arange(7), values)
    n = 40_000
    counts = np.bincount(draw(tree, n, rng, batch=1), minlength=7)
    live = values > 0
    assert counts[~live].sum() == 0
    assert chisquare(counts[live], n * values[live] / values.sum()).pvalue > 0.001


def test_zero_leaves_never_returned_adversarial() -> None:
    """Mostly zeros, a few tiny (even subnormal) values beside a huge one; every segment boundary
    and target at or past the total must still land on a positive leaf."""
    capacity = 1000
    tree = SumTree(capacity)
    positive = np.array([0, 1, 3, 500, 998])
    values = np.array([5e-324, 1e-300, 1e300, 1e-308, 2.5e-310])
    tree.set(positive, values)
    total = tree.total
    boundaries = np.cumsum(tree.get(np.arange(capacity)))
    targets = np.concatenate(
        [
            boundaries,
            np.nextafter(boundaries, 0.0),
            np.nextafter(boundaries, np.inf),
            [0.0, total, np.nextafter(total, np.inf), 2 * total, np.inf],
        ]
    )
    found = tree.find(targets)
    assert set(found.tolist()) <= set(positive.tolist())
    rng = np.random.default_rng(2)
    assert set(draw(tree, 256 * 100, rng).tolist()) <= set(positive.tolist())


def test_boundary_with_trailing_zero_leaves() -> None:
    tree = SumTree(6)
    tree.set(np.arange(6), np.array([0.1, 0.2, 0.3, 0.0, 0.0, 0.0]))
    # 0.1 + 0.2 + 0.3 rounds, so `u -= left` can exceed the right sum; the empty leaves 3..5 stay out.
    targets = np.array([tree.total, np.nextafter(tree.total, 0.0), 0.6, 0.6000000000000001])
    assert set(tree.find(targets).tolist()) <= {0, 1, 2}


def test_empty_tree_refuses_to_sample() -> None:
    tree = SumTree(5)
    with pytest.raises(ValueError, match="empty"):
        tree.sample_stratified(3, np.random.default_rng(0))


@pytest.mark.parametrize("capacity", [1, 2, 7, 1000, 1_000_003])
def test_any_capacity(capacity: int) -> None:
    rng = np.random.default_rng(capacity)
    tree = SumTree(capacity)
    values = rng.uniform(0.5, 2.0, capacity)
    tree.set(np.arange(capacity), values)
    assert np.array_equal(tree.get(np.arange(capacity)), values)
    assert tree.total == pytest.approx(math.fsum(values), rel=1e-12)
    found = tree.sample_stratified(512, rng)
    assert found.min() >= 0 and found.max() < capacity
    # the last leaf is reachable (padding leaves past it are not)
    assert tree.find(np.array([np.nextafter(tree.total, 0.0)]))[0] == capacity - 1


def test_drift_stays_bounded_over_a_million_updates() -> None:
    rng = np.random.default_rng(3)
    capacity = 10_007
    tree = SumTree(capacity)
    for _ in range(1000):
        idx = rng.integers(0, capacity, 1000)
        # mix magnitudes and zeros: the worst case for delta-updated trees
        vals = rng.choice([0.0, 1e-6, 1.0, 1e6], 1000) * rng.uniform(0.0, 1.0, 1000)
        tree.set(idx, vals)
    leaves = tree.get(np.arange(capacity))
    exact = math.fsum(leaves)
    assert abs(tree.total - exact) <= 1e-12 * exact
    fresh = SumTree(capacity)
    fresh.set_all(leaves)
    assert fresh.total == tree.total  # parents are a pure function of the leaves


def test_duplicate_indices_last_write_wins() -> None:
    tree = SumTree(4)
    tree.set(np.array([2, 2, 2]), np.array([1.0, 5.0, 3.0]))
    assert tree.get(np.array([2]))[0] == 3.0
    assert tree.total == 3.0


@pytest.mark.parametrize(
    ("indices", "values", "error"),
    [
        ([0, 4], [1.0, 1.0], IndexError),
        ([-1], [1.0], IndexError),
        ([0], [-1.0], ValueError),
        ([0], [np.nan], ValueError),
        ([0], [np.inf], ValueError),
        ([0, 1], [1.0], ValueError),
    ],
)
def test_set_rejects_bad_input(indices: list[int], values: list[float], error: type[Exception]) -> None:
    tree = SumTree(4)
    tree.set(np.arange(4), np.ones(4))
    with pytest.raises(error):
        tree.set(np.array(indices), np.array(values))
    assert np.array_equal(tree.get(np.arange(4)), np.ones(4))
    with pytest.raises(ValueError, match="capacity"):
        SumTree(0)
