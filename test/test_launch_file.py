"""The ros2 launch file (launch/neurncd.launch.py) starts what bringup starts, wired as
bringup wires it: the package's console scripts, one parameter file, the namespace and
sim time on every node, the replay (with replay.clock under sim time) only with a bag,
the Fast DDS profile in the environment.

There is no launch wheel, so here generate_launch_description() runs against small
stand-ins for launch and launch_ros (Jazzy's signatures) that record what the file builds
and evaluate its substitutions, conditions and typed parameter values as the Jazzy sources
do. Where the real launch and launch_ros are importable (a ROS install's CI) they are used
instead, launch_ros's Node only wrapped to record its arguments. Nothing is started.
"""

from __future__ import annotations

import importlib.util
import os
import runpy
import shutil
import sys
import types
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
LAUNCH_FILE = REPO / "launch" / "neurncd.launch.py"
NODES = ("embedding", "mapper", "discovery")
ARGUMENTS = ("params_file", "namespace", "use_sim_time", "bag")
DDS_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE",
            "RMW_IMPLEMENTATION")


# --- Stand-ins: what the launch file uses of launch / launch_ros, Jazzy's signatures -------

def _subs(value):
    """As launch's normalize_to_list_of_substitutions: a text or substitutions -> a list."""
    if isinstance(value, (list, tuple)):
        return [s for v in value for s in _subs(v)]
    return [value]


def perform(context, value) -> str:
    """A text, a substitution or a list of them, performed to a string (real or stand-in)."""
    if isinstance(value, str):
        return value
    if isinstance(value, (list, tuple)):
        return "".join(perform(context, v) for v in value)
    return value.perform(context)


def _typed(text: str, value_type):
    """launch's coerce_to_type: YAML rules, '1' and '0' for a bool, a str kept as it is."""
    if value_type is str:
        return text
    if value_type is bool and text in ("1", "0"):
        return text == "1"
    value = yaml.safe_load(text)
    if value_type is not None and not isinstance(value, value_type):
        raise ValueError(f"{text!r} is not a {value_type.__name__}")
    return value


