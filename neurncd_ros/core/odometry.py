"""Camera poses from the RGB-D images themselves, for inputs that carry none.

(One module, over 500 lines: dense tracking, the feature fallback, the
checks and relocalisation share one keyframe store and one loss policy.)

NYUv2 raw sequences have no poses, and many robot bags have no pose topic or
a broken /tf tree. :class:`RGBDOdometry` estimates camera-to-world poses from
colour and depth alone, frame to keyframe:

- **dense tracking** against the current keyframe with OpenCV's RGB-D odometry
  (``cv2.Odometry``, photometric + ICP terms on an image pyramid; already a
  dependency), on images downscaled to ``odometry.width`` for speed;
- **check**: the keyframe's depth points are moved by the estimate into the new
  view and compared with its depth; the share that agree (``fitness``) and
  their number (``inliers``) decide whether the estimate is trusted, and a
  step longer than ``max_step_m`` / ``max_step_deg`` is refused too;
- **wide-baseline fallback and relocalisation**: ORB features matched against
  the keyframe (and, once lost, against the stored keyframes, nearest first)
  give a PnP-RANSAC pose, refined densely and checked the same way;
- **keyframes**: a new keyframe is made when the overlap drops or the camera has
  moved ``keyframe_m`` / ``keyframe_deg``; before that, a stored keyframe near
  the current pose is tried (local refinement against the map: coming back to
  a place tracks against the keyframe seen there instead of accumulating drift);
- **tracking loss** is never silent: every result has a status and a reason.
  After ``new_segment_after`` lost frames the odometry starts a new map
  segment at the last good pose (``status="new_segment"``) on the first frame
  with depth enough to track against (a covered lens waits): poses of the new
  segment are consistent among themselves, not with the old one.

Poses are 4x4 float64 camera-to-world in OpenCV optical axes; the world frame
is the first frame's camera (or ``initial_pose``). :func:`with_odometry`
re-poses a stream of Frames offline (``neurncd convert --poses odometry``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Iterable, Iterator

import cv2
import numpy as np

from .camera import Intrinsics, invert_pose
from .frame import Frame
from .params import param

log = logging.getLogger(__name__)

STATUSES = ("ok", "lost", "relocalised", "new_segment")


@dataclasses.dataclass(frozen=True)
class OdometryConfig:
    """RGB-D odometry: poses from colour and depth when the input has none."""

    width: int = param(160, "images are downscaled to this width for dense tracking (0 = "
                       "full size); small keeps tracking within a frame period on one core "
                       "(see bench/results/odometry.json)",
                       lo=0, hi=4096, unit="px")
    method: str = param("rgbd", "dense terms: rgbd = photometric + ICP, depth = ICP only, "
                        "rgb = photometric only", choices=("rgbd", "depth", "rgb"))
    min_depth: float = param(0.2, "depths nearer than this are not used", lo=0.0, hi=10.0,
                             unit="m")
    max_depth: float = param(8.0, "depths farther than this are not used", lo=0.1, hi=100.0,
                             unit="m")
    max_depth_diff: float = param(0.3, "dense ICP correspondences further apart than this "
                                  "are rejected (generous: Kinect depth is quantised in steps "
                                  "of several cm at 4-5 m)", lo=0.001, hi=5.0, unit="m")
    max_points_part: float = param(0.25, "share of the valid pixels the dense ICP term uses "
                                   "(OpenCV's default 0.07 misaligned 1 pair in 30)",
                                   lo=0.01, hi=1.0)
    inlier_m: float = param(0.03, "a keyframe point agrees with the new depth within this "
                            "distance (plus inlier_rel of its depth)", lo=0.001, hi=1.0,
                            unit="m")
    inlier_rel: float = param(0.02, "depth-relative part of the agreement tolerance",
                              lo=0.0, hi=0.5)
    min_fitness: float = param(0.5, "an estimate is trusted when at least this share of the "
                               "keyframe points seen in the new frame agree with its depth",
                               lo=0.0, hi=1.0)
    good_fitness: float = param(0.95, "below this fitness the dense estimate is cross-checked "
                                "against ORB features + PnP and the better one kept (good "
                                "steps agree at 0.96-0.99)", lo=0.0, hi=1.0)
    min_inliers: int = param(300, "... and at least this many agree (at the working "
                             "resolution, every second pixel)", lo=1, hi=1_000_000)
    max_step_m: float = param(0.3, "a step longer than this between consecutive tracked "
                              "frames is refused as a jump", lo=0.001, hi=100.0, unit="m")
    max_step_deg: float = param(30.0, "a rotation larger than this between consecutive "
                                "tracked frames is refused as a jump", lo=0.1, hi=180.0,
                                unit="deg")
    keyframe_m: float = param(0.12, "a new keyframe after this much translation from the "
                              "current one", lo=0.0, hi=100.0, unit="m")
    keyframe_deg: float = param(10.0, "a new keyframe after this much rotation",
                                lo=0.0, hi=180.0, unit="deg")
    keyframe_overlap: float = param(0.7, "a new keyframe when fewer of the keyframe's points "
                                    "than this share land in the new frame", lo=0.0, hi=1.0)
    max_keyframes: int = param(200, "keyframes kept for revisits and relocalisation (oldest "
                               "dropped first)", lo=1, hi=100_000)
    features: int = param(1000, "ORB features per image for the wide-baseline fallback and "
                          "relocalisation (0 = off)", lo=0, hi=100_000)
    feature_width: int = param(320, "images are downscaled to this width for features (0 = "
                               "full size)", lo=0, hi=4096, unit="px")
    min_feature_inliers: int = param(25, "a feature pose needs this many PnP-RANSAC inliers",
                                     lo=6, hi=100_000)
    relocalise_keyframes: int = param(8, "keyframes tried per lost frame, nearest to the last "
                                      "good pose first", lo=1, hi=10_000)
    new_segment_after: int = param(10, "start a new map segment after this many lost frames "
                                   "in a row (0 = stay lost until relocalised)",
                                   lo=0, hi=1_000_000)


@dataclasses.dataclass
class TrackResult:
    """Outcome of :meth:`RGBDOdometry.track` for one frame.

    ``pose``: 4x4 camera-to-world, or None when ``status`` is "lost";
    ``status``: "ok" (tracked), "lost" (no trusted pose), "relocalised" (found
    again against a stored keyframe after being lost), "new_segment" (first
    frame of a new map segment; its poses are unrelated to earlier segments);
    ``fitness``: share of the reference keyframe's points that agree with the
    new depth; ``inliers``: how many; ``segment``: map segment id (0, 1, ...);
    ``keyframe``: whether this frame became a keyframe; ``reason``: why.
    """

    pose: np.ndarray | None
    status: str
    fitness: float
    inliers: int
    reason: str
    segment: int = 0
    keyframe: bool = False


@dataclasses.dataclass
class _View:
    """One frame prepared for tracking (working resolution)."""

    stamp_ns: int
    gray: np.ndarray           # (h, w) uint8
    depth: np.ndarray          # (h, w) float32 m, 0 = none
    K: np.ndarray              # 3x3 of the working resolution (positive focal lengths)
    frame: object              # cv2.OdometryFrame, prepared
    points: np.ndarray         # (N, 3) float64 camera-frame points (every second pixel)
    camera: tuple              # the caller's intrinsics, to notice a change of camera
    full_rgb: np.ndarray | None = None   # for features, only kept while needed
    full_depth: np.ndarray | None = None
    full_K: np.ndarray | None = None
    features: tuple | None = None  # (keypoints (M,2) px, descriptors, depth at keypoints)


@dataclasses.dataclass
class _Keyframe:
    view: _View
    pose: np.ndarray           # camera-to-world
    segment: int
    index: int


def rotation_deg(T: np.ndarray) -> float:
    """Rotation angle of a rigid transform in degrees."""
    c = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def _motion(T: np.ndarray) -> tuple[float, float]:
    return float(np.linalg.norm(T[:3, 3])), rotation_deg(T)


class RGBDOdometry:
    """Frame-to-keyframe RGB-D odometry with loss detection and relocalisation.

    Not thread-safe: one caller feeds frames in stamp order. ``initial_pose``
    is the world pose of the first frame (identity by default).
    """

    def __init__(self, cfg: OdometryConfig | None = None,
                 initial_pose: np.ndarray | None = None) -> None:
        self.cfg = cfg or OdometryConfig()
        if self.cfg.min_depth >= self.cfg.max_depth:
            raise ValueError(f"odometry.min_depth {self.cfg.min_depth} must be below "
                             f"max_depth {self.cfg.max_depth}")
        self.initial_pose = np.eye(4) if initial_pose is None else \
            np.asarray(initial_pose, np.float64)
        self._odo: dict[tuple, object] = {}
        self._orb = cv2.ORB_create(self.cfg.features) if self.cfg.features else None
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget everything: the next frame starts segment 0 at ``initial_pose``."""
        self.keyframes: list[_Keyframe] = []
        self._ref: _Keyframe | None = None
        self._last_pose: np.ndarray | None = None
        self._lost = 0
        self._segment = -1
        self._kf_count = 0
        self.frames = 0
        self.counts = {s: 0 for s in STATUSES}

    @property
    def segment(self) -> int:
        """Current map segment (-1 before the first frame)."""
        return self._segment

    # ------------------------------------------------------------------ preparation
    def _odometry(self, K: np.ndarray) -> object:
        key = tuple(np.round(K.ravel(), 6))
        odo = self._odo.get(key)
        if odo is None:
            c = self.cfg
            s = cv2.OdometrySettings()
            s.setCameraMatrix(K.astype(np.float32))
            s.setMinDepth(c.min_depth)
            s.setMaxDepth(c.max_depth)
            s.setMaxDepthDiff(c.max_depth_diff)
            s.setMaxPointsPart(c.max_points_part)
            s.setMaxTranslation(c.max_step_m + c.keyframe_m)
            s.setMaxRotation(min(180.0, c.max_step_deg + c.keyframe_deg))
            kind = {"rgbd": cv2.ODOMETRY_TYPE_RGB_DEPTH, "depth": cv2.ODOMETRY_TYPE_DEPTH,
                    "rgb": cv2.ODOMETRY_TYPE_RGB}[c.method]
            odo = cv2.Odometry(kind, s, cv2.ODOMETRY_ALGO_TYPE_COMMON)
            if len(self._odo) > 8:
                self._odo.clear()
            self._odo[key] = odo
        return odo

    def _prepare(self, stamp_ns: int, rgb: np.ndarray, depth: np.ndarray,
                 intr: Intrinsics) -> _View:
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"odometry: rgb must be (H, W, 3) uint8, got {rgb.shape} "
                             f"{rgb.dtype}")
        if depth.ndim != 2 or depth.shape != rgb.shape[:2]:
            raise ValueError(f"odometry: depth must be (H, W) matching rgb {rgb.shape[:2]}, "
                             f"got {depth.shape}")
        if (intr.height, intr.width) != depth.shape:
            raise ValueError(f"odometry: intrinsics are {intr.width}x{intr.height} but the "
                             f"images {depth.shape[1]}x{depth.shape[0]}")
        depth = np.nan_to_num(depth.astype(np.float32, copy=False), nan=0.0, posinf=0.0,
                              neginf=0.0)
        # A negative focal length (ICL-NUIM's y-up images) is a mirrored image of the same
        # camera frame: mirror the pixels back and the camera is an ordinary one.
        flip = (intr.fx < 0, intr.fy < 0)
        rgb, depth = _flip(rgb, flip), _flip(depth, flip)
        h, w = depth.shape
        fx, fy = abs(intr.fx), abs(intr.fy)
        cx = (w - 1 - intr.cx) if flip[0] else intr.cx
        cy = (h - 1 - intr.cy) if flip[1] else intr.cy
        full = Intrinsics(fx, fy, cx, cy, w, h)
        ww = self.cfg.width if 0 < self.cfg.width < w else w
        wh = max(8, int(round(h * ww / w)))
        work = full.scaled(ww, wh) if ww != w else full
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        if ww != w:
            gray = cv2.resize(gray, (ww, wh), interpolation=cv2.INTER_AREA)
            d = cv2.resize(depth, (ww, wh), interpolation=cv2.INTER_NEAREST)
        else:
            d = depth
        d = np.where((d >= self.cfg.min_depth) & (d <= self.cfg.max_depth), d,
                     np.float32(0)).astype(np.float32)
        K = work.K
        fr = cv2.OdometryFrame(d, gray)
        self._odometry(K).prepareFrame(fr)
        v, u = np.mgrid[0:wh:2, 0:ww:2]
        z = d[v, u]
        ok = z > 0
        z, u, v = z[ok].astype(np.float64), u[ok], v[ok]
        pts = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
        return _View(int(stamp_ns), gray, d, K, fr, pts,
                     (intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height),
                     full_rgb=rgb, full_depth=depth, full_K=full.K)

    # ------------------------------------------------------------------ measures
    def _check(self, ref: _View, cur: _View, T_cur_ref: np.ndarray) -> tuple[float, int, float]:
        """(fitness, inliers, overlap) of moving ``ref``'s points into ``cur`` by T."""
        P = ref.points @ T_cur_ref[:3, :3].T + T_cur_ref[:3, 3]
        n = len(P)
        if n == 0:
            return 0.0, 0, 0.0
        z = P[:, 2]
        front = z > 1e-6
        K = cur.K
        h, w = cur.depth.shape
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(P[:, 0] / z * K[0, 0] + K[0, 2])
            v = np.round(P[:, 1] / z * K[1, 1] + K[1, 2])
        inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        ui, vi = u[inside].astype(np.intp), v[inside].astype(np.intp)
        d = cur.depth[vi, ui]
        seen = d > 0
        zs = z[inside][seen]
        agree = np.abs(zs - d[seen]) <= self.cfg.inlier_m + self.cfg.inlier_rel * d[seen]
        n_seen = int(seen.sum())
        inl = int(agree.sum())
        return (inl / n_seen if n_seen else 0.0), inl, n_seen / n

    def _good(self, fit: float, inl: int) -> bool:
        return fit >= self.cfg.min_fitness and inl >= self.cfg.min_inliers

    # ------------------------------------------------------------------ estimators
    def _dense(self, ref: _View, cur: _View, T0: np.ndarray | None = None
               ) -> np.ndarray | None:
        """T_cur_ref by dense odometry; ``T0`` is an initial guess (warps ``ref`` first)."""
        odo = self._odometry(ref.K)
        src = ref.frame
        if T0 is not None:
            wd, wg, _ = cv2.warpFrame(ref.depth, ref.gray, None, T0, ref.K)
            src = cv2.OdometryFrame(wd.astype(np.float32), wg)
            odo.prepareFrame(src)
        try:
            ok, Rt = odo.compute(src, cur.frame)
        except cv2.error as err:
            log.debug("dense odometry failed: %s", err)
            return None
        if not ok or Rt is None or not np.all(np.isfinite(Rt)):
            return None
        Rt = np.asarray(Rt, np.float64)
        return Rt if T0 is None else Rt @ T0

    def _features(self, view: _View) -> tuple:
        """(keypoints, descriptors, depth at keypoints, K) of ``view`` at feature_width."""
        if view.features is None:
            rgb, depth, K = view.full_rgb, view.full_depth, view.full_K
            h, w = depth.shape
            fw = self.cfg.feature_width if 0 < self.cfg.feature_width < w else w
            if fw != w:
                fh = max(8, int(round(h * fw / w)))
                rgb = cv2.resize(rgb, (fw, fh), interpolation=cv2.INTER_AREA)
                depth = cv2.resize(depth, (fw, fh), interpolation=cv2.INTER_NEAREST)
                K = Intrinsics.from_matrix(K, w, h).scaled(fw, fh).K
            gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
            kps, desc = self._orb.detectAndCompute(gray, None)
            if desc is None or not kps:
                view.features = (np.zeros((0, 2)), None, np.zeros(0), K)
            else:
                xy = np.array([k.pt for k in kps], dtype=np.float64)
                ui = np.clip(np.round(xy[:, 0]).astype(int), 0, depth.shape[1] - 1)
                vi = np.clip(np.round(xy[:, 1]).astype(int), 0, depth.shape[0] - 1)
                z = depth[vi, ui].astype(np.float64)
                z[(z < self.cfg.min_depth) | (z > self.cfg.max_depth)] = 0.0
                view.features = (xy, desc, z, K)
        return view.features

    def _feature_pose(self, ref: _View, cur: _View) -> tuple[np.ndarray | None, int]:
        """T_cur_ref from ORB matches and PnP-RANSAC on ``ref``'s depth; (T, inliers)."""
        if self._orb is None:
            return None, 0
        xr, dr, zr, Kr = self._features(ref)
        xc, dc, _, Kc = self._features(cur)
        if dr is None or dc is None:
            return None, 0
        matches = self._matcher.match(dr, dc)
        if len(matches) < self.cfg.min_feature_inliers:
            return None, len(matches)
        qi = np.array([m.queryIdx for m in matches])
        ti = np.array([m.trainIdx for m in matches])
        keep = zr[qi] > 0
        qi, ti = qi[keep], ti[keep]
        if len(qi) < self.cfg.min_feature_inliers:
            return None, len(qi)
        z = zr[qi]
        obj = np.stack([(xr[qi, 0] - Kr[0, 2]) / Kr[0, 0] * z,
                        (xr[qi, 1] - Kr[1, 2]) / Kr[1, 1] * z, z], axis=1)
        img = xc[ti]
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, Kc, None, iterationsCount=200,
                                                 reprojectionError=3.0, confidence=0.999,
                                                 flags=cv2.SOLVEPNP_EPNP)
        n_inl = 0 if inl is None else len(inl)
        if not ok or n_inl < self.cfg.min_feature_inliers:
            return None, n_inl
        inl = inl[:, 0]
        ok, rvec, tvec = cv2.solvePnP(obj[inl], img[inl], Kc, None, rvec, tvec,
                                      useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = tvec[:, 0]
        return T, n_inl

    def _estimate(self, ref: _View, cur: _View) -> tuple[np.ndarray | None, float, int, float,
                                                       str]:
        """Best trusted T_cur_ref: (T or None, fitness, inliers, overlap, how).

        Dense odometry first; when its fitness is below ``good_fitness`` (a wrong
        local minimum, e.g. a long step sliding along a wall), ORB features +
        PnP-RANSAC and their dense refinement are tried too, and the candidate
        whose points agree best with the new depth wins."""
        cands: list[tuple[np.ndarray, float, int, float, str]] = []
        notes = []
        T = self._dense(ref, cur)
        if T is None:
            notes.append("dense odometry did not converge")
        else:
            fit, inl, ov = self._check(ref, cur, T)
            if fit >= self.cfg.good_fitness and inl >= self.cfg.min_inliers:
                return T, fit, inl, ov, "dense"
            cands.append((T, fit, inl, ov, "dense"))
            notes.append(f"dense fitness {fit:.2f} with {inl} inliers")
        T0, n_feat = self._feature_pose(ref, cur)
        if T0 is None:
            notes.append(f"features: {n_feat} PnP inliers")
        else:
            Tr = self._dense(ref, cur, T0)
            for Tc, how in ((T0, "features"), (Tr, "features + dense")):
                if Tc is not None:
                    fit, inl, ov = self._check(ref, cur, Tc)
                    cands.append((Tc, fit, inl, ov, how))
                    notes.append(f"{how} fitness {fit:.2f} with {inl} inliers")
        if not cands:
            return None, 0.0, 0, 0.0, "; ".join(notes)
        best = max(cands, key=lambda c: (c[1], c[2]))
        if self._good(best[1], best[2]):
            how = best[4] if best[4] == "dense" and len(cands) == 1 else \
                f"{best[4]} (best of: {'; '.join(notes)})"
            return best[:4] + (how,)
        return (None,) + best[1:4] + ("; ".join(notes),)

    # ------------------------------------------------------------------ keyframes
    def _add_keyframe(self, view: _View, pose: np.ndarray) -> _Keyframe:
        kf = _Keyframe(view, pose.copy(), self._segment, self._kf_count)
        self._kf_count += 1
        if self._orb is not None:
            self._features(view)  # for relocalisation later; the full images are not kept
        view.full_rgb = view.full_depth = None
        self.keyframes.append(kf)
        if len(self.keyframes) > self.cfg.max_keyframes:
            dropped = self.keyframes.pop(0)
            if dropped is self._ref:  # never drop the reference
                self.keyframes.insert(0, dropped)
                self.keyframes.pop(1)
        self._ref = kf
        return kf

    def _nearest_keyframes(self, pose: np.ndarray, exclude: _Keyframe | None, k: int
                           ) -> list[_Keyframe]:
        """Keyframes of the current segment nearest to ``pose`` (distance + angle)."""
        scored = []
        for kf in self.keyframes:
            if kf is exclude or kf.segment != self._segment:
                continue
            t, r = _motion(invert_pose(kf.pose) @ pose)
            scored.append((t / max(self.cfg.keyframe_m, 1e-3) +
                           r / max(self.cfg.keyframe_deg, 1e-3), kf.index, kf))
        scored.sort(key=lambda x: (x[0], -x[1]))
        return [kf for _, _, kf in scored[:k]]

    def _needs_keyframe(self, T_cur_ref: np.ndarray, overlap: float) -> bool:
        t, r = _motion(T_cur_ref)
        return (overlap < self.cfg.keyframe_overlap or t > self.cfg.keyframe_m or
                r > self.cfg.keyframe_deg)

    # ------------------------------------------------------------------ the API
    def track(self, stamp_ns: int, rgb: np.ndarray, depth: np.ndarray,
              intrinsics: Intrinsics) -> TrackResult:
        """Pose of one frame (frames in stamp order); see :class:`TrackResult`."""
        cur = self._prepare(stamp_ns, rgb, depth, intrinsics)
        self.frames += 1
        if self._ref is not None and cur.camera != self._ref.view.camera:
            reason = (f"camera changed ({self._ref.view.camera} -> {cur.camera}): new "
                      "segment")
            return self._new_segment(cur, self._last_pose, reason)
        if self._ref is None:
            if not self._has_depth(cur):
                self.counts["lost"] += 1
                return TrackResult(None, "lost", 0.0, len(cur.points),
                                   f"no tracking started: {self._depth_note(cur)}")
            return self._new_segment(cur, self.initial_pose, "first frame")
        if self._lost:
            return self._relocalise(cur)
        ref = self._ref
        T, fit, inl, ov, how = self._estimate(ref.view, cur)
        if T is not None:
            pose = ref.pose @ invert_pose(T)
            step_t, step_r = _motion(invert_pose(self._last_pose) @ pose)
            if step_t > self.cfg.max_step_m or step_r > self.cfg.max_step_deg:
                T = None
                how = (f"jump of {step_t:.2f} m / {step_r:.1f} deg refused (limits "
                       f"{self.cfg.max_step_m} m / {self.cfg.max_step_deg} deg)")
        if T is None:
            return self._lose(cur, fit, inl, f"tracking lost against keyframe {ref.index}: "
                              f"{how}")
        result = TrackResult(pose, "ok", fit, inl, how, self._segment)
        if self._needs_keyframe(T, ov):
            self._switch_or_add(cur, pose, result)
        self._accept(pose, result)
        return result

    def _accept(self, pose: np.ndarray, result: TrackResult) -> None:
        self._last_pose = pose
        self._lost = 0
        self.counts[result.status] += 1

    def _switch_or_add(self, cur: _View, pose: np.ndarray, result: TrackResult) -> None:
        """Track against a stored keyframe near ``pose`` if one fits, else make ``cur`` one."""
        for kf in self._nearest_keyframes(pose, self._ref, 2):
            T_guess = invert_pose(pose) @ kf.pose          # T_cur_kf from the pose estimate
            t, r = _motion(T_guess)
            if t > self.cfg.keyframe_m or r > self.cfg.keyframe_deg:
                break
            T = self._dense(kf.view, cur)
            if T is None:
                continue
            fit, inl, ov = self._check(kf.view, cur, T)
            if self._good(fit, inl) and ov >= self.cfg.keyframe_overlap:
                refined = kf.pose @ invert_pose(T)
                if _motion(invert_pose(pose) @ refined)[0] <= self.cfg.keyframe_m:
                    self._ref = kf
                    result.pose = refined
                    result.reason += f"; revisits keyframe {kf.index}"
                    return
        self._add_keyframe(cur, pose)
        result.keyframe = True

    def _lose(self, cur: _View, fit: float, inl: int, reason: str) -> TrackResult:
        self._lost += 1
        self.counts["lost"] += 1
        log.warning("odometry: frame %d: %s", cur.stamp_ns, reason)
        if self.cfg.new_segment_after and self._lost >= self.cfg.new_segment_after:
            if self._has_depth(cur):
                self.counts["lost"] -= 1
                return self._new_segment(cur, self._last_pose,
                                         f"{reason}; lost for {self._lost} frames: new segment")
            # A keyframe without depth would lose every frame after it: wait for depth.
            reason += f"; no new segment yet: {self._depth_note(cur)}"
        return TrackResult(None, "lost", fit, inl, reason, self._segment)

    def _has_depth(self, view: _View) -> bool:
        """Enough depth points to be a keyframe (``min_inliers``)."""
        return len(view.points) >= self.cfg.min_inliers

    def _depth_note(self, view: _View) -> str:
        return (f"the frame has {len(view.points)} depth points, a keyframe needs "
                f"{self.cfg.min_inliers} (odometry.min_inliers)")

    def _relocalise(self, cur: _View) -> TrackResult:
        best_fit, best_inl = 0.0, 0
        for kf in self._nearest_keyframes(self._last_pose, None,
                                          self.cfg.relocalise_keyframes):
            T, fit, inl, ov, how = self._estimate(kf.view, cur)
            if T is not None:
                pose = kf.pose @ invert_pose(T)
                self._ref = kf
                result = TrackResult(pose, "relocalised", fit, inl,
                                     f"relocalised against keyframe {kf.index} after "
                                     f"{self._lost} lost frame(s) ({how})", self._segment)
                if self._needs_keyframe(T, ov):
                    self._add_keyframe(cur, pose)
                    result.keyframe = True
                log.info("odometry: frame %d: %s", cur.stamp_ns, result.reason)
                self._accept(pose, result)
                return result
            best_fit, best_inl = max(best_fit, fit), max(best_inl, inl)
        return self._lose(cur, best_fit, best_inl,
                          f"still lost ({self._lost} frame(s)): no stored keyframe matches")

    def _new_segment(self, cur: _View, pose: np.ndarray, reason: str) -> TrackResult:
        first = self._segment < 0
        self._segment += 1
        self._add_keyframe(cur, pose)
        status = "ok" if first else "new_segment"
        result = TrackResult(pose.copy(), status, 1.0, len(cur.points),
                             f"{reason}: keyframe {self._ref.index} starts segment "
                             f"{self._segment}", self._segment, keyframe=True)
        if not first:
            log.warning("odometry: frame %d: %s", cur.stamp_ns, result.reason)
        self._accept(pose, result)
        return result


def _flip(img: np.ndarray, flip: tuple[bool, bool]) -> np.ndarray:
    if flip[0]:
        img = img[:, ::-1]
    if flip[1]:
        img = img[::-1]
    return np.ascontiguousarray(img)


def with_odometry(frames: Iterable[Frame], cfg: OdometryConfig | None = None,
                  results: list[TrackResult] | None = None,
                  initial_pose: np.ndarray | None = None) -> Iterator[Frame]:
    """The frames with poses estimated from their images (their own poses ignored).

    Frames whose pose cannot be estimated (tracking lost) are dropped, each with
    a logged warning; ``results``, when given, receives every frame's
    :class:`TrackResult` (to count losses and segments).
    """
    odo = RGBDOdometry(cfg, initial_pose)
    for fr in frames:
        res = odo.track(fr.stamp_ns, fr.rgb, fr.depth, fr.intrinsics)
        if results is not None:
            results.append(res)
        if res.pose is None:
            continue
        yield dataclasses.replace(fr, pose=res.pose)
