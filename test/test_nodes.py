"""The nodes in real rclpy processes over local DDS: answers, stamps, sizes, bad input."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from neurncd_ros.core import classes, msgconv
from neurncd_ros.core.camera import Intrinsics

import rosutil
from rosutil import REPO, apply_ros_env, diagnostics_of, ros_env, spin_until, start, stop

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory):
    from neurncd_ros import synth
    from neurncd_ros.core.data.bag import write_bag

    path = tmp_path_factory.mktemp("bag") / "scene.mcap"
    write_bag(path, synth.generate(1003, 15, synth.SynthConfig(width=96, height=72)))
    return path


@pytest.fixture
def ros_node(request):
    """An rclpy node in this test process, on the test's private domain."""
    domain = rosutil.domain(1)
    apply_ros_env(domain)
    import rclpy
    rclpy.init()
    node = rclpy.create_node("test_client")
    yield node, domain
    node.destroy_node()
    rclpy.shutdown()


def _frame_msgs(stamp_ns: int, w: int = 320, h: int = 240, depth_w: int | None = None):
    from sensor_msgs.msg import CameraInfo

    from neurncd_ros.nodes.common import image_msg

    rng = np.random.default_rng(stamp_ns % 1000)
    rgb = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    dw = depth_w or w
    depth = (1000 + 2000 * rng.random((h, dw))).astype(np.uint16)
    color = image_msg(rgb, "rgb8", stamp_ns, "camera")
    dmsg = image_msg(depth, "16UC1", stamp_ns, "camera")
    info = CameraInfo()
    f = msgconv.camera_info_fields(Intrinsics.from_hfov(w, h, 90.0))
    info.height, info.width, info.distortion_model = f["height"], f["width"], f["distortion_model"]
    info.d, info.k, info.r, info.p = (list(map(float, f[k])) for k in ("d", "k", "r", "p"))
    info.header.stamp.sec, info.header.stamp.nanosec = msgconv.ns_to_stamp(stamp_ns)
    return color, dmsg, info


def test_embedding_node_answers_frame_with_same_stamp_and_size(ros_node, tmp_path):
    node, domain = ros_node
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    from neurncd_ros.core.engine.records import EmbeddingSpec
    from neurncd_ros.nodes.common import latched_qos, output_qos, sensor_qos

    log = tmp_path / "embedding.log"
    proc = start(["-m", "neurncd_ros.nodes.embedding"], ros_env(domain), log)
    got, specs = [], []
    try:
        node.create_subscription(Image, "/neurncd/embedding", got.append, sensor_qos(10))
        node.create_subscription(String, "/neurncd/embedding/spec", specs.append,
                                 latched_qos())
        pubs = {t: node.create_publisher(Image, t, output_qos())
                for t in ("/camera/color/image_raw", "/camera/depth/image_raw")}
        assert spin_until(node, lambda: all(p.get_subscription_count() for p in pubs.values()),
                          60), log.read_text()

        def send(stamp, depth_w=None):
            c, d, _ = _frame_msgs(stamp, depth_w=depth_w)
            pubs["/camera/color/image_raw"].publish(c)
            pubs["/camera/depth/image_raw"].publish(d)

        # A frame whose depth does not match colour is skipped with a log, not a crash.
        for _ in range(10):
            send(2_000_000_000, depth_w=200)
            if spin_until(node, lambda: "frame 2000000000 skipped" in log.read_text(), 3):
                break
        stamp = 2_500_000_000
        for _ in range(10):
            send(stamp)
            if spin_until(node, lambda: any(msgconv.stamp_to_ns(m.header.stamp) == stamp
                                            for m in got), 10):
                break
        match = [m for m in got if msgconv.stamp_to_ns(m.header.stamp) == stamp]
        assert match, log.read_text()
        emb = msgconv.image_to_array(match[0], "/neurncd/embedding")
        assert match[0].encoding == "32FC9"
        assert emb.shape == (240, 320, 9) and emb.dtype == np.float32
        assert np.isfinite(emb).all() and emb.std() > 0
        assert not any(msgconv.stamp_to_ns(m.header.stamp) == 2_000_000_000 for m in got)
        # What the channels mean is latched beside the embedding.
        assert spin_until(node, lambda: specs, 10)
        spec = EmbeddingSpec.from_json(specs[-1].data)
        assert spec.channel_to_id == classes.KNOWN_IDS and spec.feature_channels == 0
        assert proc.poll() is None, "the node died"
    finally:
        code = stop(proc)
    text = log.read_text()
    assert "frame 2000000000 skipped" in text and "registered to colour" in text
    assert code == 0 and "pairs " in text, "the node must shut down cleanly on Ctrl-C"


