"""Feature modulation: one descriptor per geometric segment.

The paper's Algorithm 1 writes each segment's features into its own pixels of
a zeroed H x W map and flattens that map into the segment's vector. Taken
literally, two disjoint segments then have disjoint supports and cosine
similarity exactly 0, so Markov clustering could never merge segments. What it
intends, and what is implemented here, is a *pooled* descriptor per segment:

    H_s = [ pool(embedding over s) , w * pool(entropy over s) ]

- embedding part: "softmax" = mean of softmax(embedding) (a class-probability
  histogram, non-negative, so cosine similarities are in [0, 1]); "logits" =
  mean of the raw logits, L2-normalised (keeps the backbone's confidence
  structure but may be negative);
- entropy part: mean and standard deviation of the per-pixel entropy divided by
  log(S) (so in [0, 1]) and scaled by ``entropy_weight``; novel objects are
  typically high-entropy regions, which is what the entropy modulates;
- colour part (``colour_weight`` > 0, needs the RGB image): the segment's mean
  CIELAB colour (and optionally its std), scaled by ``colour_weight``. The
  backbone's logits call a picture, a window or a TV on a wall "wall" with
  confidence, so the embedding part cannot tell them apart; their colour
  usually differs from the wall's. It is a per-frame input, the same whether
  the embedding is rendered by the field or taken from the backbone.

- feature part (``feature_weight`` > 0 and an embedding with feature channels,
  ``backbone.features``): the segment's mean penultimate feature of the backbone,
  L2-normalised and scaled by ``feature_weight``. The paper's "semantic
  embedding" is the network's feature, not only its class scores; segments the
  logits call "wall" may still differ there (issue 11, direction 1; measured in
  bench/results/ncd.json, row ``features``).

- area part (``area_weight`` > 0, needs the view's depth and intrinsics): log10 of
  the segment's metric area (m^2: each pixel's footprint z^2 / (fx fy), summed; no
  slant correction), scaled by ``area_weight``. Novel objects that the logits call
  alike and whose colour is close differ in size (a picture, a window, a ceiling);
  it needs no gravity direction, so it holds for any bag's world frame. Off by
  default: on the tuning seeds it adds +0.4 all-class at 0.6 and lifts the per-frame
  logits by as much (see the README's discovery notes).

``mode`` selects the paper's ablations: "both", "embedding" only, "entropy"
only (the entropy-only descriptor is [mean, std], so under cosine affinity it
mostly separates by the std/mean ratio: a deliberately weak baseline).

Why the defaults: centred-logit pooling, because mean softmax shares a uniform
floor over all channels, which makes every high-entropy segment look alike; a
small entropy weight, because a large one lets the entropy part dominate the
descriptor of uncertain segments and merges different novel objects; entropy
pooled over each segment's interior, because the rendered entropy peaks along
every boundary, which makes all small segments look uncertain. The scores
behind these choices are in bench/results/discovery.json and
bench/results/ncd_tuning.json (``bench/discovery.py``, ``bench/ncd.py --tune``).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..params import param
from .geoseg import pair_slices
from ..uncertainty import softmax  # noqa: F401 (the one softmax; re-exported)


@dataclasses.dataclass(frozen=True)
class ModulationConfig:
    """How segment descriptors are pooled from the rendered embedding and entropy."""

    mode: str = param("both", "descriptor content: embedding+entropy, or one of them "
                      "(paper ablations)", choices=("both", "embedding", "entropy"))
    pooling: str = param("logits", "embedding pooling: L2-normalised mean centred logits, or "
                         "mean softmax", choices=("logits", "softmax"))
    entropy_weight: float = param(0.3, "scale of the entropy part relative to the embedding "
                                  "part", lo=0.0, hi=100.0)
    entropy_std: bool = param(True, "append the entropy's standard deviation to its mean")
    entropy_interior: int = param(2, "pool the entropy over the segment's interior only: "
                                  "pixels at least this far from its border (the rendered "
                                  "entropy peaks along every boundary; 0 = all pixels; "
                                  "segments without interior use all)", lo=0, hi=32, unit="px")
    colour_weight: float = param(2.0, "scale of the segment's mean CIELAB colour (L, a, b "
                                 "divided by 100) appended to the descriptor; 0 = off, no "
                                 "colour part (when no colour image is given the part is 0)",
                                 lo=0.0, hi=100.0)
    colour_std: bool = param(False, "with colour_weight > 0, also append the per-channel "
                             "standard deviation of the segment's Lab colour")
    feature_weight: float = param(0.6, "scale of the segment's L2-normalised mean backbone "
                                  "feature appended to the descriptor, when the embedding "
                                  "carries features (backbone.features); 0 = not used (0.6 "
                                  "tuned, bench/results/ncd_sweep_modulation_feature_weight_"
                                  "features-true.json)", lo=0.0, hi=100.0)
    area_weight: float = param(0.0, "scale of log10 of the segment's metric area (m^2, from "
                               "the view's depth and intrinsics) appended to the descriptor; "
                               "0 = off, no area part (without depth the part is 0)",
                               lo=0.0, hi=100.0)


@dataclasses.dataclass
class SegmentStats:
    """Per-segment summaries the labeller needs besides the descriptor."""

    pixels: np.ndarray          # (n,) int64 pixel counts
    mean_entropy: np.ndarray    # (n,) float32 mean entropy (nats)
    std_entropy: np.ndarray     # (n,) float32 entropy standard deviation (nats)
    argmax_hist: np.ndarray     # (n, S) int64 count of pixels whose embedding argmax is k
    mean_prob: np.ndarray       # (n, S) float32 mean softmax
    mean_lab: np.ndarray | None = None  # (n, 3) float32 mean CIELAB / 100 (None: no colour)
    std_lab: np.ndarray | None = None   # (n, 3) float32 its standard deviation / 100
    mean_feature: np.ndarray | None = None  # (n, F) float32 mean feature (None: none)
    area: np.ndarray | None = None  # (n,) float32 metric area m^2 (None: no depth given)


def _check(segments: np.ndarray, embedding: np.ndarray, entropy: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    segments, embedding, entropy = (np.asarray(a) for a in (segments, embedding, entropy))
    if segments.ndim != 2:
        raise ValueError(f"segments must be (H, W), got shape {segments.shape}")
    if embedding.ndim != 3 or embedding.shape[:2] != segments.shape:
        raise ValueError(f"embedding must be (H, W, S) with (H, W) = {segments.shape}, "
                         f"got {embedding.shape}")
    if entropy.shape != segments.shape:
        raise ValueError(f"entropy must be {segments.shape}, got {entropy.shape}")
    if embedding.shape[2] < 2:
        raise ValueError(f"embedding needs at least 2 channels, got {embedding.shape[2]}")
    if not np.issubdtype(segments.dtype, np.integer):
        raise ValueError(f"segments must be an integer id image, got {segments.dtype}")
    return segments, embedding.astype(np.float32, copy=False), entropy.astype(np.float32,
                                                                              copy=False)


def interior(segments: np.ndarray, radius: int) -> np.ndarray:
    """Pixels whose neighbours up to ``radius`` px away (4 directions) share their segment."""
    inside = segments >= 0
    h, w = segments.shape
    for r in range(1, radius + 1):
        for dy, dx in ((r, 0), (-r, 0), (0, r), (0, -r)):
            same = np.zeros((h, w), bool)  # a neighbour outside the image is not the same
            c, o = pair_slices(h, w, dy, dx)
            same[c] = segments[c] == segments[o]
            inside &= same
    return inside


def lab_colour(colour: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) float32 CIELAB of a uint8 RGB image, divided by 100 (L in [0, 1]).

    Why Lab: distances in it are roughly perceptual, so a picture or window on a
    wall of one backbone class differs from the wall by a comparable amount
    whatever its hue; shading changes L more than a and b.
    """
    import cv2

    from .geoseg import unit_rgb
    return cv2.cvtColor(unit_rgb(colour, shape), cv2.COLOR_RGB2Lab) * np.float32(0.01)


