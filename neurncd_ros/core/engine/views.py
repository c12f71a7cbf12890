"""Where a view's embedding comes from besides the field: the geometry of keyframes.

A rendered view blends the field with what the stored keyframes saw of the same
3D points (:mod:`.mapping` decides when and how much). These functions answer
the geometric questions that blend needs, with one visibility test
(:func:`_visible`, column arithmetic in float32): which keyframes see a point, how
far the field has learnt it (:func:`coverage`), the mean of
the views' embeddings of it (:func:`fuse_keyframes`, the multi-view evidence read
directly) and of their depths (:func:`fuse_depth`). A rendering that needs both at the
view's own resolution tests visibility once (:func:`view_visibility`) and gives the result
to both.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from ..camera import Intrinsics, invert_pose
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


def _camera_map(kf, world_to_points: np.ndarray | None = None) -> np.ndarray:
    """(3, 4) float32 map from point coordinates to a keyframe's homogeneous pixel
    coordinates (u z, v z, z): world points, or with ``world_to_points`` (the pose of the
    frame the points are given in) points in that frame."""
    M = invert_pose(kf.pose)
    if world_to_points is not None:
        M = M @ world_to_points
    return (kf.intrinsics.K @ M[:3]).astype(np.float32)


def _columns(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The x, y, z of (N, 3) points as contiguous float32 columns (millimetre precision is
    all the visibility test needs; column arithmetic is several times faster than an
    (N, 3) matmul)."""
    p = np.asarray(points, np.float32)
    return (np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1]),
            np.ascontiguousarray(p[:, 2]))


def _visible(cols: tuple[np.ndarray, np.ndarray, np.ndarray], M: np.ndarray, kf,
             tolerance: float) -> tuple[np.ndarray, ...]:
    """The points (columns ``cols``, mapped into the keyframe by ``M``) a keyframe sees:
    in its image (nearest pixel), in front, its measured depth agreeing (:func:`_agrees`).
    Returns their indices, pixel columns and rows in the keyframe, the keyframe's
    measured depth there and the points' own depth in the keyframe."""
    x, y, w0 = cols
    z = M[2, 0] * x + M[2, 1] * y + M[2, 2] * w0 + M[2, 3]
    kh, kw = kf.depth.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        uf = (M[0, 0] * x + M[0, 1] * y + M[0, 2] * w0 + M[0, 3]) / z
        vf = (M[1, 0] * x + M[1, 1] * y + M[1, 2] * w0 + M[1, 3]) / z
    idx = np.flatnonzero((z > 1e-6) & (uf >= -0.5) & (uf < kw - 0.5)
                         & (vf >= -0.5) & (vf < kh - 0.5))
    ui = (uf[idx] + 0.5).astype(np.int64)  # non-negative: truncation is the rounding
    vi = (vf[idx] + 0.5).astype(np.int64)
    zk = kf.depth.reshape(-1)[vi * kw + ui]
    zp = z[idx]
    seen = _agrees(zk, zp, tolerance)
    return idx[seen], ui[seen], vi[seen], zk[seen], zp[seen]


def coverage(points: np.ndarray, keyframes: list, maturity: np.ndarray,
             tolerance: float, visibility: ViewVisibility | None = None) -> np.ndarray:
    """Per point, the highest maturity among the keyframes that see it.

    A keyframe sees a world point if it projects into its image in front of
    the camera and the keyframe's measured depth there agrees (within
    ``tolerance`` + 3 % of the depth): visible, not occluded.
    ``visibility``: that test already done for these keyframes on these points
    (:func:`view_visibility`, :meth:`ViewVisibility.first`); None tests here.
    """
    cov = np.zeros(len(points))
    if visibility is None:
        cols = _columns(points)
        seen = (_visible(cols, _camera_map(kf), kf, tolerance) if m > 0 else None
                for kf, m in zip(keyframes, maturity))
    else:
        seen = _seen(points, keyframes, tolerance, visibility)
    for m, vis in zip(maturity, seen):
        if m > 0:
            cov[vis[0]] = np.maximum(cov[vis[0]], m)
    return cov


@dataclasses.dataclass(frozen=True)
class ViewVisibility:
    """Which keyframes see the points of a view's valid depth pixels (:func:`view_visibility`):
    ``mask`` the (H, W) pixels with depth, ``depth`` their (N,) depths in row-major order (the
    order of :func:`..camera.backproject`), and per keyframe, in the order given, the
    :func:`_visible` tuple (point indices, pixel columns and rows, the keyframe's measured
    depth there, the points' depth in the keyframe) and the keyframe centre's z in the
    view's camera."""

    mask: np.ndarray
    depth: np.ndarray
    seen: tuple
    centre_z: tuple
    keyframes: tuple

    def matches(self, keyframes: list) -> bool:
        """Whether this visibility was computed for exactly these keyframes, in this order."""
        return len(keyframes) == len(self.keyframes) and all(
            a is b for a, b in zip(keyframes, self.keyframes))

    def first(self, n: int) -> ViewVisibility:
        """The test of the first ``n`` keyframes alone (the mapper stage tests its nearest
        keyframes and then the held recent frames; its coverage reads the keyframes)."""
        if not 0 <= n <= len(self.keyframes):
            raise ValueError(f"visibility holds {len(self.keyframes)} keyframes, not {n}")
        return dataclasses.replace(self, seen=self.seen[:n], centre_z=self.centre_z[:n],
                                   keyframes=self.keyframes[:n])


