"""Segment memory, Markov re-clustering, known/novel naming and stable novel ids.

Per processed frame (:meth:`Discoverer.process`):

1. the depth is cut into convex segments (:mod:`geoseg`), each segment gets a
   pooled descriptor (:mod:`modulation`) and pixel statistics;
2. the segments enter a bounded *segment memory*: the segments of the last
   ``recent_frames`` frames are always kept; beyond ``memory_size`` segments,
   older ones are dropped uniformly at random (seeded, so runs repeat), which
   keeps a thinning sample of the whole history;
3. every ``recluster_period`` frames the memory is re-clustered with Markov
   clustering (:mod:`mcl`); in between, the new segments join the cluster with
   the nearest pixel-weighted mean descriptor among the clusters of their own kind
   (uncertain or confident, as ``segment_novelty`` separates them). Markov clustering's
   time grows about with the square of the memory (75 ms at 500 segments, 1.7-1.8 s
   at 3000 on one thread, bench/results/discovery_memory.json), so beyond
   ``recluster_segments`` segments the period is stretched by
   ceil((segments / recluster_segments)^2): on a long run discovery keeps up
   with the keyframes instead of falling further behind;
4. each cluster is named from its members' pooled statistics: if the members'
   pixel-weighted mean entropy is below ``entropy_threshold`` * log(S) and the
   majority embedding-argmax channel holds at least ``majority_share`` of their
   pixels, it is that channel's known NYU-13 class (via ``channel_to_id``);
   otherwise, if it has at least ``min_cluster_segments`` segments and
   ``min_cluster_pixels`` pixels (``uncertain_cluster_pixels`` if its mean entropy is
   above ``uncertain_region_entropy`` and its segments are at most
   ``uncertain_cluster_frames`` frames old), it is a novel class; otherwise it is left
   undecided and its pixels fall back to the per-pixel embedding argmax. With
   ``segment_novelty`` (default) uncertainty is decided per segment first: the
   segments above the entropy threshold leave their clusters and are clustered
   among themselves (at ``novel_inflation``, finer than the memory's
   ``mcl.inflation``), so a confident majority cannot absorb an uncertain
   minority that leans to its class (a picture the backbone half calls wall).
   With ``mode_split`` (off by default since ``pixel_known`` and the label fusion:
   tuning seeds all 80.94 -> 81.16, known 85.34 -> 85.74 without it at 01c25d0,
   bench/results/ncd_sweep_discovery_mode_split.json) a known cluster that holds at most
   ``mode_split_share`` of the pixels of the largest known cluster of its class
   and whose pixel-weighted mean descriptor (colour part included) is more than
   ``mode_split_distance`` from that one's is novel instead: a picture the
   backbone confidently calls wall still forms its own, small, distant cluster,
   while a class that merely varies gives clusters close to its dominant one or
   of comparable size;
5. novel ids start at ``classes.NOVEL_ID_START`` and stay stable: after a
   re-clustering, novel clusters are matched to the previous novel ids by the
   overlap of their member segments (Hungarian on overlap counts, accepted if
   the overlap is at least ``match_overlap`` of the smaller of the two member
   sets still in memory); unmatched clusters get fresh ids; ids are never
   reused. Cluster numbering therefore never influences ids. Before the
   matching, novel clusters whose pixel-weighted mean descriptors lie within
   ``novel_merge_distance`` of each other (average link) are one novel class
   with one id: Markov clustering often splits one object into several clusters
   (its views differ in colour and entropy), and each would otherwise get an id
   of its own, so the object's pixels would flip between ids from frame to
   frame. Different novel classes lie further apart than that (chosen on the
   tuning seeds; at 3edf4cd all / novel mIoU 80.24 / 65.77 with no merge, 80.69 /
   67.87 at 0.3, 81.16 / 69.33 at 0.4, 79.88 / 65.71 at 0.5, and at 0.8, which
   merges classes, 75.40 / 48.57;
   bench/results/ncd_sweep_discovery_novel_merge_distance.json).

Defaults (``min_cluster_segments`` 1, ``segment_novelty`` on; with mcl's and
modulation's) were chosen by ``bench/ncd.py --tune`` on the rendered embedding
of 8 tuning scenes (``seeds.TUNE``; scores in bench/results/ncd_tuning.json).
``entropy_threshold`` 0.6 was chosen for the shipped backbone's novelty branch
on the same scenes (bench/results/ncd_sweep_discovery_entropy_threshold.json): the branch
makes the normalised entropy of pictures, windows and TVs high and that of
known classes low, so the threshold sits between them; without the branch
(``backbone.novelty_branch`` false) the net is confident even on novel objects
and a threshold near 0.15 is needed.

With ``uncertain_region_px`` (default), large connected regions of uncertain
pixels become segments of their own first: regions the depth segmentation leaves
out (no depth, pieces dissolved as too small; a window is often such a region)
and, with ``uncertain_region_carve``, regions inside a segment that is confident
on the whole (a picture flush with a wall, left in the wall's segment). Tuning
seeds 500-509: all / novel 77.82 / 58.72 without, 80.28 / 67.53 with, novel-id
stability 0.924 -> 0.919 (bench/results/ncd_sweep_discovery_uncertain_region_*.json).
On the test scenes stability fell further, 0.917 -> 0.878, as objects once called
wall in every frame were found after their first few (README, Limits); with
``uncertain_cluster_pixels`` it is 0.909 there (bench/results/ncd.json).
Why ``uncertain_cluster_pixels``: in the frames where such an object first
appears, its carved region is a cluster of 100-350 pixels at 320x240 (a picture,
the edge of a window), below ``min_cluster_pixels``, so it was left undecided and
painted with its argmax, "wall", until the memory held enough of it; those
frames counted against the object's id. A cluster whose mean entropy is above
``uncertain_region_entropy`` is stronger evidence than one just above the
known/novel threshold, and is decided at a smaller size. Tuning seeds 500-509
(with the touching rule of :mod:`fusion` keeping the older id): all / novel /
stability 80.28 / 67.53 / 0.919 off, 80.67 / 68.97 / 0.935 at 450 (150-1000 score
alike; bench/results/ncd_sweep_discovery_uncertain_cluster_pixels.json). Only while
the cluster is new (``uncertain_cluster_frames``): on the tuning walks of
``bench/discovery_memory.py`` (one labelled frame per second for 150-300 s), old
small uncertain clusters decided at that size became ids of their own beside their
object's (a picture split 0.56 / 0.43 between two ids on seed 500), and novel mIoU fell
1-3 points; restricted to clusters whose segments are at most 3 frames old the walks
score within a point of novel mIoU of the rule off (bench/results/discovery_memory*.json),
and the 150-frame scenes as with it unrestricted (frames 0 / 1 /
3 / 6 / 10: all 80.45 / 80.57 / 80.67 / 80.67 / 80.67,
bench/results/ncd_sweep_discovery_uncertain_cluster_frames.json).
Every pixel of a processed frame gets a label: segment pixels get their
cluster's label; pixels without a segment (no depth, edges left unassigned,
undecided clusters) get the known class of the per-pixel embedding argmax,
except that those whose entropy is above the threshold take the nearest novel
label within ``novel_fill_px`` (the bands between the pieces of a novel object);
with ``novel_fill_known`` (default) so do uncertain pixels that a known segment
holds (a picture's frame or a window's glazing cut into the wall segment; tuning
seeds: all / novel 73.9 / 51.9 -> 74.1 / 52.7, stability 0.902 -> 0.904, six of the
eight scenes up, bench/results/ncd_sweep_discovery_novel_fill_known.json).
With ``pixel_known`` (default), a pixel of a segment labelled known whose own
entropy is below the threshold keeps its own argmax known class: segments are
about 0.97 pure, and a segment that straddles two known objects otherwise takes
its majority's class (tuning seeds: known 82.5 -> 83.7, all 74.3 -> 75.2;
bench/results/ncd_sweep_discovery_pixel_known.json).
With the view's pose, the frame's labels then pass through the voxel map of
:mod:`fusion` (``label_fusion.enabled``, default): a surface keeps the novel id it
had in the frames before although one frame's segment merged it into the wall
(tuning seeds: stability 0.904 -> 0.924, all-class 74.1 -> 74.3;
bench/results/ncd_sweep_label_fusion_*.json).
Label 0 is produced only at pixels outside every decided segment whose
embedding is not finite.

:meth:`Discoverer.classes` reports, for every id present in the last labelled
frame plus every currently live novel id, its name, kind and pixel count in the
last labelled frame. Not thread-safe (the node serialises calls). The module
stays one module (over 500 lines): the segment memory, the re-clustering, the
naming and the stable ids all read and update the one state of a
:class:`Discoverer`, and splitting them would pass that state around.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from ..camera import Intrinsics, check_pose
from ..classes import NOVEL_ID_START, NUM_CLASSES, class_name
from ..params import param
from .fusion import LabelFusionConfig, LabelFusion
from .geoseg import GeoSegConfig, segment_depth
from .mcl import MCLConfig, markov_cluster
from .modulation import ModulationConfig, descriptors_from_stats, segment_stats

UNDECIDED = -1


@dataclasses.dataclass(frozen=True)
class DiscoveryConfig:
    """Segment memory, re-clustering schedule and known/novel decision thresholds."""

    memory_size: int = param(3000, "segments kept in the segment memory", lo=10, hi=100000)
    recent_frames: int = param(10, "the segments of this many latest frames are never dropped",
                               lo=1, hi=10000)
    recluster_period: int = param(1, "re-cluster the memory every this many frames", lo=1,
                                  hi=10000)
    recluster_segments: int = param(1000, "with more segments than this in the memory, "
                                    "re-cluster only every ceil((segments / this)^2) x "
                                    "recluster_period frames (Markov clustering's time grows "
                                    "about with the square of the memory, so its cost per "
                                    "frame stays near what it is at this size; new segments "
                                    "join the nearest cluster of their kind in between; 0 = off)",
                                    lo=0, hi=100000)
    entropy_threshold: float = param(0.6, "known if mean entropy / log(S) is below this",
                                     lo=0.0, hi=1.0)
    majority_share: float = param(0.5, "known if the majority argmax channel holds this share "
                                  "of the cluster's pixels", lo=0.0, hi=1.0)
    min_cluster_segments: int = param(1, "a novel cluster needs at least this many segments",
                                      lo=1, hi=10000)
    min_cluster_pixels: int = param(500, "a novel cluster needs at least this many pixels",
                                    lo=0, hi=10**9, unit="px")
    segment_novelty: bool = param(True, "decide uncertainty per segment first: segments "
                                  "above entropy_threshold leave their clusters and are "
                                  "clustered among themselves (novel candidates), so a "
                                  "confident majority cannot absorb them")
    mode_split: bool = param(False, "a known cluster that is much smaller than the largest "
                             "known cluster of the same class and whose mean descriptor is "
                             "far from it becomes novel (a picture the backbone calls wall)")
    mode_split_share: float = param(0.1, "mode_split: at most this share of the dominant "
                                    "cluster's pixels", lo=0.0, hi=1.0)
    mode_split_distance: float = param(0.3, "mode_split: Euclidean distance between the two "
                                       "clusters' pixel-weighted mean descriptors above this",
                                       lo=0.0, hi=100.0)
    match_overlap: float = param(0.3, "share of shared member segments to keep a novel id",
                                 lo=0.0, hi=1.0)
    novel_merge_distance: float = param(0.4, "novel clusters whose pixel-weighted mean "
                                        "descriptors are closer than this (Euclidean, average "
                                        "link) share one novel id (one object that Markov "
                                        "clustering split; 0 = off)", lo=0.0, hi=100.0)
    novel_inflation: float = param(2.0, "Markov inflation of the uncertain segments' own "
                                   "clustering (segment_novelty; mcl.inflation is that of the "
                                   "whole memory): at 1.4 a memory of hundreds of uncertain "
                                   "segments flows into a few clusters, and the novel classes "
                                   "of a long run share ids", lo=1.01, hi=50.0)
    novel_fill_px: int = param(16, "pixels without a segment whose entropy is above "
                               "entropy_threshold take the nearest novel label within this "
                               "distance instead of the per-pixel argmax (at "
                               "segmentation.reference_width, scaled with the image; 0 = off)",
                               lo=0, hi=1000, unit="px")
    novel_fill_known: bool = param(True, "novel_fill_px also reaches uncertain pixels "
                                   "inside segments labelled known (a picture's frame in a "
                                   "wall segment), not only pixels without a segment")
    pixel_known: bool = param(True, "inside a segment labelled known, a pixel whose own "
                              "embedding is confident (entropy below entropy_threshold) "
                              "keeps its own argmax known class (a segment that straddles "
                              "a chair and the floor is not all chair)")
    uncertain_region_px: int = param(300, "connected regions of uncertain pixels (entropy "
                                     "above uncertain_region_entropy) at least this large "
                                     "become segments of their own: pixels without a segment "
                                     "and, with uncertain_region_carve, pixels of a confident "
                                     "segment (at segmentation.reference_width, scaled by "
                                     "area; 0 = off)", lo=0, hi=10**9, unit="px")
    uncertain_region_entropy: float = param(0.9, "uncertain_region_px: per-pixel entropy / "
                                            "log(S) above this", lo=0.0, hi=1.0)
    uncertain_region_carve: bool = param(True, "uncertain_region_px also takes its regions "
                                         "out of segments whose mean entropy is below "
                                         "entropy_threshold (a picture flush with a wall that "
                                         "the segmentation left in the wall's segment)")
    uncertain_region_opening: int = param(5, "uncertain_region_px: the uncertain pixels are "
                                          "first opened (eroded, then dilated) with a square "
                                          "this wide, so that thin bands along object borders "
                                          "are no region (at segmentation.reference_width; "
                                          "1 = no opening)", lo=1, hi=101, unit="px")
    uncertain_cluster_pixels: int = param(450, "a cluster whose pixel-weighted mean "
                                          "entropy / log(S) is above "
                                          "uncertain_region_entropy is novel from this many "
                                          "pixels instead of min_cluster_pixels (at "
                                          "segmentation.reference_width, scaled by area; "
                                          "0 = off)", lo=0, hi=10**9, unit="px")
    uncertain_cluster_frames: int = param(3, "uncertain_cluster_pixels applies only to a "
                                          "cluster whose segments all come from this many "
                                          "latest frames before the present one (an object "
                                          "that has just come into view; older small "
                                          "uncertain clusters still need min_cluster_pixels)",
                                          lo=0, hi=10000)
    seed: int = param(0, "seed of the memory's random thinning", lo=0, hi=2**31 - 1)


def _weighted_means(group: np.ndarray, desc: np.ndarray, pixels: np.ndarray,
                    n: int) -> np.ndarray:
    """(n, D) pixel-weighted mean descriptor of each group 0..n-1 (``group``: (N,) the
    group of each of the N segments): a cluster's place in descriptor space."""
    out = np.zeros((n, desc.shape[1]))
    np.add.at(out, group, desc * pixels[:, None])
    return out / np.maximum(np.bincount(group, weights=pixels, minlength=n), 1)[:, None]