def segment_stats(segments: np.ndarray, embedding: np.ndarray, entropy: np.ndarray,
                  entropy_interior: int = 0, colour: np.ndarray | None = None,
                  features: np.ndarray | None = None, depth: np.ndarray | None = None,
                  intrinsics=None) -> tuple[SegmentStats, np.ndarray]:
    """Per-segment stats plus the mean centred logits (n, S); ids 0..n-1, -1 = none.

    Logits are centred per pixel (their channel mean subtracted) because softmax
    ignores a common offset, so only the centred part carries information.
    ``entropy_interior`` > 0 takes the entropy statistics over each segment's
    interior (:func:`interior`), where it has one. ``colour`` (H, W, 3) uint8 RGB,
    optional, adds each segment's mean and std Lab colour (:func:`lab_colour`);
    ``features`` (H, W, F), optional, each segment's mean feature; ``depth`` (H, W) m
    with its ``intrinsics``, optional, each segment's metric area (pixels without depth
    add nothing).
    """
    segments, embedding, entropy = _check(segments, embedding, entropy)
    n = int(segments.max()) + 1 if segments.size else 0
    S = embedding.shape[2]
    flat = embedding.reshape(-1, S)
    # Pixels with a non-finite embedding or entropy belong to no segment.
    sel = (segments.ravel() >= 0) & np.isfinite(flat).all(axis=1) & np.isfinite(entropy.ravel())
    ids = segments.ravel()[sel]
    emb = flat[sel]
    ent = entropy.ravel()[sel]
    counts = np.bincount(ids, minlength=n).astype(np.int64)
    inv = 1.0 / np.maximum(counts, 1)
    prob = softmax(emb)
    centred = emb - emb.mean(axis=1, keepdims=True)
    # Per-channel bincounts: segment sums without np.add.at (which is ~10x slower).
    mean_prob = np.stack([np.bincount(ids, weights=prob[:, c], minlength=n)
                          for c in range(S)], axis=1)
    mean_logit = np.stack([np.bincount(ids, weights=centred[:, c], minlength=n)
                           for c in range(S)], axis=1)
    hist = np.bincount(ids * S + emb.argmax(axis=1), minlength=n * S).reshape(n, S)
    ent_ids, ent_px = ids, ent
    if entropy_interior > 0:
        # Interior pixels of segments that have an interior, all pixels of the rest.
        core = interior(segments, entropy_interior).ravel()[sel]
        use = core | (np.bincount(ids[core], minlength=n) == 0)[ids]
        ent_ids, ent_px = ids[use], ent[use]
    ent_n = np.bincount(ent_ids, minlength=n).astype(np.float64)
    ent_sum = np.bincount(ent_ids, weights=ent_px, minlength=n)
    ent_sq = np.bincount(ent_ids, weights=ent_px.astype(np.float64) ** 2, minlength=n)
    mean_ent = ent_sum / np.maximum(ent_n, 1)
    std_ent = np.sqrt(np.maximum(ent_sq / np.maximum(ent_n, 1) - mean_ent ** 2, 0.0))
    stats = SegmentStats(counts, mean_ent.astype(np.float32), std_ent.astype(np.float32), hist,
                         (mean_prob * inv[:, None]).astype(np.float32))
    if features is not None:
        feats = np.asarray(features, np.float32)
        if feats.ndim != 3 or feats.shape[:2] != segments.shape:
            raise ValueError(f"features must be (H, W, F) with H, W = {segments.shape}, got "
                             f"{feats.shape}")
        f = np.nan_to_num(feats.reshape(-1, feats.shape[2])[sel])
        stats.mean_feature = (np.stack([np.bincount(ids, weights=f[:, c], minlength=n)
                                        for c in range(f.shape[1])], axis=1)
                              * inv[:, None]).astype(np.float32)
    if depth is not None:
        z = np.asarray(depth, np.float64)
        if z.shape != segments.shape or intrinsics is None:
            raise ValueError(f"depth must be {segments.shape} with its intrinsics, got "
                             f"{z.shape}")
        ok = (segments >= 0) & np.isfinite(z) & (z > 0)
        stats.area = np.bincount(segments[ok], weights=z[ok] ** 2 / (intrinsics.fx
                                 * intrinsics.fy), minlength=n)[:n].astype(np.float32)
    if colour is not None:
        lab = lab_colour(colour, segments.shape).reshape(-1, 3)[sel].astype(np.float64)
        s1 = np.stack([np.bincount(ids, weights=lab[:, c], minlength=n) for c in range(3)], 1)
        s2 = np.stack([np.bincount(ids, weights=lab[:, c] ** 2, minlength=n)
                       for c in range(3)], 1)
        mean_lab = s1 * inv[:, None]
        stats.mean_lab = mean_lab.astype(np.float32)
        stats.std_lab = np.sqrt(np.maximum(s2 * inv[:, None] - mean_lab ** 2, 0.0)
                                ).astype(np.float32)
    return stats, (mean_logit * inv[:, None]).astype(np.float32)


