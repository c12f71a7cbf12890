"""What every node shares: DDS profile, the start and clean stop of a node, QoS, messages
(its parameters are in :mod:`.parameters`).

Kept small on purpose: a node is parameters in, messages converted (with
``neurncd_ros.core.msgconv``), core called, messages out.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

# Only the standard library and the (standard-library only) ConfigError at the top: a node
# module imports this before its main() installs the signal handlers, so anything heavy
# here (numpy, the config schema, rclpy) would widen the window in which a signal is lost
# or ends the start in a traceback. Heavier modules are imported where they are used.
from ..core.params import ConfigError
from ..share import share_file
from .parameters import (empty_lists, parameter_origin, params_file_error, params_files,
                         ros_args_error)
from .process import Shutdown

if TYPE_CHECKING:
    import numpy as np

PROFILE_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
PIPELINE_NODES = ("embedding", "mapper", "discovery")
"""The nodes of the graph, upstream first: what bringup and the launch file start, and
what the replay waits for (``replay.wait_for_graph``)."""


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


def dds_profile_warning(profile: str) -> str | None:
    """Why the Fast DDS profile in force will not be used (a path that names no file: Fast
    DDS then logs one XML parser line and runs on its defaults), or None."""
    if Path(profile).is_file():
        return None
    return (f"the Fast DDS profile {profile} (FASTRTPS_/FASTDDS_DEFAULT_PROFILES_FILE) is no "
            "file: Fast DDS runs on its defaults, whose shared-memory transport loses images "
            "over 1 MB (README, 'Large images and Fast DDS')")


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


def stop_executor(executor: Any, timeout_sec: float, name: str = "") -> None:
    """Stop ``executor`` once the callbacks it has already handed to its threads have run.

    Called when nothing spins the executor any more, before the node is closed and
    destroyed. A MultiThreadedExecutor's ``spin_once`` hands a callback to its thread pool
    as a task that runs later, and the task triggers the executor's guard condition when
    it starts (rclpy Jazzy, ``Executor._make_handler``). ``Executor.shutdown`` destroys
    that guard condition at once (it does not wait for the tasks: it tests the flag it has
    just set), so a task still queued or starting then failed with "InvalidHandle: cannot
    use Destroyable because destruction was requested" (one stop in three of a node fed
    with frames). So the tasks are waited for first (they are plain callbacks: they
    finish without the executor spinning), their results collected (rclpy would print an
    uncollected failure at exit as "The following exception was never retrieved"), and
    only then is the executor shut down. A failure or a callback still running after
    ``timeout_sec`` is printed naming the node (``name``).
    """
    prefix = f"{name}: " if name else ""
    deadline = time.monotonic() + timeout_sec
    tasks = list(getattr(executor, "_futures", ()))  # a MultiThreadedExecutor's tasks
    for task in tasks:
        while not (task.done() or task.cancelled()) and time.monotonic() < deadline:
            time.sleep(0.01)  # rclpy futures have no blocking wait without a spinning executor
    running = sum(1 for task in tasks if not (task.done() or task.cancelled()))
    if running:
        print(f"{prefix}{running} callback(s) still running {timeout_sec:g} s after the stop "
              "was asked: stopping anyway", file=sys.stderr)
    executor.shutdown(timeout_sec=max(0.0, deadline - time.monotonic()))
    for task in tasks:
        if task.done():
            err = task.exception()  # collected: rclpy would print it at exit otherwise
            if err is not None:
                print(f"{prefix}a callback failed while stopping: {type(err).__name__}: "
                      f"{err}", file=sys.stderr)


def ros_logger(node: Any):
    """A Health logger writing to the node's ROS logger.

    One call site per severity: rclpy remembers the severity of each call site
    and refuses ("Logger severity cannot be changed between calls") a site that
    logs at another one.
    """
    logger = node.get_logger()

    def log(level: int, text: str) -> None:
        if level <= 0:
            logger.info(text)
        elif level == 1:
            logger.warning(text)
        else:
            logger.error(text)
    return log


def run_node(factory: Callable[[], Any], name: str, description: str,
             argv: list[str] | None = None, preload: tuple[str, ...] = ()) -> int:
    """Standard main(): signals, help, DDS profile, rclpy init, spin, clean shutdown.

    The signal handlers come first, before anything heavy is imported: ``preload`` names
    the node's core modules (torch, scipy), which are imported next, before rclpy (the
    order the nodes have always loaded them in), and a signal until rclpy.init ends the
    process at once with code 0 (see :class:`Shutdown`). ``factory`` builds the node after
    ``rclpy.init``. The node may define ``close()`` (called once on the way out: stop
    workers, save state, log a summary), ``done`` (an Event: the node has finished its
    work, e.g. a replay at the end of its bag) and ``exit_code``. A ConfigError, a
    parameter file that is not YAML and ROS arguments rcl refuses are printed on one line
    and exit 2 instead of a traceback.
    """
    shutdown = Shutdown(name).install(starting=True)
    _, ros_args = parse_cli(name, description, argv)
    for path in params_files(ros_args):
        problem = params_file_error(path)
        if problem:
            print(f"{name}: configuration error: {problem}", file=sys.stderr)
            return 2
    for module in preload:
        importlib.import_module(module)
    # The process's threads (executor, stage worker, the field's training) hand the GIL
    # over every 1 ms instead of Python's 5 ms: a callback waits for the GIL several
    # times (rcl_wait, the take, the thread pool), and at 5 ms a 640x480 camera's 100
    # messages a second fell a second behind beside a busy worker, and DDS dropped them.
    sys.setswitchinterval(0.001)
    warning = dds_profile_warning(ensure_dds_profile())
    if warning:
        print(f"{name}: warning: {warning}", file=sys.stderr)
    import cv2
    cv2.setNumThreads(1)  # the nodes share the cores; torch threads are set per node
    # The odometry's own per-frame lines (Python logging, unthrottled, on stderr) repeated
    # every loss the pose stage already reports, throttled, through the node's logger and
    # /diagnostics: a node keeps only its errors.
    logging.getLogger("neurncd_ros.core.odometry").setLevel(logging.ERROR)
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from rclpy.utilities import remove_ros_args

    try:  # checked before rclpy.init, which would also log a line of its own
        remove_ros_args([name, *ros_args])
    except RuntimeError as err:  # RCLInvalidROSArgsError, UnknownROSArgsError
        print(f"{name}: error: {ros_args_error(err)}", file=sys.stderr)
        return 2
    shutdown.started()
    rclpy.init(args=[name, *ros_args], signal_handler_options=SignalHandlerOptions.NO)
    node = None
    executor = None
    code = 0
    try:
        if not shutdown.requested.is_set():  # a signal during rclpy.init: build nothing
            node = factory()
            # One thread: a node's callbacks are in its one mutually exclusive group, so a
            # MultiThreadedExecutor ran them one at a time anyway, through a thread pool
            # whose handoffs each waited for the GIL beside the node's busy threads: at
            # 1280x720 the mapper took half the camera's messages (bench/graph.py).
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            topics = getattr(node, "topics", None)
            done = getattr(node, "done", None)
            if not (done and done.is_set()):  # a replay whose bag failed at once is not
                node.get_logger().info(
                    "ready" + (f": state, counts and problems on {topics.diagnostics} once "
                               "a second" if topics is not None else ""))
            while (rclpy.ok() and not shutdown.requested.is_set()
                   and not (done and done.is_set())):
                executor.spin_once(timeout_sec=0.1)  # short waits: signals are seen promptly
        if shutdown.requested.is_set():
            if node is not None:
                node.get_logger().info(f"{shutdown.signal_name}: shutting down")
            else:
                print(f"{name}: {shutdown.signal_name}: shutting down", file=sys.stderr)
        code = int(getattr(node, "exit_code", 0) or 0)
    except ConfigError as err:
        print(f"{name}: configuration error: {err}{parameter_origin(str(err), ros_args)}",
              file=sys.stderr)
        code = 2
    except ValueError as err:  # rclpy refusing a parameter override (e.g. `key: []`)
        hint = empty_lists(ros_args)
        print(f"{name}: error: {err}" + (f" ({hint})" if hint else ""), file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if executor is not None:
            # Before the node goes: no callback may still be running when it is destroyed,
            # and before the context goes: an executor left to the garbage collector
            # destroys its SIGINT guard condition after rclpy.shutdown, and that raises at exit.
            stop_executor(executor, timeout_sec=5.0, name=name)
        if node is not None:
            close = getattr(node, "close", None)
            if close:
                close()
            node.destroy_node()
        if rclpy.ok():
            rclpy.try_shutdown()
    return code


# ---------------------------------------------------------------- QoS

def wall_timer(node: Any, period_s: float, callback: Callable[[], Any]) -> Any:
    """A node timer on the steady (wall) clock: diagnostics, housekeeping and map saves
    keep their pace with ``use_sim_time`` whether or not /clock runs (on the node's ROS
    clock they never fired before the first /clock message, nor while a bag is paused)."""
    from rclpy.clock import Clock, ClockType

    return node.create_timer(period_s, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))


class InputWatch:
    """Watches a node's input topics, on its diagnostics tick.

    Says once, as a warning, when the node has received nothing at all ``after_s`` after
    it started: the topics as resolved (namespace, remaps) and how many publishers each
    has, so a wrong name or namespace shows at once instead of a graph that waits in
    silence (the partial-input warnings need some input to arrive). And says when an
    input that had publishers has none any more (the camera, the replay or the upstream
    node stopped; a killed mapper left discovery at "running" in silence) and when one
    is back; ``health`` (optional) gets the count of such inputs as the gauge
    ``inputs_without_publisher``."""

    def __init__(self, node: Any, topics: list[str], after_s: float = 10.0,
                 health: Any = None) -> None:
        self.node, self.topics, self.after_s, self.health = node, list(topics), after_s, health
        self.started = time.monotonic()
        self.warned = False
        self.published: dict[str, int] = {}  # topic -> publishers at the last tick
        self.ever: dict[str, bool] = {}  # topic -> has had a publisher

    def _name(self, topic: str) -> str:
        try:
            return self.node.resolve_topic_name(topic)
        except Exception:  # noqa: BLE001 - an invalid name was refused at start anyway
            return topic

    def check(self, received: int) -> None:
        """Call on the node's diagnostics tick with its count of messages received."""
        counts = {t: self.node.count_publishers(self._name(t)) for t in self.topics}
        for topic, n in counts.items():
            before = self.published.get(topic)
            if before and not n:
                self.node.get_logger().info(
                    f"no publisher on {self._name(topic)} any more: the camera, the replay "
                    "or the upstream node has stopped; waiting for it to come back")
            elif n and before == 0 and self.ever.get(topic):
                self.node.get_logger().info(f"{self._name(topic)} has a publisher again")
            self.ever[topic] = self.ever.get(topic, False) or bool(n)
        self.published = counts
        if self.health is not None:
            self.health.gauge("inputs_without_publisher",
                              sum(1 for t, n in counts.items() if self.ever[t] and not n))
        if self.warned or received or time.monotonic() - self.started < self.after_s:
            return
        self.warned = True
        parts = [f"{self._name(t)} ({counts[t]} publishers)" for t in self.topics]
        if all(counts.values()):
            # The names are right: a user audit's discovery node blamed them while the
            # mapper was still choosing its pose source for a bag without poses.
            advice = ("every one has a publisher, so the names are right: the upstream "
                      "node has published nothing yet (it may still wait for its own "
                      "inputs: a camera not streaming, the mapper choosing its pose source) "
                      "or its QoS does not match this node's (README, 'Topic contract')")
        else:
            advice = ("check the topic names (topics.* parameters, the namespace, remaps) "
                      "and that the camera or the upstream node runs")
        self.node.get_logger().warning(
            f"nothing received for {self.after_s:g} s on {', '.join(parts)}: {advice}")


