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

from ..camera import Intrinsics, invert_pose, project
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


def _agrees(zk: np.ndarray, z: np.ndarray, tolerance: float) -> np.ndarray:
    """The visibility test: a keyframe's measured depth ``zk`` (0 = none) agrees with a
    point's depth ``z`` in it within ``tolerance`` + 3 % of the depth (the point is in
    view, not occluded)."""
    return (zk > 0) & (np.abs(zk - z) <= tolerance + 0.03 * z)


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
    return ok & _agrees(zk, z, tolerance), ui, vi


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


def fuse_depth(depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray, keyframes: list,
               tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """The view's depth averaged, pixel by pixel, with what the keyframes that see the
    same point measured of it, and how many depths were averaged per pixel (1 where no
    keyframe sees it; 0 where the view has no depth, which stays 0).

    A keyframe sees a pixel's point by the visibility test of :func:`seen_by`. It
    measured the surface at ``zk`` along its own ray through the point, where the view
    put it at ``z`` (both in the keyframe's camera): its estimate of the point is the
    view's point moved along that ray by the factor ``zk / z``, and the view's depth of
    that estimate is what is averaged. Sensor noise (Kinect axial noise and disparity
    quantisation, independent between viewpoints) shrinks about as the square root of
    the views averaged, so the convex segments discovery cuts on the depth follow the
    surfaces rather than the noise: the small steps around a picture or a window frame
    stand out of a flat wall. Pixels without depth are not filled (no keyframe point is
    forward-projected): discovery leaves them unlabelled as before.
    """
    depth = np.asarray(depth, np.float32)
    mask = np.isfinite(depth) & (depth > 0)
    own = depth[mask]
    v, u = np.nonzero(mask)
    # The view's points in its own camera, as contiguous columns (float32: depth noise is
    # millimetres; column arithmetic is several times faster than an (N, 3) matmul).
    x = (u.astype(np.float32) - np.float32(intrinsics.cx)) * (own / np.float32(intrinsics.fx))
    y = (v.astype(np.float32) - np.float32(intrinsics.cy)) * (own / np.float32(intrinsics.fy))
    acc, n = own.astype(np.float64), np.ones(len(own), np.float32)
    world_to_view = invert_pose(pose)
    for kf in keyframes:
        # view camera -> keyframe pixels in one 3x4 map: (u z, v z, z) of each point.
        P = (kf.intrinsics.K @ (invert_pose(kf.pose) @ pose)[:3]).astype(np.float32)
        z = P[2, 0] * x + P[2, 1] * y + P[2, 2] * own + P[2, 3]
        kh, kw = kf.depth.shape
        with np.errstate(divide="ignore", invalid="ignore"):
            uf = (P[0, 0] * x + P[0, 1] * y + P[0, 2] * own + P[0, 3]) / z
            vf = (P[1, 0] * x + P[1, 1] * y + P[1, 2] * own + P[1, 3]) / z
        idx = np.flatnonzero((z > 1e-6) & (uf >= -0.5) & (uf < kw - 0.5)
                             & (vf >= -0.5) & (vf < kh - 0.5))
        ui = (uf[idx] + 0.5).astype(np.int64)  # non-negative: truncation is the rounding
        vi = (vf[idx] + 0.5).astype(np.int64)
        zk = kf.depth.reshape(-1)[vi * kw + ui]
        zf = z[idx]
        seen = _agrees(zk, zf, tolerance)
        if not seen.any():
            continue
        idx, zk, zf = idx[seen], zk[seen], zf[seen]
        # The keyframe's centre in the view's camera: the view-z of (point - centre) is
        # own - its z, so the estimate's view depth is own + (zk / z - 1) (own - c_z).
        c_z = (world_to_view @ kf.pose)[2, 3]
        acc[idx] += own[idx] + (zk / zf - 1.0) * (own[idx] - c_z)
        n[idx] += 1.0
    out = np.zeros(depth.shape, np.float32)
    out[mask] = acc / n
    count = np.zeros(depth.shape, np.float32)
    count[mask] = n
    return out, count