def descriptors_from_stats(stats: SegmentStats, mean_logit: np.ndarray,
                           cfg: ModulationConfig) -> np.ndarray:
    """(n, D) float32 descriptors from pooled statistics (see module docstring)."""
    S = mean_logit.shape[1]
    parts = []
    if cfg.mode in ("both", "embedding"):
        if cfg.pooling == "softmax":
            parts.append(stats.mean_prob)
        else:
            norm = np.linalg.norm(mean_logit, axis=1, keepdims=True)
            parts.append(mean_logit / np.maximum(norm, 1e-12))
    if cfg.mode in ("both", "entropy"):
        scale = cfg.entropy_weight / math.log(S)
        ent = [stats.mean_entropy[:, None] * scale]
        if cfg.entropy_std:
            ent.append(stats.std_entropy[:, None] * scale)
        parts.append(np.concatenate(ent, axis=1))
    if cfg.colour_weight > 0:
        # Colour part: the same width with or without a colour image, so segments
        # of frames with and without colour can share one memory.
        n = mean_logit.shape[0]
        lab = stats.mean_lab if stats.mean_lab is not None else np.zeros((n, 3), np.float32)
        col = [lab * cfg.colour_weight]
        if cfg.colour_std:
            sd = stats.std_lab if stats.std_lab is not None else np.zeros((n, 3), np.float32)
            col.append(sd * cfg.colour_weight)
        parts.append(np.concatenate(col, axis=1))
    if cfg.feature_weight > 0 and stats.mean_feature is not None:
        f = stats.mean_feature
        parts.append(f / np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12)
                     * cfg.feature_weight)
    if cfg.area_weight > 0:  # the same width with or without depth (0 without)
        n = mean_logit.shape[0]
        area = (np.log10(stats.area.astype(np.float64) + 1e-3) if stats.area is not None
                else np.zeros(n))
        parts.append((area * cfg.area_weight)[:, None])
    return np.concatenate(parts, axis=1).astype(np.float32)


