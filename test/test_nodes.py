"""The nodes in real rclpy processes over local DDS: answers, stamps, sizes, bad input."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest

from neurncd_ros.core import classes, msgconv
from neurncd_ros.core.camera import Intrinsics

import rosutil
from rosutil import (REPO, apply_ros_env, camera_publishers, diagnostics_of, publish_frame,
                     ros_env, spin_until, start, stop)

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
        # Both: the executor runs one callback at a time, so the first subscriber's copy
        # of the last frame can still wait when the second's has arrived.
        assert spin_until(node, lambda: len(second) == len(first) == len(stamps), 120), \
            (first, second, log.read_text())
        assert proc.wait(timeout=60) == 0, log.read_text()
    finally:
        stop(proc)
    assert second == stamps and first == stamps


def test_replay_waits_for_the_graph_downstream_when_asked(ros_node, small_bag, tmp_path):
    """Under ros2 launch the replay starts with the nodes: with replay.wait_for_graph it
    plays only once the embedding, mapper and discovery nodes of its own namespace report
    on /diagnostics that they are up and see their upstream node (as bringup waits for
    them), or the mapper lost the bag's first embeddings (17-20 of 27 frames paired,
    against 27). Stand-ins report here: a mapper that does not see its upstream yet and a
    discovery node of another robot keep it waiting (it plays after
    wait_for_subscribers_s, naming them and not the embedding node); all three connected
    let it play without waiting out its limit."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import CameraInfo, Image

    node, domain = ros_node
    for t, kind in (("/camera/depth/image_raw", Image), ("/camera/color/image_raw", Image),
                    ("/camera/pose", PoseStamped), ("/camera/color/camera_info", CameraInfo)):
        node.create_subscription(kind, t, lambda m: None, 20)
    pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
    reports: dict = {}  # name -> (fully qualified name, upstream_publishers or None)

    def report() -> None:
        msg = DiagnosticArray()
        for name, (fqn, upstream) in reports.items():
            values = [KeyValue(key="pending", value="0")]
            values += [KeyValue(key="upstream_publishers", value=upstream)] if upstream else []
            msg.status.append(DiagnosticStatus(name=f"neurncd_ros: {name}", hardware_id=fqn,
                                               values=values))
        pub.publish(msg)

    def replay(name: str, limit: float, until=lambda: True) -> str:
        """Run a replay waiting for the graph at most ``limit`` s to its end (and then
        ``until``); its log."""
        log = tmp_path / f"{name}.log"
        proc = start(["-m", "neurncd_ros.nodes.replay", "--ros-args", "-p",
                      f"replay.bag:={small_bag}", "-p", "replay.wait_for_graph:=true", "-p",
                      f"replay.wait_for_subscribers_s:={limit}"], ros_env(domain), log)
        try:
            assert spin_until(node, lambda: proc.poll() is not None, 300), log.read_text()
            assert proc.returncode == 0, log.read_text()
            assert spin_until(node, until, 30), log.read_text()
        finally:
            stop(proc)
        return log.read_text()

    timer = node.create_timer(0.2, report)
    try:
        reports.update(embedding=("/embedding", None), mapper=("/mapper", "0"),
                       discovery=("/robot2/discovery", "1"))
        text = replay("waiting", 4.0)
        warning = [line for line in text.splitlines() if "playing anyway" in line]
        assert len(warning) == 1, text
        assert "the mapper node" in warning[0] and "the discovery node" in warning[0], warning
        assert "the embedding node" not in warning[0], warning
        # All three connected, in the replay's namespace: it plays at once.
        reports.update(mapper=("/mapper", "1"), discovery=("/discovery", "1"))
        second: list = []  # a subscription of its own: the first replay's frames never reach it
        node.create_subscription(Image, "/camera/depth/image_raw", second.append, 20)
        text = replay("graph", 600.0, lambda: len(second) == 15)
        assert len(second) == 15 and "playing anyway" not in text, (len(second), text)
    finally:
        node.destroy_timer(timer)


