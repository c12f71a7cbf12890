"""What every node shares: DDS profile, parameters from the schema, QoS, messages.

Kept small on purpose: a node is parameters in, messages converted (with
``neurncd_ros.core.msgconv``), core called, messages out.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

from ..core import msgconv
from .. import config as config_mod
from ..core.params import ConfigError

PACKAGE = "neurncd_ros"
PROFILE_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def share_file(*parts: str) -> Path:
    """A file of the package's share/ (colcon install) or of the source tree."""
    try:
        from ament_index_python.packages import get_package_share_directory
        path = Path(get_package_share_directory(PACKAGE)).joinpath(*parts)
        if path.exists():
            return path
    except Exception:  # not installed with colcon: fall back to the source tree
        pass
    return Path(__file__).resolve().parents[2].joinpath(*parts)


def ensure_dds_profile(env: dict[str, str] | None = None) -> str:
    """Point Fast DDS at the shipped large-shared-memory profile unless the user chose one.

    Must run before ``rclpy.init``. Returns the profile in force.
    """
    env = os.environ if env is None else env
    user = next((env[v] for v in PROFILE_VARS if env.get(v)), None)
    profile = user or str(share_file("config", "fastdds_shm.xml"))
    for var in PROFILE_VARS:
        if not env.get(var):
            env[var] = profile
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    return profile


def parse_cli(name: str, description: str, argv: list[str] | None = None
              ) -> tuple[argparse.Namespace, list[str]]:
    """Node command line: --help, then everything else (``--ros-args ...``) for rclpy."""
    parser = argparse.ArgumentParser(
        prog=name, description=description,
        epilog="ROS arguments follow --ros-args, e.g. --ros-args --params-file "
               "config/neurncd.yaml -p mapper.backend:=fast -r /camera/pose:=/slam/pose. "
               "Every parameter is listed with `neurncd params`.")
    argv = sys.argv[1:] if argv is None else argv
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        own, ros = argv[:i], argv[i:]
    else:
        own, ros = argv, []
    args = parser.parse_args(own)
    return args, ros


def _ros_value(value: Any) -> Any:
    return list(value) if isinstance(value, (list, tuple)) else value


ROS_BUILTIN_PARAMETERS = ("use_sim_time", "start_type_description_service")


def _ros_builtin(name: str) -> bool:
    """Parameters rclpy itself declares or reads (not part of our schema)."""
    return name in ROS_BUILTIN_PARAMETERS or name.startswith("qos_overrides.")


def declare_config(node: Any) -> config_mod.Config:
    """Declare every schema parameter on ``node`` and return the validated config.

    Values come from --params-file / -p overrides. A parameter name the schema
    does not know, a wrong type or an out-of-range value raises ConfigError
    naming the key and the allowed values.
    """
    defaults = config_mod.default().to_flat()
    overrides = dict(node.get_parameters_by_prefix(""))  # auto-declared from overrides
    unknown = sorted(k for k in overrides if k not in defaults and not _ros_builtin(k))
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown parameter; see `neurncd params` for the "
                          "list of parameters")
    from rcl_interfaces.msg import ParameterDescriptor

    values = {}
    for key, default in defaults.items():
        if node.has_parameter(key):
            value = node.get_parameter(key).value
        elif isinstance(default, list) and not default:
            # An empty list has no element type ROS could infer (a parameter file's
            # `[]` arrives as "not set"): declare it dynamically typed, unset = default.
            value = node.declare_parameter(
                key, None, ParameterDescriptor(dynamic_typing=True)).value
        else:
            value = node.declare_parameter(key, _ros_value(default)).value
        values[key] = default if value is None else value
    return config_mod.from_flat(values)


