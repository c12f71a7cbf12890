"""The whole system over DDS as a user runs it: bringup replays a synthetic bag into the
embedding, mapper and discovery nodes, labels come out per the topic contract, and bringup
stops everything once the bag is labelled; no process outlives it."""

from __future__ import annotations

import signal
import time

import numpy as np
import pytest

from neurncd_ros.core import classes, msgconv

import rosutil
from rosutil import apply_ros_env, node_processes, ros_env, spin_until, start

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def scene_bag(tmp_path_factory):
    from neurncd_ros import synth
    from neurncd_ros.core.data.bag import write_bag
    from neurncd_ros.core.params import build

    cfg = build(synth.SynthConfig, {"width": 160, "height": 120})
    frames = list(synth.generate(1003, 60, cfg))
    path = tmp_path_factory.mktemp("bag") / "scene.mcap"
    write_bag(path, frames, storage="mcap")
    return path, frames


def _wait_gone(domain: int, timeout: float) -> list[int]:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        left = node_processes(domain)
        if not left:
            return []
        time.sleep(0.2)
    return node_processes(domain)


def _shut_down(rclpy, proc) -> None:
    """The test's ROS context, then bringup if it is still running (a failed wait)."""
    rclpy.shutdown()
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def test_bringup_labels_a_replayed_bag_and_stops_when_done(scene_bag, tmp_path):
    """Started in the background as a script would (SIGINT ignored), bringup replays the
    bag, the nodes label every keyframe, the map can be saved on request, and once the
    nodes have drained bringup stops them all and exits 0."""
    bag, frames = scene_bag
    domain = rosutil.domain(7)
    apply_ros_env(domain)
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import Image
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from neurncd_ros.nodes.common import latched_qos, output_qos

    map_path = tmp_path / "map.pt"
    log = tmp_path / "bringup.log"
    # topics.world_frame 'map', the bag's poses in 'world': the mapper publishes its
    # keyframe poses in the frame its poses come in.
    proc = start(["-m", "neurncd_ros.nodes.bringup", "--bag", str(bag), "--ros-args",
                  "-p", f"mapper_node.map_path:={map_path}", "-p", "topics.world_frame:=map",
                  "-p", f"discovery_node.state_path:={tmp_path / 'discovery.pt'}"],
                 ros_env(domain), log, ignore_sigint=True)
    rclpy.init()
    labels, tables, keyframes = [], [], []
    try:
        node = rclpy.create_node("test_listener")
        node.create_subscription(Image, "/neurncd/labels", labels.append, output_qos(100))
        node.create_subscription(String, "/neurncd/classes", tables.append, latched_qos())
        node.create_subscription(PoseStamped, "/neurncd/keyframes", keyframes.append,
                                 output_qos(100))
        assert spin_until(node, lambda: labels and tables, 240), log.read_text()[-3000:]
        # The map can be saved on request while it trains.
        client = node.create_client(Trigger, "/mapper/save_map")
        assert client.wait_for_service(timeout_sec=30)
        future = client.call_async(Trigger.Request())
        assert spin_until(node, future.done, 60)
        assert future.result().success, future.result().message
        assert map_path.is_file() and map_path.stat().st_size > 1000
        # Bringup ends by itself once the bag is played and labelled.
        assert spin_until(node, lambda: proc.poll() is not None, 300), log.read_text()[-3000:]
        node.destroy_node()
    finally:
        _shut_down(rclpy, proc)
    text = log.read_text()
    assert proc.returncode == 0, text[-3000:]
    assert "the nodes have labelled what they received" in text, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    assert not _wait_gone(domain, 30), "node processes outlived bringup"

    stamps = {f.stamp_ns: f for f in frames}
    got = {msgconv.stamp_to_ns(m.header.stamp): m for m in labels}
    kf = {msgconv.stamp_to_ns(m.header.stamp) for m in keyframes}
    assert kf and kf <= set(got), f"keyframes not labelled: {sorted(kf - set(got))}"
    assert {m.header.frame_id for m in keyframes} == {"world"}
    assert "poses on /camera/pose are in frame 'world' (topics.world_frame is 'map')" in text
    for stamp, msg in got.items():
        assert stamp in stamps, "labels must carry the stamp of the frame they label"
        lab = msgconv.image_to_array(msg, "/neurncd/labels")
        assert msg.encoding == "mono16" and lab.shape == stamps[stamp].depth.shape
        assert msg.header.frame_id == "camera"
        ids = np.unique(lab)
        assert np.all((ids <= classes.NUM_CLASSES) | (ids >= classes.NOVEL_ID_START))
        assert (lab > 0).mean() > 0.9, "nearly every pixel of a labelled frame is labelled"
    stamp, frame_id, table = msgconv.class_table_from_text(tables[-1].data)
    assert table and all(v["kind"] in ("known", "novel") for v in table.values())
    for key, v in table.items():
        assert v["name"] == classes.class_name(key)
    # Each table carries the header of its label image, so a subscriber pairs them by
    # stamp: every id the image shows is in its table, with the image's pixel count.
    assert stamp == msgconv.stamp_to_ns(labels[-1].header.stamp) and frame_id == "camera"
    assert {msgconv.class_table_from_text(m.data)[0] for m in tables} <= set(got)
    last = msgconv.image_to_array(labels[-1], "/neurncd/labels")
    ids, counts = np.unique(last, return_counts=True)
    shown = {int(i): int(c) for i, c in zip(ids, counts) if i}
    assert {k: table.get(k, {}).get("pixels") for k in shown} == shown, (shown, table)
    assert "saved map to" in text  # at shutdown too
    # Discovery's state too, with the novel ids of the last table.
    from neurncd_ros.core.discovery.state import load_state
    assert f"saved discovery state to {tmp_path / 'discovery.pt'}" in text
    saved = load_state(tmp_path / "discovery.pt")["discovery"]
    novel = sorted(k for k, v in table.items() if v["kind"] == "novel")
    assert set(novel) <= {k for k, _ in saved["discoverer"]["_novel_members"]["__dict__"]}


