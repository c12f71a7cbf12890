"""Markov clustering (van Dongen 2000) of segment descriptors on a sparse graph.

Steps: a top-``k`` affinity graph of the descriptors (symmetrised by max),
self-loops, column normalisation, then alternate expansion (matrix power
``expansion``) and inflation (Hadamard power ``inflation`` then column
normalisation) with pruning until the matrix stops changing. Clusters are read
from the attractors: every node joins the row holding its column's largest
value; nodes linked that way (including attractors pointing at each other)
form one cluster, numbered by their smallest member index, so the result is
deterministic and invariant to nothing but the input order.

Numerical care, because inflation can be large (the paper uses 12):
- float64 throughout;
- before the Hadamard power every column is divided by its own maximum, so the
  largest entry becomes exactly 1 and cannot underflow (the PyPI
  ``markov-clustering`` package returns zero clusters at inflation 12 on a
  small dense matrix because its columns underflow and stay unnormalised);
- pruning removes entries below ``prune_threshold`` times the column maximum
  but never a column's largest entry, and keeps at most ``max_column_entries``
  entries per column, so memory stays bounded on 20,000 segments.

Affinity: "cosine" (the paper; negatives clipped to 0) or "exp" (SCIM's kernel
exp(-eta * d) of the Euclidean distance d between descriptors). Both give 1 for
identical descriptors, matching the default constant self-loop of 1. The
descriptors of :mod:`modulation` have a fixed scale (unit embedding part), so
eta is not normalised by the data: dividing d by its mean neighbour distance
would make the kernel depend on how many segments are in memory, and MCL
fragments into singletons on large graphs.

Defaults. MCL depends sharply on the inflation and on the affinity's
contrast: a correct MCL at the paper's inflation 12 on a top-30 graph of this
project's segment descriptors returns near-singletons. The shipped defaults
(exp affinity, eta 6, inflation 1.4, k 30, constant self-loop 1) were chosen
on the tuning seeds only, first at the descriptor level (``bench/discovery.py``
``tune_*``: adjusted Rand index of segment clusters against their majority
ground-truth class) and then end to end (``bench/ncd.py --tune``, mean mIoU
over all classes, jointly with the labelling thresholds), which decides where
the two disagree; the paper's setting is the ``paper_mcl`` row of
bench/results/ncd.json.
"""

from __future__ import annotations

import dataclasses
from typing import Iterable, Sequence

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import connected_components

from ..params import param


@dataclasses.dataclass(frozen=True)
class MCLConfig:
    """Graph construction and Markov-clustering parameters."""

    affinity: str = param("exp", "descriptor affinity: cosine (paper) or exp (SCIM kernel)",
                          choices=("cosine", "exp"))
    eta: float = param(6.0, "exp affinity: exp(-eta * Euclidean distance)",
                       lo=0.0, hi=100.0)
    k: int = param(30, "neighbours kept per node in the affinity graph (top-k)", lo=1, hi=1000)
    inflation: float = param(1.4, "inflation power r (higher = more, smaller clusters)",
                             lo=1.01, hi=50.0)
    expansion: int = param(2, "expansion power e (matrix power per iteration)", lo=2, hi=6)
    loop_mode: str = param("constant", "self-loop weight: self_loop times the node's strongest "
                           "edge (scale free) or the constant self_loop",
                           choices=("max", "constant"))
    self_loop: float = param(1.0, "weight of the self-loop added to every node", lo=0.0,
                             hi=100.0)
    prune_threshold: float = param(1e-4, "drop entries below this fraction of their column "
                                   "maximum", lo=0.0, hi=0.5)
    max_column_entries: int = param(128, "keep at most this many entries per column",
                                    lo=2, hi=100000)
    max_iterations: int = param(100, "iteration cap", lo=1, hi=10000)
    tol: float = param(1e-6, "converged when no entry changes by more than this",
                       lo=0.0, hi=1.0)


# ---------------------------------------------------------------- graph

