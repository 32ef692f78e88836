"""Clustering of adverb points (Rose 1999, Algorithms 4.1 and 4.2): the worked example, no empty
cluster, seeded results, and ImprovedClustering starting at D + 1 clusters."""

from __future__ import annotations

import numpy as np
import pytest

from retarget.clustering import basic_clustering, improved_clustering


def test_basic_clustering_worked_example() -> None:
    c = basic_clustering([-10.0, 0.0, 1.0, 10.0], 3, rng=np.random.default_rng(0))
    assert c.cost == pytest.approx(0.5)
    groups = sorted(sorted([-10.0, 0.0, 1.0, 10.0][i] for i in g) for g in c.members())
    assert groups == [[-10.0], [0.0, 1.0], [10.0]]
    s = basic_clustering([-10.0, 0.0, 1.0, 10.0], 4, rng=np.random.default_rng(0))
    assert s.cost == 0.0


def test_clusters_never_empty_and_seeded() -> None:
    for seed in range(20):
        rng = np.random.default_rng(seed)
        pts = rng.normal(size=(9, 2)) * np.array([1.0, 3.0])
        n = int(rng.integers(1, 10))
        c = basic_clustering(pts, n, rng=np.random.default_rng(seed), restarts=4)
        assert c.count == n
        assert np.all(np.bincount(c.labels, minlength=n) >= 1)
        again = basic_clustering(pts, n, rng=np.random.default_rng(seed), restarts=4)
        np.testing.assert_array_equal(c.labels, again.labels)
    with pytest.raises(ValueError):
        basic_clustering([0.0, 1.0], 3, rng=np.random.default_rng(0))


def test_improved_clustering_starts_at_d_plus_1() -> None:
    rng = np.random.default_rng(9)
    centres = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    pts = np.repeat(centres, 3, axis=0) + rng.normal(scale=0.1, size=(12, 2))
    loose = improved_clustering(pts, max_cost=1e9, max_clusters=12, rng=np.random.default_rng(0))
    assert loose.count == 3  # D + 1, not D
    tight = improved_clustering(pts, max_cost=2.0, max_clusters=12, rng=np.random.default_rng(0))
    assert tight.count == 4 and tight.cost <= 2.0
    with pytest.raises(ValueError):
        improved_clustering(pts[:2], max_cost=1.0, max_clusters=2, rng=np.random.default_rng(0))
