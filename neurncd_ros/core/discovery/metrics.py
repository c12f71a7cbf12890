"""Discovery metrics: confusion matrix, IoU, mIoU (known / novel / all), accuracies.

Ground truth: NYU-13 ids 0..13, 0 = void (ignored). Predictions: 0 unlabelled,
1..13 NYU-13 ids, >= 100 novel clusters. Novel clusters have no name, so they
are matched one-to-one to the ground-truth novel classes (``classes.NOVEL_IDS``)
with the Hungarian algorithm on pixel overlap counts, accumulated over all
frames; an unmatched cluster, like label 0 or a known id on a novel pixel, is
simply an error (a false negative of the true class, a false positive of no
class). Known ids are taken at face value.

- IoU_c = TP / (TP + FP + FN) per class; a mean (mIoU) is over the classes that
  occur in the ground truth (known classes, novel classes, all);
- Total Acc = correctly labelled / all non-void pixels; Avg Acc = mean over
  the ground-truth classes of per-class recall;
- ``assigned_miou`` (SCIM's): every predicted id, known or novel, is treated as
  a cluster and matched one-to-one to all GT classes by Hungarian on overlap
  counts, then the mIoU over GT classes is taken (it ignores the known names).

All mIoUs and accuracies are in percent.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..classes import KNOWN_IDS, NOVEL_ID_START, NOVEL_IDS, NUM_CLASSES

_GT_IDS = np.arange(1, NUM_CLASSES + 1)


def _check_pair(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pred, gt = np.asarray(pred), np.asarray(gt)
    if pred.shape != gt.shape:
        raise ValueError(f"pred shape {pred.shape} differs from gt shape {gt.shape}")
    if not (np.issubdtype(pred.dtype, np.integer) and np.issubdtype(gt.dtype, np.integer)):
        raise ValueError(f"labels must be integer images, got {pred.dtype} and {gt.dtype}")
    if gt.size and (gt.min() < 0 or gt.max() > NUM_CLASSES):
        raise ValueError(f"gt ids must be NYU-13 0..{NUM_CLASSES}, got {gt.min()}..{gt.max()}")
    if pred.size:
        bad = (pred < 0) | ((pred > NUM_CLASSES) & (pred < NOVEL_ID_START))
        if bad.any():
            raise ValueError(f"pred ids must be 0, 1..{NUM_CLASSES} or >= {NOVEL_ID_START}; "
                             f"got {np.unique(pred[bad])[:5].tolist()}")
    return pred.astype(np.int64).ravel(), gt.astype(np.int64).ravel()


class Evaluator:
    """Accumulates a (GT class x predicted id) overlap table over frames."""

    def __init__(self) -> None:
        self._counts: dict[int, np.ndarray] = {}  # pred id -> (NUM_CLASSES + 1,) counts by gt

    def update(self, pred: np.ndarray, gt: np.ndarray) -> None:
        """Add one frame's label images (same shape)."""
        p, g = _check_pair(pred, gt)
        keep = g > 0
        p, g = p[keep], g[keep]
        if p.size == 0:
            return
        ids, inv = np.unique(p, return_inverse=True)
        table = np.zeros((ids.size, NUM_CLASSES + 1), np.int64)
        np.add.at(table, (inv, g), 1)
        for i, pid in enumerate(ids.tolist()):
            self._counts.setdefault(pid, np.zeros(NUM_CLASSES + 1, np.int64))
            self._counts[pid] += table[i]

    def table(self) -> tuple[np.ndarray, np.ndarray]:
        """(pred ids (P,), overlap counts (13, P) with row i = GT class i + 1)."""
        ids = np.array(sorted(self._counts), np.int64)
        if ids.size == 0:
            return ids, np.zeros((NUM_CLASSES, 0), np.int64)
        return ids, np.stack([self._counts[i][1:] for i in ids.tolist()], axis=1)

    def novel_matching(self) -> dict[int, int]:
        """Novel cluster id -> GT novel class id (Hungarian on overlap counts)."""
        ids, counts = self.table()
        nov = ids >= NOVEL_ID_START
        if not nov.any():
            return {}
        rows = np.array(NOVEL_IDS) - 1
        overlap = counts[np.ix_(rows, np.flatnonzero(nov))]
        r, c = linear_sum_assignment(-overlap)
        cl = ids[nov]
        return {int(cl[j]): int(NOVEL_IDS[i]) for i, j in zip(r, c) if overlap[i, j] > 0}

    def result(self) -> dict:
        """Per-class IoU and the summary figures (percent)."""
        ids, counts = self.table()
        match = self.novel_matching()
        mapped = np.array([i if 1 <= i <= NUM_CLASSES else match.get(int(i), -1)
                           for i in ids.tolist()], np.int64)
        conf = np.zeros((NUM_CLASSES, NUM_CLASSES + 1), np.int64)  # last column: no class
        for j, m in enumerate(mapped.tolist()):
            conf[:, m - 1 if m > 0 else NUM_CLASSES] += counts[:, j]
        out = _scores(conf[:, :NUM_CLASSES], conf.sum(axis=1))
        out["novel_matching"] = {str(k): v for k, v in sorted(match.items())}
        out["assigned_miou"] = _assigned_miou(counts)
        return out


