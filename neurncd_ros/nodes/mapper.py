"""Mapper node: fits the Embedding-NeRF on a keyframe buffer and publishes its renderings.

Colour, depth, pose and the backbone embedding are paired by stamp and offered
to the core ``Mapper`` as keyframes; it trains in its own thread. A timer
renders each keyframe once it has been trained on long enough and publishes
the rendered embedding and its entropy with the keyframe's stamp.
"""

from __future__ import annotations

import os
import threading

import torch

from ..core import msgconv
from ..core.field.mapper import Mapper  # before rclpy: scipy/torch load first
from ..core.frame import Frame
from .common import (PairedFrames, StampMatcher, declare_config, fit_to, image_msg,
                     output_qos, run_node, sensor_qos)

DESCRIPTION = ("Fits the Embedding-NeRF incrementally on RGB-D keyframes and publishes "
               "/neurncd/rendered_embedding (32FC<S>) and /neurncd/entropy (32FC1) per "
               "keyframe. Services ~/save_map and ~/reset (std_srvs/Trigger).")


def make_node():
    from geometry_msgs.msg import PoseStamped
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image
    from std_srvs.srv import Trigger


    class MapperNode(PairedFrames, Node):
        def __init__(self) -> None:
            super().__init__("mapper", automatically_declare_parameters_from_overrides=True)
            self.cfg = declare_config(self)
            if self.cfg.mapper.num_threads > 0:  # this process is the mapper's
                torch.set_num_threads(self.cfg.mapper.num_threads)
            self.node_cfg, self.topics = self.cfg.mapper_node, self.cfg.topics
            self.throttle = self.node_cfg.log_throttle_s
            self.mapper = None
            self.channels = None
            self._lock = threading.Lock()
            if self.node_cfg.map_path and os.path.isfile(self.node_cfg.map_path):
                self.mapper = Mapper.load(self.node_cfg.map_path)
                self.channels = self.mapper.channels
                self.get_logger().info(f"loaded map {self.node_cfg.map_path} "
                                       f"({self.mapper.iterations} iterations)")
                self.mapper.start()
            self.matcher = StampMatcher(("color", "depth", "pose", "embedding"),
                                        int(self.node_cfg.sync_tolerance_ms * 1e6),
                                        self.node_cfg.queue_size)
            q = sensor_qos(self.node_cfg.queue_size)
            self.create_subscription(Image, self.topics.color,
                                     lambda m: self.offer("color", m), q)
            self.create_subscription(Image, self.topics.depth,
                                     lambda m: self.offer("depth", m), q)
            self.create_subscription(PoseStamped, self.topics.pose,
                                     lambda m: self.offer("pose", m), q)
            self.create_subscription(Image, self.topics.embedding,
                                     lambda m: self.offer("embedding", m), q)
            self.create_subscription(CameraInfo, self.topics.camera_info, self.on_info,
                                     sensor_qos())
            self.pub_embedding = self.create_publisher(Image, self.topics.rendered_embedding,
                                                       output_qos())
            self.pub_entropy = self.create_publisher(Image, self.topics.entropy, output_qos())
            self.create_service(Trigger, "~/save_map", self.on_save)
            self.create_service(Trigger, "~/reset", self.on_reset)
            # Rendering a keyframe takes up to a second: its own callback group lets the
            # executor's other threads keep taking frames meanwhile (the core Mapper
            # renders from a snapshot, so both may run at once).
            self.create_timer(self.node_cfg.publish_period_s, self.publish_ready,
                              callback_group=MutuallyExclusiveCallbackGroup())
            self.keyframes_admitted = self.published = 0

        def on_frame(self, stamp: int, group: dict) -> None:
            if self.intrinsics is None:
                raise ValueError(f"no camera info yet on {self.topics.camera_info}")
            rgb = msgconv.rgb_from_image(group["color"], self.topics.color)
            depth = msgconv.depth_from_image(group["depth"], self.topics.depth)
            pose = msgconv.pose_to_matrix(group["pose"], self.topics.pose)
            emb = msgconv.image_to_array(group["embedding"], self.topics.embedding)
            if emb.ndim == 2:
                emb = emb[:, :, None]
            if group["embedding"].encoding[:4] != "32FC":
                raise ValueError(f"{self.topics.embedding}: expected 32FC<S>, got "
                                 f"{group['embedding'].encoding}")
            intr = self.intrinsics
            if rgb.shape[:2] != depth.shape or depth.shape != intr.shape:
                raise ValueError(f"sizes disagree: colour {rgb.shape[1]}x{rgb.shape[0]}, depth "
                                 f"{depth.shape[1]}x{depth.shape[0]}, camera info "
                                 f"{intr.width}x{intr.height}")
            frame = Frame(stamp, rgb, depth, pose, intr).validate()
            with self._lock:
                if self.mapper is None:
                    self.channels = emb.shape[2]
                    self.mapper = Mapper.from_config(self.cfg, self.channels)
                    self.mapper.start()
                    self.get_logger().info(f"mapper started with {self.channels} channels, "
                                           f"backend {self.cfg.mapper.backend}")
                elif emb.shape[2] != self.channels:
                    raise ValueError(f"embedding has {emb.shape[2]} channels, the map has "
                                     f"{self.channels}")
                if self.mapper.add_keyframe(frame, emb):
                    self.keyframes_admitted += 1

        def publish_ready(self) -> None:
            mapper = self.mapper
            if mapper is None:
                return
            for kf in mapper.ready_keyframes(self.cfg.mapper.min_iterations_before_publish):
                intr = kf.intrinsics
                scale = self.node_cfg.render_scale
                try:
                    out = mapper.render(kf.pose, intr, max(1, round(intr.height * scale)),
                                        max(1, round(intr.width * scale)), depth=kf.depth)
                except ValueError as err:  # e.g. ~/reset emptied the map meanwhile
                    self.get_logger().warning(f"keyframe {kf.stamp_ns} not rendered: {err}",
                                              throttle_duration_sec=self.throttle)
                    continue
                emb = fit_to(out["embedding"], intr.height, intr.width)
                ent = fit_to(out["entropy"], intr.height, intr.width)
                self.pub_embedding.publish(image_msg(emb, f"32FC{emb.shape[2]}", kf.stamp_ns,
                                                     "camera", self.topics.rendered_embedding))
                self.pub_entropy.publish(image_msg(ent, "32FC1", kf.stamp_ns, "camera",
                                                   self.topics.entropy))
                self.published += 1

        def on_save(self, request, response):
            path = self.node_cfg.map_path or "neurncd_map.pt"
            if self.mapper is None:
                response.success, response.message = False, "no map yet: no keyframe admitted"
                return response
            try:
                self.mapper.save(path)
                response.success, response.message = True, f"saved map to {path}"
            except OSError as err:
                response.success, response.message = False, f"could not save {path}: {err}"
            return response

        def on_reset(self, request, response):
            if self.mapper is not None:
                self.mapper.reset()
            response.success, response.message = True, "map reset"
            return response

        def close(self) -> None:
            if self.mapper is None:
                return
            self.mapper.stop()
            if self.node_cfg.map_path:
                try:
                    self.mapper.save(self.node_cfg.map_path)
                    self.get_logger().info(f"saved map to {self.node_cfg.map_path}")
                except OSError as err:
                    self.get_logger().error(f"could not save map: {err}")
            self.get_logger().info(f"keyframes admitted {self.keyframes_admitted}, renderings "
                                   f"published {self.published}, frames skipped "
                                   f"{self.skipped}, iterations "
                                   f"{self.mapper.iterations}")

    return MapperNode()


def main(argv=None) -> int:
    return run_node(make_node, "mapper", DESCRIPTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
