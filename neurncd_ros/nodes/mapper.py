"""Mapper node: fits the Embedding-NeRF on keyframes and publishes rendered views.

A thin adapter over the engine's :class:`MapperStage`: colour, depth, pose,
camera info and the backbone embedding are converted and offered to the stage,
which pairs them, admits keyframes to the field (trained in its own thread)
and decides which view to render next (keyframes first, then the newest
frame). A worker renders it and publishes the view as messages of one stamp:
rendered embedding, entropy, and the view's depth, colour and camera info, so
discovery always has the depth a rendering belongs to. Labels coming back on
/neurncd/labels free the renderer (at most ``max_in_flight`` views unlabelled).
Services ~/save_map and ~/reset (std_srvs/Trigger); the map is saved every
``save_period_s`` and at shutdown when ``map_path`` is set, and loaded at start.
Poses come from the pose topic, /tf or RGB-D odometry (``pose_source``, the
engine's :class:`PoseStage`); tf and odometry poses are published on the pose
topic, and a new odometry map segment restarts the field.

The subscription callbacks only convert a message and queue it: an intake thread
pairs the inputs and admits keyframes, in arrival order. Admitting a keyframe in a
callback (up to 1.8 s on a busy machine, when it waited for a training step to grow
the field's box, as it no longer does) made DDS drop a second of a 30 Hz camera from the
input queues (``queue_size``), so a third of the embeddings found no colour, depth or
pose; whatever an admission costs now, the input queues are not held up by it.
"""

from __future__ import annotations

import collections
import os
import threading

# Nothing heavy at the top: main() installs the signal handlers before torch loads.
from .common import (camera_info_msg, diagnostics_msg, header_ns, image_msg, input_image_type,
                     latched_qos, pose_msg, ros_logger, run_node, sensor_qos, stamp_of,
                     view_qos, wall_timer, InputWatch)
from .parameters import ReadOnlyConfig, declare_config

DESCRIPTION = ("Fits the Embedding-NeRF incrementally on RGB-D keyframes and publishes "
               "rendered views: /neurncd/rendered_embedding (32FC<C>), /neurncd/entropy "
               "(32FC1) with the view's depth, colour and camera info under /neurncd/view/. "
               "Services ~/save_map and ~/reset (std_srvs/Trigger).")


# Imported by run_node before rclpy (torch, scipy first), once the signal handlers are in.
# torch imports torch._dynamo (for Adam) and sympy (symbolic_shapes, for the field's
# parameters) lazily when the first embedding builds the field: 3 s holding the GIL then,
# while the camera's frames come in, so they are imported here.
PRELOAD = ("torch", "torch._dynamo", "torch.fx.experimental.symbolic_shapes",
           "neurncd_ros.core.engine.mapping", "neurncd_ros.core.engine.offline",
           "neurncd_ros.core.field.mapper")


