"""Replay node: publishes a bag's messages on their topics at their recorded pace.

What `ros2 bag play` does, for the bags of this project and any other (there
are no rosbag2 wheels): the raw CDR bytes are published as they are (rclpy
takes serialized messages), so nothing is decoded on the way and any message
type the bag holds is replayed. Before playing it waits, at most
``replay.wait_for_subscribers_s``, until the contract's input topics in the bag
have subscribers (with ``wait_for_graph``, also until the embedding, mapper and
discovery nodes of its namespace report on /diagnostics that they are up and see their
upstream node, as the launch file asks); then it plays at ``rate`` from
``start_offset_s`` and exits 0 at the end of the bag (``loop`` plays it again until
stopped); with ``clock`` it publishes the bag's time on /clock as it goes, for nodes with
``use_sim_time``. A bag that cannot be read (missing, truncated, corrupt) ends it with
exit code 1 and an error naming the file.
"""

from __future__ import annotations

import importlib
import threading
import time

from .common import PIPELINE_NODES, latched_qos, node_connected, output_qos, run_node
from .parameters import ReadOnlyConfig, declare_config

DESCRIPTION = ("Publishes every message of a bag (mcap or sqlite3) on its recorded topic and "
               "pace, then exits. Set the bag with -p replay.bag:=scene.mcap.")


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

    from ..core.data.bag import BagError, bag_topics, iter_raw
    from ..core.topics import compressed_alternatives

    class ReplayNode(ReadOnlyConfig, Node):
        def __init__(self) -> None:
            super().__init__("replay", automatically_declare_parameters_from_overrides=True)
            cfg = declare_config(self)
            self.cfg, t = cfg.replay, cfg.topics
            if not self.cfg.bag:
                raise ValueError("replay.bag is empty: give a bag with -p replay.bag:=PATH")
            self.done = threading.Event()
            self.exit_code = 0
            self.published = 0  # in all passes
            self.in_bag = 0  # messages on the replayed topics, per pass
            self.passes = 0
            self.published_in_pass = 0
            self._started = None  # monotonic time the playing began
            self._stop = threading.Event()
            self.publishers_by_topic = {}
            try:
                topics = bag_topics(self.cfg.bag)
            except BagError as err:
                self.fail(str(err))
                return
            for topic, (msgtype, _) in topics.items():
                try:
                    qos = latched_qos() if msgtype == "std_msgs/msg/String" else output_qos(10)
                    self.publishers_by_topic[topic] = self.create_publisher(
                        message_class(msgtype), topic, qos)
                except ValueError as err:
                    self.get_logger().warning(f"{topic} is not replayed: {err}")
            self.pub_clock = None
            if self.cfg.clock:
                from rosgraph_msgs.msg import Clock
                self.pub_clock = self.create_publisher(Clock, "/clock", output_qos(10))
                self._clock_msg = Clock()
            self.in_bag = sum(count for topic, (_, count) in topics.items()
                              if topic in self.publishers_by_topic)
            self.wait_topics = [x for x in (t.color, t.depth, t.camera_info, t.pose)
                                if x in self.publishers_by_topic]
            # the graph downstream of the inputs (wait_for_graph): the nodes up and each
            # connected to its upstream node, as they report it on /diagnostics (bringup's
            # rule: the graph's own topic lists do not say the DDS endpoints have matched)
            self.connected: dict[str, bool] = {}
            if self.cfg.wait_for_graph:
                from diagnostic_msgs.msg import DiagnosticArray
                self.create_subscription(DiagnosticArray, t.diagnostics, self._on_diag, 50)
            images = sorted(x for x, (mt, _) in topics.items()
                            if mt.startswith("sensor_msgs/msg/") and "Image" in mt)
            for role, want in (("color", t.color), ("depth", t.depth),
                               ("camera_info", t.camera_info)):
                # A bag recorded through image_transport: the nodes read it once told.
                alt = compressed_alternatives(want, topics) if role != "camera_info" else []
                if want not in topics and not alt:
                    # The nodes listen on topics.<role>: nothing of the bag reaches them.
                    self.get_logger().warning(
                        f"the bag has no {want} (topics.{role}), where the nodes listen: "
                        f"they get none; the bag's image topics: {images}")
                if alt:
                    self.get_logger().warning(
                        f"the bag has no {want} but has {alt[0]} ({topics[alt[0]][0]}): start "
                        f"the nodes with -p topics.{role}:={alt[0]} (and this replay too, so "
                        "that it waits for their subscribers)")
            self._thread = threading.Thread(target=self._run, daemon=True, name="replay")
            self._thread.start()

        def fail(self, text: str) -> None:
            self.get_logger().error(f"replay failed: {text}")
            self.exit_code = 1
            self.done.set()

        def _wait_for_subscribers(self) -> None:
            """Until every input topic has a subscriber and the counts have held still for
            ``settle_s``: a publisher sees a subscriber as soon as its own side of the match
            is done, and a first frame published then can miss a node whose side is not
            (or a second node, such as the mapper beside the embedding node, not matched
            yet): one of five bringup runs lost the bag's first frame that way."""
            limit = self.cfg.wait_for_subscribers_s
            if limit <= 0 or not self.wait_topics:
                return
            end = time.monotonic() + limit
            counts, since, missing = None, 0.0, list(self.wait_topics)
            said = False
            while time.monotonic() < end and not self._stop.is_set():
                now = tuple(self.publishers_by_topic[x].get_subscription_count()
                            for x in self.wait_topics)
                missing = [x for x, n in zip(self.wait_topics, now) if n == 0]
                if self.cfg.wait_for_graph:
                    apart = [n for n in PIPELINE_NODES if not self.connected.get(n)]
                    missing += [f"the {n} node up and connected (/diagnostics; "
                                "replay.wait_for_graph)" for n in apart]
                    if self.pub_clock is not None:
                        # nodes on sim time: a frame before their /clock matched is lost;
                        # the replay's own clock (use_sim_time) subscribes too: not counted
                        me = (self.get_name(), self.get_namespace())
                        clocks = sum((e.node_name, e.node_namespace) != me for e in
                                     self.get_subscriptions_info_by_topic("/clock"))
                        missing += ([] if clocks >= len(PIPELINE_NODES) else
                                    ["/clock subscribed by the nodes (replay.wait_for_graph)"])
                        now += (clocks,)
                if missing and not said:  # a wait of up to a minute is not silent
                    said = True
                    self.get_logger().info(f"waiting (at most {limit:g} s, "
                                           f"replay.wait_for_subscribers_s) for subscribers "
                                           f"on {', '.join(missing)}")
                if missing:
                    counts = None
                elif now != counts:
                    counts, since = now, time.monotonic()
                elif time.monotonic() - since >= self.cfg.settle_s:
                    return
                self._stop.wait(0.05)
            if not self._stop.is_set() and missing:
                self.get_logger().warning(f"no subscriber on {', '.join(missing)} after "
                                          f"{limit:g} s: playing anyway")

        def _on_diag(self, msg) -> None:
            for name in PIPELINE_NODES:  # this graph's: the replay's namespace
                state = node_connected(msg, name, self.get_namespace())
                if state is not None:
                    self.connected[name] = state

        def _play_once(self) -> None:
            t0_wall = t0_bag = None
            offset = int(self.cfg.start_offset_s * 1e9)
            first = None
            self.passes += 1
            self.published_in_pass = 0
            for topic, _msgtype, stamp, raw in iter_raw(self.cfg.bag):
                if self._stop.is_set():
                    return
                first = stamp if first is None else first
                if stamp - first < offset:
                    continue
                pub = self.publishers_by_topic.get(topic)
                if pub is None:
                    continue
                if t0_bag is None:
                    t0_wall, t0_bag = time.monotonic(), stamp
                due = t0_wall + (stamp - t0_bag) / 1e9 / self.cfg.rate
                delay = due - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
                if self.pub_clock is not None:  # the bag's time, before what happened then
                    self._clock_msg.clock.sec, self._clock_msg.clock.nanosec = divmod(stamp,
                                                                                      10 ** 9)
                    self.pub_clock.publish(self._clock_msg)
                pub.publish(raw)
                self.published += 1
                self.published_in_pass += 1

        def _run(self) -> None:
            self._wait_for_subscribers()
            if self._stop.is_set() or (self.cfg.delay_s > 0
                                       and self._stop.wait(self.cfg.delay_s)):
                return  # stopped before playing: close() says so
            self._started = time.monotonic()
            try:
                while not self._stop.is_set():
                    self._play_once()
                    if not self.cfg.loop:
                        break
            except BagError as err:
                self.fail(str(err))
                return
            if self._stop.is_set():  # stopped mid-bag: close() says where
                return
            self.get_logger().info(f"replay finished: {self.published} messages in "
                                   f"{time.monotonic() - self._started:.1f} s")
            self._flush()
            self.done.set()

        def _flush(self, timeout_s: float = 2.0) -> None:
            """Wait until reliable subscribers acknowledged the last messages, as a process
            that exits right after publishing could otherwise lose them."""
            from rclpy.duration import Duration

            for pub in self.publishers_by_topic.values():
                try:
                    pub.wait_for_all_acked(Duration(seconds=timeout_s))
                except Exception:  # noqa: BLE001 - best effort; never block the exit
                    pass

        def close(self) -> None:
            self._stop.set()
            thread = getattr(self, "_thread", None)
            if thread is not None:
                thread.join(timeout=2)
            if not self.done.is_set():  # neither at the end of the bag nor failed: stopped
                self.get_logger().info(self.stopped_summary())

        def stopped_summary(self) -> str:
            """Where a replay stopped before the end of its bag, in messages and seconds."""
            if self._started is None:
                return (f"replay stopped before playing (while waiting for subscribers or "
                        f"replay.delay_s): 0 of the bag's {self.in_bag} messages published")
            text = (f"replay stopped after {self.published_in_pass} of the bag's "
                    f"{self.in_bag} messages")
            if self.passes > 1:
                text += f" in pass {self.passes} ({self.published} in all passes)"
            return text + f", {time.monotonic() - self._started:.1f} s after it started"

    return ReplayNode()


def main(argv=None) -> int:
    return run_node(make_node, "replay", DESCRIPTION, argv)


if __name__ == "__main__":
    raise SystemExit(main())
