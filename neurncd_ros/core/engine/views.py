"""Where a view's embedding comes from besides the field: the geometry of keyframes.

A rendered view blends the field with what the stored keyframes saw of the same
3D points (:mod:`.mapping` decides when and how much). These functions answer
the geometric questions that blend needs, with one visibility test: which
keyframes see a world point (:func:`seen_by`), how far the field has learnt it
(:func:`coverage`), and the mean of the views' embeddings of it
(:func:`fuse_keyframes`), the multi-view evidence read directly.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from ..camera import Intrinsics, project
from ..uncertainty import entropy, softmax


@dataclasses.dataclass(frozen=True)
class StoredView:
    """A recent non-keyframe frame held for the keyframe fusion (what :func:`fuse_keyframes`
    reads of a keyframe)."""

    stamp_ns: int
    pose: np.ndarray
    intrinsics: Intrinsics
    depth: np.ndarray
    embedding: np.ndarray


def resize_to(arr: np.ndarray, height: int, width: int,
              interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """Resize an (H, W) or (H, W, C) image to height x width, channels kept."""
    if arr.shape[:2] == (height, width):
        return arr
    out = cv2.resize(arr, (width, height), interpolation=interpolation)
    return out[:, :, None] if arr.ndim == 3 and out.ndim == 2 else out


def seen_by(points: np.ndarray, kf, tolerance: float
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which world points a keyframe sees (in its image, in front, its measured depth
    agreeing within ``tolerance`` + 3 % of the depth), and their pixel columns / rows."""
    u, v, z = project(points, kf.intrinsics, kf.pose)
    ui = np.floor(u + 0.5).astype(np.int64)
    vi = np.floor(v + 0.5).astype(np.int64)
    h, w = kf.depth.shape
    ok = (z > 0) & (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    zk = np.zeros(len(points), np.float32)
    zk[ok] = kf.depth[vi[ok], ui[ok]]
    return ok & (zk > 0) & (np.abs(zk - z) <= tolerance + 0.03 * z), ui, vi


def coverage(points: np.ndarray, keyframes: list, maturity: np.ndarray,
             tolerance: float) -> np.ndarray:
    """Per point, the highest maturity among the keyframes that see it.

    A keyframe sees a world point if it projects into its image in front of
    the camera and the keyframe's measured depth there agrees (within
    ``tolerance`` + 3 % of the depth): visible, not occluded.
    """
    cov = np.zeros(len(points))
    for kf, m in zip(keyframes, maturity):
        if m <= 0:
            continue
        seen, _, _ = seen_by(points, kf, tolerance)
        np.maximum(cov, m * seen, out=cov)
    return cov


def fuse_keyframes(points: np.ndarray, own: np.ndarray, keyframes: list,
                   tolerance: float, logit_channels: int | None = None,
                   view_entropy: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Per point, the mean of the frame's own embedding ``own`` (N, C) and the stored
    backbone embeddings of the keyframes that see it (the visibility test of
    :func:`coverage`), how many views were averaged (N,), and (with
    ``logit_channels`` and ``view_entropy``) the mean of the views' own entropies (N,)
    (None otherwise; it costs a second pass over the views' probabilities):
    the entropy of the mean minus this mean is the views' disagreement (their
    mutual information), zero where every view says the same.

    ``logit_channels`` S: average the first S channels as class probabilities
    (softmax) and return their log, so the entropy of the result is the
    predictive entropy over the views, which grows where they disagree (a
    novelty cue no single frame has); None averages every channel as it is.

    This is the multi-view evidence the field is trained on, read directly: until
    the field has learnt a point, the view's embedding there is the mean over the
    views of it rather than the one frame's (a per-frame confusion, e.g. a picture
    called wall from one angle, is outvoted by the others).
    """
    S = 0 if logit_channels is None else int(logit_channels)
    acc = own.astype(np.float32, copy=True)
    h_sum = None
    if S and view_entropy:
        h_sum = entropy(acc[:, :S]).astype(np.float64)
    if S:
        acc[:, :S] = softmax(acc[:, :S])
    n = np.ones(len(points), np.float32)
    for kf in keyframes:
        seen, ui, vi = seen_by(points, kf, tolerance)
        if not seen.any():
            continue
        h, w = kf.depth.shape
        eh, ew = kf.embedding.shape[:2]
        ue = np.minimum(((ui[seen] + 0.5) * ew / w).astype(np.int64), ew - 1)
        ve = np.minimum(((vi[seen] + 0.5) * eh / h).astype(np.int64), eh - 1)
        emb = kf.embedding[ve, ue, : acc.shape[1]].astype(np.float32)
        if h_sum is not None:
            h_sum[seen] += entropy(emb[:, :S])
        if S:
            emb[:, :S] = softmax(emb[:, :S])
        acc[seen] += emb
        n[seen] += 1.0
    acc /= n[:, None]
    if S:
        acc[:, :S] = np.log(np.maximum(acc[:, :S], 1e-12))
    return acc, n, (None if h_sum is None else (h_sum / n).astype(np.float32))
