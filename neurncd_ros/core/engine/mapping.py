"""Mapper stage: frames with their embedding in, keyframes to the field, views out.

(One module, over 500 lines: the stage's pairing, keyframe queue and rendering share one
lock and one set of queues, and its documented parameters sit beside the code they steer.)

Which views are rendered, in this order (``next_view``):

1. every keyframe the field admits (a keyframe's view is rendered and
   published with its own colour, depth and intrinsics, so discovery always has
   what it needs, however late it is; only when more than
   ``max_queued_keyframes`` wait is the oldest dropped, reported as
   ``keyframes_dropped``);
2. otherwise the newest frame: a frame (or keyframe) that arrives before the previous
   one was rendered replaces it (counted ``skipped_newer``), and a frame that waited
   longer than ``stale_after_s`` is dropped (``skipped_stale``). Frames that
   are not rendered are not labelled; the count is in the diagnostics.

A view is rendered at the frame's pose with its measured depth (depth-guided
samples) at ``render_scale``. Where the field has not learnt the scene yet,
it would render noise, and noise has high entropy, i.e. looks novel. So the
view blends the field with the frame's own backbone embedding by *coverage*:
the highest maturity among the keyframes that see a pixel's 3D point
(projection and depth test), a keyframe's maturity being its training
iterations since admission / ``mature_iterations`` (at most 1); at
``full_coverage`` the field alone is used. The first views of a new scene are
therefore the backbone's, and the field takes over where it has been trained.
That blending is off by default (``field_views``): the mature field labels worse
than the keyframe fusion below, which is the mean its KL fit converges to, and its
render costs ten times the fusion, so on a bag of minutes the views fell behind
the keyframes once it rendered (bench/results/graph_n5400*.json). Off, the views are
the fallback alone and the field trains for the saved map (``map_path``).

With ``fallback: keyframes`` (the default) what is blended in is not the one
frame's embedding but, per pixel, the mean over the frame and the stored
keyframes that see its 3D point (the same visibility test as the coverage),
averaged as class probabilities (``fusion``), so the view's entropy is the
predictive entropy over the views: it rises where views disagree, which a
single frame cannot show. The frame's own embedding counts ``own_view_weight``
times: the other views reach its points through poses and depths a pixel or
two off, and small objects blur in their mean. On the live schedule
(``run.training_rate_hz``) the field rarely matures within a short sequence, and
with ``field_views`` off it is never rendered into a view, so this fusion is what the
multi-view map contributes (bench/results/ncd.json, rows ``fallback_backbone`` and
``backbone_logits``).

The view's depth, which discovery cuts into convex segments, is the multi-view map's too
(``depth_fusion``): the measured depth averaged, pixel by pixel, with what the nearest
keyframes that see the same point measured of it (:func:`.views.fuse_depth`), at full
size. The sensor's noise, independent between viewpoints, shrinks, and the small depth
steps of a picture or a window frame on a wall stand out of it.

Flow control: at most ``max_in_flight`` views are published and not yet
labelled (the node sees labels come back on /neurncd/labels); the renderer
waits instead of flooding a slower discovery, so latency stays bounded and
keyframes queue here, where they are held anyway.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import threading
import time
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

from ..camera import Intrinsics, backproject, rays
from ..frame import Frame
from ..params import param
from ..sync import StampSync, max_jump_param
from .health import Health, no_camera_info, report_starved, sync_reporter
from .poses import (CHOICE_HELD_S, MAX_CAMERA_HZ, MAX_POSE_HZ, choice_frames,
                    pairing_frames)
from .records import EmbeddingRecord, EmbeddingSpec, ViewRecord
from .views import (FusionInputs, StoredView, coverage, fuse_depth, fuse_keyframes, resize_to,
                    view_visibility)


NOT_METRES_M = 100.0
"""A frame whose median depth is beyond this is not in metres (an RGB-D camera measures
up to about 10 m; depth in millimetres given as float32 has a median in the thousands,
and every pixel then lay beyond mapper.max_depth: labels silently wrong)."""

@dataclasses.dataclass(frozen=True)
class MapperNodeConfig:
    """The mapper stage: pairing, the field's keyframes, which views to render and how
    (the field itself is under `mapper`)."""

    map_path: str = param("", "map file: loaded at start if it exists, saved every "
                          "save_period_s and at shutdown ('' = none); neurncd run too loads "
                          "it and saves it at the end. The map is two files: this one and "
                          "<map_path>.spec.json beside it")
    save_period_s: float = param(30.0, "save the map this often while running, so a killed "
                                 "mapper restarts from it (0 = only at shutdown)", lo=0.0,
                                 hi=86400.0, unit="s")
    render_scale: float = param(1.0, "view size relative to the depth frame (the fusion's "
                                "and the field's cost grow with the pixels). 1 keeps the "
                                "backbone's resolution for borders and small objects: tuning "
                                "seeds 500-509, all / known / novel 77.58 / 85.39 / 58.06 at "
                                "1, 77.06 / 84.92 / 57.55 at 0.5", lo=0.1, hi=1.0)
    work_width: int = param(320, "compute the views of frames wider than this at this width "
                            "(the frame's aspect kept): the keyframe fusion of the embedding "
                            "and of the depth, whose cost grows with the pixels; the fused "
                            "depth is published at the frame's size (nearest), so the labels "
                            "are too, and discovery labels at 320 wide anyway "
                            "(discovery_node.work_width). Tuning seeds 500-503 at 640x480, "
                            "150 frames (neurncd run): all-class mIoU 78.07 at 320 against "
                            "78.53 at 640, rendering 4.4 times faster; live at 640x480 "
                            "(bench/graph.py: graph_640x480.json, "
                            "graph_640x480_work_width_640.json) label latency median 1.1 s "
                            "against 8.7 s at 640. render_scale applies on top of it; "
                            "0 = the frame's own width", lo=0, hi=8192, unit="px")
    max_in_flight: int = param(2, "views published and not yet labelled before the "
                               "renderer waits for discovery", lo=1, hi=100)
    in_flight_timeout_s: float = param(5.0, "a view not labelled within this is no longer "
                                       "waited for (discovery slow, restarted or absent)",
                                       lo=0.1, hi=600.0, unit="s")
    stale_after_s: float = param(1.0, "a non-keyframe frame not rendered within this of its "
                                 "arrival is dropped", lo=0.01, hi=600.0, unit="s")
    fallback: str = param("keyframes", "where the field has not learnt a point yet: blend in "
                          "the frame's backbone embedding by coverage ('backbone'), the mean "
                          "of it and the stored backbone embeddings of the keyframes that see "
                          "the point ('keyframes'), or render the field everywhere ('none')",
                          choices=("backbone", "keyframes", "none"))
    field_views: bool = param(False, "blend the field's own render into the views where the "
                              "keyframes that see a pixel have trained long enough (coverage: "
                              "mature_iterations, full_coverage, min_field_weight); off, the "
                              "views are the fallback alone (the keyframe fusion) and the field "
                              "trains for the saved map. Off because the mature field labels "
                              "worse than the fusion it is fitted to (tuning seeds 500-503 at "
                              "run.training_rate_hz 400: all-class 76.95 against 77.72) and its "
                              "render costs about 1.1 s per 320x240 view on one thread against "
                              "0.1 s: on a 3-minute bag (bench/graph.py --frames 5400) it "
                              "rendered from about a minute on, and the graph labelled 290 "
                              "frames and 45 % of the keyframes (latency p95 81 s) against "
                              "459 and 85 % (25 s) without it. fallback 'none' renders the "
                              "field regardless")
    mature_iterations: int = param(1000, "field_views: training iterations after which a "
                                   "keyframe's points are rendered from the field alone (the "
                                   "fast field matches the backbone after about as many, "
                                   "bench/results/field.json)",
                                   lo=1, hi=10 ** 7)
    full_coverage: float = param(1.0, "field_views: coverage at which a pixel is taken from "
                                 "the field alone (the best maturity of the keyframes seeing "
                                 "it)", lo=0.01, hi=1.0)
    min_field_weight: float = param(0.1, "field_views: pixels whose field weight is below "
                                    "this take the backbone's embedding alone and are not "
                                    "rendered (the render is the stage's main cost)",
                                    lo=0.0, hi=1.0)
    fusion: str = param("probabilities", "fallback keyframes: average the views' logits, or their "
                        "class probabilities ('probabilities': the view's entropy is then the "
                        "predictive entropy over the views, higher where they disagree)",
                        choices=("logits", "probabilities"))
    own_view_weight: float = param(2.0, "fallback keyframes: how many views the frame's own "
                                   "backbone embedding counts as in the fusion (the others "
                                   "reach its points through poses and depths a pixel or two "
                                   "off, which blurs small objects). Tuning seeds 500-509, "
                                   "all / known / novel, coverage_depth_tolerance 0.02: "
                                   "80.78 / 85.32 / 69.01 at 1, 80.95 / 85.44 / 69.30 at 2, "
                                   "80.93 / 85.46 / 69.19 at 3",
                                   lo=1.0, hi=100.0)
    disagreement_weight: float = param(0.0, "fallback keyframes, fusion probabilities: add this "
                                       "times the views' disagreement (entropy of their mean "
                                       "minus their mean entropy) to the view's entropy, so "
                                       "points the views call differently look more novel "
                                       "(0 = the predictive entropy alone)", lo=0.0, hi=100.0)
    fusion_recent: int = param(16, "fallback keyframes and depth_fusion: also fuse this "
                               "many of the most recent frames that were not admitted as "
                               "keyframes (their depth, pose and backbone embedding are held "
                               "for it; 0 = keyframes only). Tuning seeds 500-509 with "
                               "own_view_weight 2, all / known / novel: 80.87 / 85.38 / 69.22 "
                               "at 4, 80.95 / 85.44 / 69.30 at 8, 81.16 / 85.74 / 69.33 at 16, "
                               "81.15 at 24, 81.10 at 32 (8 before, chosen when the frame's own "
                               "view counted once: all 77.23 at 8, 76.87 at 16). 16 costs the "
                               "stage about a quarter more per view than 8 "
                               "(bench/results/ncd.json at 8843fa0, rows neurncd and "
                               "fusion_unweighted: 81 against 64 ms)",
                               lo=0, hi=256)
    depth_fusion: bool = param(True, "publish as the view's depth its measured depth averaged "
                               "with what the nearest keyframes (and recent frames) that see "
                               "the same points measured of them, at full size: discovery's "
                               "convex segments are cut on less sensor noise "
                               "(bench/results/ncd.json, rows neurncd and measured_depth)")
    coverage_keyframes: int = param(16, "keyframes nearest the view checked for coverage",
                                    lo=1, hi=4096)
    coverage_depth_tolerance: float = param(0.02, "a keyframe sees a point if its depth "
                                            "there agrees within this plus 3 % of the depth "
                                            "(tuning seeds 500-509, own_view_weight 2: all "
                                            "80.95 at 0.02, 80.87 at 0.05)",
                                            lo=0.001, hi=1.0, unit="m")
    min_valid_depth: float = param(0.05, "frames with a smaller share of pixels with depth "
                                   "(0, NaN and inf are no measurement) are skipped: they "
                                   "cannot place anything in the map", lo=0.0, hi=1.0)
    max_queued_keyframes: int = param(64, "keyframe views waiting to be rendered at most "
                                      "(beyond, the oldest is dropped with a warning)",
                                      lo=1, hi=10000)
    pose_source: str = param("auto", "where camera poses come from: the pose topic, /tf "
                             "(world_frame -> camera_frame), RGB-D odometry on the frames, or "
                             "auto: the first of them that shows up (see core/engine/poses.py)",
                             choices=("auto", "topic", "tf", "odometry"))
    pose_auto_wait_s: float = param(3.0, "pose_source auto: seconds of frames without a pose "
                                    "topic or /tf before odometry is chosen", lo=0.0,
                                    hi=3600.0, unit="s")
    odometry_frames: str = param("embedded", "pose_source odometry: which frames are tracked: "
                                 "embedded = those the embedding node embedded (the only ones "
                                 "the mapper uses; a third of a 30 Hz camera at "
                                 "embedding_node.max_rate_hz 10, so a third of the CPU), all = "
                                 "every colour+depth pair (shorter steps, more CPU)",
                                 choices=("embedded", "all"))
    odometry_gap_s: float = param(0.1, "odometry_frames embedded: between two embedded frames "
                                  "further apart, frames are tracked too, one at least this "
                                  "often (stamp time), so steps stay short when the embedding "
                                  "node falls behind (0 = embedded frames only)", lo=0.0,
                                  hi=60.0, unit="s")
    tf_max_gap_ms: float = param(1000.0, "pose_source tf: interpolate each /tf edge between "
                                 "samples at most this far apart (tf2 interpolates across "
                                 "any gap; a localisation's map->odom at 1-2 Hz needs 500-"
                                 "1000; at 100 a 2 Hz edge left 1 of 300 frames a pose)",
                                 lo=0.0, hi=10000.0, unit="ms")
    sync_tolerance_ms: float = param(20.0, "max stamp difference between colour, depth, pose "
                                     "and embedding", lo=0.0, hi=1000.0, unit="ms")
    sync_horizon_s: float = param(2.0, "how long a colour, depth or pose waits for its "
                                  "embedding (the embedding stage skips most frames)",
                                  lo=0.01, hi=600.0, unit="s")
    sync_max_jump_s: float = max_jump_param()
    queue_size: int = param(30, "subscription depth of the input topics; the pairing holds "
                            "up to max(2 queue_size, 90 x sync_horizon_s) messages of each "
                            "input while they wait for their embedding, sync_horizon_s of a "
                            "camera of up to 90 Hz (180 at the defaults: 387 MB of 640x480 "
                            "colour and depth at most, what a 90 Hz camera sends; a slower "
                            "one fills it less), and of the pose input 1000 x sync_horizon_s "
                            "(a motion capture's pose topic); while pose_source auto chooses, "
                            "90 x (sync_horizon_s + pose_auto_wait_s), the wait counted up to "
                            "10 s (450 at the defaults: 968 MB at 640x480 for a 90 Hz camera, "
                            "323 MB for a 30 Hz one). A faster camera: raise it to its rate x "
                            "sync_horizon_s / 2", lo=1, hi=1000)
    log_throttle_s: float = param(5.0, "min seconds between repeated reports of one kind of "
                                  "problem", lo=0.0, hi=3600.0, unit="s")


@dataclasses.dataclass
class ViewJob:
    """A frame waiting to be rendered."""

    frame: Frame
    embedding: EmbeddingRecord
    keyframe: bool
    enqueued: float


class MapperStage:
    """Pairs frames with their embedding, feeds the field, renders views newest first."""

    STREAMS = ("embedding", "color", "depth", "pose")

    def __init__(self, cfg: MapperNodeConfig, make_mapper: Callable[[int, int], Any],
                 health: Health | None = None, online: bool = True,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self._make_mapper = make_mapper
        self.online = online
        self._clock = clock
        self.health = health or Health("mapper", throttle_s=cfg.log_throttle_s, clock=clock)
        # Room for sync_horizon_s of a camera of up to MAX_CAMERA_HZ (180 messages per
        # input at the defaults: 387 MB of 640x480 colour and depth; a slower camera holds
        # only what came within sync_horizon_s): the embedding comes a second or more after
        # its frame, and a queue of a 30 Hz camera's 60 pushed the colour and depth of 50
        # of 60 embedded frames of a 60 Hz camera out first. The pose input, 128 bytes a
        # message, holds sync_horizon_s of a pose topic of up to MAX_POSE_HZ (a motion
        # capture's).
        self.pairing_capacity = pairing_frames(cfg)
        self.pose_capacity = max(self.pairing_capacity,
                                 int(round(MAX_POSE_HZ * cfg.sync_horizon_s)))
        self.sync = StampSync(self.STREAMS, int(cfg.sync_tolerance_ms * 1e6),
                              cfg.sync_horizon_s, capacity=self.pairing_capacity, clock=clock,
                              on_anomaly=self._on_sync_anomaly,
                              max_jump_ns=int(cfg.sync_max_jump_s * 1e9),
                              capacities={"pose": self.pose_capacity},
                              # An input is named missing once the others lost two queues'
                              # worth (60 at the defaults, as when that was the capacity: at
                              # 180 a wrong topic name was said seconds later).
                              starve_after=max(4, 2 * cfg.queue_size))
        self._report_sync = sync_reporter(self.health)
        self.mapper = None
        self.spec: EmbeddingSpec | None = None
        self.intrinsics: Intrinsics | None = None
        self._lock = threading.Lock()
        self._keyframe_jobs: collections.deque[ViewJob] = collections.deque()
        self._latest: ViewJob | None = None
        self._in_flight: dict[int, float] = {}
        self.keyframe_stamps: list[int] = []
        self._recent: collections.deque = collections.deque(maxlen=max(1, cfg.fusion_recent))
        self._fusion_inputs = FusionInputs()  # the render thread's alone
        self.stream_topics: dict[str, str] = {}  # stream -> topic, named in the reports
        # The node is still choosing where poses come from (pose_source auto): no pose yet
        # is the wait for that choice, not a pose topic that never publishes
        # (set_pose_choice_open).
        self.pose_choice_open = False
        # Embedding messages that came before their spec, as they came (hold_for_spec), and
        # the topic the spec comes on (named in the reports).
        self._before_spec: collections.deque = collections.deque()
        self._before_spec_lock = threading.Lock()
        self.spec_topic = "the embedding spec topic"
        self.health.set_state("waiting", "no frame with an embedding yet")

    # ------------------------------------------------------------ the field
    def _ensure_mapper(self, spec: EmbeddingSpec):
        if self.mapper is None:
            # The field learns the logits (and features: distill_features), kept by keyframes.
            self.mapper = self._make_mapper(spec.logit_channels, spec.feature_channels)
            self.spec = spec
            if self.online:
                self.mapper.start()
        elif spec != self.spec:
            raise ValueError(f"the embedding's spec {spec.to_json()} differs from the map's "
                             f"{self.spec.to_json() if self.spec else None}")
        return self.mapper

    def check_training(self) -> bool:
        """False (and the stage in error) if the field's training thread has died."""
        m = self.mapper
        if self.health.failed:
            return False
        if self.online and m is not None and not m.running:
            err = m.last_error
            self.health.fail("training", "the field's training thread stopped: "
                             f"{err!r}" if err else "the field's training thread stopped")
            return False
        return True

    def load(self, path: str | Path, load_mapper: Callable[[str], Any]) -> None:
        """Restore a map saved by :meth:`save` (the field and its embedding spec); on an
        error (ValueError) the stage keeps the map it had."""
        path = Path(path)
        spec_file = path.with_name(path.name + ".spec.json")
        if not path.is_file():
            raise ValueError(f"no map at {path} (the file a mapper_node.map_path names)")
        if not spec_file.is_file():
            raise ValueError(f"{spec_file} is missing: {path} was not saved by the mapper")
        spec = EmbeddingSpec.from_json(spec_file.read_text())
        mapper = load_mapper(str(path))
        got = mapper.channels + mapper.feature_channels
        if got != spec.channels:
            raise ValueError(f"{path} has {got} channels, its spec {spec.channels}")
        self.spec, self.mapper = spec, mapper
        if self.online:
            self.mapper.start()

    def save(self, path: str | Path) -> bool:
        """Save the map atomically (a crash mid-save leaves the previous file); False if
        there is nothing to save yet."""
        if self.mapper is None or self.spec is None:
            return False
        from ..torchfile import written_atomically

        path = Path(path)
        # The map first to its temporary file, then the spec, then the map in place.
        with written_atomically(path) as tmp:
            self.mapper.save(tmp)
            with written_atomically(path.with_name(path.name + ".spec.json")) as spec_tmp:
                spec_tmp.write_text(self.spec.to_json())
        self.health.count("map_saves")
        return True

    def stop(self) -> None:
        if self.mapper is not None:
            self.mapper.stop()

    # ------------------------------------------------------------ online input
    def offer_info(self, intrinsics: Intrinsics) -> None:
        if self.intrinsics is not None and intrinsics != self.intrinsics:
            self.health.problem("camera_info_changed", f"camera info changed from "
                                f"{self.intrinsics} to {intrinsics}: new frames use it")
        self.intrinsics = intrinsics

    def reset_map(self) -> None:
        """The map node's ~/reset: forget the field and its keyframes, and the held recent
        frames and waiting keyframe views with them (they would be fused into, or
        rendered in, the new room's first views)."""
        with self._lock:
            if self.mapper is not None:
                self.mapper.reset()
            self._recent.clear()
            self._keyframe_jobs.clear()
            self._latest = None
        self.health.count("resets")

    def hold_for_spec(self, stamp_ns: int, message: Any) -> None:
        """An embedding message that came before its spec, which says how to read it: held
        as it came (the node cannot convert or check it yet) until :meth:`release_for_spec`.
        With DDS the embedding node's latched spec and its first embeddings reach the
        mapper in any order at start; each embedding that came first was refused
        (``no_spec``), and the first frames of a run were lost. It is held as long as the
        frames it pairs with wait for it (``sync_horizon_s``, and ``pose_auto_wait_s``
        more while pose_source auto chooses) and as many as the pairing holds of each
        input (``sync.capacity``: 180 at the defaults, 2.8 MB each at 320x240x9 float32;
        the pairing would hold as many of them once converted; at embedding_node.max_rate_hz
        10 no more than 20 come within sync_horizon_s); beyond either it is refused as
        ``no_spec``, saying which."""
        now = self._clock()
        with self._before_spec_lock:
            gone = self._expired_held(now)
            self._before_spec.append((int(stamp_ns), now, message))
            over = []
            while len(self._before_spec) > self.sync.capacity:
                over.append(self._before_spec.popleft()[0])
        self._refuse_held(gone)
        self._refuse_held(over, overflow=True)

    def release_for_spec(self) -> list:
        """The spec has come: the embedding messages held for it, oldest first, to be read
        now as if they had just come (those held too long are refused first)."""
        self.expire_held()
        with self._before_spec_lock:
            out = [m for _, _, m in self._before_spec]
            self._before_spec.clear()
        return out

    def expire_held(self) -> None:
        """Refuse (``no_spec``) the embeddings held longer than their frames wait (the
        node's once-a-second tick: a spec that never comes)."""
        with self._before_spec_lock:
            gone = self._expired_held(self._clock())
        self._refuse_held(gone)

    @property
    def held_for_spec(self) -> int:
        """Embedding messages waiting for their spec."""
        with self._before_spec_lock:
            return len(self._before_spec)

    def _expired_held(self, now: float) -> list[int]:
        """Take the held embeddings older than the pairing's horizon (caller holds the
        lock); their stamps."""
        gone = []
        while self._before_spec and now - self._before_spec[0][1] > self.sync.horizon_s:
            gone.append(self._before_spec.popleft()[0])
        return gone

    def _refuse_held(self, stamps: list[int], overflow: bool = False) -> None:
        if overflow:
            reason = (f"its spec has not come on {self.spec_topic} yet, and more than "
                      f"{self.sync.capacity} embeddings wait for it (the oldest is dropped)")
        else:
            reason = (f"its spec did not come on {self.spec_topic} within "
                      f"{self.sync.horizon_s:g} s of it, as long as its frame waits "
                      "(sync_horizon_s; is the embedding node running, and its spec topic "
                      "the same?)")
        for stamp in stamps:
            self.health.refuse("embedding", "no_spec", f"embedding {stamp} skipped: {reason}",
                               reason, stamp)

    def set_pose_choice_open(self, choosing: bool) -> None:
        """Whether ``pose_source`` auto is still choosing where poses come from (the node
        says so from the pose stage). While it does, the frames' colour, depth and
        embeddings wait for the poses the choice hands on: up to ``sync_horizon_s`` +
        ``pose_auto_wait_s`` (at ``sync_horizon_s`` alone the first frames expired before
        a choice at 3 s), and as many of them as a camera of up to ``MAX_CAMERA_HZ`` sends
        meanwhile (:func:`.poses.choice_frames`: 450 per input at the defaults). Held to the
        60 of ``sync_horizon_s`` of a 30 Hz camera alone, the first second of a 30 Hz bag
        without poses was pushed out before the choice: 11 of its 50 embedded frames lost
        without a word. A longer wait than the pairing holds is said
        (``pose_choice_overflow``). Once chosen, the
        pairing is back to ``sync_horizon_s`` and its own capacity (the frames held
        meanwhile pair, or are superseded, as the poses come)."""
        with self._lock:
            self.pose_choice_open = bool(choosing)
            self.sync.horizon_s = self.cfg.sync_horizon_s + (
                self.cfg.pose_auto_wait_s if choosing else 0.0)
            self.sync.capacity = self.pairing_capacity
            if choosing:
                self.sync.capacity = max(self.pairing_capacity, choice_frames(self.cfg))

    def _on_sync_anomaly(self, stream: str, reason: str, stamp_ns: int,
                         detail: str = "") -> None:
        """The pairing's reports (called by ``self.sync``, under ``self._lock``). On a
        new timeline (a bag played again) the views in flight of the old one are no longer
        waited for: discovery restarts its own pairing too, and the renderer sat out
        in_flight_timeout_s for labels of them that never came."""
        self._report_sync(stream, reason, stamp_ns, detail)
        if reason == "time_reset":
            self._in_flight.clear()

    def offer(self, stream: str, stamp_ns: int, value: Any) -> list[ViewJob]:
        """One input message (EmbeddingRecord, rgb, depth or 4x4 pose); the frames it
        completed that were admitted and queued for rendering."""
        with self._lock:
            overflows = self.sync.drops["overflow"]
            groups = self.sync.add(stream, stamp_ns, value)
            overflows = self.sync.drops["overflow"] - overflows
            choosing, held = self.pose_choice_open, self.sync.capacity
        if overflows and choosing:  # a frame lost while the poses were not there yet
            self.health.problem(
                "pose_choice_overflow", f"{stream}: the oldest message is dropped: more than "
                f"{held} wait for their pose while pose_source auto chooses where poses come "
                f"from (the mapper holds sync_horizon_s + pose_auto_wait_s of a camera of up "
                f"to {MAX_CAMERA_HZ:g} Hz meanwhile, the wait counted up to "
                f"{CHOICE_HELD_S:g} s): set mapper_node.pose_source, or a shorter "
                "pose_auto_wait_s")
        refused = [s for s in ("color", "depth") if s in self.health.refused()]
        starved = [s for s in self.sync.starved() if s != "pose" or not self.pose_choice_open]
        report_starved(self.health, starved, self.cfg.sync_tolerance_ms,
                       f"inputs do (the embedding node cannot embed the {' and '.join(refused)}"
                       " this node refuses either; check that stamps agree" if refused else
                       "inputs do (check the topic names, that the embedding node runs, "
                       "and that stamps agree", self.stream_topics)
        queued = []
        for stamp, g in groups:
            self.health.count("frames_paired")
            intr = self.intrinsics
            if intr is None:
                self.health.problem("no_camera_info", f"frame {stamp} skipped: "
                                    f"{no_camera_info(self.health)}")
                continue
            try:
                frame = Frame(stamp, g["color"], g["depth"], g["pose"], intr).validate()
            except ValueError as err:
                self.health.problem("frame_mismatch", f"frame {stamp} skipped: {err}")
                continue
            job = self.admit(frame, g["embedding"])
            if job is not None:
                queued.append(job)
        return queued

    # ------------------------------------------------------------ keyframes
    def admit(self, frame: Frame, record: EmbeddingRecord) -> ViewJob | None:
        """Offer a complete frame to the field and queue it for rendering; the job, or
        None if the frame was refused (the reason is reported)."""
        if not self.check_training():
            return None
        valid = float(np.mean(frame.depth > 0))
        if valid < self.cfg.min_valid_depth:
            self.health.problem("no_depth", f"frame {frame.stamp_ns} skipped: only "
                                f"{100 * valid:.1f} % of its pixels have a depth measurement")
            return None
        sample = frame.depth[::8, ::8]
        sample = sample[sample > 0]
        far = float(np.median(sample)) if sample.size else 0.0
        if far > NOT_METRES_M:
            self.health.problem("depth_not_metres", f"frame {frame.stamp_ns} skipped: its "
                                f"median depth is {far:.0f} m: depth must be in metres (from "
                                "millimetres, as a 16UC1 image or PNG holds them: / 1000)")
            return None
        try:
            mapper = self._ensure_mapper(record.spec)
            keyframe = mapper.add_keyframe(frame, record.embedding)
        except ValueError as err:
            self.health.problem("frame_refused", f"frame {frame.stamp_ns} skipped: {err}")
            return None
        job = ViewJob(frame, record, keyframe, self._clock())
        with self._lock:
            if keyframe:
                self.keyframe_stamps.append(frame.stamp_ns)
                self.health.count("keyframes")
                self._keyframe_jobs.append(job)
                if self._latest is not None:
                    # Rendered after this keyframe, the older frame would reach discovery
                    # out of order (dropped there, its in-flight slot held until the
                    # timeout): a newer frame came first.
                    self.health.count("skipped_newer")
                    self._latest = None
                if len(self._keyframe_jobs) > self.cfg.max_queued_keyframes:
                    old = self._keyframe_jobs.popleft()
                    self.health.problem("keyframes_dropped", f"keyframe {old.frame.stamp_ns} "
                                        "not rendered: more than max_queued_keyframes wait")
            else:
                if self._latest is not None:
                    self.health.count("skipped_newer")
                self._latest = job
                if self.cfg.fusion_recent > 0 and (self.cfg.fallback == "keyframes"
                                                   or self.cfg.depth_fusion):
                    self._recent.append(StoredView(
                        frame.stamp_ns, frame.pose, frame.intrinsics, frame.depth,
                        np.asarray(record.embedding, np.float16)))
        self.health.set_state("running")
        return job

    # ------------------------------------------------------------ which view next
    def next_view(self) -> ViewJob | None:
        """The next frame to render, or None (nothing waiting, or discovery busy)."""
        now = self._clock()
        with self._lock:
            for stamp, t in list(self._in_flight.items()):
                if now - t > self.cfg.in_flight_timeout_s:
                    del self._in_flight[stamp]
                    self.health.count("in_flight_timeouts")
            if len(self._in_flight) >= self.cfg.max_in_flight:
                return None
            if self._keyframe_jobs:
                job = self._keyframe_jobs.popleft()
            elif self._latest is not None:
                job, self._latest = self._latest, None
                if self.online and now - job.enqueued > self.cfg.stale_after_s:
                    self.health.count("skipped_stale")
                    return None
            else:
                return None
            self._in_flight[job.frame.stamp_ns] = now
            return job

    def labelled(self, stamp_ns: int) -> None:
        """Discovery has labelled the view of this stamp (frees an in-flight slot)."""
        with self._lock:
            self._in_flight.pop(int(stamp_ns), None)

    def release(self, job: ViewJob) -> None:
        """A view that will not be published (render failed): free its slot."""
        self.labelled(job.frame.stamp_ns)

    @property
    def pending(self) -> int:
        """Views waiting to be rendered or labelled (0 = drained)."""
        with self._lock:
            return len(self._keyframe_jobs) + (self._latest is not None) + len(self._in_flight)

    # ------------------------------------------------------------ rendering
    def _nearest_keyframes(self, frame: Frame) -> list:
        """The ``coverage_keyframes`` stored keyframes nearest the frame's pose (position and
        view angle), the frame itself left out."""
        kfs = [k for k in self.mapper.buffer.keyframes() if k.stamp_ns != frame.stamp_ns]
        if not kfs:
            return []
        poses = np.stack([k.pose for k in kfs])
        gap = np.linalg.norm(poses[:, :3, 3] - frame.pose[:3, 3], axis=1)
        gap += 1.0 - np.einsum("ni,i->n", poses[:, :3, 2], frame.pose[:3, 2])  # view angle
        return [kfs[i] for i in np.argsort(gap, kind="stable")[: self.cfg.coverage_keyframes]]

    def _recent_views(self, frame: Frame) -> list:
        """The held recent non-keyframe frames (``fusion_recent``), the frame itself left
        out."""
        if self.cfg.fusion_recent <= 0:
            return []
        with self._lock:
            return [r for r in self._recent if r.stamp_ns != frame.stamp_ns]

    def field_weight(self, kfs: list, points: np.ndarray | None, mask: np.ndarray | None,
                     height: int, width: int, visibility=None) -> np.ndarray:
        """(height, width) weight of the field against the backbone (see module doc), from
        the view's nearest keyframes ``kfs`` and its back-projected depth ``points`` at
        the ``mask`` pixels; ``visibility`` the depth fusion's test, reused."""
        maturity = np.array([min(1.0, k.iterations / self.cfg.mature_iterations) for k in kfs])
        # A weight is at most the best maturity / full_coverage; below min_field_weight
        # nothing is rendered, so while no keyframe is that mature no test is needed.
        if (not np.any(maturity > 0) or maturity.max() / self.cfg.full_coverage
                < self.cfg.min_field_weight):
            return np.zeros((height, width), np.float32)
        cov = coverage(points, kfs, maturity, self.cfg.coverage_depth_tolerance,
                       None if visibility is None else visibility.first(len(kfs)))
        w = np.clip(cov / self.cfg.full_coverage, 0.0, 1.0).astype(np.float32)
        out = np.full((height, width), float(w.mean()) if w.size else 0.0, np.float32)
        out[mask] = w
        return out

    def keyframe_fill(self, frame: Frame, backbone: np.ndarray, kfs: list, points, mask,
                      logit_channels: int, visibility=None) -> tuple[np.ndarray, Any]:
        """The frame's (h, w, C) backbone embedding averaged, point by point, with the
        stored embeddings of the views ``kfs`` (the nearest keyframes and the held recent
        frames) that see it (:func:`fuse_keyframes`); pixels without depth keep the
        frame's own. Also the (h, w) mean of the views' own entropies (fusion probabilities and a
        ``disagreement_weight``; None otherwise); ``visibility`` the depth fusion's, reused."""
        if not kfs:
            return backbone, None
        out = backbone.copy()
        out[mask], _, h_views = fuse_keyframes(
            points, backbone[mask], kfs, self.cfg.coverage_depth_tolerance,
            logit_channels if self.cfg.fusion == "probabilities" else None,
            self.cfg.disagreement_weight > 0, self._fusion_inputs, visibility,
            self.cfg.own_view_weight)
        self._fusion_inputs.keep(kfs)
        if h_views is None:
            return out, None
        mean_h = np.full(backbone.shape[:2], np.nan, np.float32)
        mean_h[mask] = h_views
        return out, mean_h

    def render_view(self, job: ViewJob, cancel: threading.Event | None = None) -> ViewRecord:
        """Render the job's frame at its pose and measured depth where the field has learnt
        something (coverage > 0), and blend it there with the frame's backbone embedding."""
        from ..uncertainty import entropy

        if not self.check_training():
            raise RuntimeError(self.health.error or "the mapper stage has failed")
        f, mapper, spec = job.frame, self.mapper, job.embedding.spec
        full_h, full_w = f.depth.shape
        # The working frame: the depth fusion's (at most work_width wide)...
        work = self.cfg.work_width
        fuse_w = work if 0 < work < full_w else full_w
        fuse_h = max(1, round(full_h * fuse_w / full_w))
        fuse_intr = f.intrinsics.scaled(fuse_w, fuse_h) if fuse_w != full_w else f.intrinsics
        fuse_depth_in = resize_to(f.depth, fuse_h, fuse_w, cv2.INTER_NEAREST)
        # ... and the view's, render_scale of it.
        s = self.cfg.render_scale
        h, w = max(1, round(fuse_h * s)), max(1, round(fuse_w * s))
        backbone = resize_to(job.embedding.embedding.astype(np.float32), h, w)
        # The view's geometry, once for the coverage, the fusion and the rays.
        intr = f.intrinsics.scaled(w, h)
        depth = (fuse_depth_in if (h, w) == (fuse_h, fuse_w)
                 else resize_to(f.depth, h, w, cv2.INTER_NEAREST))
        fuse = self.cfg.fallback == "keyframes"
        kfs = (self._nearest_keyframes(f)
               if self.cfg.fallback != "none" or self.cfg.depth_fusion else [])
        views = kfs + self._recent_views(f) if fuse or self.cfg.depth_fusion else kfs
        view_depth, seen, tol = None, None, self.cfg.coverage_depth_tolerance
        if self.cfg.depth_fusion:  # discovery cuts its segments on it
            seen = view_visibility(fuse_depth_in, fuse_intr, f.pose, views, tol)
            view_depth, _ = fuse_depth(fuse_depth_in, fuse_intr, f.pose, views, tol, seen)
            view_depth = resize_to(view_depth, full_h, full_w, cv2.INTER_NEAREST)
        points, mask = backproject(depth, intr, f.pose) if views else (None, None)
        seen = seen if depth is fuse_depth_in else None  # the same test, at render_scale 1
        if self.cfg.fallback == "none":
            weight = np.ones((h, w), np.float32)
        elif self.cfg.field_views:
            weight = self.field_weight(kfs, points, mask, h, w, seen)
        else:
            weight = np.zeros((h, w), np.float32)
        mean_h = None
        if fuse:
            backbone, mean_h = self.keyframe_fill(f, backbone, views, points, mask,
                                                  spec.logit_channels, seen)
        iterations = mapper.iterations
        emb = backbone.copy()
        weight = np.where(weight >= self.cfg.min_field_weight, weight, 0.0)
        sel = weight > 0.0
        if sel.any():  # render only where the field has learnt enough to count
            v, u = np.nonzero(sel)
            origins, dirs = rays(f.pose, intr, u, v)
            z = depth[v, u]
            # The field pauses its training while it renders (mapper.yield_to_render) and
            # checks ``cancel`` between chunks (a node stops promptly even mid-render).
            field = mapper.render_rays(origins, dirs, z, cancel=cancel)["embedding"]
            wt = weight[sel][:, None]
            S = field.shape[1]  # the logits, then any features the field distils
            emb[sel, :S] = wt * field + (1.0 - wt) * backbone[sel, :S]
        emb = np.ascontiguousarray(emb, np.float32)
        ent = entropy(emb[..., : spec.logit_channels])
        if mean_h is not None:  # only with a disagreement_weight (keyframe_fill)
            # The views' disagreement where the keyframes filled in (not where the field did).
            gap = np.nan_to_num(np.maximum(ent - mean_h, 0.0)) * (1.0 - weight)
            ent = np.minimum(ent + self.cfg.disagreement_weight * gap,
                             np.log(spec.logit_channels)).astype(np.float32)
        self.health.count("views")
        self.health.count("views_keyframe" if job.keyframe else "views_frame")
        self.health.gauge("iterations", iterations)
        return ViewRecord(f, emb, ent, spec, job.keyframe, float(weight.mean()), iterations,
                          view_depth)

    def summary(self) -> str:
        c = self.health.counts
        it = self.mapper.iterations if self.mapper is not None else 0
        return (f"frames paired {c['frames_paired']}, keyframes {c['keyframes']}, views "
                f"rendered {c['views']} ({c['views_keyframe']} keyframes), frames not "
                f"rendered {c['skipped_newer'] + c['skipped_stale']} (a newer frame first "
                f"{c['skipped_newer']}, stale {c['skipped_stale']}), iterations {it}, "
                f"unpaired inputs {json.dumps(dict(self.sync.drops))}" + self._left())

    def _left(self) -> str:
        """What the stage still held (said at shutdown: a keyframe view queued but never
        rendered was never labelled either)."""
        with self._lock:
            kf, newest, flight = (len(self._keyframe_jobs), self._latest is not None,
                                  len(self._in_flight))
        if not (kf or newest or flight):
            return ""
        parts = [f"{kf} keyframe view{'s' * (kf != 1)} queued"] if kf else []
        parts += ["the newest frame"] if newest else []
        parts += [f"{flight} view{'s' * (flight != 1)} awaiting labels"] if flight else []
        return f"; not rendered or labelled: {', '.join(parts)}"
