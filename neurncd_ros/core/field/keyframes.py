"""Bounded, thread-safe keyframe buffer of the incremental mapper.

Admission: a frame becomes a keyframe when the camera moved enough since the
last admitted keyframe (translation or rotation) or enough time passed.
Eviction (buffer full): the first keyframe and the newest one are protected;
among the rest, the most redundant one goes, i.e. the one whose pose is
closest to another keyframe's (distance in units of the admission
thresholds), preferring keyframes already published, then older ones.
Rays are drawn across the buffer with a share reserved for the most recent
keyframes so a new view is learnt quickly without forgetting old ones.

The embedding may have a lower resolution than the frame: it is stored as it
is (float16) and a ray through frame pixel (u, v) reads the embedding pixel
covering the same image area (nearest, pixel-area aligned).
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import torch

from ..camera import Intrinsics, camera_directions, check_pose
from ..frame import Frame
from ..params import param


@dataclasses.dataclass(frozen=True)
class KeyframeConfig:
    """Keyframe admission, eviction and ray sampling."""

    max_keyframes: int = param(64, "keyframes kept at most (memory bound)", lo=2, hi=4096)
    min_translation: float = param(0.15, "camera translation since the last keyframe that "
                                   "admits a new one", lo=0.0, hi=100.0, unit="m")
    min_rotation: float = param(10.0, "camera rotation since the last keyframe that admits "
                                "a new one", lo=0.0, hi=180.0, unit="deg")
    max_interval: float = param(2.0, "time since the last keyframe that admits a new one "
                                "regardless of motion (0 = never)", lo=0.0, hi=3600.0, unit="s")
    recent_bias: float = param(0.3, "share of training rays drawn from the most recent "
                               "keyframes", lo=0.0, hi=1.0)
    recent_window: int = param(3, "how many of the newest keyframes count as recent",
                               lo=1, hi=1000)
    holdout_stride: int = param(0, "never train on pixels with u and v multiples of this "
                                "(held-out evaluation pixels; 0 = train on all)", lo=0, hi=64)


@dataclasses.dataclass(frozen=True)
class KeyframeInfo:
    """What the node needs to render and publish a keyframe."""

    stamp_ns: int
    pose: np.ndarray
    intrinsics: Intrinsics
    id: int
    depth: np.ndarray | None = None
    """The keyframe's measured depth (read-only view), to render it depth-guided."""


@dataclasses.dataclass
class Keyframe:
    """One stored keyframe; ``iterations`` counts training steps since admission."""

    id: int
    stamp_ns: int
    pose: np.ndarray
    intrinsics: Intrinsics
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 metres
    embedding: np.ndarray  # (h, w, S) float16 logits
    iterations: int = 0
    published: bool = False

    def info(self) -> KeyframeInfo:
        depth = self.depth.view()
        depth.flags.writeable = False
        return KeyframeInfo(self.stamp_ns, self.pose.copy(), self.intrinsics, self.id, depth)


