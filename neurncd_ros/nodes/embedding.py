"""Embedding node: RGB-D frames in, per-pixel backbone logits (the semantic embedding) out.

Subscribes colour, depth and camera info, pairs colour and depth by stamp and
runs the backbone in a worker thread on the newest pair only, so callbacks
never wait for the model and stale frames are dropped, not queued.
"""

from __future__ import annotations

import threading
import time

import torch

from ..core import msgconv
from ..core.backbone.backbone import load_backbone  # before rclpy: scipy/torch load first
from .common import (PairedFrames, StampMatcher, declare_config, header_ns, image_msg,
                     output_qos, run_node, sensor_qos)

DESCRIPTION = ("Runs the RGB-D semantic segmentation backbone and publishes the per-pixel "
               "pre-softmax logits as a 32FC<S> image on /neurncd/embedding.")


def make_node():
    from rclpy.node import Node
    from sensor_msgs.msg import CameraInfo, Image


    class EmbeddingNode(PairedFrames, Node):
        def __init__(self) -> None:
            super().__init__("embedding",
                             automatically_declare_parameters_from_overrides=True)
            self.cfg = declare_config(self)
            if self.cfg.backbone.num_threads > 0:  # this process is the backbone's
                torch.set_num_threads(self.cfg.backbone.num_threads)
            node_cfg, topics = self.cfg.embedding_node, self.cfg.topics
            self.topics = topics
            self.throttle = node_cfg.log_throttle_s
            self.backbone = load_backbone(self.cfg.backbone)
            self.get_logger().info(
                f"backbone {self.cfg.backbone.kind} with {self.backbone.channels} channels")
            self.matcher = StampMatcher(("color", "depth"),
                                        int(node_cfg.sync_tolerance_ms * 1e6),
                                        node_cfg.queue_size)
            self.pub = self.create_publisher(Image, topics.embedding, output_qos())
            self.create_subscription(Image, topics.color, self.on_color,
                                     sensor_qos(node_cfg.queue_size))
            self.create_subscription(Image, topics.depth, self.on_depth,
                                     sensor_qos(node_cfg.queue_size))
            self.create_subscription(CameraInfo, topics.camera_info, self.on_info,
                                     sensor_qos())
            self._latest = None
            self._wake = threading.Condition()
            self._stop = False
            self.frames_in = self.frames_out = self.frames_dropped = 0
            self._worker = threading.Thread(target=self._work, name="backbone", daemon=True)
            self._worker.start()

        def on_color(self, msg) -> None:
            self._offer("color", msg)

        def on_depth(self, msg) -> None:
            self._offer("depth", msg)

        def _offer(self, slot: str, msg) -> None:
            match = self.matcher.add(slot, header_ns(msg), msg)
            if match is None:
                return
            with self._wake:
                if self._latest is not None:
                    self.frames_dropped += 1  # the model was busy: keep only the newest
                self._latest = match
                self.frames_in += 1
                self._wake.notify()

        def _work(self) -> None:
            while True:
                with self._wake:
                    while self._latest is None and not self._stop:
                        self._wake.wait(0.5)
                    if self._stop:
                        return
                    stamp, group = self._latest
                    self._latest = None
                try:
                    self._process(stamp, group["color"], group["depth"])
                except ValueError as err:
                    self.get_logger().warning(f"skipped frame {stamp}: {err}",
                                              throttle_duration_sec=self.throttle)
                except Exception as err:  # never let one frame kill the worker
                    self.get_logger().error(f"backbone failed on frame {stamp}: {err!r}",
                                            throttle_duration_sec=self.throttle)

        def _process(self, stamp: int, color_msg, depth_msg) -> None:
            rgb = msgconv.rgb_from_image(color_msg, self.topics.color)
            depth = msgconv.depth_from_image(depth_msg, self.topics.depth)
            if rgb.shape[:2] != depth.shape:
                raise ValueError(f"colour is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                                 f"{depth.shape[1]}x{depth.shape[0]}: depth must be "
                                 "registered to colour")
            t0 = time.perf_counter()
            logits = self.backbone.predict(rgb, depth)
            enc = f"32FC{logits.shape[2]}"
            self.pub.publish(image_msg(logits, enc, stamp, depth_msg.header.frame_id,
                                       self.topics.embedding))
            self.frames_out += 1
            self.get_logger().debug(f"embedding {stamp} in {1e3 * (time.perf_counter() - t0):.0f} ms")

        def close(self) -> None:
            with self._wake:
                self._stop = True
                self._wake.notify()
            self._worker.join(timeout=5)
            self.get_logger().info(f"frames paired {self.frames_in}, published "
                                   f"{self.frames_out}, dropped while busy "
                                   f"{self.frames_dropped}")

    return EmbeddingNode()


def main(argv=None) -> int:
    return run_node(make_node, "embedding", DESCRIPTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