def class_iou(conf: np.ndarray, gt_total: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Per-class IoU (fraction; NaN where the class is absent from the GT) and presence.

    ``conf`` is a square GT x prediction confusion; ``gt_total`` the GT pixel
    count per class (default: the row sums, i.e. every GT pixel was predicted as
    one of the columns). The one IoU both the discovery metrics and the
    backbone's training scores use.
    """
    tp = np.diag(conf).astype(np.float64)
    gt_total = conf.sum(axis=1) if gt_total is None else gt_total
    fp = conf.sum(axis=0) - tp
    fn = gt_total - tp
    present = gt_total > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(present, tp / (tp + fp + fn), np.nan)
    return iou, present


def _scores(conf: np.ndarray, gt_total: np.ndarray) -> dict:
    """IoU/accuracy figures from a square GT x prediction confusion over NYU-13."""
    tp = np.diag(conf).astype(np.float64)
    iou, present = class_iou(conf, gt_total)
    with np.errstate(invalid="ignore", divide="ignore"):
        recall = np.where(present, tp / gt_total, np.nan)
    known = np.isin(_GT_IDS, KNOWN_IDS) & present
    novel = np.isin(_GT_IDS, NOVEL_IDS) & present

    def mean(sel: np.ndarray) -> float:
        return float(100.0 * iou[sel].mean()) if sel.any() else float("nan")

    total = gt_total.sum()
    return {
        "iou": {int(c): (float(100.0 * iou[c - 1]) if present[c - 1] else None)
                for c in _GT_IDS},
        "miou_known": mean(known),
        "miou_novel": mean(novel),
        "miou_all": mean(present),
        "total_acc": float(100.0 * tp.sum() / total) if total else float("nan"),
        "avg_acc": float(100.0 * recall[present].mean()) if present.any() else float("nan"),
        "pixels": int(total),
    }


def _assigned_miou(counts: np.ndarray) -> float:
    """SCIM's mIoU after Hungarian assignment of every predicted id to a GT class."""
    if counts.size == 0:
        return float("nan")
    gt_total = counts.sum(axis=1)
    r, c = linear_sum_assignment(-counts)
    conf = np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64)
    for gi, pj in zip(r, c):
        conf[:, gi] += counts[:, pj]
    return _scores(conf, gt_total)["miou_all"]


def evaluate(preds: np.ndarray | Iterable[np.ndarray], gts: np.ndarray | Iterable[np.ndarray]
             ) -> dict:
    """Metrics of one label image pair or of two equally long sequences of them."""
    ev = Evaluator()
    if isinstance(preds, np.ndarray) and isinstance(gts, np.ndarray) and preds.ndim == 2:
        ev.update(preds, gts)
    else:
        preds, gts = list(preds), list(gts)
        if len(preds) != len(gts):
            raise ValueError(f"{len(preds)} predictions but {len(gts)} ground-truth images")
        for p, g in zip(preds, gts):
            ev.update(p, g)
    return ev.result()


# ---------------------------------------------------------------- clustering scores

