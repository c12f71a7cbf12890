"""Discovery node: depth + rendered embedding + entropy in, known and novel labels out.

Pairs each depth frame with the mapper's rendered embedding and entropy of the
same stamp (and the camera's colour image when ``segmentation.colour_edges``),
runs the core ``Discoverer`` (segmentation, feature modulation, Markov
clustering, stable ids) and publishes the label image, its colour rendering and
the class table (transient local, so late subscribers get it).
"""

from __future__ import annotations

import json

import cv2

from ..core import msgconv
from ..core.discovery.labeller import Discoverer  # before rclpy: scipy/torch load first
from ..core import classes
from .common import (PairedFrames, StampMatcher, declare_config, fit_to, image_msg,
                     latched_qos, output_qos, run_node, sensor_qos)

DESCRIPTION = ("Segments depth into convex segments, clusters them on the rendered "
               "embedding and entropy, and publishes /neurncd/labels (mono16), "
               "/neurncd/labels_color (rgb8) and /neurncd/classes (JSON).")


def make_node():
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image
    from std_msgs.msg import String


    class DiscoveryNode(PairedFrames, Node):
        def __init__(self) -> None:
            super().__init__("discovery",
                             automatically_declare_parameters_from_overrides=True)
            self.cfg = declare_config(self)
            node_cfg, self.topics = self.cfg.discovery_node, self.cfg.topics
            self.throttle = node_cfg.log_throttle_s
            self.discoverer = None
            # Colour edges need the camera's colour image of the same stamp.
            self.use_colour = self.cfg.segmentation.colour_edges
            streams = ("depth", "embedding", "entropy") + (("color",) if self.use_colour
                                                           else ())
            self.matcher = StampMatcher(streams, int(node_cfg.sync_tolerance_ms * 1e6),
                                        node_cfg.queue_size)
            q = sensor_qos(node_cfg.queue_size)
            if self.use_colour:
                self.create_subscription(Image, self.topics.color,
                                         lambda m: self.offer("color", m), q)
            self.create_subscription(Image, self.topics.depth,
                                     lambda m: self.offer("depth", m), q)
            self.create_subscription(Image, self.topics.rendered_embedding,
                                     lambda m: self.offer("embedding", m), q)
            self.create_subscription(Image, self.topics.entropy,
                                     lambda m: self.offer("entropy", m), q)
            self.create_subscription(CameraInfo, self.topics.camera_info, self.on_info,
                                     sensor_qos())
            self.pub_labels = self.create_publisher(Image, self.topics.labels, output_qos())
            self.pub_color = self.create_publisher(Image, self.topics.labels_color,
                                                   output_qos())
            self.pub_classes = self.create_publisher(String, self.topics.classes,
                                                     latched_qos())
            self.labelled = 0

        def on_frame(self, stamp: int, group: dict) -> None:
            if self.intrinsics is None:
                raise ValueError(f"no camera info yet on {self.topics.camera_info}")
            depth_msg = group["depth"]
            depth = msgconv.depth_from_image(depth_msg, self.topics.depth)
            emb = msgconv.image_to_array(group["embedding"], self.topics.rendered_embedding)
            ent = msgconv.image_to_array(group["entropy"], self.topics.entropy)
            if emb.ndim == 2:
                emb = emb[:, :, None]
            if ent.ndim != 2:
                raise ValueError(f"{self.topics.entropy}: expected 32FC1, got "
                                 f"{group['entropy'].encoding}")
            intr = self.intrinsics
            if depth.shape != intr.shape:
                raise ValueError(f"depth is {depth.shape[1]}x{depth.shape[0]} but camera "
                                 f"info says {intr.width}x{intr.height}")
            h, w = depth.shape
            emb, ent = fit_to(emb, h, w), fit_to(ent, h, w)
            rgb = None
            if self.use_colour:
                rgb = msgconv.rgb_from_image(group["color"], self.topics.color)
                if rgb.shape[:2] != (h, w):
                    rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
            if self.discoverer is None:
                channel_to_id = classes.channel_to_id(emb.shape[2])
                self.discoverer = Discoverer(self.cfg.discovery, channel_to_id,
                                             mcl_cfg=self.cfg.mcl,
                                             seg_cfg=self.cfg.segmentation,
                                             mod_cfg=self.cfg.modulation)
            labels = self.discoverer.process(depth, intr, emb, ent, stamp, rgb)
            frame_id = depth_msg.header.frame_id
            self.pub_labels.publish(image_msg(labels, "mono16", stamp, frame_id,
                                              self.topics.labels))
            self.pub_color.publish(image_msg(classes.colourise(labels), "rgb8", stamp,
                                             frame_id, self.topics.labels_color))
            self.pub_classes.publish(String(data=json.dumps(
                {str(k): v for k, v in self.discoverer.classes().items()})))
            self.labelled += 1

        def close(self) -> None:
            self.get_logger().info(f"frames labelled {self.labelled}, skipped {self.skipped}")

    return DiscoveryNode()


def main(argv=None) -> int:
    return run_node(make_node, "discovery", DESCRIPTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