def stand_in_modules() -> dict[str, types.ModuleType]:
    """launch, launch.actions, launch.substitutions, launch.conditions, launch_ros,
    launch_ros.actions and launch_ros.parameter_descriptions."""

    class LaunchContext:
        def __init__(self, *, argv=None, noninteractive=False):
            self.launch_configurations: dict[str, str] = {}
            self.__is_shutdown = False

        def _set_is_shutdown(self, state: bool) -> None:
            self.__is_shutdown = state

        @property
        def is_shutdown(self):
            return self.__is_shutdown

        @property
        def environment(self):
            return os.environ  # as launch's: the launch process's own environment

    class LaunchDescription:
        def __init__(self, initial_entities=None, *, deprecated_reason=None):
            self.entities = list(initial_entities or [])

    class Action:
        def __init__(self, *, condition=None):
            self.condition = condition

    class DeclareLaunchArgument(Action):
        def __init__(self, name, *, default_value=None, description=None, choices=None,
                     **kwargs):
            super().__init__(**kwargs)
            if choices is not None and isinstance(default_value, str):
                assert default_value in choices, "launch refuses a default not in choices"
            self.name, self.description, self.choices = name, description, choices
            self.default_value = None if default_value is None else _subs(default_value)

    class SetEnvironmentVariable(Action):
        def __init__(self, name, value, **kwargs):
            super().__init__(**kwargs)
            self.name, self.value = _subs(name), _subs(value)

    class OpaqueFunction(Action):
        def __init__(self, *, function, args=None, kwargs=None, **left_over_kwargs):
            super().__init__(**left_over_kwargs)
            assert callable(function)
            self.function, self.args, self.kwargs = function, args or [], kwargs or {}

        def execute(self, context):
            return self.function(context, *self.args, **self.kwargs)

    class Substitution:
        def perform(self, context) -> str:
            raise NotImplementedError

    class TextSubstitution(Substitution):
        def __init__(self, *, text=""):
            self.text = text

        def perform(self, context):
            return self.text

    class LaunchConfiguration(Substitution):
        def __init__(self, variable_name, *, default=None):
            self.variable_name, self.default = _subs(variable_name), default

        def perform(self, context):
            name = perform(context, self.variable_name)
            if name in context.launch_configurations:
                return context.launch_configurations[name]
            if self.default is not None:
                return perform(context, _subs(self.default))
            raise LookupError(f"launch configuration '{name}' does not exist")

    class NotSubstitution(Substitution):
        def __init__(self, value):
            self.value = _subs(value)

        def perform(self, context):
            return str(not _typed(perform(context, self.value), bool)).lower()

    class AndSubstitution(Substitution):
        def __init__(self, left, right):
            self.left, self.right = _subs(left), _subs(right)

        def perform(self, context):
            return str(_typed(perform(context, self.left), bool)
                       and _typed(perform(context, self.right), bool)).lower()

    class EqualsSubstitution(Substitution):
        def __init__(self, left, right):
            self.left = _subs("" if left is None else left)
            self.right = _subs("" if right is None else right)

        def perform(self, context):
            left, right = perform(context, self.left), perform(context, self.right)
            truth = ("true", "false", "1", "0")
            if left.lower() in truth and right.lower() in truth:
                return str((left.lower() in ("true", "1"))
                           == (right.lower() in ("true", "1"))).lower()
            return str(left == right).lower()  # (launch also compares numbers as floats)

    class NotEqualsSubstitution(EqualsSubstitution):
        def perform(self, context):
            return str(super().perform(context) != "true").lower()

    class IfCondition:
        def __init__(self, predicate_expression):
            self.expression = _subs(predicate_expression)

        def evaluate(self, context) -> bool:
            text = perform(context, self.expression).strip().lower()
            if text not in ("true", "1", "false", "0"):
                raise ValueError(f"invalid condition expression {text!r}")
            return text in ("true", "1")

    class UnlessCondition(IfCondition):
        def evaluate(self, context) -> bool:
            return not super().evaluate(context)

    execute_process_kwargs = {"output", "condition", "emulate_tty", "respawn", "respawn_delay",
                              "sigterm_timeout", "sigkill_timeout", "cwd", "env",
                              "additional_env", "prefix", "on_exit", "log_cmd"}

    class Node(Action):
        def __init__(self, *, executable, package=None, name=None, namespace=None,
                     exec_name=None, parameters=None, remappings=None, ros_arguments=None,
                     arguments=None, **kwargs):
            assert set(kwargs) <= execute_process_kwargs, set(kwargs) - execute_process_kwargs
            assert parameters is None or isinstance(parameters, list), "launch_ros wants a list"
            super().__init__(condition=kwargs.get("condition"))
            self.recorded = dict(executable=executable, package=package, name=name,
                                 namespace=namespace, parameters=parameters, **kwargs)

    class ParameterValue:
        def __init__(self, value, *, value_type=None):
            self.value, self.value_type = _subs(value), value_type

        def evaluate(self, context):
            return _typed(perform(context, self.value), self.value_type)

    def module(name, **members):
        mod = types.ModuleType(name)
        mod.__dict__.update(members)
        return mod

    mods = {
        "launch": module("launch", LaunchDescription=LaunchDescription,
                         LaunchContext=LaunchContext),
        "launch.actions": module("launch.actions", DeclareLaunchArgument=DeclareLaunchArgument,
                                 SetEnvironmentVariable=SetEnvironmentVariable,
                                 OpaqueFunction=OpaqueFunction),
        "launch.substitutions": module(
            "launch.substitutions", LaunchConfiguration=LaunchConfiguration,
            TextSubstitution=TextSubstitution, NotSubstitution=NotSubstitution,
            AndSubstitution=AndSubstitution, EqualsSubstitution=EqualsSubstitution,
            NotEqualsSubstitution=NotEqualsSubstitution),
        "launch.conditions": module("launch.conditions", IfCondition=IfCondition,
                                    UnlessCondition=UnlessCondition),
        "launch_ros": module("launch_ros"),
        "launch_ros.actions": module("launch_ros.actions", Node=Node),
        "launch_ros.parameter_descriptions": module("launch_ros.parameter_descriptions",
                                                    ParameterValue=ParameterValue),
    }
    for name, mod in mods.items():
        if "." in name:
            parent, child = name.rsplit(".", 1)
            setattr(mods[parent], child, mod)
    return mods


def _real_launch() -> bool:
    """Whether the real launch and launch_ros are importable. Not just `import launch`: from
    the repository root that finds its launch/ folder, a namespace package."""
    for name in ("launch", "launch_ros"):
        spec = importlib.util.find_spec(name)
        if spec is None or spec.origin is None:
            return False
    return True