def view_visibility(depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray,
                    keyframes: list, tolerance: float) -> ViewVisibility:
    """The visibility test of every keyframe for the view's pixels with depth, done once in
    the view's camera (one 3x4 map per keyframe from the view's camera to its pixels), so
    that :func:`fuse_depth` and :func:`fuse_keyframes` of the same rendering share it."""
    depth = np.asarray(depth, np.float32)
    if depth.shape != intrinsics.shape:
        raise ValueError(f"depth is {depth.shape[1]}x{depth.shape[0]} but intrinsics are "
                         f"{intrinsics.width}x{intrinsics.height}")
    mask = np.isfinite(depth) & (depth > 0)
    own = depth[mask]
    v, u = np.nonzero(mask)
    # The view's points in its own camera, as contiguous columns (float32: depth noise is
    # millimetres; column arithmetic is several times faster than an (N, 3) matmul).
    x = (u.astype(np.float32) - np.float32(intrinsics.cx)) * (own / np.float32(intrinsics.fx))
    y = (v.astype(np.float32) - np.float32(intrinsics.cy)) * (own / np.float32(intrinsics.fy))
    cols = (x, y, own)
    world_to_view = invert_pose(pose)
    seen = tuple(_visible(cols, _camera_map(kf, pose), kf, tolerance) for kf in keyframes)
    centre_z = tuple(float((world_to_view @ kf.pose)[2, 3]) for kf in keyframes)
    return ViewVisibility(mask, own, seen, centre_z, tuple(keyframes))


class FusionInputs:
    """Each stored view's embedding as :func:`fuse_keyframes` reads it, computed once per
    view instead of once per rendering that reads it (:func:`view_inputs`): flattened to
    (h * w + 1, C) float32 (a zero row last) with the first S channels as class
    probabilities, and (on request) the per-pixel entropy of those S channels. An entry
    is found by the view's stamp and used only while it was made from the very embedding
    array the view holds, so a view of the same stamp after a map reset (a bag replayed
    again, another bag whose stamps start alike) is converted anew; :meth:`keep` drops the
    views a rendering no longer reads, so the memory stays that of one rendering's views."""

    def __init__(self) -> None:
        self._store: dict[tuple[int, int, int],
                          tuple[np.ndarray, np.ndarray, np.ndarray | None]] = {}

    def get(self, view, channels: int, logit_channels: int, with_entropy: bool
            ) -> tuple[np.ndarray, np.ndarray | None]:
        key = (int(view.stamp_ns), int(channels), int(logit_channels))
        hit = self._store.get(key)
        if (hit is None or hit[0] is not view.embedding
                or (with_entropy and logit_channels and hit[2] is None)):
            hit = (view.embedding, *view_inputs(view.embedding, channels, logit_channels,
                                                with_entropy))
            self._store[key] = hit
        return hit[1], hit[2]

    def keep(self, views: list) -> None:
        """Forget every view but these."""
        stamps = {int(v.stamp_ns) for v in views}
        for key in [k for k in self._store if k[0] not in stamps]:
            del self._store[key]

    def __len__(self) -> int:
        return len(self._store)