def test_replay_names_the_compressed_topic_of_a_bag_to_set(ros_node, small_bag, tmp_path):
    """A bag recorded through image_transport has .../compressed where the contract's
    colour topic would be: the replay plays it and says which topic to give the nodes."""
    from neurncd_ros.core.data import bag

    _, domain = ros_node
    items = [(t + "/compressed" if t == "/camera/color/image_raw" else t, typ, s,
              bag.deserialize(raw, typ, small_bag, t))
             for t, typ, s, raw in bag.iter_raw(small_bag)]
    path = tmp_path / "compressed.mcap"
    bag.write_messages(path, items)

    def replay_log(bag_path, *params: str) -> str:
        """The log of the replay node playing ``bag_path`` to its end."""
        log = tmp_path / f"replay{len(list(tmp_path.glob('replay*.log')))}.log"
        args = [x for p in (f"replay.bag:={bag_path}", "replay.wait_for_subscribers_s:=0",
                            *params) for x in ("-p", p)]
        proc = start(["-m", "neurncd_ros.nodes.replay", "--ros-args", *args],
                     ros_env(domain), log)
        try:
            assert proc.wait(timeout=120) == 0, log.read_text()
        finally:
            stop(proc)
        return log.read_text()

    text = replay_log(path)
    assert ("the bag has no /camera/color/image_raw but has /camera/color/image_raw/compressed"
            " (sensor_msgs/msg/Image): start the nodes with -p topics.color:=/camera/color/"
            "image_raw/compressed") in text, text
    # A colour topic the bag does not have at all (a name mistyped, or made relative for a
    # namespace): said, with the bag's image topics, not a run that labels nothing in
    # silence.
    text = replay_log(small_bag, "topics.color:=camera/color/image_raw")
    assert ("the bag has no camera/color/image_raw (topics.color), where the nodes listen: "
            "they get none; the bag's image topics: ['/camera/color/image_raw', "
            "'/camera/depth/image_raw'") in text, text


@pytest.mark.parametrize("node_name, sig, extra", [
    ("embedding", "SIGINT", []),
    ("mapper", "SIGTERM", []),
    ("discovery", "SIGINT", []),
    # it plays at once (it would wait 30 s for subscribers on the inputs not watched here)
    ("replay", "SIGTERM", ["replay.loop:=true", "replay.wait_for_subscribers_s:=0.0"]),
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
    assert f"[{node_name}]: ready" in text, text[-2000:]  # a user sees it is up


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


def test_an_empty_list_in_a_params_file_is_named(tmp_path):
    """rclpy refuses `key: []` in its Node constructor without naming the key: the node
    names it and its file."""
    f = tmp_path / "empty.yaml"
    f.write_text("/**:\n  ros__parameters:\n    convert:\n      intrinsics: []\n")
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.nodes.mapper", "--ros-args",
                        "--params-file", str(f)], env=ros_env(rosutil.domain(6)),
                       capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"convert.intrinsics in {f}: ROS cannot type an empty list" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.nodes.mapper", "--ros-args", "-p",
                        "convert.intrinsics:=[]"], env=ros_env(rosutil.domain(6)),
                       capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 2 and "convert.intrinsics given with -p" in r.stderr, r.stderr
    # bringup checks the file before it starts any node: one line.
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.nodes.bringup", "--params-file",
                        str(f)], env=ros_env(rosutil.domain(6)), capture_output=True,
                       text=True, timeout=120, cwd=REPO)
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stderr.strip() == (f"bringup: configuration error: convert.intrinsics in {f}: "
                                "ROS cannot type an empty list; leave the key out to keep "
                                "its default"), r.stderr


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


def _service(node, srv_type, name: str, request, timeout: float = 30.0):
    """Call service ``name`` from ``node`` and return the response (spinning meanwhile)."""
    client = node.create_client(srv_type, name)
    assert spin_until(node, client.service_is_ready, timeout), f"{name} never came up"
    # A request sent as soon as the server is discovered can be lost: the server may not
    # have matched the client's response reader yet (seen once in a full suite, no answer
    # in 120 s). The parameter services are idempotent, so the request is sent again.
    end = time.monotonic() + timeout
    while True:
        future = client.call_async(request)
        if spin_until(node, future.done, min(10.0, max(0.1, end - time.monotonic()))):
            break
        client.remove_pending_request(future)
        assert time.monotonic() < end, f"{name} did not answer"
    node.destroy_client(client)
    return future.result()


