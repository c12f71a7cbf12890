"""Discovery node: rendered views in, known and novel labels out.

A thin adapter over the engine's :class:`DiscoveryStage`: the pieces of each
view the mapper publishes (rendered embedding, entropy, the view's depth,
colour, camera info and pose, all with the frame's stamp) are converted and offered
to the stage, which pairs them; a worker labels complete views in order
(segmentation, feature modulation, Markov clustering, stable novel ids) and
publishes the label image, its colour rendering and the class table
(transient local, so late subscribers get it). What the embedding channels
mean arrives latched on ``topics.rendered_spec``. Service ~/reset (std_srvs/Trigger)
forgets the discovered classes (a new room).
"""

from __future__ import annotations

import threading

# Nothing heavy at the top: main() installs the signal handlers before torch loads.
from .common import (diagnostics_msg, header_ns, image_msg, latched_qos, output_qos,
                     ros_logger, run_node, view_qos, wall_timer, InputWatch)
from .parameters import ReadOnlyConfig, declare_config

DESCRIPTION = ("Segments each rendered view's depth into convex segments, clusters them on "
               "the rendered embedding and entropy, and publishes /neurncd/labels (mono16), "
               "/neurncd/labels_color (rgb8) and /neurncd/classes (JSON). Service ~/reset "
               "(std_srvs/Trigger) forgets the discovered classes.")


# Imported by run_node before rclpy (torch, scipy first), once the signal handlers are in.
PRELOAD = ("neurncd_ros.core.engine.discovery",)


