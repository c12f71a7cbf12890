"""Replay node: publishes a bag's messages on their topics at their recorded pace.

The raw CDR bytes read from the bag are published as they are (rclpy takes
serialized messages), so nothing is decoded on the way and any message type
the bag holds is replayed. Used with the project's own synthetic bags and
with converted datasets, instead of ros2 bag play (no rosbag2 wheels exist).
"""

from __future__ import annotations

import importlib
import threading
import time

from .common import declare_config, output_qos, run_node

DESCRIPTION = ("Publishes every message of a bag (mcap or sqlite3) on its recorded topic "
               "and pace. Set the bag with -p replay.bag:=scene.mcap.")


def message_class(msgtype: str):
    """``sensor_msgs/msg/Image`` -> the rclpy message class."""
    parts = msgtype.split("/")
    if len(parts) != 3:
        raise ValueError(f"message type {msgtype!r} is not of the form pkg/msg/Name")
    try:
        return getattr(importlib.import_module(f"{parts[0]}.{parts[1]}"), parts[2])
    except (ImportError, AttributeError) as err:
        raise ValueError(f"message type {msgtype} is not available in this ROS "
                         f"install: {err}") from None


def make_node():
    from rclpy.node import Node

    from ..core.data.bag import iter_raw

    class ReplayNode(Node):
        def __init__(self) -> None:
            super().__init__("replay", automatically_declare_parameters_from_overrides=True)
            self.cfg = declare_config(self).replay
            if not self.cfg.bag:
                raise ValueError("replay.bag is empty: give a bag with -p replay.bag:=PATH")
            self.iter_raw = iter_raw
            self.publishers_by_topic = {}
            self.published = 0
            self.finished = threading.Event()
            self._stop = threading.Event()
            self._thread = threading.Thread(target=self._play, daemon=True, name="replay")
            self._thread.start()

        def _publisher(self, topic: str, msgtype: str):
            pub = self.publishers_by_topic.get(topic)
            if pub is None:
                from .common import latched_qos
                qos = latched_qos() if msgtype == "std_msgs/msg/String" else output_qos(10)
                pub = self.create_publisher(message_class(msgtype), topic, qos)
                self.publishers_by_topic[topic] = pub
            return pub

        def _play(self) -> None:
            time.sleep(self.cfg.start_delay_s)
            while not self._stop.is_set():
                t0_wall = t0_bag = None
                try:
                    for topic, msgtype, stamp, raw in self.iter_raw(self.cfg.bag):
                        if self._stop.is_set():
                            return
                        if t0_bag is None:
                            t0_wall, t0_bag = time.monotonic(), stamp
                        due = t0_wall + (stamp - t0_bag) / 1e9 / self.cfg.rate
                        delay = due - time.monotonic()
                        if delay > 0 and self._stop.wait(delay):
                            return
                        self._publisher(topic, msgtype).publish(raw)
                        self.published += 1
                except ValueError as err:
                    self.get_logger().error(f"replay stopped: {err}")
                    break
                if not self.cfg.loop:
                    break
            self.get_logger().info(f"replay finished: {self.published} messages")
            self.finished.set()

        def close(self) -> None:
            self._stop.set()
            self._thread.join(timeout=2)

    return ReplayNode()


def main(argv=None) -> int:
    return run_node(make_node, "replay", DESCRIPTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