def test_configuration_parameters_are_read_only_at_run_time(ros_node, tmp_path):
    """The nodes read their configuration once, at start: `ros2 param set` of one of its
    parameters (what /<node>/set_parameters serves) is refused with a reason that says
    so and how to change it, instead of being accepted and ignored; the values given at
    start (--params-file, -p) are the ones in force, and rclpy's own parameters stay as
    rclpy declares them."""
    from rcl_interfaces.srv import (DescribeParameters, GetParameters, SetParameters,
                                    SetParametersAtomically)
    from rclpy.parameter import Parameter

    node, domain = ros_node
    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    mapper_node:\n      render_scale: 0.5\n")
    log = tmp_path / "mapper.log"
    proc = start(["-m", "neurncd_ros.nodes.mapper", "--ros-args", "--params-file",
                  str(params), "-p", "embedding_node.max_rate_hz:=7.0"], ros_env(domain), log)
    keys = ["embedding_node.max_rate_hz", "mapper_node.render_scale"]
    try:
        # Out of range, and of another node's section: both were accepted.
        request = SetParameters.Request(parameters=[
            Parameter(keys[0], value=5000.0).to_parameter_msg(),
            Parameter(keys[1], value=0.9).to_parameter_msg()])
        results = _service(node, SetParameters, "/mapper/set_parameters", request,
                           120).results
        assert [r.successful for r in results] == [False, False], results
        for key, result in zip(keys, results):
            assert result.reason.startswith(f"{key} is read-only: the node reads its "
                                            "configuration once, at start"), result.reason
            assert "--params-file" in result.reason and f"-p {key}:=VALUE" in result.reason
        atomic = _service(node, SetParametersAtomically, "/mapper/set_parameters_atomically",
                          SetParametersAtomically.Request(parameters=[
                              Parameter(keys[1], value=0.9).to_parameter_msg()])).result
        assert not atomic.successful and "is read-only" in atomic.reason, atomic
        values = _service(node, GetParameters, "/mapper/get_parameters",
                          GetParameters.Request(names=keys)).values
        assert [v.double_value for v in values] == [7.0, 0.5]
        described = _service(node, DescribeParameters, "/mapper/describe_parameters",
                             DescribeParameters.Request(
                                 names=[*keys, "mapper.backend", "use_sim_time"])).descriptors
        assert [d.read_only for d in described] == [True, True, True, False], described
        assert "read once, at start" in described[2].additional_constraints
        assert proc.poll() is None, log.read_text()
    finally:
        code = stop(proc)
    assert code == 0, log.read_text()[-2000:]


def test_a_refused_stream_is_reported_as_refused_not_as_absent():
    """A stream whose messages arrive but are refused (a colour image in rgba8) never
    reaches the pairing, which reports it starved ("nothing arrives there"): the node's
    health names it as refused, with the reason; a stream that really is absent keeps
    its report."""
    from neurncd_ros.core.engine.health import Health, report_starved

    lines: list[str] = []
    now = [100.0]
    h = Health("mapper", lambda level, text: lines.append(text), throttle_s=0.0,
                    clock=lambda: now[0])
    report_starved(h, ["color"], 5.0, "images do (check the topic names")
    assert lines[-1].startswith("waiting for color: nothing arrives there")
    h.refuse("color", "bad_color", "colour image skipped: got 'rgba8'", "got 'rgba8'")
    assert lines[-1] == "colour image skipped: got 'rgba8'"
    report_starved(h, ["embedding", "color"], 5.0, "inputs do (check the topic names")
    assert lines[-1] == ("waiting for embedding: nothing arrives there while the other "
                         "inputs do (check the topic names within 5 ms); waiting for "
                         "color: it arrives but is refused: got 'rgba8'")
    report_starved(h, ["color"], 5.0, "images do (check the topic names")
    assert lines[-1] == "waiting for color: it arrives but is refused: got 'rgba8'"
    # The node names each stream's topic as it resolved it (one wrong name among several
    # inputs, e.g. made relative under a namespace, shows which).
    report_starved(h, ["embedding"], 5.0, "inputs do (check the topic names",
                   {"embedding": "/robot1/neurncd/embedding"})
    assert lines[-1].startswith("waiting for embedding (/robot1/neurncd/embedding): nothing")
    assert h.problems == {"bad_color": 1, "starved": 4}
    from neurncd_ros.core.engine.health import no_camera_info
    assert no_camera_info(h) == "no camera info received yet"
    h.refuse("camera_info", "bad_camera_info", "camera_info message skipped: distortion",
             "distortion [0.1] is not supported")
    assert no_camera_info(h) == ("its camera info arrives but is refused: distortion [0.1] "
                                 "is not supported")
    now[0] += h.window_s + 1  # refused long ago: it may well have stopped arriving
    report_starved(h, ["color"], 5.0, "images do (check the topic names")
    assert lines[-1].startswith("waiting for color: nothing arrives there")