def make_node():
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from ..core import classes, msgconv
    from ..core.engine.discovery import DiscoveryStage
    from ..core.engine.health import Health
    from ..core.engine.records import EmbeddingSpec
    from ..core.engine.worker import Worker

    class DiscoveryNode(ReadOnlyConfig, Node):
        def __init__(self) -> None:
            super().__init__("discovery",
                             automatically_declare_parameters_from_overrides=True)
            self.cfg = declare_config(self)
            node_cfg, t = self.cfg.discovery_node, self.cfg.topics
            self.topics = t
            self.health = Health("discovery", ros_logger(self), node_cfg.log_throttle_s)
            self.stage = DiscoveryStage(self.cfg, node_cfg, self.health)
            self.frame_ids: dict[int, str] = {}
            q = view_qos(2 * node_cfg.queue_size)
            convert = {
                "depth": (t.view_depth, Image, msgconv.depth_from_image),
                "color": (t.view_color, Image, msgconv.rgb_from_image),
                "info": (t.view_camera_info, CameraInfo, msgconv.camera_info_to_intrinsics),
                "pose": (t.view_pose, PoseStamped, msgconv.pose_to_matrix),
                "entropy": (t.entropy, Image, msgconv.image_to_array),
                "embedding": (t.rendered_embedding, Image, self._embedding),
            }
            for stream, (topic, mtype, fn) in convert.items():
                self.create_subscription(
                    mtype, topic, lambda m, s=stream, tp=topic, f=fn: self.on_piece(s, tp, f, m),
                    q)
            self.create_subscription(String, t.rendered_spec, self.on_spec, latched_qos())
            self.pub_labels = self.create_publisher(Image, t.labels, output_qos())
            self.pub_color = self.create_publisher(Image, t.labels_color, output_qos())
            self.pub_classes = self.create_publisher(String, t.classes, latched_qos())
            self.pub_diag = self.create_publisher(DiagnosticArray, t.diagnostics, 10)
            self.input_watch = InputWatch(self, [t.rendered_embedding, t.view_depth],
                                          health=self.health)
            self._labelling = threading.Lock()  # a reset waits for the view being labelled
            self.create_service(Trigger, "~/reset", self.on_reset)
            wall_timer(self, 1.0, self.publish_diagnostics)
            self.worker = Worker("discovery", self.step, self.health).start()

        @staticmethod
        def _embedding(msg, topic):
            arr = msgconv.image_to_array(msg, topic)
            return arr[:, :, None] if arr.ndim == 2 else arr

        def on_piece(self, stream: str, topic: str, fn, msg) -> None:
            try:
                value = fn(msg, topic)
            except ValueError as err:
                self.health.problem(f"bad_{stream}", f"{topic}: message skipped: {err}")
                return
            stamp = header_ns(msg)
            if stream == "depth":
                self.frame_ids[stamp] = msg.header.frame_id or self.topics.camera_frame
                if len(self.frame_ids) > 256:  # views whose other parts never came
                    self.frame_ids.pop(min(list(self.frame_ids)), None)
            if self.stage.offer(stream, stamp, value):
                self.worker.notify()

        def on_spec(self, msg) -> None:
            try:
                self.stage.set_spec(EmbeddingSpec.from_json(msg.data))
            except ValueError as err:
                self.health.problem("bad_spec", f"{self.topics.rendered_spec}: {err}")
                return
            self.worker.notify()

        def step(self, cancel) -> bool:
            view = self.stage.take()
            if view is None:
                # Idle: what the last views discovered is saved once save_period_s has
                # passed (it was saved only when a later view came, or at shutdown, which
                # a SIGKILL skips: ids 105-108 were lost so).
                self._save_state(force=False)
                return False
            frame_id = self.frame_ids.pop(view.stamp_ns, self.topics.camera_frame)
            # (a copy of the keys: the callbacks add to frame_ids meanwhile)
            for old in [s for s in list(self.frame_ids) if s < view.stamp_ns]:
                self.frame_ids.pop(old, None)
            try:
                with self._labelling:
                    rec = self.stage.label(view)
            except ValueError as err:
                self.health.problem("view_skipped", f"view {view.stamp_ns} skipped: {err}")
                return True
            t = self.topics
            self.pub_labels.publish(image_msg(rec.labels, "mono16", rec.stamp_ns, frame_id,
                                              t.labels))
            self.pub_color.publish(image_msg(classes.colourise(rec.labels), "rgb8",
                                             rec.stamp_ns, frame_id, t.labels_color))
            self.pub_classes.publish(String(data=msgconv.class_table_text(
                rec.stamp_ns, frame_id, rec.classes)))
            self.health.count("published")
            self._save_state(force=False)
            return True

        def on_reset(self, request, response):
            """~/reset (std_srvs/Trigger): forget the discovered classes (a new room; the
            mapper's ~/reset clears its map)."""
            with self._labelling:
                self.stage.reset()
                # The latched table named the old room's novel ids to every late
                # subscriber until the next view: an empty one says they are gone.
                self.pub_classes.publish(String(data=msgconv.class_table_text(
                    self.get_clock().now().nanoseconds, self.topics.camera_frame, {})))
            response.success = True
            response.message = "discovery reset: novel ids start from 100 again"
            self.get_logger().info(response.message)
            return response

        def _save_state(self, force: bool) -> None:
            """The discovery state to discovery_node.state_path (on the labelling thread,
            between views: nothing changes it meanwhile)."""
            try:
                if self.stage.save_state(force) and force:
                    self.get_logger().info(f"saved discovery state to "
                                           f"{self.stage.node_cfg.state_path}")
            except (OSError, RuntimeError, TypeError) as err:
                self.health.problem("state_save", f"cannot save the discovery state to "
                                    f"{self.stage.node_cfg.state_path}: {err}")

        def publish_diagnostics(self) -> None:
            self.input_watch.check(self.stage.sync.received)
            self.health.gauge("pending", self.stage.pending + int(self.worker.busy))
            # Whether the mapper is seen yet: bringup starts a bag only then.
            self.health.gauge("upstream_publishers",
                              self.count_publishers(self.topics.rendered_embedding))
            self.pub_diag.publish(diagnostics_msg(self, [(self.health, ("views_received",
                                                                        "labelled"))]))

        def close(self) -> None:
            self.worker.stop()
            self._save_state(force=True)
            c = self.health.counts
            self.get_logger().info(f"views received {c['views_received']}, labelled "
                                   f"{c['labelled']}, problems {dict(self.health.problems)}")

    return DiscoveryNode()


def main(argv=None) -> int:
    return run_node(make_node, "discovery", DESCRIPTION, argv, preload=PRELOAD)


if __name__ == "__main__":
    raise SystemExit(main())
