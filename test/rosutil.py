"""Helpers for tests that use DDS: local-only discovery, a private domain, our profile."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Iterator

REPO = Path(__file__).resolve().parents[1]


SLOT_SIZE, SLOTS = 16, 14  # domain ids 1..224, all valid (ROS allows 0..232)
_slot_lock = None


def _session_slot() -> int:
    """A block of domain ids for this test session alone: the first slot whose lock file no
    other session holds (several checkouts may run their suites at once on one machine;
    on a shared domain their nodes would talk to each other)."""
    global _slot_lock
    import fcntl
    import tempfile

    if _slot_lock is not None:
        return _slot_lock[0]
    folder = Path(tempfile.gettempdir()) / "neurncd-test-domains"
    folder.mkdir(exist_ok=True)
    for slot in range(SLOTS):
        fh = open(folder / f"slot-{slot}.lock", "w")
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            continue
        _slot_lock = (slot, fh)  # held until this process exits
        return slot
    raise RuntimeError(f"all {SLOTS} test domain slots are taken by other test sessions")


def domain(k: int) -> int:
    """The k-th private ROS domain id of this test session (k < 16)."""
    if not 0 <= k < SLOT_SIZE:
        raise ValueError(f"domain index {k} out of 0..{SLOT_SIZE - 1}")
    return 1 + SLOT_SIZE * _session_slot() + k


def ros_env(domain_id: int | None = None) -> dict[str, str]:
    """Environment for a DDS test: never leaves this machine, private domain id."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_DOMAIN_ID"] = str(domain_id if domain_id is not None else domain(0))
    env.pop("ROS_STATIC_PEERS", None)
    profile = str(REPO / "config" / "fastdds_shm.xml")
    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = profile
    env["FASTDDS_DEFAULT_PROFILES_FILE"] = profile
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    env["PYTHONUNBUFFERED"] = "1"
    return env


def apply_ros_env(domain_id: int | None = None) -> None:
    """Set the test environment in this process (before rclpy.init)."""
    os.environ.update(ros_env(domain_id))


def _ignore_sigint() -> None:  # in the child: as `cmd &` from a script or nohup start it
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def start(args: list[str], env: dict[str, str], log: Path,
          ignore_sigint: bool = False) -> subprocess.Popen:
    """Start a node process with its output in ``log`` (optionally with SIGINT ignored, as
    a process started in the background by a non-interactive shell has it)."""
    fh = open(log, "w")
    return subprocess.Popen([sys.executable, *args], env=env, stdout=fh,
                            stderr=subprocess.STDOUT, cwd=REPO,
                            preexec_fn=_ignore_sigint if ignore_sigint else None)


def node_processes(domain_id: int) -> list[int]:
    """Pids of neurncd node processes running on ROS domain ``domain_id`` (from /proc)."""
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes()
            env = (proc / "environ").read_bytes()
        except OSError:
            continue
        if b"neurncd_ros.nodes" in cmd and f"\0ROS_DOMAIN_ID={domain_id}\0".encode() in (
                b"\0" + env + b"\0"):
            pids.append(int(proc.name))
    return pids


def diagnostics_of(node, names: tuple[str, ...]) -> dict:
    """Subscribe ``node`` to /diagnostics; the returned dict fills with the latest values
    per neurncd stage name."""
    from diagnostic_msgs.msg import DiagnosticArray

    from neurncd_ros.nodes.common import diagnostics_status

    latest: dict = {}

    def on(msg) -> None:
        for n in names:
            v = diagnostics_status(msg, n)
            if v is not None:
                latest[n] = v
    node.create_subscription(DiagnosticArray, "/diagnostics", on, 50)
    return latest


def stop(proc: subprocess.Popen, timeout: float = 10.0) -> int:
    import signal
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


@contextlib.contextmanager
def node_graph(domain_id: int, names: tuple[str, ...], args: list[str], log_dir: Path,
               node_name: str) -> Iterator[tuple[Any, dict[str, subprocess.Popen]]]:
    """The nodes ``names`` (``neurncd_ros.nodes.<name> <args>``, logs in
    ``log_dir/<name>.log``) and a test node ``node_name`` in domain ``domain_id``: yields
    (test node, processes); on leaving, the test node and rclpy are shut down and every
    process is stopped, and each must have exited 0 (unless the body raised)."""
    import rclpy

    procs = {n: start(["-m", f"neurncd_ros.nodes.{n}", *args], ros_env(domain_id),
                      log_dir / f"{n}.log") for n in names}
    rclpy.init()
    node = rclpy.create_node(node_name)
    try:
        yield node, procs
    finally:
        node.destroy_node()
        rclpy.shutdown()
        codes = [stop(p, timeout=30) for p in procs.values()]
    assert codes == [0] * len(procs), dict(zip(procs, codes))


def spin_until(node, predicate, timeout: float) -> bool:
    """Spin ``node`` until ``predicate()`` is true or ``timeout`` seconds pass."""
    import rclpy
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
        if predicate():
            return True
    return False


def camera_publishers(node) -> dict:
    """A camera driver's publishers on the default topics, best effort as drivers publish:
    colour, depth and camera info, by topic."""
    from sensor_msgs.msg import CameraInfo, Image

    from neurncd_ros.nodes.common import sensor_qos

    return {t: node.create_publisher(m, t, sensor_qos(10)) for t, m in (
        ("/camera/color/image_raw", Image), ("/camera/depth/image_raw", Image),
        ("/camera/color/camera_info", CameraInfo))}


def publish_frame(pubs: dict, frame, stamp_ns: int | None = None) -> None:
    """One frame as a camera driver sends it, through :func:`camera_publishers`: camera
    info, rgb8 colour and 16UC1 depth in millimetres, stamped ``stamp_ns`` (default the
    frame's own stamp)."""
    import numpy as np

    from neurncd_ros.nodes.common import camera_info_msg, image_msg

    stamp = frame.stamp_ns if stamp_ns is None else stamp_ns
    pubs["/camera/color/camera_info"].publish(camera_info_msg(frame.intrinsics, stamp,
                                                              "camera"))
    pubs["/camera/color/image_raw"].publish(image_msg(frame.rgb, "rgb8", stamp, "camera"))
    pubs["/camera/depth/image_raw"].publish(
        image_msg(np.round(frame.depth * 1000).astype(np.uint16), "16UC1", stamp, "camera"))