def _check_descriptors(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x)
    if x.ndim != 2:
        raise ValueError(f"descriptors must be (n, D), got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("descriptors contain non-finite values")
    return x.astype(np.float32, copy=False)


def knn_graph(descriptors: np.ndarray, cfg: MCLConfig = MCLConfig(), block: int = 1024
              ) -> sp.csc_matrix:
    """Symmetric sparse affinity of each descriptor to its top-k neighbours (no self)."""
    x = _check_descriptors(descriptors)
    n = x.shape[0]
    if n == 0:
        return sp.csc_matrix((0, 0))
    k = min(cfg.k, n - 1)
    if k <= 0:
        return sp.csc_matrix((n, n))
    if cfg.affinity == "cosine":
        norm = np.linalg.norm(x, axis=1, keepdims=True)
        xn = x / np.maximum(norm, 1e-12)
    else:
        sq = np.einsum("ij,ij->i", x, x)
    rows, cols, vals = [], [], []
    xt = torch.from_numpy(np.ascontiguousarray(xn if cfg.affinity == "cosine" else x))
    sqt = None if cfg.affinity == "cosine" else torch.from_numpy(sq)
    for s in range(0, n, block):
        e = min(n, s + block)
        idx = torch.arange(s, e)
        score = xt[s:e] @ xt.T  # larger is closer
        if sqt is not None:
            score = 2.0 * score - sqt[s:e, None] - sqt[None, :]  # -squared distance
        score[idx - s, idx] = -torch.inf
        top, part = torch.topk(score, k, dim=1, sorted=False)
        rows.append(np.repeat(np.arange(s, e), k))
        cols.append(part.numpy().ravel())
        vals.append(top.numpy().ravel())
    r, c = np.concatenate(rows), np.concatenate(cols)
    v = np.concatenate(vals).astype(np.float64)
    if cfg.affinity == "cosine":
        w = np.clip(v, 0.0, None)
    else:
        d = np.sqrt(np.maximum(-v, 0.0))
        w = np.exp(-cfg.eta * d)
    A = sp.csr_matrix((w, (r, c)), shape=(n, n))
    A = A.maximum(A.T)
    A.eliminate_zeros()
    return A.tocsc()


# ---------------------------------------------------------------- MCL core

def _column_scale(M: sp.csc_matrix, scale: np.ndarray) -> None:
    """Multiply every column j of CSC ``M`` by ``scale[j]`` in place."""
    M.data *= np.repeat(scale, np.diff(M.indptr))


def _column_reduce(M: sp.csc_matrix, ufunc: np.ufunc) -> np.ndarray:
    """``ufunc`` over each column's stored values (0 for empty columns), via reduceat on
    the CSC data: a few times faster than scipy's generic axis reductions."""
    out = np.zeros(M.shape[1])
    filled = np.diff(M.indptr) > 0
    if M.nnz:
        out[filled] = ufunc.reduceat(M.data, M.indptr[:-1][filled])
    return out


def _column_max(M: sp.csc_matrix) -> np.ndarray:
    """Largest stored value per column (entries are non-negative, so the column max)."""
    return _column_reduce(M, np.maximum)


def _normalise(M: sp.csc_matrix) -> None:
    """Column-stochastic in place (columns that are all zero stay zero)."""
    s = _column_reduce(M, np.add)
    _column_scale(M, np.where(s > 0, 1.0 / np.where(s > 0, s, 1.0), 0.0))


def _inflate(M: sp.csc_matrix, r: float) -> None:
    """Hadamard power then column normalisation, underflow-safe (max-scaled first)."""
    mx = _column_max(M)
    _column_scale(M, np.where(mx > 0, 1.0 / np.where(mx > 0, mx, 1.0), 0.0))
    np.power(M.data, r, out=M.data)
    _normalise(M)


def _column_kth_largest(M: sp.csc_matrix, k: int, block_entries: int = 4_000_000
                        ) -> np.ndarray:
    """Per column, the k-th largest stored value (0 for columns with <= k entries)."""
    counts = np.diff(M.indptr)
    out = np.zeros(M.shape[1])
    big = np.flatnonzero(counts > k)
    if big.size == 0:
        return out
    width = int(counts[big].max())
    step = max(1, block_entries // width)
    for s in range(0, big.size, step):
        cols = big[s:s + step]
        pad = np.zeros((cols.size, width))
        c = counts[cols]
        # Scatter each column's values into one row of a zero-padded block.
        row = np.repeat(np.arange(cols.size), c)
        pos = np.arange(c.sum()) - np.repeat(np.cumsum(c) - c, c)
        src = np.repeat(M.indptr[cols], c) + pos
        pad[row, pos] = M.data[src]
        out[cols] = -np.partition(-pad, k - 1, axis=1)[:, k - 1]
    return out


def _prune(M: sp.csc_matrix, threshold: float, max_entries: int) -> sp.csc_matrix:
    """Drop small entries (relative to the column max), never the column max itself.

    At most about ``max_entries`` entries per column survive (ties may keep more).
    """
    counts = np.diff(M.indptr)
    col = np.repeat(np.arange(M.shape[1]), counts)
    mx = _column_max(M)
    floor = threshold * mx
    if counts.max(initial=0) > max_entries:
        floor = np.maximum(floor, _column_kth_largest(M, max_entries))
    keep = M.data >= np.minimum(floor, mx)[col]
    indptr = np.zeros(M.shape[1] + 1, dtype=M.indptr.dtype)
    indptr[1:] = np.cumsum(np.bincount(col[keep], minlength=M.shape[1]))
    M = sp.csc_matrix((M.data[keep], M.indices[keep], indptr), shape=M.shape)
    _normalise(M)
    return M


def _clusters_from_matrix(argmax_rows: np.ndarray) -> np.ndarray:
    """Cluster ids 0..m-1 from each node's attractor row, numbered by smallest member."""
    n = argmax_rows.size
    if n == 0:
        return np.zeros(0, np.int64)
    G = sp.csr_matrix((np.ones(n), (np.arange(n), argmax_rows)), shape=(n, n))
    _, comp = connected_components(G, directed=True, connection="weak")
    first = np.full(comp.max() + 1, n, np.int64)
    np.minimum.at(first, comp, np.arange(n))
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return rank[comp].astype(np.int64)


def _loops(A_max: np.ndarray, self_loop: float, loop_mode: str) -> np.ndarray:
    """Self-loop weight per node; a node without edges always gets a loop of 1."""
    if loop_mode not in ("max", "constant"):
        raise ValueError(f"loop_mode must be 'max' or 'constant', got {loop_mode!r}")
    loops = self_loop * A_max if loop_mode == "max" else np.full(A_max.shape, self_loop)
    return np.where(A_max > 0, loops, 1.0)


def mcl(A, inflation: float = 2.0, expansion: int = 2, self_loop: float = 1.0,
        prune_threshold: float = 1e-4, max_column_entries: int = 128,
        max_iterations: int = 100, tol: float = 1e-6, loop_mode: str = "constant"
        ) -> np.ndarray:
    """Markov clustering of a non-negative affinity matrix (dense or scipy.sparse).

    Existing diagonal entries are replaced by the self-loops (``loop_mode``).
    Returns (n,) int64 cluster ids 0..m-1; isolated nodes are singletons.
    """
    if sp.issparse(A):
        M = sp.csc_matrix(A, dtype=np.float64, copy=True)
    else:
        A = np.asarray(A, dtype=np.float64)
        if A.ndim != 2:
            raise ValueError(f"affinity must be a square matrix, got shape {A.shape}")
        M = sp.csc_matrix(A)
    n = M.shape[0]
    if M.shape != (n, n):
        raise ValueError(f"affinity must be square, got shape {M.shape}")
    if n == 0:
        return np.zeros(0, np.int64)
    if M.nnz and (not np.all(np.isfinite(M.data)) or M.data.min() < 0):
        raise ValueError("affinity must be finite and non-negative")
    if inflation <= 1.0 or expansion < 2:
        raise ValueError(f"need inflation > 1 and expansion >= 2, got {inflation}, {expansion}")
    M.setdiag(0.0)
    M.eliminate_zeros()
    M.setdiag(_loops(_column_max(M), self_loop, loop_mode))
    M.eliminate_zeros()
    M.sort_indices()
    _normalise(M)
    for _ in range(max_iterations):
        prev = M
        E = M
        for _ in range(expansion - 1):
            E = E @ M
        M = sp.csc_matrix(E)
        M.sort_indices()
        _inflate(M, inflation)
        M = _prune(M, prune_threshold, max_column_entries)
        M.sort_indices()
        delta = abs(M - prev)
        if delta.nnz == 0 or delta.max() <= tol:
            break
    return _clusters_from_matrix(np.asarray(M.argmax(axis=0)).ravel())


def mcl_dense_reference(A: np.ndarray, inflation: float = 2.0, expansion: int = 2,
                        self_loop: float = 1.0, max_iterations: int = 200,
                        tol: float = 1e-9, loop_mode: str = "constant") -> np.ndarray:
    """Textbook dense MCL (float64, no pruning) to check :func:`mcl` against."""
    M = np.array(A, dtype=np.float64)
    np.fill_diagonal(M, 0.0)
    M += np.diag(_loops(M.max(axis=0), self_loop, loop_mode))
    M /= M.sum(axis=0, keepdims=True)
    for _ in range(max_iterations):
        prev = M
        M = np.linalg.matrix_power(M, expansion)
        M = M / M.max(axis=0, keepdims=True)
        M = M ** inflation
        M /= M.sum(axis=0, keepdims=True)
        if np.abs(M - prev).max() <= tol:
            break
    return _clusters_from_matrix(M.argmax(axis=0))


def markov_cluster(descriptors: np.ndarray, cfg: MCLConfig = MCLConfig()) -> np.ndarray:
    """Cluster segment descriptors (n, D): (n,) int64 ids 0..m-1."""
    A = knn_graph(descriptors, cfg)
    return mcl(A, cfg.inflation, cfg.expansion, cfg.self_loop, cfg.prune_threshold,
               cfg.max_column_entries, cfg.max_iterations, cfg.tol, cfg.loop_mode)


# ---------------------------------------------------------------- tuning

def tune(descriptor_sets: Sequence[np.ndarray], label_sets: Sequence[np.ndarray],
         inflations: Iterable[float] = (1.2, 1.4, 1.6, 1.8, 2.0, 2.5, 4.0, 12.0),
         affinities: Iterable[tuple[str, float]] = (("cosine", 0.0), ("exp", 1.0),
                                                     ("exp", 2.0), ("exp", 4.0)),
         base: MCLConfig = MCLConfig()) -> list[dict]:
    """Grid of (affinity, eta, inflation) scored on training descriptor sets.

    Each set is clustered on its own; score = mean adjusted Rand index against
    the given labels (e.g. each segment's ground-truth class); also mean
    purity and cluster count. Rows are returned best first.
    """
    from .metrics import adjusted_rand_index, purity
    rows = []
    for aff, eta in affinities:
        for r in inflations:
            cfg = dataclasses.replace(base, affinity=aff, eta=float(eta), inflation=float(r))
            aris, purs, ms = [], [], []
            for x, y in zip(descriptor_sets, label_sets):
                lab = markov_cluster(x, cfg)
                aris.append(adjusted_rand_index(y, lab))
                purs.append(purity(y, lab))
                ms.append(int(lab.max()) + 1 if lab.size else 0)
            rows.append({"affinity": aff, "eta": float(eta), "inflation": float(r),
                         "ari": float(np.mean(aris)), "purity": float(np.mean(purs)),
                         "clusters": float(np.mean(ms))})
    rows.sort(key=lambda d: -d["ari"])
    return rows
