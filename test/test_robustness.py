"""Robustness over real DDS, the nodes in separate processes, as in the field.

- 500 random malformed messages across every input topic of the three nodes (unknown
  encodings, step/size mismatch, NaN/inf/zero depth, non-finite pose, broken and changing
  camera info, bad embeddings and views, duplicate and out-of-order stamps): no node dies,
  each kind of problem is logged, valid frames keep being labelled;
- the mapper killed with SIGKILL and restarted with its saved map carries on, and labels
  resume;
- a truncated bag makes replay exit non-zero, naming the file.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from neurncd_ros.core import msgconv

import rosutil
from rosutil import REPO, apply_ros_env, diagnostics_of, ros_env, spin_until, start, stop

pytestmark = pytest.mark.ros

SEC = 1_000_000_000


@pytest.fixture(scope="module")
def frames():
    from neurncd_ros import synth
    return list(synth.generate(1004, 60, synth.SynthConfig(width=96, height=72, fps=6.0)))


class Graph:
    """The three nodes in their own processes, and a test node that feeds and listens."""

    def __init__(self, tmp, frames) -> None:
        apply_ros_env(rosutil.domain(9))
        import rclpy
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import CameraInfo, Image

        from neurncd_ros.nodes.common import output_qos, sensor_qos

        self.tmp, self.frames = tmp, frames
        self.map_path = tmp / "map.pt"
        self.logs = {n: tmp / f"{n}.log" for n in ("embedding", "mapper", "discovery")}
        self.procs = {n: self._start(n) for n in self.logs}
        rclpy.init()
        self.node = rclpy.create_node("robustness_feeder")
        self.labels: list = []
        self.node.create_subscription(Image, "/neurncd/labels", self.labels.append,
                                      output_qos(100))
        self.diag = diagnostics_of(self.node, ("embedding", "mapper", "discovery"))
        self.pub = {}
        for topic, mtype in (("/camera/color/image_raw", Image),
                             ("/camera/depth/image_raw", Image),
                             ("/camera/color/camera_info", CameraInfo),
                             ("/camera/pose", PoseStamped),
                             ("/neurncd/embedding", Image),
                             ("/neurncd/rendered_embedding", Image),
                             ("/neurncd/entropy", Image),
                             ("/neurncd/view/depth", Image),
                             ("/neurncd/view/color", Image),
                             ("/neurncd/view/camera_info", CameraInfo)):
            qos = sensor_qos(20) if topic.startswith("/camera") else output_qos(20)
            self.pub[topic] = self.node.create_publisher(mtype, topic, qos)
        self.next_stamp = 100 * SEC

    def _start(self, name: str, *extra: str):
        args = ["-m", f"neurncd_ros.nodes.{name}", "--ros-args", *extra,
                "-p", "mapper_node.save_period_s:=2.0",
                "-p", f"mapper_node.map_path:={self.map_path}",
                "-p", "embedding_node.log_throttle_s:=0.5",
                "-p", "mapper_node.log_throttle_s:=0.5",
                "-p", "discovery_node.log_throttle_s:=0.5"]
        return start(args, ros_env(rosutil.domain(9)), self.logs[name])

    def spin(self, seconds: float) -> None:
        import rclpy
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            rclpy.spin_once(self.node, timeout_sec=0.01)

    def send_frame(self, i: int, stamp: int | None = None) -> int:
        """Publish a valid frame (colour, depth, camera info, pose) with a fresh stamp."""
        from neurncd_ros.nodes.common import camera_info_msg, image_msg, pose_msg

        f = self.frames[i % len(self.frames)]
        if stamp is None:
            stamp = self.next_stamp
            self.next_stamp += SEC // 6
        self.pub["/camera/color/camera_info"].publish(camera_info_msg(f.intrinsics, stamp,
                                                                      "camera"))
        self.pub["/camera/pose"].publish(pose_msg(f.pose, stamp, "world"))
        self.pub["/camera/color/image_raw"].publish(image_msg(f.rgb, "rgb8", stamp, "camera"))
        self.pub["/camera/depth/image_raw"].publish(
            image_msg(np.round(f.depth * 1000).astype(np.uint16), "16UC1", stamp, "camera"))
        return stamp

    def labelled_after(self, stamp: int) -> list[int]:
        return [s for s in (msgconv.stamp_to_ns(m.header.stamp) for m in self.labels)
                if s >= stamp]

    def feed_until_labelled(self, since: int, timeout: float, start_index: int = 0) -> bool:
        end = time.monotonic() + timeout
        i = start_index
        while time.monotonic() < end:
            self.send_frame(i)
            i += 1
            self.spin(1 / 6)
            if self.labelled_after(since):
                return True
        return False

    def alive(self) -> dict[str, int | None]:
        return {n: p.poll() for n, p in self.procs.items()}

    def log(self, name: str) -> str:
        return self.logs[name].read_text()

    def close(self) -> None:
        import rclpy
        codes = {n: stop(p, timeout=30) for n, p in self.procs.items()}
        self.node.destroy_node()
        rclpy.shutdown()
        return codes


def _malformed(g: Graph, rng: np.random.Generator, kind: str) -> None:
    """Publish one malformed message of ``kind`` (stamps never match a valid frame)."""
    from neurncd_ros.core.camera import Intrinsics
    from neurncd_ros.nodes.common import camera_info_msg, image_msg, make_image, pose_msg

    f = g.frames[int(rng.integers(len(g.frames)))]
    stamp = int(50 * SEC + rng.integers(0, 10 * SEC))
    h, w = f.depth.shape
    if kind == "unknown_encoding":
        topic = str(rng.choice(["/camera/color/image_raw", "/camera/depth/image_raw",
                                "/neurncd/rendered_embedding", "/neurncd/view/depth"]))
        msg = image_msg(f.rgb, "rgb8", stamp, "camera")
        msg.encoding = "yuv422_weird"
        g.pub[topic].publish(msg)
    elif kind == "size_mismatch":
        topic = str(rng.choice(["/camera/color/image_raw", "/camera/depth/image_raw",
                                "/neurncd/embedding", "/neurncd/entropy"]))
        fields = msgconv.image_fields(f.rgb, "rgb8")
        fields["height"] = h + 7  # step * height no longer matches the data
        g.pub[topic].publish(make_image(fields, stamp, "camera"))
    elif kind == "bad_depth":  # a whole frame whose depth is NaN, inf, negative or zero
        value = [np.nan, np.inf, -1.0, 0.0][int(rng.integers(4))]
        d = np.full((h, w), value, np.float32)
        stamp = g.next_stamp
        g.next_stamp += SEC // 60
        g.pub["/camera/color/camera_info"].publish(camera_info_msg(f.intrinsics, stamp,
                                                                   "camera"))
        g.pub["/camera/pose"].publish(pose_msg(f.pose, stamp, "world"))
        g.pub["/camera/color/image_raw"].publish(image_msg(f.rgb, "rgb8", stamp, "camera"))
        g.pub["/camera/depth/image_raw"].publish(image_msg(d, "32FC1", stamp, "camera"))
        g.pub["/neurncd/view/depth"].publish(image_msg(d, "32FC1", stamp + 1, "camera"))
    elif kind == "bad_pose":
        msg = pose_msg(f.pose, stamp, "world")
        if rng.random() < 0.5:
            msg.pose.position.x = float("nan")
        else:
            msg.pose.orientation.w, msg.pose.orientation.x = 0.0, 0.0
            msg.pose.orientation.y = msg.pose.orientation.z = 0.0
        g.pub["/camera/pose"].publish(msg)
    elif kind == "bad_camera_info":
        topic = str(rng.choice(["/camera/color/camera_info", "/neurncd/view/camera_info"]))
        msg = camera_info_msg(Intrinsics.from_hfov(w * 2, h * 2, 60.0), stamp, "camera")
        if rng.random() < 0.5:
            msg.k = [0.0] * 9
        g.pub[topic].publish(msg)
    elif kind == "bad_embedding":
        c = int(rng.choice([3, 9, 12]))
        emb = rng.normal(size=(h, w, c)).astype(np.float32)
        emb[0, 0, 0] = np.nan
        topic = str(rng.choice(["/neurncd/embedding", "/neurncd/rendered_embedding"]))
        g.pub[topic].publish(image_msg(emb, f"32FC{c}", stamp, "camera"))
    elif kind == "bad_view":
        g.pub["/neurncd/entropy"].publish(image_msg(np.full((h, w), np.nan, np.float32),
                                                    "32FC1", stamp, "camera"))
        g.pub["/neurncd/view/color"].publish(image_msg(f.rgb[:, : w // 2].copy(), "rgb8",
                                                       stamp, "camera"))
    elif kind == "duplicate_stamp":
        s = g.send_frame(int(rng.integers(60)))
        g.send_frame(int(rng.integers(60)), stamp=s)
    elif kind == "out_of_order_stamp":
        g.send_frame(int(rng.integers(60)), stamp=int(rng.integers(1, 40)) * SEC)
    elif kind == "far_future_stamp":  # a driver's glitch: one frame 10^6 s ahead
        g.send_frame(int(rng.integers(60)), stamp=g.next_stamp + 10**6 * SEC)
    else:
        raise AssertionError(kind)


KINDS = ("unknown_encoding", "size_mismatch", "bad_depth", "bad_pose", "bad_camera_info",
         "bad_embedding", "bad_view", "duplicate_stamp", "out_of_order_stamp",
         "far_future_stamp")


@pytest.fixture(scope="module")
def graph(tmp_path_factory, frames):
    g = Graph(tmp_path_factory.mktemp("graph"), frames)
    try:
        ok = spin_until(g.node, lambda: len(g.diag) == 3, 180)
        assert ok, {n: g.log(n)[-1500:] for n in g.logs}
        assert g.feed_until_labelled(0, 240), {n: g.log(n)[-1500:] for n in g.logs}
        yield g
    finally:
        g.close()


def test_500_malformed_messages_kill_no_node_and_labels_go_on(graph):
    g = graph
    rng = np.random.default_rng(7)
    sent = dict.fromkeys(KINDS, 0)
    for k in range(500):
        kind = KINDS[int(rng.integers(len(KINDS)))]
        _malformed(g, rng, kind)
        sent[kind] += 1
        if k % 10 == 0:
            g.send_frame(k)  # valid frames keep coming meanwhile
        g.spin(0.01)
    assert all(n >= 30 for n in sent.values()), sent
    assert all(code is None for code in g.alive().values()), g.alive()
    mark = g.next_stamp
    assert g.feed_until_labelled(mark, 120), {n: g.log(n)[-2000:] for n in g.logs}
    assert all(code is None for code in g.alive().values()), g.alive()
    spin_until(g.node, lambda: False, 1.5)  # let the nodes' logs and diagnostics flush
    logs = {n: g.log(n) for n in g.logs}
    every = "".join(logs.values())
    assert "Traceback" not in every, every[-3000:]
    # Each kind of problem is named in a (throttled) log line.
    expect = {
        "unknown_encoding": "unsupported image encoding 'yuv422_weird'",
        "size_mismatch": "expected step*height",
        "bad_depth": "of its pixels have a depth measurement",
        "bad_pose": "pose message skipped",
        "bad_camera_info": "camera info",
        "bad_embedding": "embedding skipped",
        "bad_view": "view",
        "duplicate_stamp": "a second message with stamp",
        "out_of_order_stamp": "older than a frame already paired",
        "far_future_stamp": "ahead of the last frame paired",
    }
    missing = {k: v for k, v in expect.items() if v not in every}
    assert not missing, missing
    # Diagnostics count the problems by kind too.
    assert int(g.diag["mapper"].get("problem.bad_pose", 0)) > 0, g.diag["mapper"]


def test_mapper_killed_restarts_from_its_saved_map_and_labels_resume(graph):
    g = graph
    assert spin_until(g.node, lambda: g.map_path.is_file(), 60), g.log("mapper")[-2000:]
    g.spin(2.5)  # one more periodic save with what was learnt since
    g.procs["mapper"].send_signal(signal.SIGKILL)
    g.procs["mapper"].wait(timeout=30)
    # restarted with another keyframe budget, which the loaded map does not take
    g.procs["mapper"] = g._start("mapper", "-p", "keyframes.max_keyframes:=32")
    assert spin_until(g.node, lambda: "loaded map" in g.log("mapper"), 180), \
        g.log("mapper")[-2000:]
    mark = g.next_stamp
    assert g.feed_until_labelled(mark, 180), {n: g.log(n)[-2000:] for n in g.logs}
    assert all(code is None for code in g.alive().values()), g.alive()
    text = g.log("mapper")
    assert "Traceback" not in text
    it = int(text.split("loaded map")[1].split("(")[1].split(" iterations")[0])
    assert it > 0, "the restarted mapper carries on from a trained map"
    assert ("the loaded map keeps the settings it was built with: keyframes.max_keyframes "
            "64 (configured 32)") in text, text[-2000:]


def test_truncated_bag_makes_replay_exit_nonzero_naming_it(tmp_path, frames):
    from neurncd_ros.core.data.bag import write_bag

    bag = tmp_path / "cut"
    write_bag(bag, frames[:20])
    (data_file,) = bag.glob("*.mcap")
    data_file.write_bytes(data_file.read_bytes()[: data_file.stat().st_size // 2])
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.nodes.replay", "--ros-args", "-p",
                        f"replay.bag:={bag}", "-p", "replay.wait_for_subscribers_s:=0.0"],
                       env=ros_env(rosutil.domain(10)), capture_output=True, text=True, timeout=120,
                       cwd=REPO)
    assert r.returncode == 1, r.stdout + r.stderr
    out = r.stdout + r.stderr
    assert data_file.name in out and "truncated" in out and "Traceback" not in out


def test_replay_plays_the_bag_and_exits_zero(tmp_path, frames):
    from neurncd_ros.core.data.bag import bag_topics, write_bag

    bag = tmp_path / "ok.mcap"
    write_bag(bag, frames[:12])
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.nodes.replay", "--ros-args", "-p",
                        f"replay.bag:={bag}", "-p", "replay.wait_for_subscribers_s:=0.0",
                        "-p", "replay.rate:=4.0", "-p", "replay.start_offset_s:=0.5"],
                       env=ros_env(rosutil.domain(11)), capture_output=True, text=True, timeout=120,
                       cwd=REPO)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out
    # 12 frames at 6 Hz, the first 0.5 s skipped: every message of the last 9 frames.
    per_frame = sum(n for _, n in bag_topics(bag).values()) // 12
    n = int(out.split("replay finished: ")[1].split(" messages")[0])
    assert n == 9 * per_frame, out
