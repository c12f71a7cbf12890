"""Label fusion: a voxel map of the labels given so far, so a surface keeps its label.

Why: discovery labels each frame from its own segments. A flat picture or a
window whose segment merges with the wall segment in one frame (the colour edge
was too weak there) is labelled wall in that frame and novel in the next, and
one novel object split by Markov clustering can flip between two ids; the
frame-by-frame labels of one surface then disagree although the camera sees the
same surface. With the camera pose, every labelled pixel is a vote for its
label at a world point: :class:`LabelFusion` keeps, per voxel, an exponentially
decayed distribution of the labels it received (each observation of a voxel
adds one unit of mass spread over the labels of its pixels in that frame, and
the older mass is scaled by ``decay`` first), and a pixel is then labelled by its
voxel's distribution. A label the map has seen for long outweighs one frame's
change; a lasting change wins after a few frames (``decay`` sets how many).
With ``novel_only`` (default) the map only overrides the frame where either label
is novel: fusing the known classes too blurs their boundaries at the voxel size.

Chosen on the tuning seeds (bench/results/ncd_sweep_label_fusion_*.json):
stability 0.904 -> 0.924 and all-class mIoU 74.1 -> 74.3 at 3 cm and decay 0.9;
5 cm voxels over all classes lowered known mIoU by 0.5-0.7. The decay was raised
to 0.99 later, on tuning seeds 500-509 with the bfloat16 backbone
(bench/results/ncd_sweep_label_fusion_decay_precision-bfloat16.json): 0.9 / 0.95 /
0.98 / 0.99 give novel-id stability 0.895 / 0.897 / 0.899 / 0.900 for all-class mIoU
75.19 / 75.13 / 75.08 / 75.06 (novel 52.44 -> 52.07, known 84.33 -> 84.34): a voxel
keeps the label most of its observations gave, and a window whose segment merged into
the wall for the rest of a walk stays novel where its voxels were seen before. It
costs discovery about 28 ms per 320x240 frame (a profile over a 270k-voxel map).

Fresh voxels (``coarse_voxel_size``): the same surface seen from a new viewpoint,
or through new depth noise, lands on 3 cm voxels the map has not seen, and those
take the frame's label: a window whose segment merged into the wall for the rest
of a walk is called wall on all its new voxels, although the voxels beside them
say novel. A second, coarse map (15 cm) takes the same votes (aliases applied);
a pixel whose fine voxel was observed at most ``fresh_observations`` (3) times before
the frame takes the coarse voxel's label where that is novel. Known labels never
come from it, and once a voxel has been observed more often its own votes decide.
Chosen on tuning seeds 500-509 with the bfloat16 backbone
(bench/results/ncd_sweep_label_fusion_coarse_voxel_size_precision-bfloat16.json):
off / 0.09 / 0.15 / 0.2 m give novel-id stability 0.900 / 0.903 / 0.906 / 0.906
for all-class mIoU 75.06 / 75.14 / 75.14 / 75.07 (novel 52.07 / 52.16 / 52.10 /
51.88) with fresh_observations 1; then fresh_observations 1 / 2 / 3 give 0.906 /
0.908 / 0.909 for all-class mIoU 75.14 / 75.13 / 75.12 (novel 52.10 / 52.06 / 52.00;
bench/results/ncd_sweep_label_fusion_fresh_observations_precision-bfloat16.json),
and 3 is the default: a voxel's first four observations may take the coarse novel
label. It adds a second map update to each labelled frame (fewer voxels than the
fine map's).

Novel ids that discovery retires (merged into another id, or no longer live)
lose their votes: :meth:`LabelFusion.update` takes the live novel ids, so the
map never brings back an id discovery no longer publishes.

Aliases (``alias_share``): Markov clustering sometimes gives one large object two
novel ids, one for the part seen first and one for the part a later viewpoint
adds (a window seen from two sides of the room). When at least ``alias_share`` of
a frame's pixels of novel id B lie on voxels whose strongest label is another
novel id A that the frame itself does not show, B is published as A from then on,
for as long as discovery keeps B. Two ids the frame shows side by side are two
objects to discovery, and stay apart: a first version without that test, chosen on
the tuning seeds, lowered the ceiling's IoU on the test scenes from 93.4 to 80.4
(scene 2007's novel mIoU 77.7 -> 51.1, bench/results/ncd_alias_first.json at 7374037),
as two novel classes came to share one id.
Chosen on the tuning seeds 500-509 (bench/results/ncd_sweep_label_fusion_alias_share.json):
0 / 0.3 / 0.4 / 0.5 give novel-id stability 0.892 / 0.895 / 0.896 / 0.893 (0.954 /
0.968 / 0.963 / 0.959 over the pixels given a novel id), mIoU unchanged to 0.1.

Touching parts (``touch_share``): once the mapper averages the view's depth over
the keyframes (``mapper_node.depth_fusion``), the small depth steps of a window's
frame and panes cut them into separate segments, which Markov clustering puts in
separate novel clusters (bright panes, white frame): a window then carried two or
three ids in every frame. Two novel regions of one frame whose depth-continuous
shared border is at least ``touch_share`` of the smaller one's outline, on planes
within ``touch_max_angle_deg`` of parallel, are aliased from that frame on: the id
shown in fewer frames is published as the other (between ids shown alike, the smaller
as the larger). This is the exception to "side by side stays apart"
above: the ceiling meets a window at a right angle, and two objects that touch share
little of their outlines. On the tuning seeds 500-509 with the fused depth, 0 / 0.1 /
0.2 / 0.3 / 0.5 give novel-id stability 0.893 / 0.921 / 0.919 / 0.917 / 0.896 and
all-class mIoU 76.35 / 76.80 / 76.77 / 76.73 / 76.37 (window IoU 63.2 -> 69.9 at 0.2);
0.2, between the two shares that scored alike, is the default. Which id keeps its name
was first the larger region's. An object that appears as a sliver gets an id in its first
frame and its bulk often a fresh one in the next (tuning seed 500: a window 116, then
119); the larger, newer id won, and every frame before counted against the object's id.
The id shown longer is the one a subscriber knows. On the tuning seeds 500-509 with
``discovery.uncertain_cluster_pixels`` (which finds objects in such first frames):
all-class / novel mIoU / novel-id stability 80.41 / 67.93 / 0.931 with the larger id
kept, 80.67 / 68.97 / 0.935 with the older (without it, the same to 0.01 either way).

The plane test compares planes only (``touch_plane_ratio``). A window's frame seen
with its sill and reveal is no plane: on the tuning seeds its least variance was
0.3-0.7 of the next, and its best-fit normal lay 25-80 degrees from the panes' it
touched, so frame and panes kept two ids in every frame (a window 0.87-0.90 stable
on seeds 500 and 506, the loss all under a second id in the same frames). A region
that is no plane now has no normal to compare, and the shared border decides; two
planes at an angle (the ceiling and a window) still stay apart. Tuning seeds 500-509
(bench/results/ncd_sweep_label_fusion_touch_plane_ratio[_frames300].json), ratio 1
(every region a plane, the rule before) / 0.3 / 0.1 / 0.03: novel-id stability
0.940 / 0.940 / 0.943 / 0.943 at 150 frames and 0.928 / 0.932 / 0.934 / 0.934 at 300,
all-class mIoU within 0.05.

The map's pairs (``touch_mapped``): the touching rule tests the frame's own labels, but
a surface seen again from a new viewpoint beside new surface can be called by a new id
throughout the frame, while the map keeps the old id on the part it knows (five frames
of votes): the two ids touch in the published labels only, and too little of the new
id lies on the old surface for ``alias_share`` (tuning seed 505 at 300 frames: the
ceiling 104 in frames 6-10, then 118 from frame 29 on, 0.63 stable). The fused labels'
pairs of an id the frame shows and one it does not are tested too (pairs of two ids
the frame shows were tested on its own labels; in the fused labels they touch more, as
the coarse map widens novel regions, and a test over all fused pairs merged a picture
into the window beside it on tuning seed 503, novel mIoU 34.5 -> 28.1; two ids the
frame does not show are no evidence of this frame). Tuning seeds 500-509
(bench/results/ncd_sweep_label_fusion_touch_mapped[_frames300].json), off / on:
all-class mIoU 82.68 / 82.92, novel 66.65 / 67.54, novel-id stability 0.934 / 0.944 at
300 frames; at 150 frames every figure the same (81.20, 0.943).

Evidence over frames (``alias_frame_share``): an alias renames an id for good, and the
id may be one a subscriber has seen for minutes. On tuning seed 500 walked for 300 s,
one frame's clustering error gave a piece of a picture beside the TV the ceiling's id;
the piece touched the TV in the wall's plane, and the ceiling was published as the TV
from then on (later, in another frame, the window by the same path). So an alias now
needs its evidence in at least ``alias_frame_share`` of the frames that showed the id to
be renamed (for the share rule, frames in which its pixels fell on the other id's
surface; for the touching rule, frames in which the two touched). A new id (the second
side of a window, a window's panes) is renamed in its first frame, as before; an id
shown for a hundred frames is not renamed by one. The evidence is counted for the ids as
published (a new piece renamed in the frame to an established id carries that id). On that
walk: novel mIoU over the whole walk 37.0 -> 65.7, novel-id stability 0.72 -> 0.84; on the
150-frame tuning scenes all-class mIoU 77.89 -> 77.82 (``bench/discovery_memory.py``,
bench/results/ncd_sweep_label_fusion_alias_frame_share.json).

Pure numpy; the map is a sorted array of packed voxel keys with a row of votes
per key, grown as new surface is seen and bounded by ``max_voxels`` (the voxels
least recently observed are dropped first). It stays one module (over 500 lines): the
votes, the fresh-voxel rule and the two alias rules all read and update the one map and
its aliases, and splitting them would pass that state around.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..camera import Intrinsics, backproject
from ..classes import NOVEL_ID_START
from ..params import param

_BITS = 21  # per axis: 2**21 voxels, +-31 km at 3 cm, packed into one int64 key
_OFFSET = 1 << (_BITS - 1)


@dataclasses.dataclass(frozen=True)
class LabelFusionConfig:
    """The voxel map of labels that keeps a surface's label across frames (needs poses)."""

    enabled: bool = param(True, "label each pixel by the decayed label votes of its voxel "
                          "over the frames seen so far (needs the view's pose; off, or no "
                          "pose, labels each frame on its own)")
    voxel_size: float = param(0.03, "edge of a fusion voxel", lo=0.005, hi=1.0, unit="m")
    decay: float = param(0.99, "each new observation of a voxel scales its older votes by "
                         "this (0 = no memory; near 1, the majority of everything the "
                         "voxel was called)", lo=0.0, hi=0.999)
    novel_only: bool = param(True, "the map changes a pixel's label only where the frame's "
                             "label or the map's is novel (known-to-known changes are left "
                             "to the frame: the map's voxels blur the known classes' "
                             "boundaries)")
    alias_share: float = param(0.4, "a novel id of the frame whose pixels fall at least "
                               "this share on surface the map gives another novel id takes "
                               "that id from then on (one object Markov clustering split "
                               "into two ids seen from two viewpoints; 0 = off)",
                               lo=0.0, hi=1.0)
    touch_share: float = param(0.2, "two novel ids whose regions in a frame share a "
                               "depth-continuous border of at least this share of the "
                               "smaller one's outline, on surfaces within "
                               "touch_max_angle_deg of parallel, are one object: the id "
                               "shown in fewer frames (between ids shown alike, the "
                               "smaller) is published as the other from then on (a "
                               "window's panes and frame clustered apart; 0 = off)",
                               lo=0.0, hi=1.0)
    touch_mapped: bool = param(True, "touch_share also between a novel id of the frame "
                               "and one only the map gives (the fused labels): a surface "
                               "seen again beside new surface, which the frame called by "
                               "a new id throughout, keeps its id on the part the map "
                               "knows, and the new id touching it there joins it")
    touch_max_angle_deg: float = param(20.0, "touch_share: the most the best-fit planes of "
                                       "two touching novel regions may differ and still be "
                                       "one object (a window's panes and frame lie in one "
                                       "wall plane; the ceiling meets a window at 90 degrees "
                                       "and must stay a class of its own; a region that is "
                                       "no plane, a frame with its sill, is not compared)",
                                       lo=0.0, hi=90.0,
                                       unit="deg")
    touch_plane_ratio: float = param(0.1, "touch_max_angle_deg compares planes only: a "
                                     "region is one when the variance of its points along "
                                     "their least direction is at most this share of that "
                                     "along the next (a pane or a ceiling: below 0.03; a "
                                     "window's frame seen with its sill and reveal: 0.3-0.7, "
                                     "its best-fit normal then points anywhere); between "
                                     "a region that is no plane and another, the shared "
                                     "border alone decides (1 = every region is a plane)",
                                     lo=0.0, hi=1.0)
    alias_frame_share: float = param(0.5, "alias_share and touch_share rename an id only "
                                     "if their evidence (its pixels on the other id's "
                                     "surface; its region touching the other's) came in at "
                                     "least this share of the frames that showed it: one "
                                     "frame's clustering error must not rename an id a "
                                     "subscriber has seen for minutes (0 = one frame "
                                     "suffices)", lo=0.0, hi=1.0)
    coarse_voxel_size: float = param(0.15, "a pixel on a voxel the map has observed at most "
                                     "fresh_observations times takes, where it is novel, the "
                                     "label of the coarse voxel of this edge around it (a "
                                     "surface seen from a new viewpoint, or through new depth "
                                     "noise, falls on new voxels but keeps its neighbourhood's "
                                     "label; 0 = off)", lo=0.0, hi=2.0, unit="m")
    fresh_observations: int = param(3, "coarse_voxel_size: voxels observed at most this many "
                                    "times before the frame count as fresh", lo=0, hi=1000)
    max_voxels: int = param(500_000, "voxels kept (about 450 m2 of surface at 3 cm; "
                            "beyond, the least recently observed are dropped)", lo=1000,
                            hi=10**8)