def sensor_qos(depth: int = 5):
    """Best effort, keep last: accepts both camera drivers and reliable publishers."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.BEST_EFFORT,
                      history=HistoryPolicy.KEEP_LAST)


def output_qos(depth: int = 10):
    """Reliable, keep last: what the nodes publish reaches every subscriber that keeps up."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy, HistoryPolicy
    return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE,
                      history=HistoryPolicy.KEEP_LAST)


def latched_qos():
    """Transient local: late subscribers get the last message (the class table)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def view_qos(depth: int = 10):
    """Reliable, keep last: the pieces of a view (and the embedding) are not dropped by the
    transport; the stages decide what to drop, and count it."""
    return output_qos(depth)


# ---------------------------------------------------------------- messages

def input_image_type(topic: str):
    """The message class the nodes subscribe an input image topic with: CompressedImage
    for image_transport's ``.../compressed`` and ``.../compressedDepth``, else Image."""
    from sensor_msgs.msg import CompressedImage, Image

    from ..core.topics import is_compressed_topic
    return CompressedImage if is_compressed_topic(topic) else Image


def make_image(fields: dict[str, Any], stamp_ns: int, frame_id: str):
    """An rclpy sensor_msgs/Image from ``msgconv.image_fields``-style fields."""
    import numpy as np
    from sensor_msgs.msg import Image

    from ..core import msgconv
    msg = Image()
    msg.header.stamp.sec, msg.header.stamp.nanosec = msgconv.ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(fields["height"]), int(fields["width"])
    msg.encoding, msg.is_bigendian = fields["encoding"], int(fields["is_bigendian"])
    msg.step = int(fields["step"])
    msg.data = np.ascontiguousarray(fields["data"], dtype=np.uint8).tobytes()
    return msg