def make_node():
    import cv2
    import torch
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from ..core import msgconv
    from ..core.engine.health import Health
    from ..core.engine.mapping import MapperStage
    from ..core.engine.offline import mapper_factory
    from ..core.engine.poses import PoseStage
    from ..core.engine.records import EmbeddingRecord, EmbeddingSpec
    from ..core.engine.worker import Worker
    from ..core.field.mapper import Mapper, kept_settings_text

    class MapperNode(ReadOnlyConfig, Node):
        def __init__(self) -> None:
            super().__init__("mapper", automatically_declare_parameters_from_overrides=True)
            self.cfg = declare_config(self)
            if self.cfg.mapper.num_threads > 0:  # this process is the mapper's
                torch.set_num_threads(self.cfg.mapper.num_threads)
                cv2.setNumThreads(self.cfg.mapper.num_threads)  # the odometry's OpenCV
            self.node_cfg, self.topics = self.cfg.mapper_node, self.cfg.topics
            # The frame of the published keyframe and view poses: topics.world_frame, or
            # the frame_id the pose topic's messages carry (on_pose).
            self.world_frame = self.topics.world_frame
            self.health = Health("mapper", ros_logger(self), self.node_cfg.log_throttle_s)
            self.stage = MapperStage(self.node_cfg, mapper_factory(self.cfg), self.health)
            try:
                from tf2_msgs.msg import TFMessage
            except ImportError:  # no tf2_msgs wheel on PyPI: /tf cannot be subscribed
                TFMessage = None
            self.poses = PoseStage(self.node_cfg, self.cfg.odometry, self.topics, self.health,
                                   tf_available=TFMessage is not None)
            # While pose_source auto has not chosen (up to pose_auto_wait_s of frames), the
            # frames' colour, depth and embeddings wait for the poses the choice hands on.
            self._deciding = self.poses.mode is None
            self.stage.set_pose_choice_open(self._deciding)
            self.pub_pose = None
            self._own_poses: dict[int, None] = {}  # stamps of the poses we published lately
            self._segment = 0
            self.exit_code = 0
            self.spec: EmbeddingSpec | None = None
            path = self.node_cfg.map_path
            if path:  # a folder given as the map: one line at start, not a failed save later
                from ..core.torchfile import check_save_path
                check_save_path(path, "mapper_node.map_path")
            if path and os.path.isfile(path):
                # a bad file: clear error, exit 2
                self.stage.load(path, lambda p: Mapper.load_configured(p, self.cfg))
                self.spec = self.stage.spec
                self.get_logger().info(f"loaded map {path} ({self.stage.mapper.iterations} "
                                       f"iterations, {len(self.stage.mapper.buffer)} "
                                       "keyframes)")
                kept = self.stage.mapper.kept_settings(self.cfg)
                if kept:
                    self.get_logger().warning(
                        f"the loaded map keeps the settings it was built with: "
                        f"{kept_settings_text(kept)}; they apply to a new map only")
            self.frame_id = self.topics.camera_frame
            # Inputs converted by the callbacks, paired and admitted by the intake thread
            # (module doc); the oldest goes when the thread is sync_horizon_s behind.
            self.intake: collections.deque = collections.deque(
                maxlen=len(self.stage.STREAMS) * self.stage.pairing_capacity)
            self._intake_lock = threading.Lock()  # an intake job, or a map reset
            q = sensor_qos(self.node_cfg.queue_size)
            self.create_subscription(input_image_type(self.topics.color), self.topics.color,
                                     self.on_color, q)
            self.create_subscription(input_image_type(self.topics.depth), self.topics.depth,
                                     self.on_depth, q)
            self.create_subscription(PoseStamped, self.topics.pose, self.on_pose, q)
            if TFMessage is not None:
                self.create_subscription(TFMessage, self.topics.tf,
                                         lambda m: self.on_tf(m, False), q)
                self.create_subscription(TFMessage, self.topics.tf_static,
                                         lambda m: self.on_tf(m, True), latched_qos())
            self.create_subscription(Image, self.topics.embedding, self.on_embedding,
                                     view_qos(self.node_cfg.queue_size))
            self.create_subscription(CameraInfo, self.topics.camera_info, self.on_info,
                                     sensor_qos())
            self.create_subscription(String, self.topics.embedding_spec, self.on_spec,
                                     latched_qos())
            self.create_subscription(Image, self.topics.labels, self.on_labels, sensor_qos(10))
            depth = 2 * self.node_cfg.max_in_flight + 2
            views = (("embedding", self.topics.rendered_embedding),
                     ("entropy", self.topics.entropy), ("depth", self.topics.view_depth),
                     ("color", self.topics.view_color))
            self.pub = {name: self.create_publisher(Image, topic, view_qos(depth))
                        for name, topic in views}
            self.pub_info = self.create_publisher(CameraInfo, self.topics.view_camera_info,
                                                  view_qos(depth))
            self.pub_view_pose = self.create_publisher(PoseStamped, self.topics.view_pose,
                                                       view_qos(depth))
            self.pub_spec = self.create_publisher(String, self.topics.rendered_spec,
                                                  latched_qos())
            self.pub_keyframes = self.create_publisher(PoseStamped, self.topics.keyframes,
                                                       view_qos(50))
            self.pub_diag = self.create_publisher(DiagnosticArray, self.topics.diagnostics, 10)
            self.create_service(Trigger, "~/save_map", self.on_save)
            self.create_service(Trigger, "~/reset", self.on_reset)
            self.input_watch = InputWatch(self, [self.topics.color, self.topics.depth,
                                                 self.topics.embedding], health=self.health)
            self.stage.stream_topics = {s: self.resolve_topic_name(getattr(self.topics, s))
                                        for s in ("color", "depth", "embedding", "pose")}
            self.stage.spec_topic = self.resolve_topic_name(self.topics.embedding_spec)
            wall_timer(self, 1.0, self.on_tick)
            if self.node_cfg.map_path and self.node_cfg.save_period_s > 0:
                wall_timer(self, self.node_cfg.save_period_s, self.autosave)
            if self.spec is not None:
                self.pub_spec.publish(String(data=self.spec.to_json()))
            self.worker = Worker("render", self.step, self.health).start()
            self.intake_worker = Worker("intake", self._intake_step, self.health).start()

        # ------------------------------------------------------------ input
        def _queue(self, job) -> None:
            """Hand ``job`` (no arguments) to the intake thread; called by the callbacks."""
            if len(self.intake) == self.intake.maxlen:
                self.health.problem("intake_overflow", "the mapper's intake is "
                                    f"{self.intake.maxlen} messages behind its inputs: the "
                                    "oldest is dropped (the machine is too slow for the "
                                    "camera's rate and size)")
            self.intake.append(job)
            self.intake_worker.notify()

        def _intake_step(self, cancel) -> bool:
            try:
                job = self.intake.popleft()
            except IndexError:
                return False
            with self._intake_lock:
                job()
            return True

        def _convert(self, stream: str, fn, msg, topic: str):
            """``fn(msg, topic)``, or None if it refuses the message: problem
            ``bad_<stream>``, and input ``stream`` arrives but is refused."""
            try:
                return fn(msg, topic)
            except ValueError as err:
                self.health.refuse(stream, f"bad_{stream}", f"{stream} message skipped: {err}",
                                   str(err), stamp_of(msg))
                return None

        def _offer(self, stream: str, stamp: int, value) -> None:
            if value is None:
                return
            for job in self.stage.offer(stream, stamp, value):
                if job.keyframe:
                    self.pub_keyframes.publish(pose_msg(job.frame.pose, job.frame.stamp_ns,
                                                        self.world_frame))
            self.worker.notify()

        def _offer_poses(self, poses) -> None:
            """Poses from the pose stage to the mapper stage (and out, from tf/odometry)."""
            if self._deciding:  # the choice made: the frames tracked meanwhile go first
                poses = self.poses.poll() + list(poses)
            for stamp, T in poses:
                if self.poses.publishes:
                    if self.pub_pose is None:
                        self.pub_pose = self.create_publisher(PoseStamped, self.topics.pose,
                                                              view_qos(10))
                    self._own_poses[int(stamp)] = None  # before it can come back (on_pose)
                    if len(self._own_poses) > 256:
                        del self._own_poses[next(iter(self._own_poses))]
                    self.pub_pose.publish(pose_msg(T, stamp, self.topics.world_frame))
                self._check_segment()
                self._offer("pose", stamp, T)
            if self._deciding and self.poses.mode is not None and not self.poses.waiting:
                self._deciding = False
                self.stage.set_pose_choice_open(False)

        def _check_segment(self) -> None:
            odo = self.poses.odometry
            if odo is not None and odo.segment != self._segment:
                self._segment = odo.segment
                if self.stage.mapper is not None:
                    self.health.problem("new_segment", "odometry lost track for too long and "
                                        "started a new map segment: the field restarts")
                    self.stage.mapper.reset()

        def _image(self, stream: str, msg, value) -> None:
            stamp = header_ns(msg)
            self._offer(stream, stamp, value)
            self._offer_poses(self.poses.offer_image(stream, stamp, value,
                                                     self.stage.intrinsics))

        def on_color(self, msg) -> None:
            value = self._convert("color", msgconv.rgb_from_image, msg, self.topics.color)
            if value is not None:
                self._queue(lambda: self._image("color", msg, value))

        def on_depth(self, msg) -> None:
            value = self._convert("depth", msgconv.depth_from_image, msg, self.topics.depth)
            if value is not None:
                if msg.header.frame_id:  # a refused message's frame_id is not taken
                    self.frame_id = msg.header.frame_id
                self._queue(lambda: self._image("depth", msg, value))

        def on_pose(self, msg) -> None:
            if self.pub_pose is not None:
                # Our own poses (tf/odometry) come back here; another publisher's are
                # ignored too, but said (a SLAM started after pose_source auto had chosen
                # odometry was ignored in silence, its poses mixed with ours on the topic).
                if header_ns(msg) not in self._own_poses:
                    how = ("pose_source auto chose it: no pose came within "
                           "pose_auto_wait_s of the first frame"
                           if self.node_cfg.pose_source == "auto" else "pose_source")
                    self.health.problem(
                        "pose_ignored", f"poses from another publisher on {self.topics.pose} "
                        f"are ignored: this mapper takes its poses from {self.poses.mode} "
                        f"({how}) and publishes them on that topic; to use that "
                        "publisher's poses, restart the mapper with -p "
                        "mapper_node.pose_source:=topic (or start it before the camera)")
                return
            pose = self._convert("pose", msgconv.pose_to_matrix, msg, self.topics.pose)
            if pose is None:
                return
            frame = msg.header.frame_id.lstrip("/")
            if frame and frame != self.world_frame:
                # The keyframe and view poses are published in the frame the poses come
                # in, so that they sit in the user's tf tree whatever topics.world_frame.
                self.world_frame = frame
                self.health.note("pose_frame", f"poses on {self.topics.pose} are in frame "
                                 f"'{frame}' (topics.world_frame is "
                                 f"'{self.topics.world_frame}'): the keyframe and view "
                                 f"poses are published in '{frame}'")
            self._queue(lambda: self._offer_poses(self.poses.offer_pose(header_ns(msg), pose)))

        def on_tf(self, msg, static: bool) -> None:
            self._queue(lambda: self._tf(msg, static))

        def _tf(self, msg, static: bool) -> None:
            try:
                poses = self.poses.offer_tf(msg, static)
            except ValueError as err:
                self.health.problem("bad_tf", f"{self.topics.tf}: message skipped: {err}")
                return
            self._offer_poses(poses)

        def on_info(self, msg) -> None:
            intr = self._convert(
                "camera_info", lambda m, t: msgconv.camera_info_to_intrinsics(
                    m, t, self.topics.distortion), msg, self.topics.camera_info)
            if intr is not None:
                self._queue(lambda: self.stage.offer_info(intr))

        def on_spec(self, msg) -> None:
            try:
                spec = EmbeddingSpec.from_json(msg.data)
            except ValueError as err:
                self.health.problem("bad_spec", f"{self.topics.embedding_spec}: {err}")
                return
            if self.stage.spec is not None and spec != self.stage.spec:
                self.health.problem("spec_mismatch", f"the embedding spec {spec.to_json()} "
                                    f"differs from the map's {self.stage.spec.to_json()}: its "
                                    "embeddings are refused (reset the map to change backbone)")
            self.spec = spec
            self.pub_spec.publish(String(data=spec.to_json()))
            for held in self.stage.release_for_spec():  # those that came before it
                self.on_embedding(held)

        def on_embedding(self, msg) -> None:
            if self.spec is None:  # held for it (the latched spec may come second)
                self.stage.hold_for_spec(header_ns(msg), msg)
                return
            arr = self._convert("embedding", msgconv.image_to_array, msg,
                                self.topics.embedding)
            if arr is None:
                return
            arr = arr[:, :, None] if arr.ndim == 2 else arr
            try:
                self.spec.check(arr, self.topics.embedding)
            except ValueError as err:
                self.health.refuse("embedding", "bad_embedding", f"embedding skipped: {err}",
                                   str(err), stamp_of(msg))
                return
            stamp = header_ns(msg)
            record = EmbeddingRecord(stamp, arr, self.spec)
            self._queue(lambda: self._embedding(stamp, record))

        def _embedding(self, stamp: int, record) -> None:
            self._offer("embedding", stamp, record)
            self._offer_poses(self.poses.offer_embedding(stamp, self.stage.intrinsics))

        def on_labels(self, msg) -> None:
            self.stage.labelled(header_ns(msg))
            self.worker.notify()

        # ------------------------------------------------------------ output
        def step(self, cancel) -> bool:
            job = self.stage.next_view()
            if job is None:
                return False
            try:
                view = self.stage.render_view(job, cancel)
            except BaseException:
                self.stage.release(job)
                raise
            stamp, f, fid = view.stamp_ns, view.frame, self.frame_id
            t = self.topics
            # Depth and colour first: discovery pairs the view once every piece arrived.
            self.pub["depth"].publish(image_msg(view.view_depth, "32FC1", stamp, fid,
                                                t.view_depth))
            self.pub["color"].publish(image_msg(f.rgb, "rgb8", stamp, fid, t.view_color))
            self.pub_info.publish(camera_info_msg(f.intrinsics, stamp, fid))
            self.pub_view_pose.publish(pose_msg(f.pose, stamp, self.world_frame))
            self.pub["entropy"].publish(image_msg(view.entropy, "32FC1", stamp, fid,
                                                  t.entropy))
            self.pub["embedding"].publish(image_msg(view.embedding,
                                                    f"32FC{view.embedding.shape[2]}", stamp,
                                                    fid, t.rendered_embedding))
            self.health.count("published")
            return True

        def on_tick(self) -> None:
            self.stage.expire_held()
            held = self.stage.held_for_spec
            self.input_watch.check(self.stage.sync.received + len(self.intake) + held)
            if not self.stage.check_training():
                self.worker.cancel.set()  # no stale output after the field died
            if self._deciding:  # a stream that ended within pose_auto_wait_s is decided too
                self._queue(lambda: self._offer_poses(self.poses.poll()))
            backlog = len(self.intake) + int(self.intake_worker.busy)
            self.health.gauge("pending", self.stage.pending + int(self.worker.busy) + backlog
                              + self.poses.waiting + held)
            self.health.gauge("intake_backlog", backlog)
            self.health.gauge("embeddings_held_for_spec", held)
            # Whether the embedding node is seen yet: bringup starts a bag only then.
            self.health.gauge("upstream_publishers", self.count_publishers(self.topics.embedding))
            self.health.gauge("keyframes_in_map", len(self.stage.mapper.buffer)
                              if self.stage.mapper is not None else 0)
            self.pub_diag.publish(diagnostics_msg(self, [(self.health, (
                "frames_paired", "keyframes", "views"))]))

        def autosave(self) -> None:
            try:
                if self.stage.save(self.node_cfg.map_path):
                    self.get_logger().debug(f"saved map to {self.node_cfg.map_path}")
            except (OSError, RuntimeError, ValueError) as err:
                self.health.problem("save_failed", f"could not save the map: {err}")

        def on_save(self, request, response):
            path = self.node_cfg.map_path or "neurncd_map.pt"
            try:
                ok = self.stage.save(path)
                response.success = ok
                response.message = (f"saved map to {path}" if ok
                                    else "no map yet: no keyframe admitted")
            except (OSError, RuntimeError, ValueError) as err:
                response.success, response.message = False, f"could not save {path}: {err}"
            return response

        def on_reset(self, request, response):
            with self._intake_lock:  # not in the middle of admitting a keyframe
                self.stage.reset_map()
                self.poses.reset_odometry()  # a new room: its first frame is the origin
                self._segment = 0
            response.success = True
            response.message = "map reset: the field and its keyframes forgotten" + (
                "; the odometry starts again at the next frame"
                if self.poses.odometry is not None else "")
            self.get_logger().info(response.message)
            return response

        def close(self) -> None:
            self.intake_worker.stop(timeout=3.0)
            self.worker.stop(timeout=3.0)
            self.stage.stop()
            if self.node_cfg.map_path and self.stage.mapper is not None:
                try:
                    self.stage.save(self.node_cfg.map_path)
                    self.get_logger().info(f"saved map to {self.node_cfg.map_path}")
                except (OSError, RuntimeError, ValueError) as err:
                    self.get_logger().error(f"could not save the map: {err}")
            left = len(self.intake) + self.stage.held_for_spec
            self.get_logger().info(self.stage.summary() + f", problems "
                                   f"{dict(self.health.problems)}; {self.poses.summary()}"
                                   + (f"; {left} input message{'s' * (left != 1)} not yet "
                                      "taken in" if left else ""))

    return MapperNode()


def main(argv=None) -> int:
    return run_node(make_node, "mapper", DESCRIPTION, argv, preload=PRELOAD)


if __name__ == "__main__":
    raise SystemExit(main())
