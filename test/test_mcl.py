"""Markov clustering: planted clusters, agreement with the dense reference, high inflation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from neurncd_ros.core.discovery.mcl import MCLConfig, knn_graph, markov_cluster, mcl, \
    mcl_dense_reference
from neurncd_ros.core.discovery.metrics import adjusted_rand_index

torch.set_num_threads(1)


def _blocks(sizes, within=1.0, between=0.05):
    truth = np.repeat(np.arange(len(sizes)), sizes)
    A = np.where(truth[:, None] == truth[None, :], within, between)
    np.fill_diagonal(A, 0.0)
    return A, truth


def _groups(n, groups, dim=38, noise=0.6, seed=0):
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(groups, dim))
    y = rng.integers(0, groups, n)
    return (centres[y] + noise * rng.normal(size=(n, dim))).astype(np.float32), y


@pytest.mark.parametrize("inflation", [2, 3, 4, 6, 12, 20])
def test_planted_blocks_found_and_match_dense_reference(inflation):
    A, truth = _blocks([5, 8, 3, 6, 12])
    dense = mcl_dense_reference(A, inflation=inflation)
    sparse = mcl(sp.csr_matrix(A), inflation=inflation)
    assert dense.tolist() == truth.tolist()
    assert sparse.tolist() == truth.tolist()
    assert mcl(A, inflation=inflation).tolist() == truth.tolist()  # dense input too


@pytest.mark.parametrize("inflation", [1.5, 2.0, 3.0])
def test_noisy_blocks_agree_with_dense_reference(inflation):
    rng = np.random.default_rng(1)
    A, truth = _blocks([10, 14, 7, 9], within=0.8, between=0.1)
    A = A + rng.uniform(0, 0.15, A.shape)
    A = (A + A.T) / 2
    np.fill_diagonal(A, 0)
    ref = mcl_dense_reference(A, inflation=inflation)
    got = mcl(A, inflation=inflation, prune_threshold=0.0, max_column_entries=10**6)
    assert adjusted_rand_index(ref, got) == pytest.approx(1.0)


def test_high_inflation_on_small_dense_matrix_gives_clusters_not_zero():
    # Where sklearn-normalize-based MCL underflows and returns no cluster.
    rng = np.random.default_rng(2)
    A, truth = _blocks([4, 4, 4], within=0.9, between=0.3)
    A = A + rng.uniform(0, 0.05, A.shape)
    A = (A + A.T) / 2
    for r in (12.0, 20.0, 40.0):
        lab = mcl(A, inflation=r)
        assert lab.shape == (12,)
        assert lab.min() == 0 and 1 <= lab.max() + 1 <= 12
        assert sorted(set(lab.tolist())) == list(range(lab.max() + 1))


def test_markov_cluster_recovers_groups_at_inflation_2():
    x, y = _groups(600, 6, seed=3)
    lab = markov_cluster(x, MCLConfig(affinity="cosine", inflation=2.0, k=20))
    assert adjusted_rand_index(y, lab) > 0.95
    # Higher inflation splits (more clusters), it never returns nothing.
    lab12 = markov_cluster(x, MCLConfig(affinity="cosine", inflation=12.0, k=20))
    assert lab12.max() + 1 > lab.max() + 1


def test_deterministic_and_order_invariant():
    x, y = _groups(300, 4, seed=4)
    cfg = MCLConfig(k=15)
    a = markov_cluster(x, cfg)
    assert markov_cluster(x, cfg).tolist() == a.tolist()
    perm = np.random.default_rng(0).permutation(len(x))
    b = markov_cluster(x[perm], cfg)
    assert adjusted_rand_index(a[perm], b) == pytest.approx(1.0)
    # Ids are numbered by smallest member: the first node is always in cluster 0.
    assert a[0] == 0 and b[0] == 0


def test_exp_affinity_clusters_groups():
    x, y = _groups(400, 5, seed=5)
    x = x / 5.0  # within-group distances ~1, between ~2 (eta acts on absolute distance)
    lab = markov_cluster(x, MCLConfig(affinity="exp", eta=2.0, inflation=1.6, k=20))
    assert adjusted_rand_index(y, lab) > 0.9


def test_knn_graph_is_symmetric_and_sparse():
    x, _ = _groups(200, 3, seed=6)
    A = knn_graph(x, MCLConfig(k=10))
    assert A.shape == (200, 200)
    assert abs(A - A.T).max() == 0
    assert A.diagonal().max() == 0
    assert ((A > 0).sum(axis=1) >= 10).all() and A.nnz <= 2 * 200 * 10
    assert A.data.min() > 0 and A.data.max() <= 1.0 + 1e-6


def test_pruning_caps_column_entries_without_losing_structure():
    x, y = _groups(800, 8, seed=7)
    cfg = MCLConfig(affinity="cosine", inflation=2.0, k=30, max_column_entries=40)
    lab = markov_cluster(x, cfg)
    assert adjusted_rand_index(y, lab) > 0.9


def test_small_and_bad_inputs():
    assert markov_cluster(np.zeros((0, 4), np.float32)).shape == (0,)
    assert markov_cluster(np.ones((1, 4), np.float32)).tolist() == [0]
    assert mcl(np.zeros((3, 3))).tolist() == [0, 1, 2]  # isolated nodes are singletons
    with pytest.raises(ValueError, match="square"):
        mcl(np.ones((2, 3)))
    with pytest.raises(ValueError, match="non-negative"):
        mcl(-np.ones((3, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        markov_cluster(np.full((3, 2), np.nan, np.float32))
    with pytest.raises(ValueError, match=r"\(n, D\)"):
        markov_cluster(np.ones(5, np.float32))
    with pytest.raises(ValueError, match="inflation"):
        mcl(np.ones((3, 3)), inflation=1.0)
    assert dataclasses.replace(MCLConfig(), k=5).k == 5