def _yuv_msg(stamp_ns: int, w: int = 96, h: int = 72):
    from sensor_msgs.msg import Image

    msg = Image()
    msg.header.stamp.sec, msg.header.stamp.nanosec = msgconv.ns_to_stamp(stamp_ns)
    msg.header.frame_id = "camera"
    msg.height, msg.width, msg.encoding, msg.step = h, w, "yuv422", 2 * w
    msg.data = bytes(2 * w * h)
    return msg


@pytest.mark.parametrize("node_name", ["embedding", "mapper"])
def test_refused_colour_is_bad_color_and_not_reported_as_absent(node_name, ros_node,
                                                                tmp_path):
    """Colour in an encoding the nodes refuse (yuv422), depth and pose valid: both nodes
    count it as problem `bad_color` (the mapper said `bad_colour`) and say colour arrives
    but is refused, not "waiting for color: nothing arrives there"."""
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import Image

    from neurncd_ros.nodes.common import image_msg, output_qos, pose_msg

    node, domain = ros_node
    log = tmp_path / f"{node_name}.log"
    proc = start(["-m", f"neurncd_ros.nodes.{node_name}", "--ros-args", "-p",
                  f"{node_name}_node.log_throttle_s:=0.5"], ros_env(domain), log)
    try:
        diag = diagnostics_of(node, (node_name,))
        pubs = {t: node.create_publisher(m, t, output_qos()) for t, m in (
            ("/camera/color/image_raw", Image), ("/camera/depth/image_raw", Image),
            ("/camera/pose", PoseStamped))}
        assert spin_until(node, lambda: node_name in diag, 120), log.read_text()
        refused = "waiting for color: it arrives but is refused: /camera/color/image_raw: " \
                  "colour image must be rgb8, bgr8, rgba8 or bgra8, got 'yuv422'"
        stamp = 10**9
        end = time.monotonic() + 60
        while time.monotonic() < end and not (
                refused in log.read_text()
                and int(diag[node_name].get("problem.bad_color", 0)) > 0):
            stamp += 10**9 // 20
            pubs["/camera/color/image_raw"].publish(_yuv_msg(stamp))
            pubs["/camera/depth/image_raw"].publish(
                image_msg(np.full((72, 96), 1500, np.uint16), "16UC1", stamp, "camera"))
            pubs["/camera/pose"].publish(pose_msg(np.eye(4), stamp, "world"))
            spin_until(node, lambda: False, 0.05)
        assert proc.poll() is None, log.read_text()
    finally:
        code = stop(proc)
    text = log.read_text()
    assert refused in text, text[-3000:]
    assert "waiting for color: nothing arrives there" not in text, text[-3000:]
    assert int(diag[node_name]["problem.bad_color"]) > 0, diag[node_name]
    assert "problem.bad_colour" not in diag[node_name]
    if node_name == "mapper":  # an input that is really absent is still named so, with why
        assert "waiting for embedding (/neurncd/embedding): nothing arrives there while the " \
               "other inputs do (the embedding node cannot embed the color this node refuses " \
               "either" in text, text[-3000:]
    assert code == 0, text[-2000:]