def test_replay_waits_until_every_subscriber_has_matched(ros_node, small_bag, tmp_path):
    """A subscriber that joins just after the replay saw the first one still gets the
    bag's first frame: the replay plays only once the number of subscribers has held
    still for replay.settle_s (one of five bringup runs lost the first frame when it
    played as soon as one subscriber was there)."""
    from sensor_msgs.msg import Image

    from neurncd_ros.core.data.bag import FrameReader

    node, domain = ros_node
    stamps = [f.stamp_ns for f in FrameReader(small_bag)]
    first, second = [], []
    topic = "/camera/depth/image_raw"
    node.create_subscription(Image, topic, lambda m: first.append(
        msgconv.stamp_to_ns(m.header.stamp)), 20)
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import CameraInfo
    for t, kind in (("/camera/color/image_raw", Image), ("/camera/pose", PoseStamped),
                    ("/camera/color/camera_info", CameraInfo)):  # every input the replay waits for
        node.create_subscription(kind, t, lambda m: None, 20)
    log = tmp_path / "replay.log"
    proc = start(["-m", "neurncd_ros.nodes.replay", "--ros-args", "-p",
                  f"replay.bag:={small_bag}"], ros_env(domain), log)
    try:
        assert spin_until(node, lambda: node.count_publishers(topic) > 0, 120), \
            log.read_text()
        # The scenario: a second node subscribes a moment later (well within settle_s).
        spin_until(node, lambda: False, 0.3)
        node.create_subscription(Image, topic, lambda m: second.append(
            msgconv.stamp_to_ns(m.header.stamp)), 20)
        assert spin_until(node, lambda: len(second) == len(stamps), 120), (second,
                                                                          log.read_text())
        assert proc.wait(timeout=60) == 0, log.read_text()
    finally:
        stop(proc)
    assert second == stamps and first == stamps


@pytest.mark.parametrize("node_name, sig, extra", [
    ("embedding", "SIGINT", []),
    ("mapper", "SIGTERM", []),
    ("discovery", "SIGINT", []),
    ("replay", "SIGTERM", ["replay.loop:=true"]),
])
def test_nodes_stop_cleanly_on_signals_even_with_sigint_ignored(node_name, sig, extra,
                                                                tmp_path, small_bag):
    """Started as `cmd &` from a script (SIGINT ignored), a node still stops on SIGINT and
    SIGTERM: it logs its summary and exits 0."""
    import signal

    domain = rosutil.domain(2 + ["embedding", "mapper", "discovery", "replay"].index(node_name))
    apply_ros_env(domain)
    import rclpy
    rclpy.init()
    node = rclpy.create_node("watcher")
    log = tmp_path / f"{node_name}.log"
    args = ["-p", f"replay.bag:={small_bag}", *sum((["-p", e] for e in extra), [])]
    proc = start(["-m", f"neurncd_ros.nodes.{node_name}", "--ros-args", *args],
                 ros_env(domain), log, ignore_sigint=True)
    try:
        if node_name == "replay":
            from sensor_msgs.msg import Image
            from neurncd_ros.nodes.common import sensor_qos
            seen = []
            node.create_subscription(Image, "/camera/depth/image_raw", seen.append,
                                     sensor_qos(5))
            ready = lambda: bool(seen)  # noqa: E731 - it is playing
        else:
            diag = diagnostics_of(node, (node_name,))
            ready = lambda: node_name in diag  # noqa: E731 - it is up and reporting
        assert spin_until(node, ready, 120), log.read_text()
        proc.send_signal(getattr(signal, sig))
        code = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        node.destroy_node()
        rclpy.shutdown()
    text = log.read_text()
    assert code == 0, text[-2000:]
    assert f"{sig}: shutting down" in text or node_name == "replay", text[-2000:]
    assert "Traceback" not in text, text[-2000:]