def image_msg(arr: np.ndarray, encoding: str, stamp_ns: int, frame_id: str, topic: str = ""):
    """A sensor_msgs/Image of ``arr`` (``topic`` names it in a conversion error)."""
    from ..core import msgconv
    return make_image(msgconv.image_fields(arr, encoding, topic), stamp_ns, frame_id)


def camera_info_msg(intr, stamp_ns: int, frame_id: str):
    """A sensor_msgs/CameraInfo of pinhole intrinsics ``intr``."""
    from sensor_msgs.msg import CameraInfo

    from ..core import msgconv
    f = msgconv.camera_info_fields(intr)
    msg = CameraInfo()
    msg.header.stamp.sec, msg.header.stamp.nanosec = msgconv.ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.height, msg.width, msg.distortion_model = f["height"], f["width"], f["distortion_model"]
    msg.d, msg.k, msg.r, msg.p = (list(map(float, f[k])) for k in ("d", "k", "r", "p"))
    return msg


def pose_msg(T: np.ndarray, stamp_ns: int, frame_id: str):
    """A geometry_msgs/PoseStamped of the 4x4 camera-to-world ``T``."""
    from geometry_msgs.msg import PoseStamped

    from ..core import msgconv
    f = msgconv.matrix_to_pose_fields(T)
    msg = PoseStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = msgconv.ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    p, q = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z = f["position"]
    q.x, q.y, q.z, q.w = f["orientation"]
    return msg