def run_node(factory: Callable[[], Any], name: str, description: str,
             argv: list[str] | None = None) -> int:
    """Standard main(): help, DDS profile, rclpy init, spin, clean shutdown.

    ``factory`` builds the node after ``rclpy.init``; a ConfigError is printed
    and exits 2 instead of a traceback.
    """
    _, ros_args = parse_cli(name, description, argv)
    ensure_dds_profile()
    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    # Ctrl-C arrives as KeyboardInterrupt while the context is still valid, so
    # the node can save its map and log a summary before shutdown.
    rclpy.init(args=[name, *ros_args], signal_handler_options=SignalHandlerOptions.NO)
    node = None
    try:
        node = factory()
        executor = MultiThreadedExecutor(num_threads=3)
        executor.add_node(node)
        while rclpy.ok():  # short waits so Ctrl-C is seen promptly
            executor.spin_once(timeout_sec=0.2)
    except ConfigError as err:
        print(f"{name}: configuration error: {err}", file=sys.stderr)
        return 2
    except ValueError as err:  # rclpy refusing a parameter override (e.g. `key: []`)
        print(f"{name}: parameter error: {err} (an empty list in a parameter file has no "
              "type in ROS: leave the key out to get its default)", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            close = getattr(node, "close", None)
            if close:
                close()
            node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
    return 0


# ---------------------------------------------------------------- QoS

def sensor_qos(depth: int = 5):
    """Best effort, keep last: accepts both camera drivers and reliable publishers."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT,
                      history=HistoryPolicy.KEEP_LAST)


def output_qos(depth: int = 10):
    from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      history=HistoryPolicy.KEEP_LAST)


def latched_qos():
    """Transient local: late subscribers get the last message (the class table)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


# ---------------------------------------------------------------- messages

def fit_to(arr: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resize a rendering to the depth frame's size (bilinear; channels kept)."""
    if arr.shape[:2] == (height, width):
        return arr
    out = cv2.resize(arr, (width, height), interpolation=cv2.INTER_LINEAR)
    return out[:, :, None] if arr.ndim == 3 and out.ndim == 2 else out


def make_image(fields: dict[str, Any], stamp_ns: int, frame_id: str):
    """An rclpy sensor_msgs/Image from ``msgconv.image_fields``-style fields."""
    from sensor_msgs.msg import Image
    msg = Image()
    msg.header.stamp.sec, msg.header.stamp.nanosec = msgconv.ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(fields["height"]), int(fields["width"])
    msg.encoding, msg.is_bigendian = fields["encoding"], int(fields["is_bigendian"])
    msg.step = int(fields["step"])
    msg.data = np.ascontiguousarray(fields["data"], dtype=np.uint8).tobytes()
    return msg


def image_msg(arr: np.ndarray, encoding: str, stamp_ns: int, frame_id: str, topic: str = ""):
    return make_image(msgconv.image_fields(arr, encoding, topic), stamp_ns, frame_id)


def header_ns(msg: Any) -> int:
    return msgconv.stamp_to_ns(msg.header.stamp)


class StampMatcher:
    """Pairs messages of several topics by header stamp, without message_filters.

    ``add(slot, stamp_ns, value)`` stores a message; when every slot has a
    value within ``tolerance_ns`` of one stamp, the group is returned and
    removed. Older incomplete groups are dropped (counted) when ``capacity``
    is exceeded, so memory stays bounded whatever arrives.
    """

    def __init__(self, slots: tuple[str, ...], tolerance_ns: int, capacity: int) -> None:
        self.slots, self.tolerance_ns, self.capacity = slots, int(tolerance_ns), capacity
        self._pending: dict[str, list[tuple[int, Any]]] = {s: [] for s in slots}
        self.dropped = 0

    def starved(self) -> tuple[str, ...]:
        """Slots with nothing pending while another slot's queue is full: the topics
        that are not arriving (or not within the tolerance) while the rest are."""
        if not any(len(q) >= self.capacity for q in self._pending.values()):
            return ()
        return tuple(s for s, q in self._pending.items() if not q)

    def add(self, slot: str, stamp_ns: int, value: Any) -> tuple[int, dict[str, Any]] | None:
        if slot not in self._pending:
            raise KeyError(f"unknown slot {slot!r}; slots: {self.slots}")
        queue = self._pending[slot]
        queue.append((stamp_ns, value))
        if len(queue) > self.capacity:
            queue.pop(0)
            self.dropped += 1
        return self._match(stamp_ns)

    def _match(self, stamp_ns: int) -> tuple[int, dict[str, Any]] | None:
        picked = {}
        for slot, queue in self._pending.items():
            best = None
            for i, (s, _) in enumerate(queue):
                d = abs(s - stamp_ns)
                if d <= self.tolerance_ns and (best is None or d < best[0]):
                    best = (d, i)
            if best is None:
                return None
            picked[slot] = best[1]
        group = {}
        for slot, i in picked.items():
            queue = self._pending[slot]
            group[slot] = queue[i][1]
            # Everything older than the matched message can never match again.
            self.dropped += i
            del queue[: i + 1]
        return stamp_ns, group


class PairedFrames:
    """Mixin of the nodes that pair topics by stamp and need the camera intrinsics.

    The node sets ``self.matcher``, ``self.topics``, ``self.throttle`` and
    implements ``on_frame(stamp_ns, group)``; a ValueError from it skips that
    frame with a throttled warning (counted in ``self.skipped``), never the node.
    """

    intrinsics = None
    skipped = 0

    def on_info(self, msg) -> None:
        try:
            self.intrinsics = msgconv.camera_info_to_intrinsics(msg, self.topics.camera_info)
        except ValueError as err:
            self.get_logger().warning(str(err), throttle_duration_sec=self.throttle)

    def offer(self, slot: str, msg) -> None:
        match = self.matcher.add(slot, header_ns(msg), msg)
        if match is None:
            starved = self.matcher.starved()
            if starved:
                self.get_logger().warning(
                    f"waiting for {', '.join(starved)}: nothing pending while other topics "
                    f"arrive ({self.matcher.dropped} unpaired messages dropped so far; check "
                    f"the topic names and that stamps agree within the sync tolerance)",
                    throttle_duration_sec=self.throttle)
            return
        try:
            self.on_frame(*match)
        except ValueError as err:
            self.skipped += 1
            self.get_logger().warning(f"skipped frame {match[0]}: {err}",
                                      throttle_duration_sec=self.throttle)
