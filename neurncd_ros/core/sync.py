"""Stamp pairing: the one place where messages of several streams are matched by stamp.

Offline (:class:`..data.bag.FrameReader`) and online (the engine's stages)
match with the same rule: the nearest stamp within a tolerance wins, and
poses may be interpolated between two samples at most ``max_gap_ns`` apart.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from .camera import matrix_to_quat, pose_from_tq


def nearest(times: np.ndarray, t: int) -> tuple[int, int]:
    """Index of the entry of sorted int64 ``times`` nearest ``t``, and |difference| (ns)."""
    j = int(np.searchsorted(times, t))
    cands = [k for k in (j - 1, j) if 0 <= k < len(times)]
    if not cands:
        return -1, 1 << 62
    k = min(cands, key=lambda c: abs(int(times[c]) - t))
    return k, abs(int(times[k]) - t)


def interpolate_pose(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """Pose a fraction ``w`` of the way from a to b (linear translation, slerp rotation)."""
    qa, qb = np.array(matrix_to_quat(a[:3, :3])), np.array(matrix_to_quat(b[:3, :3]))
    if qa @ qb < 0:
        qb = -qb
    cos = float(np.clip(qa @ qb, -1.0, 1.0))
    ang = math.acos(cos)
    if ang < 1e-9:
        q = qa
    else:
        q = (math.sin((1 - w) * ang) * qa + math.sin(w * ang) * qb) / math.sin(ang)
    return pose_from_tq((1 - w) * a[:3, 3] + w * b[:3, 3], q)


def pose_at(times: np.ndarray, poses: Sequence[Any], t: int, skew_ns: int,
            max_gap_ns: int = 0) -> np.ndarray:
    """Pose at stamp ``t`` from a sorted timeline of poses (entries may be error strings).

    Exact stamp first; then interpolation between the two samples around ``t``
    if they are at most ``max_gap_ns`` apart (0 = never); then the nearest
    sample within ``skew_ns``. Raises LookupError saying why none fits.
    """
    if len(times) == 0:
        raise LookupError("no pose samples")
    k, d = nearest(times, t)
    j = int(np.searchsorted(times, t))
    if d > 0 and max_gap_ns > 0 and 0 < j < len(times):
        t0, t1 = int(times[j - 1]), int(times[j])
        a, b = poses[j - 1], poses[j]
        if t1 - t0 <= max_gap_ns and isinstance(a, np.ndarray) and isinstance(b, np.ndarray):
            return interpolate_pose(a, b, (t - t0) / (t1 - t0))
    if d > skew_ns:
        gap = f" and none to interpolate within {max_gap_ns / 1e6:g} ms" if max_gap_ns else ""
        raise LookupError(f"no sample within {skew_ns / 1e6:g} ms{gap}")
    if isinstance(poses[k], str):
        raise LookupError(f"invalid sample: {poses[k]}")
    return poses[k]