def test_mapper_says_when_another_publishers_poses_are_ignored(ros_node, tmp_path):
    """With poses from odometry (pose_source auto chooses it when no pose comes within
    pose_auto_wait_s, e.g. a SLAM started after the camera) the mapper publishes them on
    the pose topic and ignores what arrives there: its own poses, and another publisher's,
    which it ignored in silence. It says so now (problem ``pose_ignored``), and not for its
    own poses."""
    from geometry_msgs.msg import PoseStamped

    from neurncd_ros import synth
    from neurncd_ros.nodes.common import output_qos, pose_msg

    node, domain = ros_node
    frames = list(synth.generate(1004, 20, synth.SynthConfig(width=96, height=72, fps=6.0)))
    log = tmp_path / "mapper.log"
    proc = start(["-m", "neurncd_ros.nodes.mapper", "--ros-args",
                  "-p", "mapper_node.pose_source:=odometry",
                  "-p", "mapper_node.odometry_frames:=all",
                  "-p", "mapper_node.log_throttle_s:=0.5"], ros_env(domain), log)
    ignored = "poses from another publisher on /camera/pose are ignored"
    try:
        diag = diagnostics_of(node, ("mapper",))
        pubs = {**camera_publishers(node),
                "/camera/pose": node.create_publisher(PoseStamped, "/camera/pose",
                                                      output_qos())}
        own = []
        node.create_subscription(PoseStamped, "/camera/pose", own.append, output_qos())
        assert spin_until(node, lambda: "mapper" in diag, 120), log.read_text()
        k = 0

        def feed(until, foreign: bool, timeout: float) -> bool:
            nonlocal k
            end = time.monotonic() + timeout
            while time.monotonic() < end and not until():
                f, stamp = frames[k % len(frames)], 10**9 + k * 10**9 // 6
                publish_frame(pubs, f, stamp)
                if foreign:  # a SLAM's pose of the frame, stamped as it computed it
                    pubs["/camera/pose"].publish(pose_msg(f.pose, stamp + 3_000_000, "map"))
                k += 1
                spin_until(node, lambda: False, 1 / 6)
            return until()

        # The mapper's own poses come back to it: not reported.
        n = len(frames) // 2
        assert feed(lambda: len(own) >= n, False, 60), log.read_text()[-3000:]
        spin_until(node, lambda: False, 1.5)  # a diagnostics tick after the last echo
        assert "problem.pose_ignored" not in diag["mapper"], diag["mapper"]
        assert ignored not in log.read_text()
        # Another publisher's poses: said, once per log_throttle_s, and counted.
        assert feed(lambda: ignored in log.read_text()
                    and int(diag["mapper"].get("problem.pose_ignored", 0)) > 0, True, 60), \
            log.read_text()[-3000:]
        assert proc.poll() is None, log.read_text()
    finally:
        code = stop(proc)
    text = log.read_text()
    assert "mapper_node.pose_source:=topic" in text, text[-3000:]
    assert code == 0, text[-2000:]


def test_mapper_pairs_the_embeddings_that_came_before_their_spec(ros_node, tmp_path):
    """At start the embedding node's latched spec and its first embeddings reach the mapper
    in any order over DDS. An embedding that came before the spec was refused (`no_spec`)
    and its frame lost: the first frames of a run. They are held until the spec comes, and
    paired then."""
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import Image
    from std_msgs.msg import String

    from neurncd_ros import synth
    from neurncd_ros.core.engine.records import EmbeddingSpec
    from neurncd_ros.nodes.common import image_msg, latched_qos, output_qos, pose_msg

    node, domain = ros_node
    frames = list(synth.generate(1004, 6, synth.SynthConfig(width=96, height=72)))
    log = tmp_path / "mapper.log"
    # A long sync_horizon_s: the frames wait for their embeddings whatever the test's pace.
    proc = start(["-m", "neurncd_ros.nodes.mapper", "--ros-args",
                  "-p", "mapper_node.pose_source:=topic",
                  "-p", "mapper_node.sync_horizon_s:=30.0"], ros_env(domain), log)
    try:
        diag = diagnostics_of(node, ("mapper",))
        pubs = {**camera_publishers(node),
                "/camera/pose": node.create_publisher(PoseStamped, "/camera/pose",
                                                      output_qos()),
                "/neurncd/embedding": node.create_publisher(Image, "/neurncd/embedding",
                                                            output_qos())}
        assert spin_until(node, lambda: "mapper" in diag and all(
            p.get_subscription_count() >= 1 for p in pubs.values()), 120), log.read_text()
        rng = np.random.default_rng(0)
        for f in frames:  # as the camera, the embedding node and a SLAM send them
            publish_frame(pubs, f)
            pubs["/camera/pose"].publish(pose_msg(f.pose, f.stamp_ns, "world"))
            emb = rng.normal(size=f.depth.shape + (9,)).astype(np.float32)
            pubs["/neurncd/embedding"].publish(image_msg(emb, "32FC9", f.stamp_ns, "camera"))

        def value(key: str) -> int:
            return int(diag["mapper"].get(key, 0))

        # Every embedding has reached the mapper before the spec: held for it (refused).
        assert spin_until(node, lambda: value("embeddings_held_for_spec") == len(frames)
                          or value("problem.no_spec") >= len(frames), 60), \
            (diag["mapper"], log.read_text()[-3000:])
        spec = node.create_publisher(String, "/neurncd/embedding/spec", latched_qos())
        spec.publish(String(data=EmbeddingSpec(tuple(range(1, 10)),
                                               backbone="test").to_json()))
        assert spin_until(node, lambda: value("frames_paired") >= len(frames), 60), \
            (diag["mapper"], log.read_text()[-3000:])
        assert spin_until(node, lambda: value("embeddings_held_for_spec") == 0, 10)
        assert value("frames_paired") == len(frames) and value("keyframes") >= 1
        assert "problem.no_spec" not in diag["mapper"], diag["mapper"]
        assert proc.poll() is None, log.read_text()
    finally:
        code = stop(proc)
    assert "skipped" not in log.read_text(), log.read_text()[-3000:]
    assert code == 0, log.read_text()[-2000:]


