"""Pose stage: a camera pose for every frame, whether or not the input carries one.

``mapper_node.pose_source`` picks where poses come from:

- ``topic``: geometry_msgs/PoseStamped on ``topics.pose`` (camera-to-world);
- ``tf``: /tf and /tf_static, looked up as ``topics.world_frame`` ->
  ``topics.camera_frame`` at each frame's stamp (edges interpolated within
  ``tf_max_gap_ms``);
- ``odometry``: RGB-D odometry on the frames themselves (:mod:`..odometry`),
  tracked frame to keyframe. With ``odometry_frames`` "embedded" (default) a
  colour+depth pair is held until its embedding arrives and only then tracked,
  so the odometry runs on the frames the mapper uses (the embedding stage
  embeds at most ``embedding_node.max_rate_hz``), not on every camera frame;
  between two embedded frames further apart than ``odometry_gap_s`` (a busy
  embedding node) held frames are tracked too, so steps stay short. "all"
  tracks every pair. Losses are reported with their reason and the
  frames they cover get no pose (they are skipped, never placed wrongly); a new
  map segment is a warning too (the node then restarts the field);
- ``auto``: the first of these that shows up: a pose topic publisher, then a
  /tf tree linking the two frames, else odometry once ``auto_wait_s`` of frames
  passed without either. The choice is logged once and kept. Frames are
  tracked while the choice is open; when it falls on odometry their poses are
  handed on (the mapper pairs those whose embeddings still wait). The node
  polls the choice once a second (:meth:`PoseStage.poll`), so a stream that ends within
  the wait (a short bag) is decided and handed on too.

With tf or odometry the node publishes the poses on ``topics.pose`` for the
other nodes (and the user); with ``topic`` it publishes nothing.
"""

from __future__ import annotations

import collections
import time
from typing import Any, Callable

import numpy as np

from ..camera import Intrinsics
from ..sync import StampSync, TfBuffer
from .health import Health, no_camera_info, sync_reporter

SOURCES = ("auto", "topic", "tf", "odometry")

MAX_CAMERA_HZ = 90.0
"""The fastest camera the mapper's pairing is sized for: a RealSense streams at 90, 60 or
30 fps (some drivers at 15 or 6). The pairing holds a frame's colour and depth until its
embedding comes, up to a second and a half later (more at 1280x720), and the embedding node
embeds at most embedding_node.max_rate_hz (10) of them a second, so it holds every frame of
that time. Sized for 30 Hz (60 messages per input), a 60 Hz camera pushed the colour and
depth of 50 of 60 embedded frames out of the pairing before their embedding came, a 90 Hz
one those of 54 (test/test_poses.py). A slower camera holds less: the pairing gives up what
waited ``sync_horizon_s``, so this only bounds what it holds."""

MAX_POSE_HZ = 1000.0
"""The fastest pose topic the mapper's pairing is sized for (a motion capture publishes
at 100-360 Hz, an estimator at its IMU's rate): 128 bytes a pose, against 2.15 MB for a
640x480 frame's colour and depth. Held to a 30 Hz camera's count, a 120 Hz pose topic kept
half a second of poses, and 55 of 60 embedded frames of a 30 Hz camera, whose embedding
comes a second after them, found theirs pushed out."""

CHOICE_HELD_S = 10.0
"""pose_source auto: at most this much of ``pose_auto_wait_s`` of frames is held for the
choice (:func:`choice_frames`); frames beyond it are dropped, oldest first, and said."""


def pairing_frames(cfg) -> int:
    """Messages of each input the mapper's pairing holds while they wait for their
    partners (:class:`.mapping.MapperStage`, ``pairing_capacity``):
    max(4, 2 ``queue_size``, ``MAX_CAMERA_HZ`` x ``sync_horizon_s``), 180 at the defaults.
    That bounds the memory of the frames waiting for their embedding: 180 colour and
    depth images take 387 MB at 640x480 and 1.16 GB at 1280x720 (a RealSense streams that
    size at 30 fps at most, so it holds 60 of them at most, 387 MB): a camera of f Hz
    holds f x ``sync_horizon_s`` frames at most, as the pairing gives up what waited
    longer, and this caps what a faster stream (or a burst of stamps) holds. The pose
    input holds ``MAX_POSE_HZ`` x ``sync_horizon_s`` (2000 at the defaults, under 1 MB)."""
    return max(4, 2 * cfg.queue_size, int(round(MAX_CAMERA_HZ * cfg.sync_horizon_s)))


