"""Embedding stage: colour + depth of a frame in, the backbone's semantic embedding out.

Online, colour and depth are paired by stamp (:class:`..sync.StampSync`) and
the newest pair is embedded first: a pair that arrives while the backbone is
busy replaces the one waiting (counted as ``busy``), so the embedding is never
late by more than one frame. ``max_rate_hz`` embeds at most that many frames
per second of stamp time: the mapper needs only keyframes and the frames it
renders, and on 2 cores a 30 Hz backbone would take a whole core from the
field. Offline the same rate gate (by stamp, so deterministic) picks the same
frames.
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np

from ..params import param
from ..sync import StampSync, max_jump_param
from .health import Health, report_starved, sync_reporter
from .records import EmbeddingRecord, EmbeddingSpec

MAX_LOGIT = 1.0e4
"""Beyond this a logit is a diverged net's (a trained one's stay within tens): the frame is
refused with that reason, not stored as float16 infinities that fail every later stage."""


@dataclasses.dataclass(frozen=True)
class EmbeddingNodeConfig:
    """The embedding stage (the backbone itself is under `backbone`)."""

    max_rate_hz: float = param(10.0, "embed at most this many frames per second of stamp "
                               "time (0 = every frame): the mapper needs only keyframes and "
                               "the views it renders", lo=0.0, hi=1000.0, unit="Hz")
    output_scale: float = param(0.0, "published embedding size relative to the frame (the "
                                "mapper reads it at any size of the same aspect). 0: as wide "
                                "as the backbone's input (at most the frame), the resolution "
                                "the network saw, so nothing is lost: a 640x480 frame's "
                                "embedding is published at 320x240 with the default backbone, "
                                "a quarter of the DDS traffic and of the mapper's keyframe "
                                "memory; 1: the frame's size", lo=0.0, hi=1.0)
    sync_tolerance_ms: float = param(5.0, "max stamp difference to pair colour and depth",
                                     lo=0.0, hi=1000.0, unit="ms")
    sync_horizon_s: float = param(1.0, "how long a colour or depth image waits for its "
                                  "partner", lo=0.01, hi=60.0, unit="s")
    sync_max_jump_s: float = max_jump_param()
    queue_size: int = param(5, "subscription depth; older frames are dropped", lo=1, hi=100)
    log_throttle_s: float = param(5.0, "min seconds between repeated reports of one kind "
                                  "of problem", lo=0.0, hi=3600.0, unit="s")


class EmbeddingStage:
    """Pairs colour and depth, keeps the newest pair, runs the backbone on it."""

    def __init__(self, backbone, cfg: EmbeddingNodeConfig = EmbeddingNodeConfig(),
                 health: Health | None = None) -> None:
        self.backbone = backbone
        self.cfg = cfg
        self.spec: EmbeddingSpec = backbone.spec
        self.health = health or Health("embedding", throttle_s=cfg.log_throttle_s)
        self.stream_topics: dict[str, str] = {}  # stream -> topic, named in the reports
        self.sync = StampSync(("depth", "color"), int(cfg.sync_tolerance_ms * 1e6),
                              cfg.sync_horizon_s, capacity=max(2, 3 * cfg.queue_size),
                              on_anomaly=sync_reporter(self.health),
                              max_jump_ns=int(cfg.sync_max_jump_s * 1e9))
        self.input_width = int(backbone.input_size[0])  # the width the network runs at
        self._lock = threading.Lock()
        self._latest: tuple[int, np.ndarray, np.ndarray] | None = None
        self._last_stamp: int | None = None
        self.health.set_state("waiting", "no colour+depth pair yet")

    # ------------------------------------------------------------ online input
    def offer(self, stream: str, stamp_ns: int, image: np.ndarray) -> bool:
        """A colour (rgb uint8) or depth (float32 m) image; True when it completed a pair
        that is now waiting to be embedded."""
        with self._lock:
            groups = self.sync.add(stream, stamp_ns, image)
            got = False
            for stamp, g in groups:
                self.health.count("pairs")
                if not self.wanted(stamp):
                    self.health.count("skipped_rate")
                    continue
                if self._latest is not None:
                    self.health.count("dropped_busy")
                self._latest = (stamp, g["color"], g["depth"])
                got = True
            starved = self.sync.starved()
        report_starved(self.health, starved, self.cfg.sync_tolerance_ms,
                       "images do (check the topic names and that stamps agree",
                       self.stream_topics)
        return got

    def take(self) -> tuple[int, np.ndarray, np.ndarray] | None:
        """The newest waiting pair (stamp, rgb, depth), or None. The rate gate counts from
        the pair taken: pairs that arrive while the backbone embeds it are gated against
        its stamp, not against the previous embedding's (which let through the next frame
        or two of a 30 Hz camera, 13-15 embeddings a second at ``max_rate_hz`` 10, where
        offline, embedding each pair as it passes the gate, takes every third frame)."""
        with self._lock:
            job, self._latest = self._latest, None
            if job is not None:
                self._last_stamp = int(job[0])
            return job

    @property
    def pending(self) -> int:
        with self._lock:
            return int(self._latest is not None)

    def wanted(self, stamp_ns: int) -> bool:
        """The rate gate: embed this stamp? (at most max_rate_hz by stamp time; a stamp that
        goes back restarts the gate, as a looped bag does)."""
        if self.cfg.max_rate_hz <= 0 or self._last_stamp is None:
            return True
        gap = (stamp_ns - self._last_stamp) * 1e-9
        # 10 % slack so a 30 Hz stream gated at 10 Hz takes every third frame.
        return gap < 0 or gap >= 0.9 / self.cfg.max_rate_hz

    # ------------------------------------------------------------ the work
    def embed(self, stamp_ns: int, rgb: np.ndarray, depth: np.ndarray) -> EmbeddingRecord:
        """Run the backbone (ValueError on bad input, e.g. sizes that disagree)."""
        if rgb.shape[:2] != depth.shape:
            raise ValueError(f"colour is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                             f"{depth.shape[1]}x{depth.shape[0]}: depth must be registered "
                             "to colour")
        h, w = depth.shape
        s = self.cfg.output_scale
        if s == 0.0:  # at the backbone's resolution, at most the frame's
            s = self.input_width / w if self.input_width < w else 1.0
        # The network's output interpolated once, to the published size (a resize of the
        # frame-size embedding after it would cost a second pass, and OpenCV's area
        # resize refuses more than 4 channels at a scale that is no integer ratio).
        emb = (self.backbone.embed(rgb, depth) if s == 1.0 else
               self.backbone.embed(rgb, depth, size=(max(1, round(h * s)),
                                                     max(1, round(w * s)))))
        logits = emb[..., : self.spec.logit_channels]
        peak = float(np.max(np.abs(logits))) if logits.size else 0.0
        if not peak <= MAX_LOGIT:  # NaN too
            raise ValueError(
                f"the backbone's logits reach {peak:.3g} (a sane net's stay within tens; the "
                f"keyframes hold them as float16, which ends at 65504): the "
                f"{self.spec.backbone or 'backbone'} checkpoint looks diverged in training; "
                "retrain it with a lower learning rate (train-backbone --lr)")
        self._last_stamp = int(stamp_ns)
        self.health.count("embedded")
        self.health.set_state("running")
        return EmbeddingRecord(int(stamp_ns), np.ascontiguousarray(emb, np.float32), self.spec)