def view_inputs(embedding: np.ndarray, channels: int, logit_channels: int,
                with_entropy: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """One stored view's (h, w, >= channels) embedding as the fusion reads it (see
    :class:`FusionInputs`): (h * w + 1, channels) float32, the first ``logit_channels`` as
    class probabilities, and their (h * w + 1,) entropy if asked. The last row is zeros:
    :func:`fuse_keyframes` points the points a view does not see at it, and adds every
    point's row densely (a scatter into the seen points' rows costs several times more)."""
    hw = int(np.prod(embedding.shape[:2]))
    flat = np.zeros((hw + 1, channels), np.float32)
    flat[:hw] = np.asarray(embedding[..., :channels]).reshape(hw, channels)
    S = int(logit_channels)
    h = None
    if S and with_entropy:
        h = np.zeros(hw + 1, np.float32)
        h[:hw] = entropy(flat[:hw, :S])
    if S:
        flat[:hw, :S] = softmax(flat[:hw, :S])
    return flat, h


def _seen(points: np.ndarray, keyframes: list, tolerance: float,
          visibility: ViewVisibility | None):
    """Per keyframe, the :func:`_visible` tuple of the world ``points``: ``visibility``'s
    when it was computed for these keyframes and as many points, else tested here."""
    if visibility is not None:
        if not visibility.matches(keyframes) or len(visibility.depth) != len(points):
            raise ValueError("visibility was computed for other keyframes or points")
        return visibility.seen
    cols = _columns(points)
    return (_visible(cols, _camera_map(kf), kf, tolerance) for kf in keyframes)


def fuse_keyframes(points: np.ndarray, own: np.ndarray, keyframes: list,
                   tolerance: float, logit_channels: int | None = None,
                   view_entropy: bool = False, inputs: FusionInputs | None = None,
                   visibility: ViewVisibility | None = None, own_weight: float = 1.0
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
    ``inputs`` keeps each keyframe's probabilities between renderings (the softmax of
    a stored view is then computed once, not per rendering); None computes them here.
    ``visibility``: the test already done for these keyframes on these points (the
    view's depth pixels, :func:`view_visibility`); None tests here. ``own_weight``: how
    many views the frame's own embedding counts as in the mean (and in the mean entropy):
    the other views reach a point through their poses and depths, whose small errors
    shift it by a pixel or two, which blurs small objects and borders; the frame itself
    sees every point where it is.

    This is the multi-view evidence the field is trained on, read directly: until
    the field has learnt a point, the view's embedding there is the mean over the
    views of it rather than the one frame's (a per-frame confusion, e.g. a picture
    called wall from one angle, is outvoted by the others).
    """
    S = 0 if logit_channels is None else int(logit_channels)
    C = own.shape[1]
    acc = own.astype(np.float32, copy=True)
    h_sum = None
    if S and view_entropy:
        h_sum = entropy(acc[:, :S]).astype(np.float64)
    if S:
        acc[:, :S] = softmax(acc[:, :S])
    if own_weight != 1.0:
        acc *= own_weight
        if h_sum is not None:
            h_sum *= own_weight
    n = np.ones(len(points), np.float32)
    seen = _seen(points, keyframes, tolerance, visibility)
    for kf, (idx, ui, vi, _, _) in zip(keyframes, seen):
        if not idx.size:
            continue
        h, w = kf.depth.shape
        eh, ew = kf.embedding.shape[:2]
        if (eh, ew) == (h, w):
            flat_i = vi * ew + ui
        else:
            flat_i = (np.minimum(((vi + 0.5) * eh / h).astype(np.int64), eh - 1) * ew
                      + np.minimum(((ui + 0.5) * ew / w).astype(np.int64), ew - 1))
        probs, ent = (inputs.get(kf, C, S, h_sum is not None) if inputs is not None
                      else view_inputs(kf.embedding, C, S, h_sum is not None))
        rows = np.full(len(acc), len(probs) - 1, np.int64)  # unseen: the zero row
        rows[idx] = flat_i
        if h_sum is not None:
            h_sum += ent[rows]
        acc += np.take(probs, rows, axis=0)
        n[idx] += 1.0
    weights = n + (own_weight - 1.0)  # the views, the frame's own counted own_weight times
    acc /= weights[:, None]
    if S:
        acc[:, :S] = np.log(np.maximum(acc[:, :S], 1e-12))
    return acc, n, (None if h_sum is None else (h_sum / weights).astype(np.float32))


def fuse_depth(depth: np.ndarray, intrinsics: Intrinsics, pose: np.ndarray, keyframes: list,
               tolerance: float, visibility: ViewVisibility | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """The view's depth averaged, pixel by pixel, with what the keyframes that see the
    same point measured of it, and how many depths were averaged per pixel (1 where no
    keyframe sees it; 0 where the view has no depth, which stays 0).

    A keyframe sees a pixel's point by the visibility test of :func:`_visible`. It
    measured the surface at ``zk`` along its own ray through the point, where the view
    put it at ``z`` (both in the keyframe's camera): its estimate of the point is the
    view's point moved along that ray by the factor ``zk / z``, and the view's depth of
    that estimate is what is averaged. Sensor noise (Kinect axial noise and disparity
    quantisation, independent between viewpoints) shrinks about as the square root of
    the views averaged, so the convex segments discovery cuts on the depth follow the
    surfaces rather than the noise: the small steps around a picture or a window frame
    stand out of a flat wall. Pixels without depth are not filled (no keyframe point is
    forward-projected): discovery leaves them unlabelled as before. ``visibility``: the
    test already done for this view and these keyframes (:func:`view_visibility`).
    """
    if visibility is None:
        visibility = view_visibility(depth, intrinsics, pose, keyframes, tolerance)
    elif not visibility.matches(keyframes) or visibility.mask.shape != np.shape(depth):
        raise ValueError("visibility was computed for other keyframes or another view size")
    mask, own = visibility.mask, visibility.depth
    acc, n = own.astype(np.float64), np.ones(len(own), np.float32)
    for (idx, _, _, zk, zf), c_z in zip(visibility.seen, visibility.centre_z):
        if not idx.size:
            continue
        # c_z is the keyframe's centre in the view's camera: the view-z of (point - centre)
        # is own - c_z, so the estimate's view depth is own + (zk / z - 1) (own - c_z).
        acc[idx] += own[idx] + (zk / zf - 1.0) * (own[idx] - c_z)
        n[idx] += 1.0
    out = np.zeros(mask.shape, np.float32)
    out[mask] = acc / n
    count = np.zeros(mask.shape, np.float32)
    count[mask] = n
    return out, count
