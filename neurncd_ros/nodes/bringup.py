"""Bringup: starts the embedding, mapper and discovery nodes (and a replay with --bag).

There is no ros2 launch wheel, so this is a small process supervisor, each
node in its own process (the field's training and the backbone do not share a
GIL), all with one parameter file:

- a node that exits stops the others (bringup exits with its code; 128 + the signal
  number for a node killed by a signal, as a shell reports it);
- with ``--bag``, the replay starts once every node reports on /diagnostics
  (it is up and subscribed) and the mapper and discovery see their upstream
  node's publisher (at most ``--ready-timeout``), so nothing the bag
  holds is published before a node can take it; when the replay reaches the
  end of the bag (exit 0) the
  nodes keep running until they have labelled what they received: until
  every node reports nothing pending on /diagnostics (or ``--drain-timeout``);
  then all are stopped and bringup exits 0 (a replay that fails, e.g. on a
  truncated bag, stops everything with its exit code);
- SIGINT / SIGTERM stop all nodes cleanly (each saves what it is configured to
  save); a node that does not stop within ``--stop-timeout`` is killed;
- no child outlives bringup: each runs in its own process group (so a
  terminal's Ctrl-C reaches bringup, which stops them in order) with a
  parent-death signal, so they get SIGTERM even if bringup is killed. They start
  with SIGINT and SIGTERM blocked, and unblock them once their handlers are installed
  (``process.Shutdown.install``), so a stop sent while a child is still starting is held until
  it can be handled instead of ending the child's interpreter with a traceback;
- a parameter file that is not valid YAML or not valid for the schema is reported on
  one line naming the file, exit code 2 (as ``neurncd`` does);
- before it starts the nodes and after they stop it removes the shared-memory segments
  of Fast DDS processes that died without removing them (a node killed leaves a 128 MB
  file in /dev/shm with the shipped profile, memory that is otherwise lost until reboot).
"""

from __future__ import annotations

import argparse
import ctypes
import os
import signal
import subprocess
import sys
import threading
import time

from .common import (ConfigError, dds_profile_warning, diagnostics_status, ensure_dds_profile,
                     PIPELINE_NODES, node_connected, share_file)
from .parameters import empty_lists, given_with_p, params_file_error, started_configuration
from .process import STOP_SIGNALS, Shutdown, exit_status, remove_stale_shm

NODES = PIPELINE_NODES
PR_SET_PDEATHSIG = 1


def _child_setup() -> None:  # runs in the child between fork and exec
    os.setpgrp()
    # Held until the node's own handlers are in (Shutdown.install unblocks them): the mask
    # survives exec, the Python handlers bringup installed do not.
    signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:  # not Linux: the process group still lets bringup stop it
        pass


def build_commands(params_file: str, bag: str | None, ros_args: list[str]
                   ) -> dict[str, list[str]]:
    """One command per node: ``python -m neurncd_ros.nodes.<node> --ros-args ...``."""
    base = ["--ros-args", "--params-file", params_file, *ros_args]
    # -P: the package bringup itself runs from, not a source tree in the current folder
    # (python -m puts the current folder first on sys.path).
    py = [sys.executable, "-P", "-m"]
    cmds = {n: [*py, f"neurncd_ros.nodes.{n}", *base] for n in NODES}
    if bag:
        cmds["replay"] = [*py, "neurncd_ros.nodes.replay", *base,
                          "-p", f"replay.bag:={bag}"]
        if uses_sim_time(ros_args):  # the nodes' clocks follow the bag, as with --clock
            cmds["replay"] += ["-p", "replay.clock:=true"]
    return cmds


def uses_sim_time(ros_args: list[str]) -> bool:
    """Whether the ROS arguments set ``use_sim_time`` true (``-p use_sim_time:=true``)."""
    return given_with_p(ros_args).get("use_sim_time", "").strip().lower() in ("true", "1")


