"""Training data of the backbone: targets, arrays, augmentation and outlier pastes.

Targets: NYU-13 ground truth becomes a channel index for the 9 known classes
and :data:`IGNORE` for void and the novel classes (the network never learns
them); :data:`OUTLIER` marks pasted outlier pixels (:func:`paste_outliers`),
whose loss asks for a uniform prediction. :func:`augment` is the geometric and
colour augmentation of every batch. Used by :mod:`.train`.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np
import torch
import torch.nn.functional as F

from .. import classes
from ..frame import Frame

IGNORE = 255
"""Target value of pixels left out of the loss (void and novel classes)."""

OUTLIER = 254
"""Target value of pasted outlier pixels (outlier exposure): the loss pushes their
prediction towards uniform instead of towards a class (:func:`paste_outliers`)."""

# NYU-13 id -> training target (channel index for known classes, IGNORE otherwise).
_ID_TO_TARGET = np.where(classes.KNOWN_CHANNEL >= 0, classes.KNOWN_CHANNEL,
                         IGNORE).astype(np.uint8)


def semantic_to_target(semantic: np.ndarray) -> np.ndarray:
    """NYU-13 label image (uint16) -> uint8 targets: channel index, or IGNORE."""
    if semantic.dtype != np.uint16:
        raise ValueError(f"semantic must be uint16 NYU-13 ids, got {semantic.dtype}")
    return _ID_TO_TARGET[semantic]


# ----------------------------------------------------------------------------- data
ARRAY_KEYS = ("rgb", "depth", "semantic")


def check_arrays(data: dict[str, np.ndarray], what: str) -> int:
    """Validate training arrays (rgb N,H,W,3 uint8; depth N,H,W float32; semantic N,H,W
    uint16 NYU-13 ids); returns N or raises ValueError naming ``what``."""
    missing = [k for k in ARRAY_KEYS if k not in data]
    if missing:
        raise ValueError(f"{what}: missing arrays {missing}; need {list(ARRAY_KEYS)}")
    rgb, depth, sem = (np.asarray(data[k]) for k in ARRAY_KEYS)
    if rgb.ndim != 4 or rgb.shape[-1] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"{what}: rgb must be (N, H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if depth.shape != rgb.shape[:3] or sem.shape != rgb.shape[:3]:
        raise ValueError(f"{what}: depth {depth.shape} and semantic {sem.shape} must be "
                         f"{rgb.shape[:3]}")
    if sem.dtype != np.uint16:
        raise ValueError(f"{what}: semantic must be uint16 NYU-13 ids, got {sem.dtype}")
    if len(rgb) == 0:
        raise ValueError(f"{what}: no frames")
    return len(rgb)


def frames_to_arrays(frames: Iterable[Frame], width: int = 320, height: int = 240
                     ) -> tuple[dict[str, np.ndarray], int]:
    """Frames with semantic ground truth -> training arrays at ``width`` x ``height``.

    Every frame is resized to the size the backbone runs at (colour bilinear,
    depth and labels nearest, so holes and class borders stay crisp); frames
    without ground truth are skipped and counted. Returns (arrays, skipped).
    """
    import cv2

    rgb, depth, sem = [], [], []
    skipped = 0
    for fr in frames:
        if fr.semantic is None:
            skipped += 1
            continue
        r, d, s = fr.rgb, fr.depth, fr.semantic
        if d.shape != (height, width):
            r = cv2.resize(r, (width, height), interpolation=cv2.INTER_AREA)
            d = cv2.resize(d, (width, height), interpolation=cv2.INTER_NEAREST)
            s = cv2.resize(s, (width, height), interpolation=cv2.INTER_NEAREST)
        rgb.append(r)
        depth.append(d.astype(np.float32))
        sem.append(s.astype(np.uint16))
    if not rgb:
        return {"rgb": np.zeros((0, height, width, 3), np.uint8),
                "depth": np.zeros((0, height, width), np.float32),
                "semantic": np.zeros((0, height, width), np.uint16)}, skipped
    return {"rgb": np.stack(rgb), "depth": np.stack(depth), "semantic": np.stack(sem)}, skipped


# ----------------------------------------------------------------------------- augmentation
def augment(rgb: torch.Tensor, depth: torch.Tensor, target: torch.Tensor,
            gen: torch.Generator, scale: tuple[float, float] = (0.8, 1.35),
            jitter: float = 0.25, crop: tuple[int, int] | None = None
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random flip, scale-crop (zoom in/out with translation) and colour jitter, batched.

    ``crop`` = (h, w) cuts windows of that size (at the sampled zoom) instead of
    keeping the full frame: cheaper steps, same apparent object sizes.

    rgb (B,3,H,W) float 0..255, depth (B,1,H,W) m, target (B,H,W) long with
    IGNORE. One affine warp per sample (grid_sample): bilinear for rgb,
    nearest for depth and labels; area outside the source is a depth hole
    and ignored in the loss. Zooming changes apparent size but not metric
    depth, which is what happens when the same object is seen at another
    focal length.
    """
    b, _, h, w = rgb.shape
    oh, ow = crop if crop is not None else (h, w)
    s = torch.empty(b).uniform_(*scale, generator=gen)  # >1 zooms in
    flip = (torch.rand(b, generator=gen) < 0.5).float() * 2 - 1
    sx, sy = (ow / w) / s, (oh / h) / s  # window half-size in normalised source coords
    tx = (torch.rand(b, generator=gen) * 2 - 1) * ((1 - sx).clamp(min=0) + 0.05)
    ty = (torch.rand(b, generator=gen) * 2 - 1) * ((1 - sy).clamp(min=0) + 0.05)
    theta = torch.zeros(b, 2, 3)
    theta[:, 0, 0] = flip * sx
    theta[:, 1, 1] = sy
    theta[:, 0, 2] = tx
    theta[:, 1, 2] = ty
    grid = F.affine_grid(theta, [b, 1, oh, ow], align_corners=False)
    rgb = F.grid_sample(rgb, grid, mode="bilinear", padding_mode="border", align_corners=False)
    depth = F.grid_sample(depth, grid, mode="nearest", padding_mode="zeros", align_corners=False)
    lab = F.grid_sample((target + 1).float()[:, None], grid, mode="nearest",
                        padding_mode="zeros", align_corners=False)[:, 0].long() - 1
    target = torch.where(lab < 0, torch.full_like(lab, IGNORE), lab)
    # Colour jitter: brightness, contrast, saturation, per-channel gain.
    bright = 1 + (torch.rand(b, 1, 1, 1, generator=gen) * 2 - 1) * jitter
    contrast = 1 + (torch.rand(b, 1, 1, 1, generator=gen) * 2 - 1) * jitter
    sat = 1 + (torch.rand(b, 1, 1, 1, generator=gen) * 2 - 1) * jitter
    gain = 1 + (torch.rand(b, 3, 1, 1, generator=gen) * 2 - 1) * jitter * 0.3
    grey = rgb.mean(dim=1, keepdim=True)
    rgb = grey + (rgb - grey) * sat
    mean = rgb.mean(dim=(1, 2, 3), keepdim=True)
    rgb = (mean + (rgb - mean) * contrast) * bright * gain
    rgb = rgb + torch.randn(rgb.shape, generator=gen) * 3.0  # sensor noise
    return rgb.clamp(0, 255), depth, target


