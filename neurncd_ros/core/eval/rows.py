"""The ablation's and baselines' rows of Tables 1-3, re-run on one engine pass's cache
(:func:`.evaluate.collect`): the discovery stage over other embeddings (GS+PSSN+EP+MCL,
the explicit map), geometry alone (GS), and the explicit voxel map of the backbone's
logits (after Nakajima et al. 2019)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .. import classes
from ..camera import backproject
from ..discovery.geoseg import points_image, segment_depth, surface_normals
from ..discovery.labeller import Discoverer
from ..discovery.mcl import markov_cluster
from ..uncertainty import entropy as softmax_entropy
from . import progress as progress_mod

if TYPE_CHECKING:
    from tqdm import tqdm

VOXEL_SIZE = 0.05  # m, the explicit map's voxel edge
GS_MAX_SEGMENTS = 1500  # segments MCL clusters for the GS row (the rest join the nearest)


def discover(keep: dict, cfg, mod_cfg, source: str = "rendered",
              embeddings: list | None = None, depth: str = "view_depth", bar: tqdm | None = None
              ) -> list[np.ndarray]:
    """The discovery stage (a fresh Discoverer) over the cached frames, segmenting
    ``keep[depth]`` (the mapper's view depth, or ``"depth"``: the measured one); every
    labelled frame, with ground truth or not, as the engine's discovery saw them.
    ``bar`` (a progress bar) advances one per frame."""
    c2i = np.asarray(keep["_c2i"])
    d = Discoverer(cfg.discovery, c2i, mcl_cfg=cfg.mcl, seg_cfg=cfg.segmentation,
                   mod_cfg=mod_cfg, fusion_cfg=cfg.label_fusion)
    out = []
    for i in range(len(keep["stamp"])):
        if embeddings is not None:
            emb = embeddings[i]
            ent = softmax_entropy(emb)
        else:
            emb = keep["embedding"][i].astype(np.float32)
            ent = keep["entropy"][i]
        rgb = keep["rgb"][i] if cfg.segmentation.colour_edges else None
        out.append(d.process(keep[depth][i], keep["intr"][i], emb, ent,
                             keep["stamp"][i], rgb, pose=keep["pose"][i]))
        progress_mod.tick(bar)
    return out


def geometry_only(keep: dict, cfg, seed: int = 0, bar: tqdm | None = None) -> list[np.ndarray]:
    """GS alone: depth segments described by their world-frame mean normal and height,
    clustered by the same MCL over all frames (novel-style ids >= 100, no names).
    ``bar`` advances one per frame segmented, then shows the clustering."""
    rng = np.random.default_rng(seed)
    segs, descs, owner = [], [], []
    for i in range(len(keep["stamp"])):
        depth, intr, pose = keep["view_depth"][i], keep["intr"][i], keep["pose"][i]
        seg = segment_depth(depth, intr, cfg.segmentation)
        segs.append(seg)
        progress_mod.tick(bar)
        pts = points_image(depth, intr)
        valid = np.isfinite(pts).all(axis=2) & (depth > 0)
        nrm = surface_normals(np.nan_to_num(pts), valid.astype(np.float32), 5).transpose(1, 2, 0)
        R = pose[:3, :3] if pose is not None else np.eye(3)
        t = pose[:3, 3] if pose is not None else np.zeros(3)
        sel = (seg >= 0) & valid
        n = int(seg.max()) + 1 if seg.size and seg.max() >= 0 else 0
        if n == 0:
            continue
        ids = seg[sel]
        cnt = np.maximum(np.bincount(ids, minlength=n), 1)[:, None]
        nw = np.nan_to_num(nrm[sel]) @ R.T
        pw = np.nan_to_num(pts[sel]) @ R.T + t
        mn = np.stack([np.bincount(ids, nw[:, k], n) for k in range(3)], 1) / cnt
        mn /= np.maximum(np.linalg.norm(mn, axis=1, keepdims=True), 1e-9)
        hz = np.bincount(ids, pw[:, 2], n)[:, None] / cnt
        present = np.bincount(ids, minlength=n) > 0
        d = np.concatenate([np.abs(mn), hz / 1.0], axis=1)[present]
        descs.append(d)
        owner.extend((i, s) for s in np.flatnonzero(present).tolist())
    if not descs:
        return [np.zeros_like(s, np.uint16) for s in segs]
    D = np.concatenate(descs).astype(np.float32)
    if bar is not None:
        bar.set_postfix_str(f"MCL over {min(len(D), GS_MAX_SEGMENTS)} segments")
    pick = rng.choice(len(D), size=min(len(D), GS_MAX_SEGMENTS), replace=False)
    cl = markov_cluster(D[pick], cfg.mcl) if pick.size > 1 else np.zeros(1, np.int64)
    _, cl = np.unique(cl, return_inverse=True)
    cent = np.stack([D[pick][cl == c].mean(0) for c in range(cl.max() + 1)])
    lab = np.argmin(((D[:, None, :] - cent[None]) ** 2).sum(-1), axis=1)
    seg_lab: dict[tuple[int, int], int] = {o: int(c) for o, c in zip(owner, lab)}
    out = []
    for i, seg in enumerate(segs):
        n = int(seg.max()) + 1 if seg.max() >= 0 else 0
        table = np.array([classes.NOVEL_ID_START + seg_lab[(i, s)] if (i, s) in seg_lab
                          else 0 for s in range(n)], np.int64)
        out.append(np.where(seg >= 0, table[np.maximum(seg, 0)] if n else 0, 0)
                   .astype(np.uint16))
    return out


class VoxelMap:
    """An explicit semantic map: voxel hash of back-projected points, running mean of the
    per-frame backbone logits in each voxel (the explicit-map baseline, no field)."""

    def __init__(self, channels: int, voxel: float = VOXEL_SIZE) -> None:
        self.voxel = voxel
        self.keys = np.zeros(0, np.int64)
        self.sums = np.zeros((0, channels), np.float64)
        self.counts = np.zeros(0, np.int64)

    @staticmethod
    def _key(pts: np.ndarray, voxel: float) -> np.ndarray:
        v = np.floor(pts / voxel).astype(np.int64) + (1 << 20)
        return (v[:, 0] << 42) | (v[:, 1] << 21) | v[:, 2]

    def fuse(self, depth, intr, pose, logits) -> None:
        """Add one frame's per-pixel logits at its back-projected points."""
        pts, mask = backproject(depth, intr, pose)
        k = self._key(pts, self.voxel)
        u, inv = np.unique(k, return_inverse=True)
        s = np.zeros((u.size, logits.shape[2]))
        np.add.at(s, inv, logits[mask].astype(np.float64))
        c = np.bincount(inv, minlength=u.size)
        keys = np.concatenate([self.keys, u])
        uk, inv2 = np.unique(keys, return_inverse=True)
        sums = np.zeros((uk.size, s.shape[1]))
        np.add.at(sums, inv2, np.concatenate([self.sums, s]))
        counts = np.bincount(inv2, weights=np.concatenate([self.counts, c]), minlength=uk.size)
        self.keys, self.sums, self.counts = uk, sums, counts.astype(np.int64)

    def lookup(self, depth, intr, pose, fallback: np.ndarray) -> np.ndarray:
        """(H, W, S) fused logits of a view (the frame's own logits where unmapped)."""
        pts, mask = backproject(depth, intr, pose)
        k = self._key(pts, self.voxel)
        pos = np.clip(np.searchsorted(self.keys, k), 0, max(self.keys.size - 1, 0))
        hit = self.keys[pos] == k if self.keys.size else np.zeros(k.size, bool)
        out = fallback.astype(np.float32).copy()
        vals = out[mask]
        vals[hit] = (self.sums[pos[hit]] / self.counts[pos[hit], None]).astype(np.float32)
        out[mask] = vals
        return out


def explicit_baseline(keep: dict, cfg, bar: tqdm | None = None) -> list[np.ndarray]:
    """Backbone logits of every labelled frame fused in a voxel map; each frame's fused
    embedding and its entropy labelled by the same discovery stage on the measured depth
    (no field, no mapper stage). Frames without ground truth are fused too: the map is
    built from the stream, not from the labels. ``bar`` advances one per frame fused,
    then one per frame labelled."""
    S = keep["logits"][0].shape[2]
    vm = VoxelMap(S)
    fused = []
    for i in range(len(keep["stamp"])):
        lg = keep["logits"][i].astype(np.float32)
        if keep["pose"][i] is not None:
            vm.fuse(keep["depth"][i], keep["intr"][i], keep["pose"][i], lg)
            lg = vm.lookup(keep["depth"][i], keep["intr"][i], keep["pose"][i], lg)
        fused.append(lg)
        progress_mod.tick(bar, phase="fuse")
    if bar is not None:
        bar.set_postfix(phase="label", refresh=False)
    return discover(keep, cfg, cfg.modulation, embeddings=fused, depth="depth", bar=bar)
