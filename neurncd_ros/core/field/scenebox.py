"""The mapper's scene box: what a keyframe sees, and how the box grows to hold it.

The box (an AABB in world metres) gives every ray its near/far. It only grows,
by whole cells of the backend's lattice (so a backend whose parameters are laid
out over the box can pad them and keep what it learnt), with slack so that it
is not regrown for every keyframe, and never beyond the backend's cap of cells
per axis.
"""

from __future__ import annotations

import numpy as np

from ..camera import Intrinsics, backproject, camera_directions
from ..frame import Frame


# keyframe_extent reads at most about this many depth pixels (every step-th pixel of
# each row and column): a 320x240 frame whole, a 1280x720 one every 4th. The percentiles
# of a regular subsample are the same box within a fraction of the lattice's cell, and
# the whole 1280x720 frame took a third of a second on a busy machine, in the mapper
# node's intake of frames.
EXTENT_PIXELS = 320 * 240


def keyframe_extent(frame: Frame, max_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Robust box of what a frame sees (1st..99th percentile of its depth points, read
    from at most about ``EXTENT_PIXELS`` of them)."""
    intr, depth = frame.intrinsics, frame.depth
    step = max(1, int(np.ceil(np.sqrt(depth.size / EXTENT_PIXELS))))
    if step > 1:  # pixel (i step, j step) is pixel (i, j) of this camera
        depth = depth[::step, ::step]
        intr = Intrinsics(intr.fx / step, intr.fy / step, intr.cx / step, intr.cy / step,
                          depth.shape[1], depth.shape[0])
    depth = np.where(depth <= max_depth, depth, 0.0).astype(np.float32)
    pts, _ = backproject(depth, intr, frame.pose)
    if len(pts) < 16:
        # No usable depth: assume the frustum up to 3 m.
        full = frame.intrinsics
        u = np.array([0, full.width - 1, 0, full.width - 1])
        v = np.array([0, 0, full.height - 1, full.height - 1])
        d = camera_directions(full, u, v) * 3.0
        pts = d @ frame.pose[:3, :3].T + frame.pose[:3, 3]
    pts = np.concatenate([pts, frame.pose[None, :3, 3]])
    lo, hi = np.percentile(pts, [1, 99], axis=0)  # one selection for both
    return lo, hi


def grow(box: tuple[np.ndarray, np.ndarray] | None, lo: np.ndarray, hi: np.ndarray,
         cell: float, cap: int, growth: float
         ) -> tuple[tuple[np.ndarray, np.ndarray] | None, bool]:
    """The box grown to hold [lo, hi], or None if it need not change; and whether the cap
    stopped it short.

    ``box`` is the current (lo, hi) or None (first keyframe); the new box is
    on the lattice of ``cell`` through the old corner, at most ``cap`` cells
    per axis, with ``growth`` times the half-extent of slack on each grown side.
    """
    if box is not None and np.all(lo >= box[0]) and np.all(hi <= box[1]):
        return None, False
    all_lo = lo if box is None else np.minimum(lo, box[0])
    all_hi = hi if box is None else np.maximum(hi, box[1])
    slack = growth * (all_hi - all_lo) / 2
    if box is None:
        n_lo = np.zeros(3)
        base_lo = lo - slack
        cells = np.ceil((hi + slack - base_lo) / cell)
        n_hi = np.minimum(cells, cap)
        clipped = bool(np.any(cells > cap))
    else:
        base_lo, old_hi = box
        old = np.round((old_hi - base_lo) / cell)
        n_lo = np.where(lo < base_lo, np.ceil((base_lo - lo + slack) / cell), 0)
        n_hi = np.where(hi > old_hi, np.ceil((hi + slack - old_hi) / cell), 0)
        room = np.maximum(cap - old, 0)
        want = n_lo + n_hi
        scale = np.where(want > room, room / np.maximum(want, 1), 1.0)
        clipped = bool(np.any(want > room))
        n_lo, n_hi = np.floor(n_lo * scale), np.floor(n_hi * scale)
        n_hi = n_hi + old
        if not np.any(n_lo + n_hi > old):
            return None, clipped
    new_lo = base_lo - n_lo * cell
    return (new_lo, new_lo + (n_lo + n_hi) * cell), clipped
