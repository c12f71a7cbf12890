"""DDS transport: the shipped Fast DDS profile carries large best-effort images between
processes, and the nodes pick it up unless the user chose their own."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from neurncd_ros.nodes.common import PROFILE_VARS, ensure_dds_profile

from rosutil import apply_ros_env, ros_env, spin_until, start, stop

pytestmark = pytest.mark.ros


def test_profile_set_unless_user_chose_one():
    env = {}
    profile = ensure_dds_profile(env)
    assert profile.endswith("config/fastdds_shm.xml")
    assert all(env[v] == profile for v in PROFILE_VARS)
    user = {"FASTDDS_DEFAULT_PROFILES_FILE": "/etc/my_profile.xml"}
    assert ensure_dds_profile(user) == "/etc/my_profile.xml"
    assert user["FASTRTPS_DEFAULT_PROFILES_FILE"] == "/etc/my_profile.xml"
    # A mistyped path of the user's is named: Fast DDS would run on its defaults.
    from neurncd_ros.nodes.common import dds_profile_warning
    assert dds_profile_warning(profile) is None
    assert "/etc/my_profile.xml (FASTRTPS_/FASTDDS_DEFAULT_PROFILES_FILE) is no file" in \
        dds_profile_warning("/etc/my_profile.xml")


PUBLISHER = textwrap.dedent("""
    import sys, time, numpy as np, rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image
    from neurncd_ros.nodes.common import image_msg
    rclpy.init()
    node = rclpy.create_node('big_image_pub')
    pub = node.create_publisher(Image, '/big', QoSProfile(depth=2,
        reliability=ReliabilityPolicy.BEST_EFFORT))
    arr = np.arange(240 * 320 * 37, dtype=np.float32).reshape(240, 320, 37)
    end = time.monotonic() + float(sys.argv[1])
    i = 0
    while time.monotonic() < end:
        pub.publish(image_msg(arr + i, '32FC37', 1_000_000_000 + i, 'camera'))
        i += 1
        rclpy.spin_once(node, timeout_sec=0.2)
    """)


def test_large_best_effort_image_crosses_processes(tmp_path):
    apply_ros_env()
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image

    from neurncd_ros.core import msgconv

    script = tmp_path / "pub.py"
    script.write_text(PUBLISHER)
    proc = start([str(script), "20"], ros_env(), tmp_path / "pub.log")
    rclpy.init()
    got = []
    try:
        node = rclpy.create_node("big_image_sub")
        node.create_subscription(Image, "/big", got.append,
                                 QoSProfile(depth=2, reliability=ReliabilityPolicy.BEST_EFFORT))
        assert spin_until(node, lambda: len(got) >= 30, 25), \
            f"only {len(got)} images arrived: " + (tmp_path / "pub.log").read_text()
        # Without the profile about two thirds of these frames are lost (measured: 16 of 48).
        ids = [m.header.stamp.nanosec for m in got]
        delivered = len(ids) / (ids[-1] - ids[0] + 1)
        assert delivered >= 0.9, f"only {delivered:.0%} of best-effort frames arrived"
        msg = got[-1]
        arr = msgconv.image_to_array(msg, "/big")
        assert arr.shape == (240, 320, 37) and arr.nbytes > 11_000_000
        i = msg.header.stamp.nanosec
        expect = np.arange(240 * 320 * 37, dtype=np.float32).reshape(240, 320, 37) + i
        np.testing.assert_array_equal(arr, expect)
        node.destroy_node()
    finally:
        rclpy.shutdown()
        stop(proc)