def header_ns(msg: Any) -> int:
    """A message's header stamp in nanoseconds."""
    from ..core import msgconv
    return msgconv.stamp_to_ns(msg.header.stamp)


def stamp_of(msg: Any) -> int | None:
    """:func:`header_ns`, or None for a message without a usable header (a refused
    message is remembered with its stamp where it has one)."""
    try:
        return header_ns(msg)
    except (AttributeError, TypeError, ValueError):
        return None


def diagnostics_msg(node: Any, healths: list) -> Any:
    """A diagnostic_msgs/DiagnosticArray with one status per stage health."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
    arr = DiagnosticArray()
    arr.header.stamp = node.get_clock().now().to_msg()
    for health, rates in healths:
        snap = health.snapshot(rates)
        st = DiagnosticStatus()
        st.level = bytes([snap["level"]])
        st.name = f"neurncd_ros: {health.name}"
        st.message = snap["message"][:200]
        st.hardware_id = node.get_fully_qualified_name()
        st.values = [KeyValue(key=k, value=v) for k, v in snap["values"].items()]
        arr.status.append(st)
    return arr


def diagnostics_status(msg: Any, name: str, namespace: str | None = None
                       ) -> dict[str, str] | None:
    """The values of the status named ``neurncd_ros: <name>`` in a DiagnosticArray;
    ``namespace`` (``/robot1``, ``/`` or ``''`` for the root): only a status of a node in
    it (its ``hardware_id``, the node's fully qualified name), so that two graphs on one
    domain, whose reports share /diagnostics, are told apart."""
    want = None if namespace is None else namespace.rstrip("/")
    for st in msg.status:
        if st.name == f"neurncd_ros: {name}" and (
                want is None or not st.hardware_id
                or st.hardware_id.rsplit("/", 1)[0] == want):
            return {kv.key: kv.value for kv in st.values}
    return None


def node_connected(msg: Any, name: str, namespace: str | None = None) -> bool | None:
    """What a DiagnosticArray says of node ``name`` (in ``namespace``, as in
    :func:`diagnostics_status`): None if it did not report in it, else whether it sees its
    upstream node's publisher (``upstream_publishers``: the mapper the embedding node's,
    discovery the mapper's; a node without it, once it reports). Before that, what is
    published to it is lost to DDS discovery (bringup and the replay wait)."""
    values = diagnostics_status(msg, name, namespace)
    if values is None:
        return None
    return int(values.get("upstream_publishers", "1") or 0) > 0