class DrainWatcher:
    """Listens to /diagnostics in a thread; tells when every node has nothing pending."""

    def __init__(self, topic: str, ros_args: list[str] = ()) -> None:
        """``ros_args``: the nodes' ROS arguments; their namespace and remappings apply here
        too, so a relative or remapped diagnostics topic is the one the nodes publish on
        (under ``-r __ns:=/robot1`` the watcher once listened to another topic and the
        bag waited for --ready-timeout)."""
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self._context = rclpy.Context()
        remaps = []
        for i, a in enumerate(ros_args):
            if a in ("-r", "--remap") and i + 1 < len(ros_args):
                remaps += ["-r", ros_args[i + 1]]
        rclpy.init(context=self._context,
                   args=["bringup", *(["--ros-args", *remaps] if remaps else [])],
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("bringup", context=self._context)
        self._latest: dict[str, tuple[float, int]] = {}
        self._connected: dict[str, bool] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.node.create_subscription(DiagnosticArray, topic, self._on_diag, 50)
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self._context.ok():
            try:
                self._executor.spin_once(timeout_sec=0.1)
            except Exception:  # noqa: BLE001 - the context went away at shutdown
                break

    def _on_diag(self, msg) -> None:
        now = time.monotonic()
        namespace = self.node.get_namespace()  # the nodes' (bringup takes their -r __ns)
        for name in NODES:
            values = diagnostics_status(msg, name, namespace)
            if values is not None:
                with self._lock:
                    self._latest[name] = (now, int(values.get("pending", "1") or 1))
                    self._connected[name] = bool(node_connected(msg, name, namespace))

    def ready(self) -> bool:
        """Every node has reported (it is up, its subscriptions made) and sees its upstream
        node's publisher, so the first frames of a bag are not lost to DDS discovery."""
        with self._lock:
            return all(name in self._latest and self._connected.get(name, False)
                       for name in NODES)

    def drained_since(self, t0: float) -> bool:
        """Every node reported pending 0 in a status received after ``t0``."""
        with self._lock:
            return all(name in self._latest and self._latest[name][0] > t0
                       and self._latest[name][1] == 0 for name in NODES)

    def close(self) -> None:
        """Stop spinning first, then destroy: no callback may run on a destroyed node."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        try:
            self._executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
            self._context.try_shutdown()
        except Exception:  # noqa: BLE001
            pass


def _stop_all(procs: dict[str, subprocess.Popen], timeout: float) -> None:
    for p in procs.values():
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    deadline = time.monotonic() + timeout
    for name, p in procs.items():
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            print(f"bringup: {name} did not stop within {timeout:g} s: killed", file=sys.stderr)
            p.kill()
            p.wait()


def main(argv: list[str] | None = None) -> int:
    """Start the nodes (and the replay), supervise them, stop them; the exit code."""
    # First: until the nodes are started a signal ends bringup at once, exit 0.
    shutdown = Shutdown("bringup").install(starting=True)
    parser = argparse.ArgumentParser(
        prog="bringup", description="Start the embedding, mapper and discovery nodes with "
        "one parameter file; with --bag also replay a bag into them and stop once they "
        "have labelled it.",
        epilog="Extra ROS arguments after --ros-args are passed to every node.")
    parser.add_argument("--params-file", default=str(share_file("config", "neurncd.yaml")),
                        help="ROS 2 parameter file (default: the shipped config/neurncd.yaml)")
    parser.add_argument("--bag", default=None, help="bag to replay into the nodes")
    parser.add_argument("--ready-timeout", type=float, default=180.0,
                        help="with --bag, wait at most this long (s) for the nodes to come "
                        "up before the replay starts")
    parser.add_argument("--drain-timeout", type=float, default=120.0,
                        help="after the bag ends, wait at most this long (s) for the nodes "
                        "to finish what they received")
    parser.add_argument("--stop-timeout", type=float, default=10.0,
                        help="seconds a node gets to stop cleanly before it is killed")
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

    try:
        problem = (params_file_error(args.params_file)
                   or empty_lists(["--params-file", args.params_file, *ros_args]))
        if problem:
            raise ConfigError(problem)
        # What each node would refuse, refused once here, before any starts.
        nodes = (*NODES, "replay") if args.bag else NODES
        topic = started_configuration(args.params_file, ros_args, nodes).topics.diagnostics
    except ConfigError as err:
        print(f"bringup: configuration error: {err}", file=sys.stderr)
        return 2
    warning = dds_profile_warning(ensure_dds_profile())
    if warning:
        print(f"bringup: warning: {warning}", file=sys.stderr)
    _clean_shm(60.0)  # what earlier runs' killed processes left
    shutdown.started()
    watcher = DrainWatcher(topic, ros_args)
    cmds = build_commands(args.params_file, args.bag, ros_args)
    replay_cmd = cmds.pop("replay", None)
    procs: dict[str, subprocess.Popen] = {}
    if not shutdown.requested.is_set():  # not after a signal during the watcher's start
        procs = {name: subprocess.Popen(cmd, preexec_fn=_child_setup)
                 for name, cmd in cmds.items()}
    code = 0
    drain_from: float | None = None
    ready_by = time.monotonic() + args.ready_timeout
    try:
        while not shutdown.requested.is_set():
            if replay_cmd is not None and (watcher.ready() or time.monotonic() > ready_by):
                if not watcher.ready():
                    print(f"bringup: not every node is up and connected after "
                          f"{args.ready_timeout:g} s: replaying anyway", file=sys.stderr)
                procs["replay"] = subprocess.Popen(replay_cmd, preexec_fn=_child_setup)
                replay_cmd = None
            time.sleep(0.2)
            dead = [(n, p.returncode) for n, p in procs.items()
                    if n != "replay" and p.poll() is not None]
            if dead:
                name, rc = dead[0]
                code, what = exit_status(rc)
                code = code or 1  # a node is not meant to end on its own
                print(f"bringup: {name} {what}: stopping the others; bringup exits {code}",
                      file=sys.stderr)
                break
            replay = procs.get("replay")
            if replay is not None and drain_from is None and replay.poll() is not None:
                if replay.returncode != 0:
                    code, what = exit_status(replay.returncode)
                    print(f"bringup: replay failed ({what}): stopping; bringup exits {code}",
                          file=sys.stderr)
                    break
                drain_from = time.monotonic()
                print("bringup: the bag has been played; waiting for the nodes to finish",
                      flush=True)
            if drain_from is not None:
                if watcher.drained_since(drain_from + 1.0):
                    print("bringup: the nodes have labelled what they received: stopping",
                          flush=True)
                    break
                if time.monotonic() - drain_from > args.drain_timeout:
                    print(f"bringup: nodes still busy {args.drain_timeout:g} s after the bag "
                          "ended: stopping", file=sys.stderr)
                    break
        if shutdown.requested.is_set():
            print(f"bringup: {shutdown.signal_name}: stopping the nodes", file=sys.stderr)
    finally:
        _stop_all(procs, args.stop_timeout)
        watcher.close()
        _clean_shm(5.0)  # a node killed after --stop-timeout (or by someone) left its own
    return code


def _clean_shm(min_age_s: float) -> None:
    """Free the shared memory of Fast DDS processes that died without removing it
    (:func:`.process.remove_stale_shm`), saying so."""
    n, freed = remove_stale_shm(min_age_s=min_age_s)
    if n:
        print(f"bringup: removed {n} shared-memory segment(s) ({freed / 2**20:.0f} MB) that "
              "stopped Fast DDS processes left in /dev/shm", file=sys.stderr)


if __name__ == "__main__":
    raise SystemExit(main())
