"""The whole system over DDS: bringup replays a synthetic bag into the embedding, mapper and
discovery nodes, and labels come out per the topic contract."""

from __future__ import annotations

import json

import numpy as np
import pytest

from neurncd_ros.core import msgconv
from neurncd_ros.core import classes

from rosutil import apply_ros_env, ros_env, spin_until, start, stop

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def scene_bag(tmp_path_factory):
    from neurncd_ros import synth
    from neurncd_ros.core.data.bag import write_bag
    from neurncd_ros.core.params import build

    cfg = build(synth.SynthConfig, {"width": 160, "height": 120})
    frames = list(synth.generate(1003, 45, cfg))
    path = tmp_path_factory.mktemp("bag") / "scene.mcap"
    write_bag(path, frames, storage="mcap")
    return path, frames


def test_bringup_labels_replayed_bag(scene_bag, tmp_path):
    bag, frames = scene_bag
    domain = 141
    apply_ros_env(domain)
    import rclpy
    from sensor_msgs.msg import Image
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from neurncd_ros.nodes.common import latched_qos, sensor_qos

    map_path = tmp_path / "map.pt"
    log = tmp_path / "bringup.log"
    proc = start(["-m", "neurncd_ros.nodes.bringup", "--bag", str(bag), "--ros-args",
                  "-p", "mapper.min_iterations_before_publish:=15",
                  "-p", "replay.rate:=0.5", "-p", "replay.start_delay_s:=8.0",
                  "-p", f"mapper_node.map_path:={map_path}"], ros_env(domain), log)
    rclpy.init()
    labels, tables = [], []
    try:
        node = rclpy.create_node("test_listener")
        node.create_subscription(Image, "/neurncd/labels", labels.append, sensor_qos(50))
        node.create_subscription(String, "/neurncd/classes", tables.append, latched_qos())
        ok = spin_until(node, lambda: len(labels) >= 3 and tables, 150)
        assert ok, f"{len(labels)} label images arrived\n" + log.read_text()[-3000:]
        stamps = {f.stamp_ns: f for f in frames}
        for msg in labels:
            stamp = msgconv.stamp_to_ns(msg.header.stamp)
            assert stamp in stamps, "labels must carry the stamp of the depth frame they label"
            lab = msgconv.image_to_array(msg, "/neurncd/labels")
            assert msg.encoding == "mono16" and lab.shape == stamps[stamp].depth.shape
            ids = np.unique(lab)
            assert np.all((ids <= classes.NUM_CLASSES) | (ids >= classes.NOVEL_ID_START))
            assert (lab > 0).mean() > 0.9, "nearly every pixel of a processed frame is labelled"
        table = json.loads(tables[-1].data)
        assert table and all(v["kind"] in ("known", "novel") for v in table.values())
        for key, v in table.items():
            assert v["name"] == classes.class_name(int(key))
        # The map can be saved on request while it trains.
        client = node.create_client(Trigger, "/mapper/save_map")
        assert client.wait_for_service(timeout_sec=10)
        future = client.call_async(Trigger.Request())
        assert spin_until(node, future.done, 30)
        assert future.result().success, future.result().message
        assert map_path.is_file() and map_path.stat().st_size > 1000
        node.destroy_node()
    finally:
        rclpy.shutdown()
        code = stop(proc, timeout=30)
    text = log.read_text()
    assert "Traceback" not in text, text[-3000:]
    assert code == 0, text[-2000:]
