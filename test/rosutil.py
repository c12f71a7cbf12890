"""Helpers for tests that use DDS: local-only discovery, a private domain, our profile."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def ros_env(domain: int | None = None) -> dict[str, str]:
    """Environment for a DDS test: never leaves this machine, private domain id."""
    env = dict(os.environ)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["ROS_DOMAIN_ID"] = str(domain if domain is not None else 100 + os.getpid() % 100)
    env.pop("ROS_STATIC_PEERS", None)
    profile = str(REPO / "config" / "fastdds_shm.xml")
    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = profile
    env["FASTDDS_DEFAULT_PROFILES_FILE"] = profile
    env["RMW_IMPLEMENTATION"] = "rmw_fastrtps_cpp"
    env["PYTHONUNBUFFERED"] = "1"
    return env


def apply_ros_env(domain: int | None = None) -> None:
    """Set the test environment in this process (before rclpy.init)."""
    os.environ.update(ros_env(domain))


def start(args: list[str], env: dict[str, str], log: Path) -> subprocess.Popen:
    """Start a node process with its output in ``log``."""
    fh = open(log, "w")
    return subprocess.Popen([sys.executable, *args], env=env, stdout=fh,
                            stderr=subprocess.STDOUT, cwd=REPO)


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


def spin_until(node, predicate, timeout: float) -> bool:
    """Spin ``node`` until ``predicate()`` is true or ``timeout`` seconds pass."""
    import rclpy
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
        if predicate():
            return True
    return False