def _pose_gaps(poses: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (m) and rotation (deg) between each pose (N, 4, 4) and each ref (M, 4, 4)."""
    dt = np.linalg.norm(poses[:, None, :3, 3] - ref[None, :, :3, 3], axis=-1)
    tr = np.einsum("nij,mij->nm", poses[:, :3, :3], ref[:, :3, :3])
    dr = np.degrees(np.arccos(np.clip((tr - 1) / 2, -1.0, 1.0)))
    return dt, dr


def check_embedding(frame: Frame, embedding: np.ndarray) -> np.ndarray:
    """Validate an (h, w, S) embedding against its frame; returns float32."""
    emb = np.asarray(embedding)
    if emb.ndim != 3:
        raise ValueError(f"embedding must be (H, W, S), got shape {emb.shape}")
    if not np.issubdtype(emb.dtype, np.floating):
        raise ValueError(f"embedding must be floating point logits, got {emb.dtype}")
    h, w = frame.intrinsics.height, frame.intrinsics.width
    if emb.shape[0] > h or emb.shape[1] > w or emb.shape[0] < 1 or emb.shape[1] < 1:
        raise ValueError(f"embedding is {emb.shape[1]}x{emb.shape[0]}, must be at most the "
                         f"frame's {w}x{h}")
    if abs(emb.shape[1] / emb.shape[0] - w / h) > 0.05 * w / h:
        raise ValueError(f"embedding aspect {emb.shape[1]}x{emb.shape[0]} differs from the "
                         f"frame's {w}x{h}")
    if not np.all(np.isfinite(emb)):
        raise ValueError("embedding has non-finite values")
    return emb


class KeyframeBuffer:
    """Thread-safe bounded keyframe store with admission, eviction and ray sampling."""

    def __init__(self, cfg: KeyframeConfig | None = None) -> None:
        self.cfg = cfg or KeyframeConfig()
        self._lock = threading.RLock()
        self._frames: list[Keyframe] = []
        self._next_id = 0
        self._last_pose: np.ndarray | None = None
        self._last_stamp: int | None = None
        self.admitted = 0
        self.evicted = 0

    def __len__(self) -> int:
        with self._lock:
            return len(self._frames)

    def keyframes(self) -> list[Keyframe]:
        """A snapshot list (the keyframe objects are shared; treat as read-only)."""
        with self._lock:
            return list(self._frames)

    def should_admit(self, pose: np.ndarray, stamp_ns: int) -> bool:
        """Would a frame with this pose and stamp be admitted now?"""
        with self._lock:
            if self._last_pose is None:
                return True
            dt, dr = _pose_gaps(pose[None], self._last_pose[None])
            if dt[0, 0] >= self.cfg.min_translation or dr[0, 0] >= self.cfg.min_rotation:
                return True
            elapsed = (stamp_ns - self._last_stamp) * 1e-9
            return self.cfg.max_interval > 0 and elapsed >= self.cfg.max_interval

    def add(self, frame: Frame, embedding: np.ndarray, force: bool = False) -> bool:
        """Admit the frame if it passes admission (or ``force``); evicts when full."""
        frame.validate()
        emb = check_embedding(frame, embedding)
        with self._lock:
            if not force and not self.should_admit(frame.pose, frame.stamp_ns):
                return False
            kf = Keyframe(self._next_id, int(frame.stamp_ns), check_pose(frame.pose).copy(),
                          frame.intrinsics, np.ascontiguousarray(frame.rgb),
                          np.ascontiguousarray(frame.depth, dtype=np.float32),
                          emb.astype(np.float16))
            self._next_id += 1
            self._last_pose, self._last_stamp = kf.pose, kf.stamp_ns
            self._frames.append(kf)
            self.admitted += 1
            while len(self._frames) > self.cfg.max_keyframes:
                self._evict()
            return True

    def _evict(self) -> None:
        n = len(self._frames)
        poses = np.stack([k.pose for k in self._frames])
        dt, dr = _pose_gaps(poses, poses)
        gap = dt / max(self.cfg.min_translation, 1e-3) + dr / max(self.cfg.min_rotation, 1e-3)
        np.fill_diagonal(gap, np.inf)
        score = gap.min(axis=1)
        score += np.array([0.0 if k.published else 0.5 for k in self._frames])
        score += 1e-6 * np.arange(n)  # older first on ties
        score[0] = score[-1] = np.inf  # first and newest are protected
        del self._frames[int(np.argmin(score))]
        self.evicted += 1

    def tick(self, n: int = 1) -> None:
        """Count n training iterations for every stored keyframe."""
        with self._lock:
            for k in self._frames:
                k.iterations += n

    def ready(self, min_iterations: int) -> list[KeyframeInfo]:
        """Keyframes trained >= min_iterations since admission, each returned once."""
        with self._lock:
            out = [k for k in self._frames if not k.published and k.iterations >= min_iterations]
            for k in out:
                k.published = True
            return [k.info() for k in out]

    def clear(self) -> None:
        with self._lock:
            self._frames.clear()
            self._last_pose = self._last_stamp = None

    def keyframe_weights(self) -> np.ndarray:
        """Sampling probability of each stored keyframe (uniform + recent share)."""
        with self._lock:
            n = len(self._frames)
        if n == 0:
            return np.zeros(0)
        p = np.full(n, (1.0 - self.cfg.recent_bias) / n)
        k = min(self.cfg.recent_window, n)
        p[n - k:] += self.cfg.recent_bias / k
        return p / p.sum()

    def sample_rays(self, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        """n training rays across the buffer: world origins, z-normalised dirs and targets."""
        with self._lock:
            frames = list(self._frames)
            p = self.keyframe_weights()
        if not frames:
            raise ValueError("no keyframes to sample rays from")
        which = rng.choice(len(frames), size=n, p=p)
        counts = np.bincount(which, minlength=len(frames))
        s = frames[0].embedding.shape[-1]
        out = {"origins": np.empty((n, 3)), "dirs": np.empty((n, 3)),
               "rgb": np.empty((n, 3), np.float32), "depth": np.empty(n, np.float32),
               "embedding": np.empty((n, s), np.float32)}
        start = 0
        stride = self.cfg.holdout_stride
        for i in np.nonzero(counts)[0]:
            kf, m = frames[i], int(counts[i])
            h, w = kf.depth.shape
            u, v = rng.integers(0, w, m), rng.integers(0, h, m)
            if stride > 0:
                held = (u % stride == 0) & (v % stride == 0)
                u = np.where(held, np.where(u + 1 < w, u + 1, u - 1), u)
            eh, ew = kf.embedding.shape[:2]
            ue = np.minimum(((u + 0.5) * ew / w).astype(np.int64), ew - 1)
            ve = np.minimum(((v + 0.5) * eh / h).astype(np.int64), eh - 1)
            sl = slice(start, start + m)
            d = camera_directions(kf.intrinsics, u, v) @ kf.pose[:3, :3].T
            out["origins"][sl] = kf.pose[:3, 3]
            out["dirs"][sl] = d
            out["rgb"][sl] = kf.rgb[v, u] / 255.0
            out["depth"][sl] = kf.depth[v, u]
            out["embedding"][sl] = kf.embedding[ve, ue]
            start += m
        return out

    # --------------------------------------------------------------- persistence
    def state(self) -> dict:
        """Plain dict of tensors, ints and lists (loadable with torch.load(weights_only=True))."""
        with self._lock:
            return {
                "next_id": self._next_id,
                "last_pose": None if self._last_pose is None else _t(self._last_pose),
                "last_stamp": self._last_stamp,
                "frames": [{
                    "id": k.id, "stamp_ns": k.stamp_ns, "pose": _t(k.pose),
                    "intrinsics": [k.intrinsics.fx, k.intrinsics.fy, k.intrinsics.cx,
                                   k.intrinsics.cy, k.intrinsics.width, k.intrinsics.height],
                    "rgb": _t(k.rgb), "depth": _t(k.depth), "embedding": _t(k.embedding),
                    "iterations": k.iterations, "published": k.published,
                } for k in self._frames],
            }

    def load_state(self, state: dict) -> None:
        with self._lock:
            self._next_id = int(state["next_id"])
            self._last_pose = None if state["last_pose"] is None else _np(
                state["last_pose"], np.float64)
            self._last_stamp = state["last_stamp"]
            self._frames = []
            for f in state["frames"]:
                fx, fy, cx, cy, w, h = f["intrinsics"]
                self._frames.append(Keyframe(
                    int(f["id"]), int(f["stamp_ns"]), _np(f["pose"], np.float64),
                    Intrinsics(float(fx), float(fy), float(cx), float(cy), int(w), int(h)),
                    _np(f["rgb"], np.uint8), _np(f["depth"], np.float32),
                    _np(f["embedding"], np.float16), int(f["iterations"]),
                    bool(f["published"])))



def _t(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a).copy())


def _np(t: torch.Tensor, dtype) -> np.ndarray:
    return np.ascontiguousarray(t.numpy(), dtype=dtype)