def paste_outliers(rgb: torch.Tensor, target: torch.Tensor, gen: torch.Generator,
                   prob: float = 0.5, size: tuple[float, float] = (0.1, 0.4),
                   min_known: float = 0.97, tries: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """Outlier exposure by cut and paste: colour that does not belong to its geometry.

    Why: the network learns the known classes and nothing else, so an unseen
    flat object on a wall (a picture, a screen) is confidently "wall"; the
    entropy that discovery relies on never rises there. Here, with probability
    ``prob`` per sample, a rectangle of another sample's colour (sides ``size``
    of the window's) is pasted at a random place while the depth stays the
    destination's, and its pixels get target :data:`OUTLIER`, whose loss asks for
    a uniform prediction (:func:`loss_terms`). Only known classes are pasted: a
    source rectangle with less than ``min_known`` known-class pixels (novel, void or
    outside the frame) is not used, so the novel classes do not enter training,
    not even as outliers; nor is one whose majority class is the destination's
    (wall texture on a wall is not an outlier). Up to ``tries`` source places are
    drawn per sample. Destination pixels that were IGNORE stay IGNORE.
    rgb (B, 3, H, W), target (B, H, W) long; returns new tensors.
    """
    b, _, h, w = rgb.shape
    rgb, target = rgb.clone(), target.clone()
    if b < 2 or prob <= 0:
        return rgb, target
    src_rgb, src_tgt = rgb.clone(), target.clone()  # pastes read the unpasted batch
    use = torch.rand(b, generator=gen) < prob
    sides = torch.empty(b, 2).uniform_(*size, generator=gen)
    dest = torch.rand(b, 2, generator=gen)
    srcs = torch.rand(b, tries, 2, generator=gen)
    n = classes.NUM_KNOWN
    for i in torch.nonzero(use).flatten().tolist():
        j = (i + 1) % b
        ph, pw = max(int(sides[i, 0] * h), 2), max(int(sides[i, 1] * w), 2)
        dy, dx = int(dest[i, 0] * (h - ph)), int(dest[i, 1] * (w - pw))
        dst = target[i, dy:dy + ph, dx:dx + pw]
        dst_known = dst[dst < n]
        dst_major = int(torch.bincount(dst_known, minlength=n).argmax()) \
            if dst_known.numel() else -1
        for t in range(tries):
            sy, sx = int(srcs[i, t, 0] * (h - ph)), int(srcs[i, t, 1] * (w - pw))
            src = src_tgt[j, sy:sy + ph, sx:sx + pw]
            known = src < n
            if known.float().mean() < min_known or \
                    int(torch.bincount(src[known], minlength=n).argmax()) == dst_major:
                continue
            rgb[i, :, dy:dy + ph, dx:dx + pw] = src_rgb[j, :, sy:sy + ph, sx:sx + pw]
            target[i, dy:dy + ph, dx:dx + pw] = torch.where(dst == IGNORE, dst,
                                                            torch.full_like(dst, OUTLIER))
            break
    return rgb, target