def choice_frames(cfg) -> int:
    """Frames of a ``MAX_CAMERA_HZ`` camera that come while ``pose_source`` auto chooses, and
    that the mapper holds until the choice hands their poses on: ``sync_horizon_s`` +
    ``pose_auto_wait_s`` (at most ``CHOICE_HELD_S`` of the wait) of them; 450 at the
    defaults. Held per input as images: colour (rgb8) and depth (float32 metres) take
    2.15 MB a frame at 640x480, so 968 MB at the defaults for a 90 Hz camera, 323 MB for
    a 30 Hz one (150 frames: the pairing gives up what waited longer), and at most
    2.3 GB (1080 frames of a 90 Hz camera, a wait of 10 s or more); at 1280x720, 6.45 MB a
    frame, 968 MB at the defaults for a 30 Hz camera. The embeddings come at the embedding
    node's rate (at most its max_rate_hz 10 a second)."""
    return int(round(MAX_CAMERA_HZ * (cfg.sync_horizon_s
                                      + min(cfg.pose_auto_wait_s, CHOICE_HELD_S))))


class PoseStage:
    """Turns pose messages, /tf or the images into (stamp, camera-to-world) pairs."""

    def __init__(self, node_cfg, odometry_cfg, topics, health: Health,
                 clock: Callable[[], float] = time.monotonic, tf_available: bool = True
                 ) -> None:
        self.cfg = node_cfg
        self.odometry_cfg = odometry_cfg
        self.topics = topics
        self.health = health
        self._clock = clock
        source = node_cfg.pose_source
        if source == "tf" and not tf_available:
            raise ValueError("mapper_node.pose_source 'tf' needs the tf2_msgs message package, "
                             "which this ROS install lacks (there is no PyPI wheel of it): "
                             "use pose_source 'topic' or 'odometry', or convert the bag with "
                             "`neurncd convert --kind bag --tf-parent ... --tf-child ...`")
        self.tf_available = tf_available
        self.mode: str | None = None if source == "auto" else source
        self.tf = TfBuffer(horizon_ns=int(10e9))
        # Depth stamps waiting for /tf to give their pose: while auto chooses, every frame
        # of the wait, as the mapper holds them (kept to 4 queue_size, 120, the first 141
        # frames of a 90 Hz camera went without a pose when /tf linked the frames at 2.9 s).
        self._tf_pending: list[int] = []
        self._tf_max = max(4 * node_cfg.queue_size, choice_frames(node_cfg))
        self.sync = StampSync(("depth", "color"), int(node_cfg.sync_tolerance_ms * 1e6),
                              node_cfg.sync_horizon_s, capacity=max(4, node_cfg.queue_size),
                              clock=clock, on_anomaly=sync_reporter(health),
                              max_jump_ns=int(node_cfg.sync_max_jump_s * 1e9))
        self.odometry = None
        self.odometry_seconds = 0.0   # wall time spent tracking
        # colour+depth pairs (stamp, rgb, depth, intrinsics) waiting for their embedding,
        # at most sync_horizon_s of them (odometry_frames "embedded"), and the embeddings'
        # stamps whose pair has not come yet
        self._held: collections.deque = collections.deque(
            maxlen=max(8 * max(4, node_cfg.queue_size), pairing_frames(node_cfg)))
        self._wanted: collections.deque = collections.deque(maxlen=max(4, node_cfg.queue_size))
        self._last_tracked: int | None = None
        # Tracked while auto was undecided, handed on once it chose odometry: the poses of
        # every frame of the wait (odometry_frames all tracks each frame of a 30 Hz camera;
        # 128 bytes a pose). Kept to 30 before (the size of _wanted), the first 60 frames
        # of a 30 Hz camera had no pose after a choice at 3 s with odometry_frames all.
        self._early: list[tuple[int, np.ndarray]] = []
        self._early_max = choice_frames(node_cfg)
        self._first_frame: float | None = None
        self._topic_seen = False
        if self.mode is not None:
            self.health.gauge("pose_source", self.mode)

    @property
    def publishes(self) -> bool:
        """The node should publish the poses it gets from here on ``topics.pose``."""
        return self.mode in ("tf", "odometry")

    def reset_odometry(self) -> None:
        """A new room (the mapper's ~/reset): the odometry forgets its keyframes and the
        frames held for it, and the next frame starts it again at the origin (it tracked
        the new room against the old room's keyframes and lost its first 10 frames, until
        a new segment). Its counts for the exit line are kept."""
        odo = self.odometry
        if odo is not None:
            frames, counts = odo.frames, dict(odo.counts)
            odo.reset()
            odo.frames, odo.counts = frames, counts
        self._held.clear()
        self._wanted.clear()
        self._early.clear()
        self._last_tracked = None

    def summary(self) -> str:
        """One line for the node's exit log: the source and, with odometry, what it did."""
        odo = self.odometry
        if odo is None or self.mode != "odometry":
            return f"pose source {self.mode or 'undecided'}"
        ms = 1000 * self.odometry_seconds / max(odo.frames, 1)
        return (f"pose source odometry: {odo.frames} frames tracked ({ms:.1f} ms per frame), "
                + ", ".join(f"{k} {v}" for k, v in odo.counts.items())
                + f", segments {odo.segment + 1}")

    @property
    def waiting(self) -> int:
        """Frames tracked while ``auto`` has not chosen: their poses wait for the choice
        (work the mapper still has to do)."""
        return len(self._early)

    def poll(self) -> list[tuple[int, np.ndarray]]:
        """Make the ``auto`` choice on the clock alone and hand on the poses tracked while
        it was open: without this a stream that ended within ``pose_auto_wait_s`` (a
        5-frame bag) was never decided, as only a later frame made the choice."""
        if self._decide() != "odometry" or not self._early:
            return []
        out, self._early = self._early, []
        return out

    # ------------------------------------------------------------ choosing
    def _decide(self) -> str | None:
        if self.mode is not None:
            return self.mode
        if self._topic_seen:
            mode = "topic"
        elif self.tf_available and self._tf_links():
            mode = "tf"
        elif (self._first_frame is not None
              and self._clock() - self._first_frame >= self.cfg.pose_auto_wait_s):
            mode = "odometry"
        else:
            return None
        self.mode = mode
        if mode != "tf":
            self._tf_pending.clear()
        if mode != "odometry":
            self._held.clear()
            self._wanted.clear()
            self._early.clear()
        self.health.gauge("pose_source", mode)
        why = ""
        if mode == "odometry":
            why = (f": no pose on {self.topics.pose} within {self.cfg.pose_auto_wait_s:g} s"
                   + (f", and no /tf link from {self.topics.world_frame} to "
                      f"{self.topics.camera_frame}" if self.tf_available else
                      ", and /tf cannot be read here (no tf2_msgs message package: there "
                      "is no PyPI wheel of it; a ROS 2 install has it)"))
        self.health.note("pose_source", f"pose source: {mode} (pose_source auto){why}")
        return mode

    def _tf_links(self) -> bool:
        frames = self.tf.frames()
        if self.topics.world_frame not in frames or self.topics.camera_frame not in frames:
            return False
        chain_w = self.tf.chain(self.topics.world_frame)
        return any(f in chain_w for f in self.tf.chain(self.topics.camera_frame))

    # ------------------------------------------------------------ inputs
    def offer_pose(self, stamp_ns: int, pose: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """A pose message from another publisher."""
        self._topic_seen = True
        return [(stamp_ns, pose)] if self._decide() == "topic" else []

    def offer_tf(self, msg: Any, static: bool) -> list[tuple[int, np.ndarray]]:
        """A TFMessage; poses of frames that were waiting for it."""
        self.tf.add(msg, static)
        if self._decide() != "tf":
            return []
        return self._lookup_pending()

    def offer_image(self, stream: str, stamp_ns: int, image: np.ndarray,
                    intrinsics: Intrinsics | None) -> list[tuple[int, np.ndarray]]:
        """Colour (rgb) or depth (m) of a frame; the poses this completes."""
        if self._first_frame is None:
            self._first_frame = self._clock()
        mode = self._decide()
        if mode == "topic":
            return []
        if mode == "tf":
            if stream == "depth":
                self._tf_pending.append(int(stamp_ns))
                return self._lookup_pending()
            return []
        if mode is None and stream == "depth" and self.tf_available:
            # Undecided: /tf may come later than the first frames; they are looked up
            # once it links the frames (as with pose_source tf), not lost.
            self._tf_pending = (self._tf_pending + [int(stamp_ns)])[-self._tf_max:]
        # odometry, or still undecided: track anyway, so a late decision loses nothing
        out = []
        for stamp, g in self.sync.add(stream, stamp_ns, image):
            if self.cfg.odometry_frames == "all":
                out += self._tracked(stamp, g["color"], g["depth"], intrinsics)
            else:
                self._held.append((stamp, g["color"], g["depth"], intrinsics))
                horizon = stamp - int(self.cfg.sync_horizon_s * 1e9)
                while self._held[0][0] < horizon:   # as long as the mapper waits for it
                    self._held.popleft()
                out += self._match(intrinsics)
        return out

    def offer_embedding(self, stamp_ns: int, intrinsics: Intrinsics | None = None
                        ) -> list[tuple[int, np.ndarray]]:
        """An embedding's stamp: with ``odometry_frames`` "embedded", its frame is tracked
        as soon as its colour and depth are there (a busy node may take the embedding
        first); held pairs older than it are dropped, tracked only to keep steps short
        (``odometry_gap_s``). ``intrinsics``: the camera's now, for pairs held before the
        camera info arrived. The poses this gives."""
        if self.cfg.odometry_frames != "embedded" or self._decide() in ("topic", "tf"):
            return []
        self._wanted.append(int(stamp_ns))
        return self._match(intrinsics)

    def _match(self, intrinsics: Intrinsics | None = None) -> list[tuple[int, np.ndarray]]:
        """Track the held pairs that embeddings asked for, in stamp order, and between
        them one at least every ``odometry_gap_s`` (short steps when embeddings are far
        apart)."""
        out = []
        tol = int(self.cfg.sync_tolerance_ms * 1e6)
        gap = int(self.cfg.odometry_gap_s * 1e9)
        while self._wanted and self._held:
            want, (stamp, rgb, depth, intr) = self._wanted[0], self._held[0]
            if stamp < want - tol:      # no embedding asked for this frame
                self._held.popleft()
                if gap and (self._last_tracked is None or stamp - self._last_tracked >= gap):
                    out += self._tracked(stamp, rgb, depth, intr or intrinsics)
            elif stamp > want + tol:    # the frame asked for will not come
                self._wanted.popleft()
                self.health.problem("odometry_no_frame", f"frame {want} not tracked: its "
                                    "colour and depth did not arrive (dropped, or too late)")
            else:
                self._wanted.popleft()
                self._held.popleft()
                out += self._tracked(stamp, rgb, depth, intr or intrinsics)
        return out

    def _tracked(self, stamp: int, rgb: np.ndarray, depth: np.ndarray,
                 intrinsics: Intrinsics | None) -> list[tuple[int, np.ndarray]]:
        pose = self._track(stamp, rgb, depth, intrinsics)
        self._last_tracked = stamp
        if pose is None:
            return []
        mode = self._decide()
        if mode is None:
            self._early = (self._early + [(stamp, pose)])[-self._early_max:]
            return []
        if mode != "odometry":
            return []
        out, self._early = self._early + [(stamp, pose)], []
        return out

    # ------------------------------------------------------------ sources
    def _lookup_pending(self) -> list[tuple[int, np.ndarray]]:
        out, keep = [], []
        skew = int(self.cfg.sync_tolerance_ms * 1e6)
        gap = int(self.cfg.tf_max_gap_ms * 1e6)
        newest = max(self._tf_pending, default=0)
        for stamp in self._tf_pending:
            try:
                out.append((stamp, self.tf.lookup(self.topics.world_frame,
                                                  self.topics.camera_frame, stamp, skew, gap)))
            except LookupError as err:
                if newest - stamp > int(self.cfg.sync_horizon_s * 1e9):
                    hint = (" (an edge published less often: raise mapper_node.tf_max_gap_ms "
                            "above its period)" if "interpolate" in str(err) else "")
                    self.health.problem("no_tf", f"frame {stamp} has no pose: {err}{hint}")
                else:
                    keep.append(stamp)
        self._tf_pending = keep[-self._tf_max:]
        return out

    def _track(self, stamp: int, rgb: np.ndarray, depth: np.ndarray,
               intrinsics: Intrinsics | None) -> np.ndarray | None:
        if intrinsics is None:
            self.health.problem("no_camera_info", f"frame {stamp} not tracked: "
                                f"{no_camera_info(self.health)}")
            return None
        if self.odometry is None:
            from ..odometry import RGBDOdometry
            self.odometry = RGBDOdometry(self.odometry_cfg)
        t0 = time.perf_counter()
        try:
            result = self.odometry.track(stamp, rgb, depth, intrinsics)
        except ValueError as err:
            self.health.problem("odometry_input", f"frame {stamp} not tracked: {err}")
            return None
        self.odometry_seconds += time.perf_counter() - t0
        self.health.count(f"odometry_{result.status}")
        if result.status != "ok":
            level = 0 if result.status == "relocalised" else 1
            self.health.problem(f"tracking_{result.status}",
                                f"odometry {result.status} at frame {stamp}: {result.reason}",
                                level=level)
        return result.pose
