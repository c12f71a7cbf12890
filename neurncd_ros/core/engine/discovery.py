"""Discovery stage: a view (depth, colour, pose, rendered embedding, entropy) in, labels out.

Online the pieces of a view arrive as messages with one stamp, published
together by the mapper, so they pair at once; complete views wait in a
bounded first-in first-out queue (the mapper's flow control keeps it short).
The embedding's meaning (which NYU-13 class each logit channel predicts) comes
with the view as its :class:`EmbeddingSpec`; a view that arrives before the
spec is known waits for it (``spec_wait_s``) rather than being guessed.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import threading
import time
from typing import Any, Callable

import cv2
import numpy as np

from ..camera import Intrinsics
from ..params import param
from ..sync import StampSync, max_jump_param
from .health import Health, sync_reporter
from .views import resize_to
from .records import EmbeddingSpec, LabelsRecord, ViewRecord


@dataclasses.dataclass(frozen=True)
class DiscoveryNodeConfig:
    """The discovery stage (the science is under `segmentation`, `modulation`, `mcl` and
    `discovery`)."""

    queue_size: int = param(8, "complete views waiting to be labelled at most (the oldest "
                            "is dropped beyond)", lo=1, hi=1000)
    sync_tolerance_ms: float = param(1.0, "max stamp difference between the messages of one "
                                     "view (the mapper stamps them alike)", lo=0.0, hi=1000.0,
                                     unit="ms")
    sync_horizon_s: float = param(10.0, "how long a piece of a view waits for the rest",
                                  lo=0.01, hi=600.0, unit="s")
    sync_max_jump_s: float = max_jump_param()
    work_width: int = param(320, "label views wider than this at this width (depth, "
                            "embedding, entropy and colour scaled down; the labels scaled "
                            "back up to the view's size, nearest): discovery's time grows "
                            "with the pixels, and its defaults were tuned on 320x240 views. "
                            "Tuning seeds 500-503 at 640x480, 150 frames: all-class mIoU "
                            "78.8 at 320 against 76.5 at the full 640 (80.5 for the same "
                            "scenes at 320x240), discovery about 3 times faster; 0 = at the "
                            "view's own size", lo=0, hi=8192, unit="px")
    spec_wait_s: float = param(30.0, "how long views wait for the embedding spec before "
                               "they are dropped", lo=0.0, hi=3600.0, unit="s")
    state_path: str = param("", "discovery state file: loaded at start if it exists (a "
                            "restarted node keeps its novel ids for the same objects), saved "
                            "every save_period_s and at shutdown; neurncd run loads it and "
                            "saves it at the end ('' = none: each start numbers novel "
                            "classes from 100 again)")
    save_period_s: float = param(30.0, "with state_path: save the state at most this often "
                                 "when views were labelled since the last save, also while "
                                 "no view comes (so a node killed after its input stopped "
                                 "keeps what it discovered); 0 = only at shutdown",
                                 lo=0.0, hi=86400.0, unit="s")
    log_throttle_s: float = param(5.0, "min seconds between repeated reports of one kind of "
                                  "problem", lo=0.0, hi=3600.0, unit="s")


@dataclasses.dataclass
class ViewInput:
    """A view as discovery needs it: what arrives over ROS. The pose (camera-to-world)
    feeds the label fusion (``fusion``); None labels the view on its own."""

    stamp_ns: int
    depth: np.ndarray
    intrinsics: Intrinsics
    embedding: np.ndarray
    entropy: np.ndarray
    rgb: np.ndarray | None
    keyframe: bool = False
    arrived: float = 0.0
    pose: np.ndarray | None = None

    @classmethod
    def of(cls, view: ViewRecord) -> "ViewInput":
        f = view.frame
        return cls(f.stamp_ns, view.view_depth, f.intrinsics, view.embedding, view.entropy, f.rgb,
                   view.keyframe, pose=f.pose)


class DiscoveryStage:
    """Segments, modulates, clusters and names; one Discoverer per embedding spec."""

    STREAMS = ("depth", "embedding", "entropy", "color", "info", "pose")

    def __init__(self, cfg, node_cfg: DiscoveryNodeConfig = DiscoveryNodeConfig(),
                 health: Health | None = None, clock: Callable[[], float] = time.monotonic
                 ) -> None:
        """``cfg``: an object with the ``discovery``, ``mcl``, ``segmentation`` and
        ``modulation`` sections (the whole configuration will do)."""
        self.cfg = cfg
        self.node_cfg = node_cfg
        self._clock = clock
        self.health = health or Health("discovery", throttle_s=node_cfg.log_throttle_s,
                                       clock=clock)
        self.sync = StampSync(self.STREAMS, int(node_cfg.sync_tolerance_ms * 1e6),
                              node_cfg.sync_horizon_s, capacity=4 * node_cfg.queue_size,
                              clock=clock, on_anomaly=sync_reporter(self.health),
                              max_jump_ns=int(node_cfg.sync_max_jump_s * 1e9))
        self.spec: EmbeddingSpec | None = None
        self.discoverer = None
        self._queue: collections.deque[ViewInput] = collections.deque()
        # A saved state (state_path) waits for the embedding spec, which makes the
        # discoverer; a file that cannot be read is an error here, at start.
        self._saved_state = None
        self.continued: list[int] | None = None  # the novel ids a loaded state brought
        self._last_save = clock()
        self._unsaved = False  # labelled since the last save
        self.state_refused: str | None = None  # why a loaded state was not continued
        path = node_cfg.state_path
        if path:
            from ..torchfile import check_save_path
            check_save_path(path, "discovery_node.state_path")
        if path and os.path.isfile(path):
            from ..discovery.state import load_state
            self._saved_state = load_state(path)
        self._lock = threading.Lock()
        self.health.set_state("waiting", "no view yet")

    def _new_discoverer(self, spec: EmbeddingSpec):
        from ..discovery.labeller import Discoverer

        c = self.cfg
        return Discoverer(c.discovery, spec.ids(), mcl_cfg=c.mcl, seg_cfg=c.segmentation,
                          mod_cfg=c.modulation, fusion_cfg=c.label_fusion)

    def reset(self) -> None:
        """Forget what was discovered (segment memory, clusters, novel ids, label fusion):
        a new room. Novel ids start from 100 again; the next save overwrites the state
        file. Call it from the thread that labels."""
        if self.spec is not None:
            self.discoverer = self._new_discoverer(self.spec)
            self._unsaved = True
        self.health.count("resets")

    def set_spec(self, spec: EmbeddingSpec) -> None:
        """The meaning of the embedding channels; a new spec starts a new discovery."""
        if spec != self.spec:
            if self.spec is not None:
                self.health.problem("spec_changed", f"embedding spec changed from "
                                    f"{self.spec.to_json()} to {spec.to_json()}: "
                                    "discovery restarts")
            self.discoverer = self._new_discoverer(spec)
            self.spec = spec
            saved, self._saved_state = self._saved_state, None
            if saved is not None:
                try:
                    self.discoverer.restore(saved["discovery"])
                except (KeyError, ValueError) as err:
                    path = self.node_cfg.state_path
                    kept = path + ".not-continued"
                    try:  # a mistyped parameter must not cost the ids saved in it
                        os.replace(path, kept)
                        where = f"kept as {kept}"
                    except OSError as move_err:
                        where = f"could not be kept aside ({move_err})"
                    self.state_refused = f"{err}; the file is {where}"
                    self.health.problem("state_not_continued", f"{path}: not continued "
                                        f"({err}); discovery starts afresh, the saved state "
                                        f"is {where}", level=2)
                else:
                    d = self.discoverer
                    self.continued = d.novel_ids
                    self.health.note("state", f"continued discovery state "
                                     f"{self.node_cfg.state_path}: {d.memory_len} segments, "
                                     f"novel ids {d.novel_ids}")

    def save_state(self, force: bool = True) -> bool:
        """Save the discovery state to ``state_path`` (unless ``force``, only when a view was
        labelled since the last save and ``save_period_s`` has passed); False when there is
        no path, nothing learnt yet or nothing new. Call it from the thread that labels:
        the node calls it after each view and while idle, so what was discovered just
        before the input stopped is saved within the period, not only at shutdown."""
        path = self.node_cfg.state_path
        if not path or self.discoverer is None:
            return False
        now = self._clock()
        period = self.node_cfg.save_period_s
        if not force and (not self._unsaved or period <= 0
                          or now - self._last_save < period):
            return False
        from ..discovery.state import save_state

        saved = self.discoverer
        save_state(path, {"discovery": saved.state()})
        self._last_save = now
        # A reset (the node's service thread) during the write leaves it unsaved: the
        # file holds the old room until the next due save writes the new start.
        self._unsaved = self.discoverer is not saved
        self.health.count("state_saves")
        return True

    # ------------------------------------------------------------ online input
    def offer(self, stream: str, stamp_ns: int, value: Any) -> bool:
        """One piece of a view; True when a view is complete and queued."""
        with self._lock:
            groups = self.sync.add(stream, stamp_ns, value)
            for stamp, g in groups:
                self.health.count("views_received")
                item = ViewInput(stamp, g["depth"], g["info"], g["embedding"], g["entropy"],
                                 g["color"], arrived=self._clock(), pose=g["pose"])
                self._queue.append(item)
                if len(self._queue) > self.node_cfg.queue_size:
                    old = self._queue.popleft()
                    self.health.problem("queue_full", f"view {old.stamp_ns} dropped: more "
                                        f"than {self.node_cfg.queue_size} views wait")
            return bool(groups)

    def take(self) -> ViewInput | None:
        """The oldest complete view ready to label (None while the spec is unknown)."""
        with self._lock:
            if not self._queue:
                return None
            if self.spec is None:
                old = self._queue[0]
                if self._clock() - old.arrived > self.node_cfg.spec_wait_s:
                    self._queue.popleft()
                    self.health.problem("no_spec", f"view {old.stamp_ns} dropped: no "
                                        "embedding spec received (is the embedding node "
                                        "running?)")
                return None
            return self._queue.popleft()

    @property
    def pending(self) -> int:
        with self._lock:
            return len(self._queue)

    # ------------------------------------------------------------ the work
    def label(self, view: ViewInput) -> LabelsRecord:
        """Label one view at its depth frame's size (ValueError on inconsistent input)."""
        if self.spec is None:
            raise ValueError("no embedding spec: the meaning of the channels is unknown")
        spec = self.spec
        depth = np.asarray(view.depth, np.float32)
        if depth.ndim != 2:
            raise ValueError(f"depth must be (H, W), got {depth.shape}")
        if view.intrinsics.shape != depth.shape:
            raise ValueError(f"depth is {depth.shape[1]}x{depth.shape[0]} but its camera info "
                             f"says {view.intrinsics.width}x{view.intrinsics.height}")
        emb = spec.check(view.embedding, "rendered embedding")
        ent = np.asarray(view.entropy, np.float32)
        if ent.shape != emb.shape[:2]:
            raise ValueError(f"entropy is {ent.shape} but the embedding is {emb.shape[:2]}")
        if not (np.all(np.isfinite(emb)) and np.all(np.isfinite(ent))):
            raise ValueError("rendered embedding or entropy has non-finite values")
        full = depth.shape
        intrinsics = view.intrinsics
        if 0 < self.node_cfg.work_width < full[1]:
            s = self.node_cfg.work_width / full[1]
            size = (max(1, round(full[0] * s)), self.node_cfg.work_width)
            depth = resize_to(depth, *size, cv2.INTER_NEAREST)  # no depths mixed at edges
            intrinsics = intrinsics.scaled(size[1], size[0])
        h, w = depth.shape
        logits = resize_to(np.ascontiguousarray(emb[..., : spec.logit_channels], np.float32),
                           h, w)
        ent = resize_to(ent, h, w)
        rgb = None
        if view.rgb is not None and (self.cfg.segmentation.colour_edges
                                     or self.cfg.modulation.colour_weight > 0):
            rgb = view.rgb
            if rgb.shape[:2] != (h, w):
                rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
        features = None
        if spec.feature_channels and self.cfg.modulation.feature_weight > 0:
            features = resize_to(np.ascontiguousarray(emb[..., spec.logit_channels:],
                                                      np.float32), h, w)
        labels = self.discoverer.process(depth, intrinsics, logits, ent, view.stamp_ns,
                                         rgb, features, view.pose)
        self._unsaved = True
        if labels.shape != full:
            labels = cv2.resize(labels, (full[1], full[0]), interpolation=cv2.INTER_NEAREST)
        self.health.count("labelled")
        self.health.set_state("running")
        return LabelsRecord(view.stamp_ns, labels, self.discoverer.classes(labels),
                            view.keyframe)

    def label_view(self, view: ViewRecord) -> LabelsRecord:
        """Offline: label a view record from the mapper stage directly."""
        self.set_spec(view.spec)
        return self.label(ViewInput.of(view))
