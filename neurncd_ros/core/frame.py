"""The RGB-D frame every part of the core passes around."""

from __future__ import annotations

import dataclasses

import numpy as np

from .camera import Intrinsics, check_pose


@dataclasses.dataclass
class Frame:
    """One synchronised RGB-D observation with its camera pose.

    - ``stamp_ns``: integer nanoseconds;
    - ``rgb``: (H, W, 3) uint8 in RGB order;
    - ``depth``: (H, W) float32 metric z-depth, 0 (or NaN / inf) where there is no
      measurement, never negative;
    - ``pose``: 4x4 float64 camera-to-world, OpenCV optical axes; None only for
      frames read without poses on their way to the odometry
      (:func:`neurncd_ros.core.odometry.with_odometry`);
    - ``semantic`` / ``instance``: optional (H, W) uint16 ground truth
      (NYU-13 ids, 0 void; instance ids, 0 none).
    """

    stamp_ns: int
    rgb: np.ndarray
    depth: np.ndarray
    pose: np.ndarray | None
    intrinsics: Intrinsics
    semantic: np.ndarray | None = None
    instance: np.ndarray | None = None

    def validate(self) -> "Frame":
        """Raise ValueError naming the problem if the frame is inconsistent."""
        if isinstance(self.stamp_ns, bool) or not isinstance(self.stamp_ns,
                                                              (int, np.integer)):
            raise ValueError(f"stamp_ns must be an integer number of nanoseconds, got "
                             f"{type(self.stamp_ns).__name__} {self.stamp_ns!r} (a stamp in "
                             "seconds: int(round(seconds * 1e9)))")
        optional = ("semantic", "instance")
        for name in ("rgb", "depth") + optional:
            img = getattr(self, name)
            if not (isinstance(img, np.ndarray) or (img is None and name in optional)):
                raise ValueError(f"{name} must be a numpy array, got {type(img).__name__}")
        if not isinstance(self.intrinsics, Intrinsics):
            raise ValueError(f"intrinsics must be an Intrinsics, got "
                             f"{type(self.intrinsics).__name__} (from a 3x3 K: "
                             "Intrinsics.from_matrix(K, width, height))")
        h, w = self.intrinsics.height, self.intrinsics.width
        size = np.shape(self.rgb)[:2]
        if size != (h, w) and size == np.shape(self.depth):  # the camera info is what is off
            raise ValueError(f"the camera info is for {w}x{h} but the colour and depth images "
                             f"are {size[1]}x{size[0]}")
        if self.rgb.shape != (h, w, 3) or self.rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be ({h}, {w}, 3) uint8, got {self.rgb.shape} "
                             f"{self.rgb.dtype}")
        if self.depth.shape != (h, w) or self.depth.dtype != np.float32:
            mm = (" (millimetres, as a 16UC1 image holds them? depth.astype(np.float32) / "
                  "1000)" if self.depth.dtype == np.uint16 else "")
            raise ValueError(f"depth must be ({h}, {w}) float32, got {self.depth.shape} "
                             f"{self.depth.dtype}{mm}")
        if (self.depth < 0).any():
            raise ValueError(f"depth must be >= 0 metres (0 = no measurement), min is "
                             f"{float(np.nanmin(self.depth))}")
        for name in ("semantic", "instance"):
            img = getattr(self, name)
            if img is not None and (img.shape != (h, w) or img.dtype != np.uint16):
                raise ValueError(f"{name} must be ({h}, {w}) uint16, got {img.shape} "
                                 f"{img.dtype}")
        if self.pose is not None:
            self.pose = check_pose(self.pose)
        return self