def segment_descriptors(segments: np.ndarray, embedding: np.ndarray, entropy: np.ndarray,
                        cfg: ModulationConfig = ModulationConfig(),
                        colour: np.ndarray | None = None,
                        features: np.ndarray | None = None, depth: np.ndarray | None = None,
                        intrinsics=None) -> np.ndarray:
    """(n, D) float32 descriptor per segment id 0..n-1 (empty ids get a zero embedding part)."""
    stats, mean_logit = segment_stats(segments, embedding, entropy, cfg.entropy_interior,
                                      colour if cfg.colour_weight > 0 else None,
                                      features if cfg.feature_weight > 0 else None,
                                      *((depth, intrinsics) if cfg.area_weight > 0
                                        else (None, None)))
    return descriptors_from_stats(stats, mean_logit, cfg)


def simulate_embedding(semantic: np.ndarray, instance: np.ndarray | None = None,
                       channel_to_id: np.ndarray | None = None, peak: float = 4.0,
                       novel_peak: float = 1.5, instance_std: float = 0.5,
                       pixel_std: float = 0.7, seed: int = 0) -> np.ndarray:
    """Stand-in backbone logits (H, W, S) from ground truth, for tests and tuning only.

    Known class: a peak of ``peak`` on its channel. Novel class: a fixed,
    class-specific low-contrast mix over 2-3 known channels (``novel_peak``),
    the same in every scene (a backbone confuses a novel class consistently),
    so novel pixels are high-entropy but separable. Every instance adds a
    per-channel offset (``instance_std``), every pixel noise (``pixel_std``).
    """
    from ..classes import CHANNEL_TO_ID, NUM_CLASSES
    c2i = CHANNEL_TO_ID if channel_to_id is None else np.asarray(channel_to_id)
    S = c2i.size
    table = np.zeros((NUM_CLASSES + 1, S), np.float32)
    cls_rng = np.random.default_rng(12345)  # fixed: the "backbone" is the same everywhere
    for cid in range(1, NUM_CLASSES + 1):
        hit = np.flatnonzero(c2i == cid)
        if hit.size:
            table[cid, hit[0]] = peak
        else:
            ch = cls_rng.choice(S, size=int(cls_rng.integers(2, 4)), replace=False)
            table[cid, ch] = novel_peak * cls_rng.uniform(0.6, 1.0, ch.size)
    rng = np.random.default_rng(seed)
    sem = np.asarray(semantic).astype(np.int64)
    logits = table[np.clip(sem, 0, NUM_CLASSES)]
    if instance is not None:
        inst = np.asarray(instance).astype(np.int64)
        ids, inv = np.unique(inst, return_inverse=True)
        offs = rng.normal(0.0, instance_std, (ids.size, S)).astype(np.float32)
        logits = logits + offs[inv.reshape(inst.shape)]
    logits += rng.normal(0.0, pixel_std, logits.shape).astype(np.float32)
    return logits.astype(np.float32)
