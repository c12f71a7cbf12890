"""The one camera module: pinhole intrinsics, poses, rays, back-projection.

Conventions used everywhere in the project:
- camera axes are OpenCV's optical axes (x right, y down, z forward);
- a pose is a 4x4 camera-to-world transform T_wc (float64);
- depth is metric z-depth along the optical axis (not ray length), 0 = invalid;
- pixel (u, v) is the column and row; pixel centres are at integer + 0.5 when
  casting rays (``ray_directions``) and at integers in ``K`` (the usual
  CameraInfo convention, cx = (W - 1) / 2 for a centred principal point).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of an image of ``width`` x ``height`` pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(math.isfinite(v) for v in vals):
            raise ValueError(f"intrinsics must be finite, got {vals}")
        if self.fx == 0 or self.fy == 0:
            raise ValueError(f"focal lengths must be non-zero, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_deg: float = 90.0) -> "Intrinsics":
        """Square pixels, centred principal point, given horizontal field of view."""
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)

    @classmethod
    def from_matrix(cls, K: np.ndarray, width: int, height: int) -> "Intrinsics":
        K = np.asarray(K, dtype=np.float64).reshape(3, 3)
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                   int(width), int(height))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same camera seen at another resolution (pixel-corner aligned)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5,
                          (self.cy + 0.5) * sy - 0.5, int(width), int(height))


def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Integer pixel coordinates (u, v) of every pixel, each shaped (H, W)."""
    v, u = np.mgrid[0:height, 0:width]
    return u, v


def camera_directions(intr: Intrinsics, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Camera-frame directions with z = 1 through pixels (u, v): shape (..., 3).

    With z = 1, ``origin + t * direction`` sits at z-depth ``t``, so a depth
    image gives the ray parameter directly.
    """
    x = (np.asarray(u, dtype=np.float64) - intr.cx) / intr.fx
    y = (np.asarray(v, dtype=np.float64) - intr.cy) / intr.fy
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def rays(pose: np.ndarray, intr: Intrinsics, u: np.ndarray, v: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray]:
    """World-frame ray origins and z-normalised directions through pixels (u, v)."""
    pose = check_pose(pose)
    d_cam = camera_directions(intr, u, v)
    d_world = d_cam @ pose[:3, :3].T
    origins = np.broadcast_to(pose[:3, 3], d_world.shape).copy()
    return origins, d_world


def backproject(depth: np.ndarray, intr: Intrinsics, pose: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Points of the valid depth pixels, in world frame (or camera frame if no pose).

    Returns ``(points (N, 3), mask (H, W))`` where mask marks the pixels used
    (finite and > 0).
    """
    depth = np.asarray(depth)
    if depth.shape != intr.shape:
        raise ValueError(f"depth is {depth.shape[1]}x{depth.shape[0]} but intrinsics are "
                         f"{intr.width}x{intr.height}")
    mask = np.isfinite(depth) & (depth > 0)
    v, u = np.nonzero(mask)
    z = depth[mask].astype(np.float64)
    # Column by column into one (N, 3) array (several times faster than stacking the
    # directions and an (N, 3) matmul; the same float64 values).
    cam = np.empty((len(z), 3))
    np.multiply((u - intr.cx) / intr.fx, z, out=cam[:, 0])
    np.multiply((v - intr.cy) / intr.fy, z, out=cam[:, 1])
    cam[:, 2] = z
    if pose is None:
        return cam, mask
    pose = check_pose(pose)
    pts = np.empty_like(cam)
    for i in range(3):
        r = pose[i]
        np.multiply(cam[:, 0], r[0], out=pts[:, i])
        pts[:, i] += cam[:, 1] * r[1]
        pts[:, i] += cam[:, 2] * r[2]
        pts[:, i] += r[3]
    return pts, mask


def project(points_world: np.ndarray, intr: Intrinsics, pose: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project world points into a camera: pixel coords (u, v) and z-depth."""
    pose = check_pose(pose)
    T_cw = invert_pose(pose)
    p = np.asarray(points_world, dtype=np.float64) @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * p[:, 0] / z + intr.cx
        v = intr.fy * p[:, 1] / z + intr.cy
    return u, v, z


def reproject_depth_error(depth_a: np.ndarray, pose_a: np.ndarray, depth_b: np.ndarray,
                          pose_b: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """|z predicted from frame a - z measured in frame b| at the pixels a lands on in b."""
    pts, _ = backproject(depth_a, intr, pose_a)
    u, v, z = project(pts, intr, pose_b)
    ui, vi = np.round(u).astype(np.int64, copy=False), np.round(v).astype(np.int64, copy=False)
    ok = (z > 0) & (ui >= 0) & (ui < intr.width) & (vi >= 0) & (vi < intr.height)
    zb = depth_b[vi[ok], ui[ok]].astype(np.float64)
    valid = np.isfinite(zb) & (zb > 0)
    return np.abs(z[ok][valid] - zb[valid])


# ---------------------------------------------------------------- poses

def check_pose(pose: np.ndarray, what: str = "pose") -> np.ndarray:
    """Validate a 4x4 rigid transform; returns it as float64."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4):
        raise ValueError(f"{what} must be 4x4, got shape {pose.shape}")
    if not np.all(np.isfinite(pose)):
        raise ValueError(f"{what} has non-finite entries")
    R = pose[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
        raise ValueError(f"{what} rotation is not orthonormal with det +1")
    if not np.allclose(pose[3], [0, 0, 0, 1], atol=1e-6):
        raise ValueError(f"{what} last row must be [0, 0, 0, 1], got {pose[3]}")
    return pose


def invert_pose(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform from its parts: (R^T, -R^T t), no general inverse."""
    R, t = pose[:3, :3], pose[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def quat_to_matrix(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """Unit quaternion (x, y, z, w; normalised here) to a 3x3 rotation."""
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"quaternion {q[1:].tolist() + [q[0]]} is not finite or has zero norm")
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R: np.ndarray) -> tuple[float, float, float, float]:
    """3x3 rotation to a unit quaternion (x, y, z, w) with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x = 0.25 * s, (R[2, 1] - R[1, 2]) / s
        y, z = (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        w, x = (R[2, 1] - R[1, 2]) / s, 0.25 * s
        y, z = (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        w, x = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s
        y, z = 0.25 * s, (R[1, 2] + R[2, 1]) / s
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        w, x = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s
        y, z = (R[1, 2] + R[2, 1]) / s, 0.25 * s
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return tuple(float(c) for c in q)


def pose_from_tq(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 pose from translation and quaternion (x, y, z, w)."""
    pose = np.eye(4)
    pose[:3, :3] = quat_to_matrix(*q_xyzw)
    pose[:3, 3] = np.asarray(t, dtype=np.float64)
    if not np.all(np.isfinite(pose)):
        raise ValueError("pose translation is not finite")
    return pose


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)
            ) -> np.ndarray:
    """Camera-to-world pose at ``eye`` looking at ``target`` (OpenCV axes, world z up)."""
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
    return pose


def pose_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation angle (deg) between two poses."""
    dt = float(np.linalg.norm(a[:3, 3] - b[:3, 3]))
    R = a[:3, :3].T @ b[:3, :3]
    ang = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(R) - 1) / 2))))
    return dt, ang