def test_bringup_under_a_namespace_with_sim_time(scene_bag, tmp_path):
    """A robot's launch: the graph in /robot1 (its diagnostics and labels relative names),
    use_sim_time with the bag's clock. Bringup sees the nodes come up in their namespace,
    replays with /clock, and stops once they have drained (it used to wait out
    --ready-timeout in silence: it listened to /diagnostics, and on the ROS clock the
    nodes' diagnostics timers never fired before the first /clock)."""
    bag, frames = scene_bag
    domain = rosutil.domain(9)
    apply_ros_env(domain)
    import rclpy
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Image

    from neurncd_ros.nodes.common import output_qos, sensor_qos

    log = tmp_path / "bringup.log"
    proc = start(["-m", "neurncd_ros.nodes.bringup", "--bag", str(bag), "--ready-timeout",
                  "600", "--ros-args", "-r", "__ns:=/robot1", "-p", "use_sim_time:=true",
                  "-p", "topics.diagnostics:=diagnostics", "-p", "topics.labels:=neurncd/labels"],
                 ros_env(domain), log)
    rclpy.init()
    labels, clock = [], []
    try:
        node = rclpy.create_node("test_listener")
        node.create_subscription(Image, "/robot1/neurncd/labels", labels.append,
                                 output_qos(100))
        node.create_subscription(Clock, "/clock", clock.append, sensor_qos(10))
        assert spin_until(node, lambda: labels, 150), log.read_text()[-3000:]
        assert spin_until(node, lambda: proc.poll() is not None, 200), log.read_text()[-3000:]
        node.destroy_node()
    finally:
        _shut_down(rclpy, proc)
    text = log.read_text()
    assert proc.returncode == 0 and "the nodes have labelled what they received" in text, \
        text[-3000:]
    assert "replaying anyway" not in text
    stamps = {f.stamp_ns for f in frames}
    assert {msgconv.stamp_to_ns(m.header.stamp) for m in labels} <= stamps
    assert clock and {msgconv.stamp_to_ns(c.clock) for c in clock} <= stamps
    assert not _wait_gone(domain, 30), "node processes outlived bringup"


def test_no_node_outlives_a_killed_bringup(scene_bag, tmp_path):
    """Even SIGKILL, which bringup cannot handle, leaves no node behind: each child has a
    parent-death signal."""
    bag, _ = scene_bag
    domain = rosutil.domain(8)
    log = tmp_path / "bringup.log"
    proc = start(["-m", "neurncd_ros.nodes.bringup", "--bag", str(bag), "--ros-args",
                  "-p", "replay.loop:=true"], ros_env(domain), log)
    try:
        end = time.monotonic() + 120
        while time.monotonic() < end and len(node_processes(domain)) < 5:
            time.sleep(0.2)
        assert len(node_processes(domain)) == 5, log.read_text()[-2000:]  # bringup + 4
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        assert not _wait_gone(domain, 60), "nodes outlived their killed bringup"
    finally:
        for pid in node_processes(domain):
            try:
                import os
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
