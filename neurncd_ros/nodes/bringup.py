"""Bringup: starts the embedding, mapper and discovery nodes (and optionally a replay).

There is no ros2 launch wheel, so this is a small process supervisor: each
node runs in its own process (the mapper's training and the backbone do not
share a GIL), all with the same parameter file, and all are stopped together
when one fails or on Ctrl-C.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time

from .common import ensure_dds_profile, share_file

NODES = ("embedding", "mapper", "discovery")


def build_commands(params_file: str, bag: str | None, ros_args: list[str]) -> list[list[str]]:
    """One command per node: ``python -m neurncd_ros.nodes.<node> --ros-args ...``."""
    base = ["--ros-args", "--params-file", params_file, *ros_args]
    cmds = [[sys.executable, "-m", f"neurncd_ros.nodes.{n}", *base] for n in NODES]
    if bag:
        cmds.append([sys.executable, "-m", "neurncd_ros.nodes.replay", *base,
                     "-p", f"replay.bag:={bag}"])
    return cmds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="bringup", description="Start the embedding, mapper and discovery nodes with "
        "one parameter file; with --bag also replay a bag into them.",
        epilog="Extra ROS arguments after --ros-args are passed to every node.")
    parser.add_argument("--params-file", default=str(share_file("config", "neurncd.yaml")),
                        help="ROS 2 parameter file (default: the shipped config/neurncd.yaml)")
    parser.add_argument("--bag", default=None, help="bag to replay into the nodes")
    argv = sys.argv[1:] if argv is None else argv
    ros_args: list[str] = []
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        argv, ros_args = argv[:i], argv[i + 1:]
    args = parser.parse_args(argv)
    if not os.path.isfile(args.params_file):
        parser.error(f"parameter file {args.params_file} does not exist")
    if args.bag and not os.path.exists(args.bag):
        parser.error(f"bag {args.bag} does not exist")
    ensure_dds_profile()
    procs = [subprocess.Popen(c) for c in build_commands(args.params_file, args.bag, ros_args)]
    code = 0
    try:
        while all(p.poll() is None for p in procs):
            time.sleep(0.5)
        failed = [p for p in procs if p.poll() not in (None, 0)]
        code = failed[0].returncode if failed else 0
    except KeyboardInterrupt:
        pass
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 10
        for p in procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
    return code


if __name__ == "__main__":
    raise SystemExit(main())
