"""``ros2 launch neurncd_ros neurncd.launch.py``: the embedding, mapper and discovery nodes
with one parameter file, and with ``bag:=...`` a replay of the bag into them.

Arguments (``NAME:=VALUE`` after the file name):

- ``params_file``: the parameter file of every node (default: the installed
  ``share/neurncd_ros/config/neurncd.yaml``);
- ``namespace``: the nodes' namespace (default ``''``, the root). The topic names are
  absolute, so it moves the node names only (README, "On a robot");
- ``use_sim_time``: ``true`` or ``false`` (default): the nodes' clocks follow /clock, and
  the replay publishes the bag's time there (``replay.clock``), as bringup does;
- ``bag``: a bag to replay into the nodes (the replay node's ``replay.bag``; default
  ``''``: no replay, a live camera publishes the input topics).

Before a node starts it points Fast DDS at the shipped shared-memory profile
(``FASTRTPS_/FASTDDS_DEFAULT_PROFILES_FILE``, and ``RMW_IMPLEMENTATION``) unless the user
set them, with the nodes' own helper: default Fast DDS loses images over 1 MB. A
parameter file or bag that does not exist, or a parameter file with a value a node
would refuse (``neurncd check-config --node``, each node's view of the file), stops the
launch before any node starts, with one error (a parameter file launch_ros cannot find
is only a warning, and each node would refuse a bad value on its own, the others running
on). As with bringup, a node or replay
that fails (a crash: an exit code other than 0) stops the others, and ``ros2 launch``
exits 1.

The same start as ``bringup``: here the replay starts with the nodes, and waits itself
(``replay.wait_for_graph``, at most ``replay.wait_for_subscribers_s``) until the nodes
report on /diagnostics that they are up and see their upstream node, as bringup waits
before it starts the replay; the nodes keep running after the bag until Ctrl-C (bringup
stops them once they have labelled it).
"""

import os
import subprocess
import sys

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, SetEnvironmentVariable
from launch.conditions import IfCondition
from launch.substitutions import (AndSubstitution, LaunchConfiguration, NotEqualsSubstitution,
                                  NotSubstitution)
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from neurncd_ros.config import node_name
from neurncd_ros.nodes.common import PIPELINE_NODES as NODES, ensure_dds_profile

PACKAGE = "neurncd_ros"


def before_the_nodes(context, *args, **kwargs):
    """At launch time, before the nodes: refuse a parameter file or bag that does not exist,
    and set the Fast DDS variables the nodes' :func:`ensure_dds_profile` would set in the
    environment the nodes inherit (only those the user has not set)."""
    params_file = LaunchConfiguration("params_file").perform(context)
    if not os.path.isfile(params_file):
        raise RuntimeError(f"neurncd.launch.py: parameter file {params_file} does not exist")
    bag = LaunchConfiguration("bag").perform(context)
    if bag and not os.path.exists(bag):
        raise RuntimeError(f"neurncd.launch.py: bag {bag} does not exist")
    # Each node's own view of the file, as rcl gives it (/** and the node's own entries):
    # another node's entry in a shared file is not this launch's concern.
    namespace = LaunchConfiguration("namespace").perform(context)
    names = [*NODES, "replay"] if bag else list(NODES)
    views = [f"--node={node_name(namespace, name)}" for name in names]
    check = subprocess.run([*neurncd_command(), "check-config", params_file, *views],
                           capture_output=True, text=True, start_new_session=True)
    if check.returncode != 0:
        lines = (check.stderr or check.stdout).strip().splitlines() or [
            f"neurncd check-config exited {check.returncode}"]
        raise RuntimeError("neurncd.launch.py: " + "\n".join(
            line.removeprefix("neurncd check-config: ") for line in lines))
    env = dict(context.environment)
    ensure_dds_profile(env)
    return [SetEnvironmentVariable(name, value) for name, value in env.items()
            if context.environment.get(name) != value]


def neurncd_command() -> list[str]:
    """The offline tool as ``ros2 run neurncd_ros neurncd`` starts it (its interpreter is
    the one with the package's dependencies, which ros2 launch's may lack), else this
    interpreter's (the source tree)."""
    prefix = os.path.dirname(os.path.dirname(get_package_share_directory(PACKAGE)))
    exe = os.path.join(prefix, "lib", PACKAGE, "neurncd")
    return [exe] if os.access(exe, os.X_OK) else [sys.executable, "-m", "neurncd_ros.cli"]


def after_a_process(event, context):
    """A node or the replay that fails while the launch is not shutting down (a crash, a
    value it refused: an exit code other than 0) stops the launch with an error (ros2
    launch exits 1), as bringup stops the others. A node exits 0 only when asked to stop (SIGINT,
    SIGTERM), the replay at the end of its bag: Ctrl-C in a terminal reaches every node at
    once, and a node may end before launch has seen the signal; stopping the launch then
    would signal the nodes a second time, which ends them at once, without their save."""
    if context.is_shutdown or event.returncode == 0:
        return None
    raise RuntimeError(f"neurncd.launch.py: {event.process_name} exited with code "
                       f"{event.returncode}: stopping the others")


def generate_launch_description():
    """The arguments, the environment, the three nodes and the replay (under ``bag``)."""
    params_file = LaunchConfiguration("params_file")
    namespace = LaunchConfiguration("namespace")
    use_sim_time = LaunchConfiguration("use_sim_time")
    bag = LaunchConfiguration("bag")
    # Typed: the values stay a bool and a string whatever they look like to YAML (a bag
    # called 2024 or on), as bringup's -p values do for rcl.
    sim_time = {"use_sim_time": ParameterValue(use_sim_time, value_type=bool)}
    # The replay starts with the nodes: it waits for the graph downstream too (the mapper
    # and discovery listening), or the first frames reach only the embedding node.
    replay_bag = {"replay.bag": ParameterValue(bag, value_type=str),
                  "replay.wait_for_graph": True}
    has_bag = NotEqualsSubstitution(bag, "")

    def node(executable, *parameters, condition=None):
        return Node(package=PACKAGE, executable=executable, namespace=namespace,
                    parameters=[params_file, sim_time, *parameters], output="screen",
                    condition=condition, on_exit=after_a_process)

    return LaunchDescription([
        DeclareLaunchArgument(
            "params_file",
            default_value=os.path.join(get_package_share_directory(PACKAGE), "config",
                                       "neurncd.yaml"),
            description="ROS 2 parameter file of every node"),
        DeclareLaunchArgument(
            "namespace", default_value="",
            description="namespace of the nodes (their topic names stay absolute)"),
        DeclareLaunchArgument(
            "use_sim_time", default_value="false", choices=["true", "false", "True", "False"],
            description="the nodes' clocks follow /clock; the replay publishes the bag's time"),
        DeclareLaunchArgument(
            "bag", default_value="",
            description="bag to replay into the nodes ('' = none: a live camera)"),
        OpaqueFunction(function=before_the_nodes),
        *(node(name) for name in NODES),
        # The replay twice, under exclusive conditions: replay.clock is set only with
        # use_sim_time, as bringup does, so a parameter file's replay.clock holds otherwise.
        node("replay", replay_bag,
             condition=IfCondition(AndSubstitution(has_bag, NotSubstitution(use_sim_time)))),
        node("replay", replay_bag, {"replay.clock": True},
             condition=IfCondition(AndSubstitution(has_bag, use_sim_time))),
    ])