class LabelFusion:
    """Voxel map of decayed label votes; :meth:`update` fuses one labelled frame."""

    def __init__(self, cfg: LabelFusionConfig = LabelFusionConfig()) -> None:
        self.cfg = cfg
        # The coarse map votes with the labels this one publishes (aliases applied).
        self._coarse = (LabelFusion(dataclasses.replace(
            cfg, voxel_size=cfg.coarse_voxel_size, coarse_voxel_size=0.0, alias_share=0.0,
            touch_share=0.0))
            if cfg.coarse_voxel_size > 0 else None)
        self.reset()

    def reset(self) -> None:
        self._keys = np.zeros(0, np.int64)     # sorted packed voxel keys
        self._row = np.zeros(0, np.int64)      # storage row of each sorted key
        self._votes = np.zeros((0, 0), np.float32)  # storage: (capacity, label columns)
        self._seen = np.zeros(0, np.int64)     # storage: frame of the last observation
        self._n = 0                            # storage rows in use
        self._columns: dict[int, int] = {}     # label id -> column
        self._frame = 0
        self._alias: dict[int, int] = {}       # novel id -> the novel id it is published as
        # Evidence for aliases, in frames: id -> frames that showed it (as published);
        # (b, a) -> frames in which b fell on a's surface, or touched a (two counts).
        self._shown: dict[int, int] = {}
        self._onto: dict[tuple[int, int], int] = {}
        self._touched: dict[tuple[int, int], int] = {}
        # The evidence counted in this frame ((rule, src, dst)): a frame counts once.
        self._counted: set[tuple[bool, int, int]] = set()
        if self._coarse is not None:
            self._coarse.reset()

    def __len__(self) -> int:
        return int(self._keys.size)

    @property
    def aliases(self) -> dict[int, int]:
        """Novel id -> the novel id it is published as (``alias_share``)."""
        return dict(self._alias)

    # ------------------------------------------------------------ helpers
    def _pack(self, points: np.ndarray) -> np.ndarray:
        idx = np.floor(points / self.cfg.voxel_size).astype(np.int64) + _OFFSET
        idx = np.clip(idx, 0, (1 << _BITS) - 1)
        return (idx[:, 0] << (2 * _BITS)) | (idx[:, 1] << _BITS) | idx[:, 2]

    def _column_of(self, ids: np.ndarray) -> np.ndarray:
        for i in ids.tolist():
            if i not in self._columns:
                self._columns[i] = len(self._columns)
        n = len(self._columns)
        if self._votes.shape[1] < n:
            grown = np.zeros((self._votes.shape[0], n), np.float32)
            grown[:, : self._votes.shape[1]] = self._votes
            self._votes = grown
        return np.array([self._columns[i] for i in ids.tolist()], np.int64)

    def _rows_of(self, keys: np.ndarray) -> np.ndarray:
        """Storage rows of these (unique, sorted) keys; new keys get new rows (storage
        grows by doubling, the sorted index by one merge per frame)."""
        pos = np.searchsorted(self._keys, keys)
        found = np.zeros(keys.size, bool)
        if self._keys.size:
            found = self._keys[np.minimum(pos, self._keys.size - 1)] == keys
        new = keys[~found]
        if new.size:
            need = self._n + new.size
            if need > self._seen.size:
                cap = max(need, 2 * self._seen.size, 1024)
                votes = np.zeros((cap, self._votes.shape[1]), np.float32)
                votes[: self._n] = self._votes[: self._n]
                seen = np.zeros(cap, np.int64)
                seen[: self._n] = self._seen[: self._n]
                self._votes, self._seen = votes, seen
            rows = np.arange(self._n, need, dtype=np.int64)
            self._votes[rows] = 0.0
            self._seen[rows] = self._frame
            self._n = need
            at = pos[~found]
            self._keys = np.insert(self._keys, at, new)
            self._row = np.insert(self._row, at, rows)
            pos = np.searchsorted(self._keys, keys)
        return self._row[pos]

    def _retire(self, live_novel: set[int] | None) -> None:
        """Forget the votes of novel ids discovery no longer publishes (an id others are
        published as lives while they do)."""
        if live_novel is None:
            return
        self._alias = {a: b for a, b in self._alias.items() if a in live_novel}
        live_novel = set(live_novel) | set(self._alias.values())
        self._shown = {k: v for k, v in self._shown.items() if k in live_novel}
        self._onto = {k: v for k, v in self._onto.items()
                      if k[0] in live_novel and k[1] in live_novel}
        self._touched = {k: v for k, v in self._touched.items()
                         if k[0] in live_novel and k[1] in live_novel}
        dead = {i for i in self._columns if i >= NOVEL_ID_START and i not in live_novel}
        if dead:
            keep = sorted((c, i) for i, c in self._columns.items() if i not in dead)
            self._votes = np.ascontiguousarray(self._votes[:, [c for c, _ in keep]])
            self._columns = {i: j for j, (_, i) in enumerate(keep)}

    def _bound(self) -> None:
        """Beyond ``max_voxels`` (by an eighth, so this runs rarely), keep the most
        recently observed ``max_voxels``."""
        if self._keys.size <= self.cfg.max_voxels * 9 // 8:
            return
        seen = self._seen[self._row]
        keep_sorted = np.zeros(self._keys.size, bool)
        keep_sorted[np.argsort(-seen, kind="stable")[: self.cfg.max_voxels]] = True
        old_rows = self._row[keep_sorted]
        self._keys = self._keys[keep_sorted]
        self._votes = self._votes[old_rows].copy()
        self._seen = self._seen[old_rows].copy()
        self._n = int(old_rows.size)
        self._row = np.arange(self._n, dtype=np.int64)

    def _best_ids(self, rows: np.ndarray) -> np.ndarray:
        """Strongest label id of these storage rows (0 where a row has no vote)."""
        if not self._votes.shape[1]:
            return np.zeros(rows.size, np.int64)
        vox = self._votes[rows]
        best = vox.argmax(1)
        ids_of_col = np.zeros(self._votes.shape[1], np.int64)
        for i, c in self._columns.items():
            ids_of_col[c] = i
        return np.where(vox[np.arange(rows.size), best] > 0, ids_of_col[best], 0)

    def _renamed(self, lab: np.ndarray) -> np.ndarray:
        """Integer labels with every aliased novel id replaced by the id it is published as."""
        if not self._alias:
            return lab
        src = np.array(list(self._alias), np.int64)
        lut = np.arange(max(int(lab.max()), int(src.max())) + 1, dtype=np.int64)
        lut[src] = [self._alias[a] for a in src.tolist()]
        return lut[lab]

    def _add_alias(self, src: int, dst: int) -> None:
        """Publish novel id ``src`` as ``dst`` from now on; ids published as ``src`` follow
        (the table stays flat: one lookup resolves any id)."""
        self._alias[src] = dst
        for k, v in self._alias.items():
            if v == src:
                self._alias[k] = dst

    def _aliased(self, lab: np.ndarray, rows: np.ndarray, inv: np.ndarray) -> np.ndarray:
        """The frame's labels (at its depth pixels; their voxels' storage ``rows`` and
        each pixel's voxel ``inv``) with novel ids renamed: known aliases first, then new
        ones where a novel id's pixels land mostly on surface the map already gives
        another novel id (``alias_share``)."""
        lab = self._renamed(lab)
        novel = lab >= NOVEL_ID_START
        if self.cfg.alias_share <= 0 or not novel.any() or not self._votes.shape[1]:
            return lab
        before = self._best_ids(rows)[inv[novel]]  # the map before this frame's votes
        mine = lab[novel]
        present = np.unique(mine)
        for b in present.tolist():
            sel = mine == b
            other = before[sel]
            # Only onto an id the frame does not show: two ids discovery tells apart
            # in one frame are two objects (a window beside the ceiling), not one.
            other = other[(other >= NOVEL_ID_START) & (other != b) & ~np.isin(other, present)]
            if not other.size:
                continue
            ids, n = np.unique(other, return_counts=True)
            if n.max() >= self.cfg.alias_share * sel.sum():
                a = int(ids[n.argmax()])
                a = self._alias.get(a, a)
                if a == b:
                    continue
                if not self._enough_evidence(self._onto, b, a):
                    continue
                self._add_alias(b, a)
                lab = np.where(lab == b, a, lab)
        return lab

    def _touching(self, lab: np.ndarray, depth: np.ndarray, points: np.ndarray,
                  mask: np.ndarray, framed: set[int] | None = None) -> None:
        """Alias novel ids the frame shows as parts of one surface (``touch_share``);
        ``lab``: the frame's labels as published (int64, known aliases applied), with at
        least two novel ids; or, with ``framed`` (``touch_mapped``), the fused labels,
        of whose pairs only those of an id in ``framed`` (the ids of the frame's own
        labels) and one outside it are tested: two ids the frame does not show would
        count evidence in frames that did not show them, on regions the coarse map
        widened.

        Markov clustering gives the parts of one object different ids when their colour
        and entropy differ (a window's bright panes and its frame): the object's pixels
        then carry two or three ids in every frame. Two novel regions of the frame are
        one object when the border they share, counted over pixel pairs whose depths
        agree (3 cm + 2 %: one surface, not an object in front of another), is at least
        ``touch_share`` of the smaller region's outline, and their best-fit planes are
        within ``touch_max_angle_deg`` of parallel. Two objects that merely touch share
        a small part of their outlines; the ceiling meets a window at a right angle. A
        region that is no plane (``touch_plane_ratio``: a window's frame with its sill) has
        no normal to compare, and the shared border alone decides.
        The id shown in fewer frames is renamed (between ids shown alike, the smaller
        region's), and only if the two touched in at least ``alias_frame_share`` of the
        frames that showed it (counted in :meth:`update`).
        """
        z = np.where(mask, depth, 0.0).astype(np.float32)
        outline = np.zeros(int(lab.max()) + 1, np.int64)
        keys = []
        for a, b, za, zb in ((lab[:, :-1], lab[:, 1:], z[:, :-1], z[:, 1:]),
                             (lab[:-1], lab[1:], z[:-1], z[1:])):
            diff = a != b
            outline += np.bincount(a[diff], minlength=outline.size)
            outline += np.bincount(b[diff], minlength=outline.size)
            lo, hi = np.minimum(za, zb), np.maximum(za, zb)
            shared = (diff & (a >= NOVEL_ID_START) & (b >= NOVEL_ID_START) & (lo > 0)
                      & (hi - lo <= 0.03 + 0.02 * lo))
            pa, pb = np.minimum(a[shared], b[shared]), np.maximum(a[shared], b[shared])
            keys.append(pa * (1 << 32) + pb)
        keys = np.concatenate(keys)
        if not keys.size:
            return
        pairs, border = np.unique(keys, return_counts=True)
        at = lab[mask]
        normals: dict[int, np.ndarray | None] = {}

        def normal(i: int) -> np.ndarray | None:
            if i not in normals:
                pts = points[at == i]
                pts = pts[:: max(1, len(pts) // 2000)]
                if len(pts) < 30:
                    normals[i] = None
                else:  # a zero vector: no plane, nothing to compare
                    ev, vec = np.linalg.eigh(np.cov(pts.T))
                    planar = ev[0] <= self.cfg.touch_plane_ratio * ev[1]
                    normals[i] = vec[:, 0] if planar else np.zeros(3)
            return normals[i]

        cos_max = np.cos(np.radians(self.cfg.touch_max_angle_deg))
        size = np.bincount(lab.ravel(), minlength=outline.size)
        for key, n in zip(pairs.tolist(), border.tolist()):
            a, b = key >> 32, key & 0xFFFFFFFF
            if framed is not None and (a in framed) == (b in framed):
                continue  # the frame's own pair (tested on its labels), or none of its ids
            if n < self.cfg.touch_share * min(outline[a], outline[b]):
                continue
            na, nb = normal(a), normal(b)
            if na is None or nb is None:
                continue
            if na.any() and nb.any() and abs(float(na @ nb)) < cos_max:
                continue  # two planes at an angle: the ceiling and a window
            # The evidence is counted for the ids as published: a region's id may be an
            # alias of an established one, and that id is what an alias would rename.
            a, b = self._alias.get(a, a), self._alias.get(b, b)
            # The id shown longer keeps its name; between ids shown alike, the larger.
            rank = {i: (self._shown.get(i, 0), size[i]) for i in (a, b)}
            keep, renamed = (a, b) if rank[a] >= rank[b] else (b, a)
            if keep != renamed and self._enough_evidence(self._touched, renamed, keep):
                self._add_alias(renamed, keep)

    def _enough_evidence(self, counts: dict[tuple[int, int], int], src: int, dst: int
                         ) -> bool:
        """Count one more frame of evidence (in ``counts``) that novel id ``src`` is
        ``dst``; True once it came in at least ``alias_frame_share`` of the frames that
        showed ``src`` (counted in :meth:`update`), the test both alias rules share. A
        frame counts once: a pair tested again in it (the touching rule on the frame's
        and the fused labels, or a pair that became this one as an id was aliased in the
        frame) is no more evidence."""
        if (counts is self._onto, src, dst) not in self._counted:
            self._counted.add((counts is self._onto, src, dst))
            counts[(src, dst)] = counts.get((src, dst), 0) + 1
        return counts[(src, dst)] >= self.cfg.alias_frame_share * self._shown.get(src, 1)

    # ------------------------------------------------------------ main entry
    def update(self, labels: np.ndarray, depth: np.ndarray, intrinsics: Intrinsics,
               pose: np.ndarray, live_novel: set[int] | None = None) -> np.ndarray:
        """Add one frame's labels (H, W uint16; 0 = no label, no vote) seen from ``pose``
        (camera-to-world) and return the fused labels: every pixel with valid depth
        takes its voxel's strongest label; pixels without depth keep theirs; aliased
        novel ids are published as the id they are aliased to, everywhere.
        ``live_novel``: the novel ids discovery still publishes (others lose their votes)."""
        labels = np.asarray(labels)
        if labels.shape != np.shape(depth):
            raise ValueError(f"labels are {labels.shape} but depth is {np.shape(depth)}")
        points, mask = backproject(depth, intrinsics, pose)
        self._counted = set()
        published = self._renamed(labels.astype(np.int64))
        shown = np.unique(published)
        shown = shown[shown >= NOVEL_ID_START]
        for i in shown.tolist():  # alias_frame_share's count
            self._shown[i] = self._shown.get(i, 0) + 1
        if self.cfg.touch_share > 0 and shown.size >= 2:
            self._touching(published, depth, points, mask)
        out = labels.astype(np.uint16, copy=True)
        vals = self._fuse(labels[mask].astype(np.int64), points, live_novel)
        out[mask] = vals
        if self._alias:
            # Every id as published: pixels without depth keep the frame's own label, and a
            # voxel's strongest vote may be for an id cast before it was aliased; neither
            # may show an aliased id, which the class table no longer lists.
            out = self._renamed(out.astype(np.int64)).astype(np.uint16)
        if self.cfg.touch_share > 0 and self.cfg.touch_mapped:
            fused = out.astype(np.int64)
            framed = set(self._renamed(shown).tolist()) if shown.size else set()
            novel = set(np.unique(fused[fused >= NOVEL_ID_START]).tolist())
            if len(novel) >= 2 and novel & framed and not novel <= framed:
                self._touching(fused, depth, points, mask, framed)
                if self._alias:
                    out = self._renamed(fused).astype(np.uint16)
        return out

    def _fuse(self, lab: np.ndarray, points: np.ndarray, live_novel: set[int] | None
              ) -> np.ndarray:
        """:meth:`update` on the frame's labels ``lab`` at its back-projected ``points``:
        the fused labels of those points."""
        self._frame += 1
        self._retire(live_novel)
        if not points.size:
            return lab
        keys = self._pack(points)
        ukeys, inv = np.unique(keys, return_inverse=True)
        rows = self._rows_of(ukeys)
        if self.cfg.alias_share > 0 or self._alias:
            lab = self._aliased(lab, rows, inv)
        vals = lab.copy()
        if self._coarse is not None:
            # How often each voxel was observed before this frame (its decayed vote mass).
            seen_before = self._votes[rows].sum(1) if self._votes.shape[1] else \
                np.zeros(rows.size, np.float32)
        voting = lab > 0
        if voting.any():
            present = np.bincount(lab[voting])  # label ids are small: no sort needed
            ids = np.flatnonzero(present)
            lut = np.zeros(present.size, np.int64)
            lut[ids] = np.arange(ids.size)
            lab_idx = lut[lab[voting]]
            cols = self._column_of(ids)
            v = inv[voting]
            # One unit of mass per observed voxel, spread over its pixels' labels.
            mass = np.bincount(v * ids.size + lab_idx, minlength=ukeys.size * ids.size
                               ).reshape(ukeys.size, ids.size).astype(np.float32)
            total = mass.sum(1, keepdims=True)
            obs = total[:, 0] > 0
            r = rows[obs]
            self._votes[r] *= self.cfg.decay
            self._votes[np.ix_(r, cols)] += mass[obs] / total[obs]
            self._seen[r] = self._frame
        if self._votes.shape[1]:
            fused = self._best_ids(rows)[inv]
            keep = fused > 0
            if self.cfg.novel_only:
                keep &= (fused >= NOVEL_ID_START) | (vals >= NOVEL_ID_START)
            vals[keep] = fused[keep]
        if self._coarse is not None:
            live = None if live_novel is None else set(live_novel) | set(self._alias.values())
            coarse = self._coarse._fuse(lab, points, live)
            fresh = (seen_before < self.cfg.fresh_observations + 0.5)[inv]
            take = fresh & (coarse >= NOVEL_ID_START) & (coarse != vals)
            vals[take] = coarse[take]
        self._bound()
        return vals