@dataclasses.dataclass
class _Memory:
    """Column store of the remembered segments."""

    uid: np.ndarray           # (N,) int64 unique segment ids
    frame: np.ndarray         # (N,) int64 frame index
    desc: np.ndarray          # (N, D) float32
    pixels: np.ndarray        # (N,) int64
    ent_sum: np.ndarray       # (N,) float64 entropy summed over pixels
    hist: np.ndarray          # (N, S) int64 argmax histogram
    cluster: np.ndarray       # (N,) int64 label of the segment's cluster (id or UNDECIDED)

    @classmethod
    def empty(cls, D: int, S: int) -> "_Memory":
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, D), np.float32),
                   np.zeros(0, np.int64), np.zeros(0), np.zeros((0, S), np.int64),
                   np.zeros(0, np.int64))

    def take(self, idx: np.ndarray) -> "_Memory":
        return _Memory(*(getattr(self, f.name)[idx] for f in dataclasses.fields(self)))

    def extend(self, other: "_Memory") -> "_Memory":
        return _Memory(*(np.concatenate([getattr(self, f.name), getattr(other, f.name)])
                         for f in dataclasses.fields(self)))

    def __len__(self) -> int:
        return int(self.uid.size)


class Discoverer:
    """Online novel class discovery over a stream of (depth, embedding, entropy) frames."""

    def __init__(self, cfg: DiscoveryConfig = DiscoveryConfig(),
                 channel_to_id: np.ndarray | None = None, mcl_cfg: MCLConfig = MCLConfig(),
                 seg_cfg: GeoSegConfig = GeoSegConfig(),
                 mod_cfg: ModulationConfig = ModulationConfig(),
                 fusion_cfg: LabelFusionConfig = LabelFusionConfig()) -> None:
        if channel_to_id is None:
            from ..classes import CHANNEL_TO_ID
            channel_to_id = CHANNEL_TO_ID
        c2i = np.asarray(channel_to_id)
        if c2i.ndim != 1 or c2i.size < 2:
            raise ValueError(f"channel_to_id must be a 1-D array of >= 2 ids, got {c2i.shape}")
        if c2i.min() < 1 or c2i.max() > NUM_CLASSES:
            raise ValueError(f"channel_to_id must hold NYU-13 ids 1..{NUM_CLASSES}, got "
                             f"{c2i.tolist()}")
        self.cfg, self.mcl_cfg, self.seg_cfg, self.mod_cfg = cfg, mcl_cfg, seg_cfg, mod_cfg
        self._novel_mcl = dataclasses.replace(mcl_cfg, inflation=cfg.novel_inflation)
        self.fusion = LabelFusion(fusion_cfg) if fusion_cfg.enabled else None
        self.channel_to_id = c2i.astype(np.uint16)
        self.S = int(c2i.size)
        self._rng = np.random.default_rng(cfg.seed)
        self.reset()

    # ------------------------------------------------------------ state

    def reset(self) -> None:
        """Forget every segment and novel id (ids restart at NOVEL_ID_START)."""
        self._mem: _Memory | None = None
        self._frames = 0
        self._last_recluster = -(10 ** 9)  # the first frame re-clusters
        self._next_uid = 0
        self._next_novel = NOVEL_ID_START
        self._novel_members: dict[int, np.ndarray] = {}  # novel id -> member uids
        self._last_counts: dict[int, int] = {}
        self._area_scale = 1.0
        self.last_segments: np.ndarray | None = None
        self.last_stamp_ns: int | None = None
        if self.fusion is not None:
            self.fusion.reset()

    _NOT_STATE = ("cfg", "mcl_cfg", "seg_cfg", "mod_cfg", "_novel_mcl", "fusion",
                  "channel_to_id", "S")

    def _made_for(self) -> dict:
        """What a saved state must match to be continued: the embedding's classes, the
        segment descriptor's make-up and the label fusion's voxels (thresholds may
        change between sessions)."""
        from ..params import to_dict

        fusion = None if self.fusion is None else (self.fusion.cfg.voxel_size,
                                                   self.fusion.cfg.coarse_voxel_size)
        return {"channel_to_id": [int(i) for i in self.channel_to_id],
                "modulation": to_dict(self.mod_cfg), "label_fusion_voxels": fusion}

    def state(self) -> dict:
        """Everything discovery has learnt (segment memory, clusters, novel ids, the label
        fusion) as plain data for :func:`.state.save_state`."""
        from .state import fields_state, fusion_state, to_plain

        return {"made_for": to_plain(self._made_for()),
                "discoverer": fields_state(self, self._NOT_STATE),
                "fusion": None if self.fusion is None else fusion_state(self.fusion)}

    def restore(self, state: dict) -> None:
        """Continue from :meth:`state`: the same novel ids for the same objects. A state
        made for other classes, descriptors or voxels is a ValueError naming it."""
        from .state import from_plain, restore_fields, restore_fusion

        want, got = self._made_for(), from_plain(state["made_for"])
        for key in want:
            if got.get(key) != want[key]:
                raise ValueError(f"the saved discovery state was made with {key} "
                                 f"{got.get(key)}, this configuration has {want[key]}")
        if (state["fusion"] is None) != (self.fusion is None):
            raise ValueError("the saved discovery state differs in label_fusion.enabled")
        restore_fields(self, state["discoverer"], {"_mem": _Memory})
        if self.fusion is not None:
            restore_fusion(self.fusion, state["fusion"])

    @property
    def novel_ids(self) -> list[int]:
        """The novel ids discovery holds now, ascending."""
        return sorted(self._novel_members)

    @property
    def memory_len(self) -> int:
        return 0 if self._mem is None else len(self._mem)

    def recluster_every(self) -> int:
        """Frames between two re-clusterings at the memory's present size
        (``recluster_period``, stretched by ``recluster_segments`` on a large memory)."""
        every = self.cfg.recluster_period
        if self.cfg.recluster_segments > 0 and self.memory_len > self.cfg.recluster_segments:
            every *= math.ceil((self.memory_len / self.cfg.recluster_segments) ** 2)
        return every

    # ------------------------------------------------------------ main entry

    def process(self, depth: np.ndarray, intrinsics: Intrinsics, embedding: np.ndarray,
                entropy: np.ndarray, stamp_ns: int = 0, colour: np.ndarray | None = None,
                features: np.ndarray | None = None, pose: np.ndarray | None = None
                ) -> np.ndarray:
        """Label one frame: (H, W) uint16 with known ids 1..13 and novel ids >= 100.

        ``colour`` (H, W, 3) uint8 RGB, optional, adds geoseg's colour edges;
        ``features`` (H, W, F), optional, the backbone's features for the descriptor
        (``modulation.feature_weight``); ``pose`` (4x4 camera-to-world), optional, fuses
        the labels in the voxel map of :mod:`fusion` (``label_fusion.enabled``)."""
        embedding = np.asarray(embedding)
        if embedding.ndim != 3 or embedding.shape[2] != self.S:
            raise ValueError(f"embedding must be (H, W, {self.S}) to match channel_to_id, got "
                             f"{embedding.shape}")
        if embedding.shape[:2] != np.asarray(depth).shape:
            raise ValueError(f"embedding is {embedding.shape[:2]} but depth is "
                             f"{np.asarray(depth).shape}")
        if pose is not None:  # checked before any state changes
            pose = check_pose(pose, "view pose")
        # The embedding, entropy and colour also cut segments where the appearance
        # changes (geoseg's appearance and colour edges): flush pictures, TVs, windows
        # and doors leave the wall.
        segments = segment_depth(depth, intrinsics, self.seg_cfg, embedding, entropy, colour)
        segments = self._uncertain_regions(segments, entropy)
        labels = self._label_segments(segments, embedding, entropy, colour, features,
                                      depth, intrinsics)
        if self.fusion is not None and pose is not None:
            labels = self.fusion.update(labels, depth, intrinsics, pose,
                                        set(self._novel_members))
        self._count(labels)
        self.last_stamp_ns = int(stamp_ns)
        return labels

    def _uncertain_regions(self, segments: np.ndarray, entropy: np.ndarray) -> np.ndarray:
        """Segments for large connected regions of uncertain pixels (``uncertain_region_*``):
        pixels without a segment and, with ``uncertain_region_carve``, pixels inside a
        segment that is confident on the whole.

        Why: the novel objects are where the embedding is unsure, but the depth
        segmentation does not see them all. A window's glazing bars, its noisy depth and
        its colour edges cut it into pieces below ``segmentation.min_segment_size``, which
        are dissolved, so the window had no segment and took the per-pixel argmax
        "wall". A picture flush with a wall whose frame is close to the wall's colour
        stays in the wall's segment, whose mean entropy is the wall's, so the picture
        was called wall as a whole (on tuning seed 502 walked for 150 s, 74 % of the
        pictures' pixels, at a mean normalised entropy of 0.92). Where the embedding is
        unsure over a large region, that region is evidence to cluster like any
        segment. The opening first drops thin bands of uncertainty along the borders of
        known objects, which are not objects.
        """
        if self.cfg.uncertain_region_px <= 0:
            return segments
        scale = segments.shape[1] / self.seg_cfg.reference_width
        area = self.cfg.uncertain_region_px * scale * scale
        ent = np.nan_to_num(np.asarray(entropy, np.float64), nan=0.0)
        candidate = segments < 0
        if self.cfg.uncertain_region_carve and segments.max() >= 0:
            ids = segments.ravel()
            inside = ids >= 0
            n = int(segments.max()) + 1
            mean = (np.bincount(ids[inside], weights=ent.ravel()[inside], minlength=n)
                    / np.maximum(np.bincount(ids[inside], minlength=n), 1))
            sure = mean <= self.cfg.entropy_threshold * np.log(self.S)
            candidate |= (segments >= 0) & sure[np.maximum(segments, 0)]
        hot = candidate & (ent > self.cfg.uncertain_region_entropy * np.log(self.S))
        k = max(1, int(round(self.cfg.uncertain_region_opening * scale))) | 1
        if k > 1:
            hot = cv2.morphologyEx(hot.astype(np.uint8), cv2.MORPH_OPEN,
                                   np.ones((k, k), np.uint8)).astype(bool)
        if not hot.any():
            return segments
        n, comp, stats, _ = cv2.connectedComponentsWithStats(hot.astype(np.uint8),
                                                              connectivity=4)
        big = stats[:, cv2.CC_STAT_AREA] >= max(area, 1)
        big[0] = False  # background
        if not big.any():
            return segments
        new_id = np.full(n, -1, np.int64)
        new_id[big] = int(segments.max()) + 1 + np.arange(int(big.sum()))
        return np.where(comp > 0, new_id[comp], segments).astype(segments.dtype)

    def process_segments(self, segments: np.ndarray, embedding: np.ndarray,
                         entropy: np.ndarray, colour: np.ndarray | None = None,
                         features: np.ndarray | None = None) -> np.ndarray:
        """As :meth:`process` but with a given segmentation (ids 0..n-1, -1 = none).

        ``colour`` feeds the descriptor's colour part (``modulation.colour_weight``),
        ``features`` its feature part (``modulation.feature_weight``)."""
        labels = self._label_segments(segments, embedding, entropy, colour, features)
        self._count(labels)
        return labels

    def _label_segments(self, segments: np.ndarray, embedding: np.ndarray,
                        entropy: np.ndarray, colour: np.ndarray | None,
                        features: np.ndarray | None, depth: np.ndarray | None = None,
                        intrinsics: Intrinsics | None = None) -> np.ndarray:
        """:meth:`process_segments` without counting the ids for :meth:`classes` (the
        caller counts the labels it publishes, after the label fusion)."""
        stats, mean_logit = segment_stats(
            segments, embedding, entropy, self.mod_cfg.entropy_interior,
            colour if self.mod_cfg.colour_weight > 0 else None,
            features if self.mod_cfg.feature_weight > 0 else None,
            *((depth, intrinsics) if self.mod_cfg.area_weight > 0 else (None, None)))
        desc = descriptors_from_stats(stats, mean_logit, self.mod_cfg)
        if self._mem is not None and desc.shape[1] != self._mem.desc.shape[1]:
            raise ValueError(f"segment descriptors of {desc.shape[1]} values, the memory's "
                             f"have {self._mem.desc.shape[1]}: every frame must come with "
                             "features or none")
        present = stats.pixels > 0
        n = int(stats.pixels.size)
        new = _Memory(uid=np.arange(self._next_uid, self._next_uid + n, dtype=np.int64),
                      frame=np.full(n, self._frames, np.int64), desc=desc,
                      pixels=stats.pixels, ent_sum=stats.mean_entropy * stats.pixels,
                      hist=stats.argmax_hist, cluster=np.full(n, UNDECIDED, np.int64))
        self._next_uid += n
        # uncertain_cluster_pixels is given at the reference width, as the segmentation's sizes.
        self._area_scale = (segments.shape[1] / self.seg_cfg.reference_width) ** 2
        new = new.take(np.flatnonzero(present))
        if self._mem is None:
            self._mem = _Memory.empty(desc.shape[1], self.S)
        if self._frames - self._last_recluster >= self.recluster_every():
            self._mem = self._thin(self._mem.extend(new))
            self._recluster()
            self._last_recluster = self._frames
        else:
            new.cluster = self._nearest_cluster(new)
            self._mem = self._thin(self._mem.extend(new))
        self._frames += 1
        # Labels of this frame's segments, by uid.
        seg_label = np.full(n, UNDECIDED, np.int64)
        mine = self._mem.frame == self._frames - 1
        seg_label[self._mem.uid[mine] - (self._next_uid - n)] = self._mem.cluster[mine]
        labels = self._paint(segments, seg_label, embedding, entropy)
        self.last_segments = segments
        return labels

    def _count(self, labels: np.ndarray) -> None:
        """Pixels per id of the last labelled frame, for :meth:`classes`."""
        ids, counts = np.unique(labels, return_counts=True)
        self._last_counts = dict(zip(ids.tolist(), counts.tolist()))

    # ------------------------------------------------------------ memory

    def _thin(self, mem: _Memory) -> _Memory:
        """Drop random old segments beyond ``memory_size`` (recent frames are kept)."""
        excess = len(mem) - self.cfg.memory_size
        if excess <= 0:
            return mem
        old = np.flatnonzero(mem.frame < self._frames - self.cfg.recent_frames + 1)
        if old.size == 0:
            return mem
        drop = self._rng.choice(old, size=min(excess, old.size), replace=False)
        keep = np.ones(len(mem), bool)
        keep[drop] = False
        return mem.take(np.flatnonzero(keep))

    # ------------------------------------------------------------ clustering

    def _recluster(self) -> None:
        mem = self._mem
        if len(mem) == 0:
            return
        clusters = markov_cluster(mem.desc, self.mcl_cfg) if len(mem) > 1 else np.zeros(1, int)
        if self.cfg.segment_novelty:
            clusters = self._split_uncertain(clusters)
        mem.cluster = self.name_clusters(clusters)

    def _uncertain(self, mem: _Memory) -> np.ndarray:
        """(N,) bool: the segments whose mean entropy is above the known/novel threshold."""
        return (mem.ent_sum / np.maximum(mem.pixels, 1)
                > self.cfg.entropy_threshold * np.log(self.S))

    def _split_uncertain(self, clusters: np.ndarray) -> np.ndarray:
        """Take the segments above the entropy threshold out of their clusters and
        cluster them among themselves: a confident majority cannot absorb them."""
        mem = self._mem
        unsure = np.flatnonzero(self._uncertain(mem))
        if unsure.size == 0 or unsure.size == len(mem):
            return clusters
        out = np.asarray(clusters, np.int64).copy()
        sub = (markov_cluster(mem.desc[unsure], self._novel_mcl) if unsure.size > 1
               else np.zeros(1, np.int64))
        out[unsure] = out.max() + 1 + sub
        _, out = np.unique(out, return_inverse=True)
        return out.astype(np.int64)

    def name_clusters(self, clusters: np.ndarray) -> np.ndarray:
        """Per memory segment label (known id, stable novel id or UNDECIDED) from cluster ids.

        Updates the novel-id bookkeeping; cluster numbering does not matter.
        """
        mem = self._mem
        cfg = self.cfg
        clusters = np.asarray(clusters, np.int64)
        m = int(clusters.max()) + 1 if clusters.size else 0
        pix = np.bincount(clusters, weights=mem.pixels, minlength=m)
        ent = np.bincount(clusters, weights=mem.ent_sum, minlength=m) / np.maximum(pix, 1)
        hist = np.zeros((m, self.S))
        np.add.at(hist, clusters, mem.hist)
        share = hist.max(axis=1) / np.maximum(hist.sum(axis=1), 1)
        nseg = np.bincount(clusters, minlength=m)
        known = (ent <= cfg.entropy_threshold * np.log(self.S)) & (share >= cfg.majority_share)
        # Pixel-weighted mean descriptor per cluster (the mode split and the merge use it).
        cent = _weighted_means(clusters, mem.desc, mem.pixels, m)
        if cfg.mode_split:
            known &= ~self._distinct_modes(known, hist.argmax(axis=1), pix, cent)
        enough = pix >= cfg.min_cluster_pixels
        if cfg.uncertain_cluster_pixels > 0:  # stronger evidence, smaller clusters
            oldest = np.full(m, np.iinfo(np.int64).max)
            np.minimum.at(oldest, clusters, mem.frame)
            enough |= ((ent > cfg.uncertain_region_entropy * np.log(self.S))
                       & (pix >= cfg.uncertain_cluster_pixels * self._area_scale)
                       & (oldest >= self._frames - cfg.uncertain_cluster_frames))
        novel = ~known & (nseg >= cfg.min_cluster_segments) & enough
        cluster_label = np.full(m, UNDECIDED, np.int64)
        cluster_label[known] = self.channel_to_id[hist[known].argmax(axis=1)]
        novel_idx = np.flatnonzero(novel)
        group = self._novel_groups(cent[novel_idx])
        ids = self._match_novel([mem.uid[np.isin(clusters, novel_idx[group == g])]
                                 for g in range(int(group.max()) + 1 if group.size else 0)])
        cluster_label[novel_idx] = ids[group]
        return cluster_label[clusters]

    def _novel_groups(self, cent: np.ndarray) -> np.ndarray:
        """Group number 0..g-1 per novel cluster, given their mean descriptors ``cent``:
        average-link agglomeration cut at ``novel_merge_distance`` (each cluster its own
        group when the distance is 0).

        Why average link, not single link: on a long run the memory holds dozens of novel
        clusters, and pieces between two objects (a segment half picture, half wall) put
        a chain of clusters each within the distance of the next from one novel class to
        another. Single link followed such chains and gave a picture, a window and the
        ceiling one id (tuning seed 500 walked for 150 s: novel mIoU 21 with single link at
        ``novel_inflation`` 1.4); average link joins two groups only when they are close
        on the whole."""
        k = len(cent)
        if k < 2 or self.cfg.novel_merge_distance <= 0:
            return np.arange(k, dtype=np.int64)
        from scipy.cluster.hierarchy import fcluster, linkage

        tree = linkage(np.asarray(cent, np.float64), method="average")
        group = fcluster(tree, t=self.cfg.novel_merge_distance, criterion="distance")
        _, group = np.unique(group, return_inverse=True)
        return group.astype(np.int64)

    def _distinct_modes(self, known: np.ndarray, channel: np.ndarray, pix: np.ndarray,
                        cent: np.ndarray) -> np.ndarray:
        """(m,) bool: known clusters that are a separate, small mode of their class
        (``cent``: the clusters' pixel-weighted mean descriptors).

        Why: a picture or window on a wall is confidently "wall" to the backbone, so
        its cluster passes the entropy and majority tests; but it is its own cluster,
        far (in descriptor space, colour included) from the wall's dominant cluster
        and much smaller. A class that merely varies forms clusters close to its
        dominant one, or of comparable size, and stays known.
        """
        out = np.zeros(len(known), bool)
        for ch in np.unique(channel[known]).tolist():
            idx = np.flatnonzero(known & (channel == ch))
            if idx.size < 2:
                continue
            dom = idx[np.argmax(pix[idx])]
            rest = idx[idx != dom]
            far = np.linalg.norm(cent[rest] - cent[dom], axis=1) > self.cfg.mode_split_distance
            small = pix[rest] <= self.cfg.mode_split_share * pix[dom]
            out[rest[far & small]] = True
        return out

    def _match_novel(self, members: list[np.ndarray]) -> np.ndarray:
        """Stable ids for novel clusters given their member uids (Hungarian on overlap)."""
        prev_ids = np.array(sorted(self._novel_members), np.int64)
        out = np.full(len(members), -1, np.int64)
        if len(members) and prev_ids.size:
            prev_uid = np.concatenate([self._novel_members[i] for i in prev_ids.tolist()])
            prev_idx = np.repeat(np.arange(prev_ids.size),
                                 [self._novel_members[i].size for i in prev_ids.tolist()])
            live = np.isin(prev_uid, self._mem.uid)
            prev_uid, prev_idx = prev_uid[live], prev_idx[live]
            prev_size = np.bincount(prev_idx, minlength=prev_ids.size)
            order = np.argsort(prev_uid)
            prev_uid, prev_idx = prev_uid[order], prev_idx[order]
            new_uid = np.concatenate(members)
            new_idx = np.repeat(np.arange(len(members)), [m.size for m in members])
            pos = np.clip(np.searchsorted(prev_uid, new_uid), 0, max(prev_uid.size - 1, 0))
            hit = (prev_uid.size > 0) & (prev_uid[pos] == new_uid) if prev_uid.size else \
                np.zeros(new_uid.size, bool)
            overlap = np.zeros((len(members), prev_ids.size))
            np.add.at(overlap, (new_idx[hit], prev_idx[pos[hit]]), 1)
            r, c = linear_sum_assignment(-overlap)
            for i, j in zip(r, c):
                smaller = min(members[i].size, prev_size[j])
                if overlap[i, j] > 0 and overlap[i, j] >= self.cfg.match_overlap * smaller:
                    out[i] = prev_ids[j]
        # Fresh ids in a deterministic order: by smallest member uid.
        firsts = [int(m.min()) if m.size else -1 for m in members]
        for i in np.argsort(firsts, kind="stable").tolist():
            if out[i] < 0:
                out[i] = self._next_novel
                self._next_novel += 1
        self._novel_members = {int(out[i]): members[i] for i in range(len(members))}
        return out

    def _nearest_cluster(self, new: _Memory) -> np.ndarray:
        """Labels for segments arriving between re-clusterings: the cluster with the
        nearest (Euclidean, as Markov clustering's affinity) pixel-weighted mean
        descriptor. With ``segment_novelty``, an uncertain segment (mean entropy above
        the threshold) joins only among the clusters of uncertain segments, and a
        confident one among those of confident segments, as a re-clustering would
        place them (either kind joins any cluster while the memory has none of its own).

        Why: past ``recluster_segments`` most frames are labelled this way (eight of
        nine at the memory cap). Nearest by cosine over every cluster put a picture's
        new segments into the wall's cluster, and on tuning seed 500 walked for 300 s
        the novel mIoU of each 25-frame window after the cap fell to 10-34; labelled as
        a re-clustering would, it stays at 36-51, as with re-clustering every frame
        (``recluster_segments`` 0), for a fraction of the time."""
        mem = self._mem
        if len(mem) == 0 or len(new) == 0:
            return np.full(len(new), UNDECIDED, np.int64)
        out = np.full(len(new), UNDECIDED, np.int64)
        if self.cfg.segment_novelty:
            mem_unsure, new_unsure = self._uncertain(mem), self._uncertain(new)
            kinds = [(mem_unsure == k, np.flatnonzero(new_unsure == k)) for k in (False, True)]
        else:
            kinds = [(np.ones(len(mem), bool), np.arange(len(new)))]
        for pool, todo in kinds:
            if todo.size == 0:
                continue
            if not pool.any():
                pool = np.ones(len(mem), bool)
            labs, inv = np.unique(mem.cluster[pool], return_inverse=True)
            cent = _weighted_means(inv, mem.desc[pool], mem.pixels[pool], labs.size)
            dist = np.linalg.norm(new.desc[todo, None, :] - cent[None], axis=2)
            out[todo] = labs[np.argmin(dist, axis=1)]
        return out

    # ------------------------------------------------------------ output

    def _paint(self, segments: np.ndarray, seg_label: np.ndarray, embedding: np.ndarray,
               entropy: np.ndarray | None = None) -> np.ndarray:
        """Label image: segment labels, per-pixel argmax known class elsewhere; with
        ``pixel_known``, confident pixels of a known segment keep their own known class;
        with ``novel_fill_px``, uncertain pixels without a segment near a novel label take it.

        Why ``pixel_known``: a depth segment can straddle two known objects (a chair
        and the floor it stands on) and its cluster's label is its majority; where the
        embedding is sure of a pixel (the same test that calls a cluster known), the
        pixel's own class is the better label.

        Why the fill: colour and geometry edges, and pieces too small to be a segment,
        leave bands of pixels without a segment inside and around a novel object (a
        window's glazing bars, a picture's frame); their argmax is the backbone's
        "wall", so the object would be cut up and its id would cover a different part
        in every frame. Pixels the embedding itself is unsure of (entropy above the
        known/novel threshold) belong with the nearest novel label instead; with
        ``novel_fill_known`` also those inside a known segment, whose label is the
        segment's majority and says nothing about its uncertain minority.
        """
        finite = np.all(np.isfinite(embedding), axis=2)
        fallback = np.where(finite, self.channel_to_id[np.argmax(
            np.nan_to_num(embedding, nan=-np.inf), axis=2)], 0).astype(np.uint16)
        lab = np.where(segments >= 0, seg_label[np.maximum(segments, 0)] if seg_label.size
                       else UNDECIDED, UNDECIDED)
        out = np.where(lab > 0, lab, fallback).astype(np.uint16)
        limit = self.cfg.entropy_threshold * np.log(self.S)
        if self.cfg.pixel_known and entropy is not None:
            sure = np.nan_to_num(entropy, nan=np.inf) < limit
            own = sure & (lab > 0) & (lab < NOVEL_ID_START) & (fallback > 0)
            out[own] = fallback[own]
        reach = self.cfg.novel_fill_px * segments.shape[1] / self.seg_cfg.reference_width
        if reach <= 0 or entropy is None:
            return out
        novel = out >= NOVEL_ID_START
        hot = np.nan_to_num(entropy, nan=0.0) > limit
        hot &= (lab < NOVEL_ID_START) if self.cfg.novel_fill_known else (lab <= 0)
        if not novel.any() or not hot.any():
            return out
        dist, near = cv2.distanceTransformWithLabels((~novel).astype(np.uint8), cv2.DIST_L2,
                                                     5, labelType=cv2.DIST_LABEL_PIXEL)
        # Distance-transform label -> flat index of its novel pixel.
        src = np.flatnonzero(novel.ravel())
        owner = np.zeros(int(near.max()) + 1, np.int64)
        owner[near.ravel()[src]] = src
        take = hot & (dist <= reach)
        out[take] = out.ravel()[owner[near[take]]]
        return out

    def classes(self, labels: np.ndarray | None = None) -> dict[int, dict]:
        """{id: {"name", "kind": "known"|"novel", "pixels"}}: the ids of the last labelled
        frame and every novel id discovery holds; ``pixels`` counted in ``labels``, the
        last frame's labels as published (scaled to the view's size), or else as labelled."""
        if labels is not None:
            self._count(labels)
        ids = set(self._last_counts) | set(self._novel_members)
        ids.discard(0)
        if self.fusion is not None:  # ids published under another id are not classes
            ids -= set(self.fusion.aliases)
        return {i: {"name": class_name(i), "kind": "novel" if i >= NOVEL_ID_START else "known",
                    "pixels": int(self._last_counts.get(i, 0))} for i in sorted(ids)}