def _compressed_frame(stamp_ns: int, w: int = 96, h: int = 72, broken: bool = False):
    """Colour as image_transport's compressed (JPEG) and depth as its compressedDepth (a
    12-byte header, then a PNG of millimetres), built here with cv2."""
    import struct

    import cv2
    from sensor_msgs.msg import CompressedImage

    v, u = np.mgrid[0:h, 0:w]
    bgr = np.stack([u * 2, v * 3, 200 - u], -1).astype(np.uint8)
    depth = (1200 + 10 * u + 5 * v).astype(np.uint16)
    msgs = []
    for fmt, data in (("bgr8; jpeg compressed bgr8",
                       b"not a jpeg" if broken else cv2.imencode(".jpg", bgr)[1].tobytes()),
                      ("16UC1; compressedDepth png",
                       struct.pack("<iff", 0, 0, 0) + cv2.imencode(".png", depth)[1].tobytes())):
        m = CompressedImage()
        m.header.stamp.sec, m.header.stamp.nanosec = msgconv.ns_to_stamp(stamp_ns)
        m.header.frame_id, m.format, m.data = "camera", fmt, data
        msgs.append(m)
    return msgs


@pytest.mark.parametrize("node_name", ["embedding", "mapper"])
def test_nodes_take_compressed_colour_and_depth(node_name, ros_node, tmp_path):
    """Topics named as image_transport names them (.../compressed, .../compressedDepth)
    are subscribed as sensor_msgs/CompressedImage; the embedding node embeds such a frame
    (same stamp, the backbone's size) and logs an undecodable one as bad colour."""
    from sensor_msgs.msg import CompressedImage, Image

    from neurncd_ros.nodes.common import output_qos, sensor_qos

    node, domain = ros_node
    color, depth = "/cam/color/image_raw/compressed", "/cam/depth/image_raw/compressedDepth"
    log = tmp_path / f"{node_name}.log"
    proc = start(["-m", f"neurncd_ros.nodes.{node_name}", "--ros-args",
                  "-p", f"topics.color:={color}", "-p", f"topics.depth:={depth}",
                  "-p", f"{node_name}_node.log_throttle_s:=0.5"], ros_env(domain), log)
    got = []
    try:
        node.create_subscription(Image, "/neurncd/embedding", got.append, sensor_qos(10))
        pubs = {t: node.create_publisher(CompressedImage, t, output_qos())
                for t in (color, depth)}
        assert spin_until(node, lambda: all(p.get_subscription_count() for p in pubs.values()),
                          120), log.read_text()
        for t in (color, depth):
            types = {i.topic_type for i in node.get_subscriptions_info_by_topic(t)}
            assert types == {"sensor_msgs/msg/CompressedImage"}, (t, types)
        if node_name == "embedding":
            stamp = 3_000_000_000
            for _ in range(10):
                for topic, m in zip((color, depth), _compressed_frame(stamp)):
                    pubs[topic].publish(m)
                if spin_until(node, lambda: any(msgconv.stamp_to_ns(m.header.stamp) == stamp
                                                for m in got), 10):
                    break
            match = [m for m in got if msgconv.stamp_to_ns(m.header.stamp) == stamp]
            assert match, log.read_text()
            emb = msgconv.image_to_array(match[0])
            assert emb.shape == (72, 96, 9) and np.isfinite(emb).all() and emb.std() > 0
            bad = "colour image skipped: /cam/color/image_raw/compressed: compressed image " \
                  "(format 'bgr8; jpeg compressed bgr8') cannot be decoded (10 bytes)"
            for k in range(20):
                for topic, m in zip((color, depth),
                                    _compressed_frame(stamp + (k + 1) * 10**8, broken=True)):
                    pubs[topic].publish(m)
                if spin_until(node, lambda: bad in log.read_text(), 2):
                    break
            assert bad in log.read_text(), log.read_text()[-3000:]
        assert proc.poll() is None, log.read_text()
    finally:
        code = stop(proc)
    assert code == 0, log.read_text()[-2000:]