@pytest.mark.parametrize("args, expect", [
    (["-p", "mapper.backend:=gpu"],
     "mapper.backend: 'gpu' is not allowed; allowed: one of"),
    (["-p", "mapper.no_such:=1"], "mapper.no_such: unknown parameter"),
    # A section written as a value, in a file: rcl merges files and overrides before the
    # node sees a value, so the node names the file itself.
    (["--params-file", "{ok}", "--params-file", "{bad}"], "mapper: unknown parameter"),
    (["--params-file", "{bad_type}"], "mapper.lambda_embedding"),
])
def test_bad_parameter_stops_node_with_clear_message(args, expect, tmp_path):
    files = {"ok": "/**:\n  ros__parameters:\n    mcl:\n      inflation: 2.0\n",
             "bad": "/**:\n  ros__parameters:\n    mapper: 3\n",
             "bad_type": "mapper:\n  ros__parameters:\n    mapper:\n"
                         "      lambda_embedding: fast\n"}
    paths = {}
    for key, text in files.items():
        paths[key] = tmp_path / f"{key}.yaml"
        paths[key].write_text(text)
    args = [a.format(**paths) for a in args]
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.nodes.mapper", "--ros-args", *args],
                       env=ros_env(rosutil.domain(6)), capture_output=True, text=True,
                       timeout=120, cwd=REPO)
    assert r.returncode == 2, r.stdout + r.stderr
    assert expect in r.stderr
    assert "Traceback" not in r.stderr
    if "-p" in args:
        assert "(given with -p)" in r.stderr
    else:  # the file holding the bad value is named, not the good one
        bad = args[-1]
        assert f"(given in params file {bad})" in r.stderr, r.stderr


def test_node_health_logs_every_severity_from_one_logger(ros_node):
    """Problems of every level through the same Health: rclpy must accept each of them
    (it refuses a call site whose severity changes, which once stopped the mapper)."""
    from neurncd_ros.core.engine.health import Health
    from neurncd_ros.nodes.common import ros_logger

    node, _ = ros_node
    h = Health("x", ros_logger(node), throttle_s=0.0)
    for level in (1, 0, 2, 0, 1):
        h.problem(f"kind{level}", f"a problem at level {level}", level)
    h.fail("training", "thread died")
    assert h.problems["kind0"] == 2 and h.failed


def test_mapper_reports_when_it_sees_the_embedding_publisher(tmp_path):
    """The mapper's diagnostics say whether the embedding node is seen yet
    (`upstream_publishers`), which bringup waits for before it plays a bag."""
    domain = rosutil.domain(13)
    apply_ros_env(domain)
    import rclpy
    from sensor_msgs.msg import Image

    from neurncd_ros.nodes.common import sensor_qos

    rclpy.init()
    node = rclpy.create_node("upstream_watcher")
    log = tmp_path / "mapper.log"
    proc = start(["-m", "neurncd_ros.nodes.mapper"], ros_env(domain), log)
    try:
        diag = diagnostics_of(node, ("mapper",))
        assert spin_until(node, lambda: "mapper" in diag, 120), log.read_text()
        assert diag["mapper"]["upstream_publishers"] == "0"
        node.create_publisher(Image, "/neurncd/embedding", sensor_qos(1))
        assert spin_until(node, lambda: diag["mapper"]["upstream_publishers"] == "1", 60), \
            log.read_text()
    finally:
        stop(proc)
        node.destroy_node()
        rclpy.shutdown()