# --- The launch file, loaded as ros2 launch loads it -----------------------------------------

class Launched:
    """The launch file's description, with what evaluates it: the (real or stand-in)
    launch module, the Node class whose instances recorded their arguments, the share."""

    def __init__(self, launch, node_cls, share: Path, module) -> None:
        self.launch, self.node_cls, self.share, self.module = launch, node_cls, share, module
        self.description = module.generate_launch_description()
        self.entities = list(self.description.entities)

    def arguments(self) -> dict:
        return {e.name: e for e in self.entities if type(e).__name__ == "DeclareLaunchArgument"}

    def context(self, **given: str):
        """A launch context with the arguments given on the command line, the other
        arguments at their defaults (as ros2 launch sets them)."""
        ctx = self.launch.LaunchContext()
        for name, arg in self.arguments().items():
            ctx.launch_configurations[name] = (given[name] if name in given
                                               else perform(ctx, arg.default_value))
        return ctx

    def nodes(self) -> list:
        return [e for e in self.entities if isinstance(e, self.node_cls)]

    def started(self, ctx) -> list:
        """The nodes whose condition holds in ``ctx``: the ones ros2 launch would start."""
        return [n for n in self.nodes()
                if n.recorded.get("condition") is None or n.recorded["condition"].evaluate(ctx)]

    def before_the_nodes(self, ctx) -> list:
        """What the launch file's OpaqueFunction returns in ``ctx`` (it runs first)."""
        opaque = [e for e in self.entities if type(e).__name__ == "OpaqueFunction"]
        assert len(opaque) == 1
        assert self.entities.index(opaque[0]) < min(map(self.entities.index, self.nodes()))
        return list(opaque[0].execute(ctx) or [])


def node_parameters(node, ctx) -> tuple[list[str], dict]:
    """A node's parameter files and its parameters given as values (later ones win), as
    launch_ros evaluates them."""
    files, values = [], {}
    for item in node.recorded["parameters"]:
        if isinstance(item, dict):
            values.update({k: v.evaluate(ctx) if hasattr(v, "evaluate") else v
                           for k, v in item.items()})
        else:
            assert not values, "a parameter file after values would override them"
            files.append(perform(ctx, item))
    return files, values


