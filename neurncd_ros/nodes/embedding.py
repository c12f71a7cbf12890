"""Embedding node: RGB-D frames in, the backbone's per-pixel semantic embedding out.

A thin adapter over the engine's :class:`EmbeddingStage`: colour and depth
messages are converted and offered to the stage (which pairs them by stamp
and keeps the newest pair); a worker thread embeds the newest pair and
publishes it, so callbacks never wait for the network. What the channels mean
is published once, latched, on ``topics.embedding_spec``.
"""

from __future__ import annotations

# Nothing heavy at the top: main() installs the signal handlers before torch loads.
from .common import (diagnostics_msg, header_ns, image_msg, input_image_type, latched_qos,
                     output_qos, ros_logger, run_node, sensor_qos, stamp_of, wall_timer,
                     InputWatch)
from .parameters import ReadOnlyConfig, declare_config

DESCRIPTION = ("Runs the RGB-D semantic segmentation backbone on the newest colour+depth pair "
               "and publishes its embedding (32FC<C>: logits, then features) on "
               "/neurncd/embedding, with what the channels mean on /neurncd/embedding/spec.")


# Imported by run_node before rclpy (torch, scipy first), once the signal handlers are in.
PRELOAD = ("neurncd_ros.core.backbone.backbone", "neurncd_ros.core.engine.embedding")


def make_node():
    import torch
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    from ..core import msgconv
    from ..core.backbone.backbone import load_backbone, threshold_warning
    from ..core.engine.embedding import EmbeddingStage
    from ..core.engine.health import Health
    from ..core.engine.worker import Worker

    class EmbeddingNode(ReadOnlyConfig, Node):
        def __init__(self) -> None:
            super().__init__("embedding",
                             automatically_declare_parameters_from_overrides=True)
            self.cfg = declare_config(self)
            node_cfg, self.topics = self.cfg.embedding_node, self.cfg.topics
            if self.cfg.backbone.num_threads > 0:
                torch.set_num_threads(self.cfg.backbone.num_threads)
            self.health = Health("embedding", ros_logger(self), node_cfg.log_throttle_s)
            self.stage = EmbeddingStage(load_backbone(self.cfg.backbone), node_cfg,
                                        self.health)
            self.stage.backbone.warm_up()  # backbone.graph: traced now, not on frame one
            spec = self.stage.spec
            self.get_logger().info(f"backbone {spec.backbone}: {spec.logit_channels} logit + "
                                   f"{spec.feature_channels} feature channels, novelty branch "
                                   f"{'on' if self.stage.backbone.novelty_branch else 'off'}, "
                                   f"{self.stage.backbone.precision} convolutions")
            advice = threshold_warning(self.stage.backbone, self.cfg.discovery.entropy_threshold)
            if advice:
                self.get_logger().warn(advice)
            self.frame_id = self.topics.camera_frame
            self.pub = self.create_publisher(Image, self.topics.embedding, output_qos())
            self.pub_spec = self.create_publisher(String, self.topics.embedding_spec,
                                                  latched_qos())
            self.pub_spec.publish(String(data=spec.to_json()))
            self.pub_diag = self.create_publisher(DiagnosticArray, self.topics.diagnostics, 10)
            q = sensor_qos(node_cfg.queue_size)
            self.create_subscription(input_image_type(self.topics.color), self.topics.color,
                                     self.on_color, q)
            self.create_subscription(input_image_type(self.topics.depth), self.topics.depth,
                                     self.on_depth, q)
            self.input_watch = InputWatch(self, [self.topics.color, self.topics.depth],
                                          health=self.health)
            self.stage.stream_topics = {s: self.resolve_topic_name(getattr(self.topics, s))
                                        for s in ("color", "depth")}
            wall_timer(self, 1.0, self.publish_diagnostics)
            self.worker = Worker("backbone", self.step, self.health).start()

        def on_color(self, msg) -> None:
            try:
                rgb = msgconv.rgb_from_image(msg, self.topics.color)
            except ValueError as err:
                self.health.refuse("color", "bad_color", f"colour image skipped: {err}",
                                   str(err), stamp_of(msg))
                return
            if self.stage.offer("color", header_ns(msg), rgb):
                self.worker.notify()

        def on_depth(self, msg) -> None:
            try:
                depth = msgconv.depth_from_image(msg, self.topics.depth)
            except ValueError as err:
                self.health.refuse("depth", "bad_depth", f"depth image skipped: {err}",
                                   str(err), stamp_of(msg))
                return
            if msg.header.frame_id:
                self.frame_id = msg.header.frame_id
            if self.stage.offer("depth", header_ns(msg), depth):
                self.worker.notify()

        def step(self, cancel) -> bool:
            job = self.stage.take()
            if job is None:
                return False
            try:
                rec = self.stage.embed(*job)
            except ValueError as err:
                self.health.problem("frame_skipped", f"frame {job[0]} skipped: {err}")
                return True
            self.pub.publish(image_msg(rec.embedding, f"32FC{rec.embedding.shape[2]}",
                                       rec.stamp_ns, self.frame_id, self.topics.embedding))
            self.health.count("published")
            return True

        def publish_diagnostics(self) -> None:
            self.input_watch.check(self.stage.sync.received)
            self.health.gauge("pending", self.stage.pending + int(self.worker.busy))
            self.pub_diag.publish(diagnostics_msg(self, [(self.health, ("pairs",
                                                                        "published"))]))

        def close(self) -> None:
            self.worker.stop()
            c = self.health.counts
            self.get_logger().info(
                f"pairs {c['pairs']}, embedded {c['embedded']}, published {c['published']}, "
                f"skipped by the rate limit {c['skipped_rate']}, replaced while busy "
                f"{c['dropped_busy']}, problems {dict(self.health.problems)}")

    return EmbeddingNode()


def main(argv=None) -> int:
    return run_node(make_node, "embedding", DESCRIPTION, argv, preload=PRELOAD)


if __name__ == "__main__":
    raise SystemExit(main())