def _contingency(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a, b = np.asarray(a).ravel(), np.asarray(b).ravel()
    if a.shape != b.shape:
        raise ValueError(f"label vectors differ in length: {a.size} vs {b.size}")
    _, ai = np.unique(a, return_inverse=True)
    _, bi = np.unique(b, return_inverse=True)
    table = np.zeros((ai.max(initial=-1) + 1, bi.max(initial=-1) + 1), np.int64)
    np.add.at(table, (ai, bi), 1)
    return table


def adjusted_rand_index(truth: np.ndarray, pred: np.ndarray) -> float:
    """Adjusted Rand index of two labellings (1 = identical partitions, ~0 = chance)."""
    t = _contingency(truth, pred)
    n = t.sum()
    if n < 2:
        return 1.0

    def c2(x):
        x = np.asarray(x, np.float64)
        return (x * (x - 1) / 2).sum()

    idx = c2(t)
    a, b = c2(t.sum(1)), c2(t.sum(0))
    expected = a * b / (n * (n - 1) / 2)
    top = (a + b) / 2
    if top == expected:
        return 1.0
    return float((idx - expected) / (top - expected))


def purity(truth: np.ndarray, pred: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Share of items whose cluster's majority truth label is their own (optionally weighted)."""
    truth, pred = np.asarray(truth).ravel(), np.asarray(pred).ravel()
    if truth.size == 0:
        return float("nan")
    w = np.ones(truth.size) if weights is None else np.asarray(weights, np.float64).ravel()
    _, ti = np.unique(truth, return_inverse=True)
    _, pi = np.unique(pred, return_inverse=True)
    table = np.zeros((pi.max() + 1, ti.max() + 1))
    np.add.at(table, (pi, ti), w)
    return float(table.max(axis=1).sum() / table.sum())


# ---------------------------------------------------------------- novel id stability

class IdStability:
    """How steadily each novel object keeps one id over the frames of a scene.

    A novel object is a ground-truth instance whose class is novel
    (``classes.NOVEL_IDS``). Over all frames given to :meth:`update`, the object's
    pixels are counted per predicted id (known ids, 0 and novel ids alike); its
    stability is the share of its pixels carrying its most common id. An object
    split between two novel ids, or half "wall" and half novel, scores 0.5. The
    scene's figure is the mean over objects, each object counting once (a small
    picture as much as a large window). Instance ids must be those of one scene.
    ``novel_only`` counts only the pixels that carry a novel id, i.e. whether the
    object keeps the same novel id once it is found, apart from whether it is found.
    Fractions in [0, 1]; NaN when no novel object was seen.
    """

    def __init__(self) -> None:
        self._counts: dict[int, dict[int, int]] = {}  # instance -> pred id -> pixels

    def update(self, pred: np.ndarray, gt: np.ndarray, instance: np.ndarray) -> None:
        """Add one frame: predicted ids, NYU-13 ground truth, instance ids (same shape)."""
        p, g = _check_pair(pred, gt)
        inst = np.asarray(instance)
        if inst.shape != np.shape(pred):
            raise ValueError(f"instance shape {inst.shape} differs from pred shape "
                             f"{np.shape(pred)}")
        if not np.issubdtype(inst.dtype, np.integer):
            raise ValueError(f"instance must be an integer image, got {inst.dtype}")
        inst = inst.astype(np.int64).ravel()
        sel = np.isin(g, NOVEL_IDS) & (inst > 0)
        if not sel.any():
            return
        pairs, n = np.unique(np.stack([inst[sel], p[sel]]), axis=1, return_counts=True)
        for (i, pid), c in zip(pairs.T.tolist(), n.tolist()):
            row = self._counts.setdefault(i, {})
            row[pid] = row.get(pid, 0) + c

    def per_object(self, novel_only: bool = False) -> dict[int, float]:
        """Instance id -> stability; ``novel_only``: over the pixels with a novel id
        (objects never given a novel id are left out)."""
        out = {}
        for i, row in sorted(self._counts.items()):
            counts = [c for pid, c in row.items() if not novel_only or pid >= NOVEL_ID_START]
            if counts:
                out[i] = max(counts) / sum(counts)
        return out

    def result(self) -> dict:
        """``novel_id_stability`` (all of an object's pixels), ``novel_id_stability_found``
        (its novel-labelled pixels only), ``novel_objects`` (how many were seen)."""
        every, found = self.per_object(), self.per_object(novel_only=True)
        nan = float("nan")
        return {"novel_id_stability": float(np.mean(list(every.values()))) if every else nan,
                "novel_id_stability_found": (float(np.mean(list(found.values())))
                                             if found else nan),
                "novel_objects": len(every), "novel_objects_found": len(found)}