@pytest.fixture
def launched(tmp_path, monkeypatch) -> Launched:
    share = tmp_path / "install" / "share" / "neurncd_ros"
    (share / "config").mkdir(parents=True)
    for name in ("neurncd.yaml", "fastdds_shm.xml"):
        shutil.copy(REPO / "config" / name, share / "config" / name)

    def share_directory(package: str) -> str:
        assert package == "neurncd_ros"
        return str(share)

    try:
        import ament_index_python.packages as packages
    except ImportError:  # a machine with neither ROS nor its wheels
        packages = types.ModuleType("ament_index_python.packages")
        monkeypatch.setitem(sys.modules, "ament_index_python", types.ModuleType("ament"))
        monkeypatch.setitem(sys.modules, "ament_index_python.packages", packages)
    monkeypatch.setattr(packages, "get_package_share_directory", share_directory,
                        raising=False)

    if _real_launch():
        import launch
        import launch_ros.actions

        class RecordingNode(launch_ros.actions.Node):
            """The real Node (it checks its arguments), keeping them for the test."""

            def __init__(self, **kwargs):
                self.recorded = kwargs
                super().__init__(**kwargs)

        monkeypatch.setattr(launch_ros.actions, "Node", RecordingNode)
        node_cls = RecordingNode
    else:
        for name, mod in stand_in_modules().items():
            monkeypatch.setitem(sys.modules, name, mod)
        launch = sys.modules["launch"]
        node_cls = sys.modules["launch_ros.actions"].Node
    spec = importlib.util.spec_from_file_location("neurncd_launch_file", LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return Launched(launch, node_cls, share, module)


def setup_py(monkeypatch) -> dict:
    """The keywords setup.py passes to setuptools.setup (run with setup() recording them)."""
    import setuptools

    recorded = {}
    monkeypatch.setattr(setuptools, "setup", lambda **kw: recorded.update(kw))
    monkeypatch.chdir(REPO)  # its globs are relative
    runpy.run_path(str(REPO / "setup.py"), run_name="__main__")
    return recorded


# --- The tests -------------------------------------------------------------------------------

def test_setup_py_installs_the_launch_file(monkeypatch):
    data_files = dict(setup_py(monkeypatch)["data_files"])
    assert data_files["share/neurncd_ros/launch"] == ["launch/neurncd.launch.py"]


def test_the_nodes_are_the_packages_console_scripts(launched, monkeypatch):
    scripts = {line.split("=")[0].strip()
               for line in setup_py(monkeypatch)["entry_points"]["console_scripts"]}
    nodes = launched.nodes()
    for node in nodes:
        assert node.recorded["package"] == "neurncd_ros"
        assert node.recorded["executable"] in scripts
        assert node.recorded.get("name") is None  # the node's own name, as bringup starts it
    # The three always; the replay only under a condition; nothing else.
    always = [n.recorded["executable"] for n in nodes if n.recorded.get("condition") is None]
    assert sorted(always) == sorted(NODES)
    assert {n.recorded["executable"] for n in nodes} == {*NODES, "replay"}


def test_arguments_and_the_default_params_file(launched):
    args = launched.arguments()
    assert set(args) == set(ARGUMENTS)
    ctx = launched.context()
    assert ctx.launch_configurations == {
        "params_file": str(launched.share / "config" / "neurncd.yaml"),
        "namespace": "", "use_sim_time": "false", "bag": ""}
    assert "false" in args["use_sim_time"].choices and "true" in args["use_sim_time"].choices
    for arg in args.values():
        assert arg.description


@pytest.mark.parametrize("given", [
    {},
    {"namespace": "/robot1", "use_sim_time": "true", "params_file": "/my/params.yaml"},
    {"namespace": "robot2", "use_sim_time": "false", "bag": "scene.mcap"},
    {"use_sim_time": "True", "bag": "scene.mcap"},
])
def test_every_node_gets_the_params_file_namespace_and_sim_time(launched, given):
    ctx = launched.context(**given)
    started = launched.started(ctx)
    assert len(started) == 3 + bool(given.get("bag"))
    for node in started:
        files, values = node_parameters(node, ctx)
        assert files == [given.get("params_file", str(launched.share / "config" /
                                                       "neurncd.yaml"))]
        assert perform(ctx, node.recorded["namespace"]) == given.get("namespace", "")
        # A bool, not the text: rclpy refuses a string for use_sim_time.
        assert values["use_sim_time"] is (given.get("use_sim_time", "false").lower() == "true")


@pytest.mark.parametrize("bag, sim_time, clock", [
    ("", "false", None), ("", "true", None),
    ("scene.mcap", "false", None),  # replay.clock left to the parameter file, as bringup does
    ("scene.mcap", "true", True),
    ("2024", "false", None),  # a bag name YAML would read as a number stays a string
])
def test_the_replay_only_with_a_bag_and_its_clock_with_sim_time(launched, bag, sim_time,
                                                                 clock, tmp_path):
    ctx = launched.context(bag=bag, use_sim_time=sim_time)
    replays = [n for n in launched.started(ctx) if n.recorded["executable"] == "replay"]
    assert len(replays) == (1 if bag else 0)
    if not bag:
        return
    files, values = node_parameters(replays[0], ctx)
    assert values["replay.bag"] == bag and isinstance(values["replay.bag"], str)
    assert values.get("replay.clock") is clock
    # It starts with the nodes: it waits until they report that they are up and connected.
    assert values["replay.wait_for_graph"] is True
    # The node takes them: launch_ros writes them into a params file of its own (/** as the
    # nodes get no name), read here as the nodes and bringup read their configuration.
    from neurncd_ros.nodes.parameters import params_file_error, started_configuration

    extra = tmp_path / "launch_params_replay"
    extra.write_text(yaml.dump({"/**": {"ros__parameters": values}}))
    assert params_file_error(str(extra)) is None
    cfg = started_configuration(files[0], ["--params-file", str(extra)])
    assert cfg.replay.bag == bag
    assert cfg.replay.clock is (clock is True) and cfg.replay.wait_for_graph is True


def test_the_fast_dds_profile_unless_the_user_chose_one(launched, monkeypatch):
    from neurncd_ros.share import share_file

    # the running package's own (in an install, its share/: test_packaging)
    profile = str(share_file("config", "fastdds_shm.xml"))
    assert os.path.isfile(profile)

    def set_by_launch() -> dict[str, str]:
        ctx = launched.context()
        actions = launched.before_the_nodes(ctx)
        assert all(type(a).__name__ == "SetEnvironmentVariable" for a in actions)
        return {perform(ctx, a.name): perform(ctx, a.value) for a in actions}

    for var in DDS_VARS:
        monkeypatch.delenv(var, raising=False)
    assert set_by_launch() == {"FASTRTPS_DEFAULT_PROFILES_FILE": profile,
                               "FASTDDS_DEFAULT_PROFILES_FILE": profile,
                               "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
    # The user's profile (either variable) is used for both; their RMW is kept.
    monkeypatch.setenv("FASTDDS_DEFAULT_PROFILES_FILE", "/mine.xml")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp")
    assert set_by_launch() == {"FASTRTPS_DEFAULT_PROFILES_FILE": "/mine.xml"}
    monkeypatch.setenv("FASTRTPS_DEFAULT_PROFILES_FILE", "/mine.xml")
    assert set_by_launch() == {}


def test_a_missing_params_file_or_bag_stops_before_any_node(launched, tmp_path):
    with pytest.raises(RuntimeError, match="parameter file /nowhere.yaml does not exist"):
        launched.before_the_nodes(launched.context(params_file="/nowhere.yaml"))
    with pytest.raises(RuntimeError, match="bag /nowhere.mcap does not exist"):
        launched.before_the_nodes(launched.context(bag="/nowhere.mcap"))
    bag = tmp_path / "scene.mcap"
    bag.write_bytes(b"")
    launched.before_the_nodes(launched.context(bag=str(bag)))  # an existing one is fine


def test_a_params_file_the_nodes_would_refuse_stops_before_any_node(launched, tmp_path):
    """Each node would refuse the value on its own (one error per node, the launch exiting
    0); the launch file checks the file as `neurncd check-config` does, before any node,
    and names every bad value once."""
    bad = tmp_path / "bad.yaml"
    bad.write_text("/**:\n  ros__parameters:\n    embedding_node:\n      max_rate_hz: -3.0\n"
                   "    mapper:\n      lambda_embedding: -1.0\n")
    with pytest.raises(RuntimeError) as info:
        launched.before_the_nodes(launched.context(params_file=str(bad)))
    text = str(info.value)
    assert text.startswith("neurncd.launch.py: ")
    assert "embedding_node.max_rate_hz: -3.0 is out of range" in text
    assert "mapper.lambda_embedding: -1.0 is out of range" in text
    assert "Traceback" not in text
    # What each node is given, as rcl gives it: another node's or robot's entry in a
    # shared file is not this launch's error; its own robot's is.
    shared = tmp_path / "shared.yaml"
    shared.write_text("/**:\n  ros__parameters:\n    mapper:\n      lambda_embedding: 0.5\n"
                      "camera_driver:\n  ros__parameters:\n    fps: 30\n"
                      "/robot2/*:\n  ros__parameters:\n    embedding_node:\n"
                      "      max_rate_hz: -3.0\n")
    launched.before_the_nodes(launched.context(params_file=str(shared), namespace="robot1"))
    with pytest.raises(RuntimeError, match=r"max_rate_hz: -3.0 is out of range.*\(node "
                                           r"/robot2/embedding, /robot2/mapper, "
                                           r"/robot2/discovery\)"):
        launched.before_the_nodes(launched.context(params_file=str(shared),
                                                   namespace="robot2"))


def test_a_node_that_fails_stops_the_launch(launched):
    """A node or replay that fails while the launch runs (a crash, a refused value: an exit
    code other than 0) stops the launch with an error, so ros2 launch exits 1 and no node
    runs on without the others, as under bringup. An exit 0 is a requested stop (Ctrl-C
    in a terminal reaches the nodes before launch may have seen it; stopping the launch
    would signal them again) or the replay at its bag's end: no error, nor any end during
    the launch's own shutdown."""
    ctx = launched.context(bag="scene.mcap")
    started = launched.started(ctx)
    assert len(started) == 4

    class Exited:  # what launch's ProcessExited carries that the handler reads
        def __init__(self, name, returncode):
            self.process_name, self.returncode = name, returncode

    for node in started:
        on_exit = node.recorded["on_exit"]
        assert on_exit(Exited("x-1", 0), ctx) is None
        for code in (1, 2, -9, -11):
            with pytest.raises(RuntimeError, match=rf"x-1 exited with code {code}: stopping"):
                on_exit(Exited("x-1", code), ctx)
    ctx._set_is_shutdown(True)
    for node in started:
        assert node.recorded["on_exit"](Exited("x-1", -15), ctx) is None
