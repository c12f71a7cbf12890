"""A node's parameters: the schema declared read-only on the node, and the one-line
errors for what rcl and rclpy refuse without saying where (a params file that is not YAML,
a value refused by the schema, an empty list, ROS arguments rcl cannot parse).

Split from :mod:`.common` so each stays one subject. Like it, only the standard library
and ConfigError at the top: a node imports this before its signal handlers are in.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..core.params import ConfigError

if TYPE_CHECKING:
    from .. import config as config_mod


def _ros_value(value: Any) -> Any:
    return list(value) if isinstance(value, (list, tuple)) else value


def declare_config(node: Any) -> config_mod.Config:
    """Declare every schema parameter on ``node``, read-only, and return the validated config.

    Values come from --params-file / -p overrides. A parameter name the schema
    does not know, a wrong type or an out-of-range value raises ConfigError
    naming the key and the allowed values.

    The nodes read their configuration once, here: a value set at run time (``ros2 param
    set``) would be accepted and never used. So each parameter is declared read-only (its
    descriptor also carries the schema's description and allowed values, which ``ros2
    param describe`` shows), and rclpy refuses a set; :class:`ReadOnlyConfig` makes the
    refusal say how to change the value. rclpy's own parameters (``use_sim_time``) are
    left as rclpy declares them.
    """
    from .. import config as config_mod

    defaults = config_mod.default().to_flat()
    overrides = dict(node.get_parameters_by_prefix(""))  # auto-declared from overrides
    unknown = sorted(k for k in overrides
                     if k not in defaults and not config_mod.ros_builtin(k))
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown parameter; see `neurncd params` for the "
                          "list of parameters")
    specs = {f"{section}.{spec.name}": spec
             for section, section_specs in config_mod.schema().items()
             for spec in section_specs}
    values = {}
    for key, default in defaults.items():
        spec = specs[key]  # the schema names every parameter of the defaults
        if node.has_parameter(key):  # given with --params-file / -p: declared by rclpy
            value = node.get_parameter(key)
            # The value stays as given (the schema checks its type below); only the
            # descriptor changes.
            node.set_descriptor(key, _read_only(spec, value.type_.value))
            value = value.value
        elif isinstance(default, list) and not default:
            # An empty list default has no element type ROS could infer: declare it
            # dynamically typed, unset = default. (A parameter file's `[]` never gets here:
            # rclpy refuses it in the Node's constructor; run_node names it, empty_lists.)
            value = node.declare_parameter(key, None, _read_only(spec, 0)).value
        else:
            value = node.declare_parameter(key, _ros_value(default), _read_only(spec)).value
        values[key] = default if value is None else value
    return config_mod.from_flat(values)


READ_ONLY_REASON = ("{key} is read-only: the node reads its configuration once, at start, "
                    "and would not use a value set now; restart the node with the new value "
                    "(--ros-args --params-file FILE, or -p {key}:=VALUE)")


def _read_only(spec: Any, type_: int | None = None) -> Any:
    """A read-only ParameterDescriptor for a schema parameter (``spec``: its schema entry),
    of ``type_``, a rcl_interfaces ParameterType number (None: the type
    ``declare_parameter`` infers from the default; 0, not set: dynamically typed, as an
    empty list has no element type ROS could infer)."""
    from rcl_interfaces.msg import ParameterDescriptor

    desc = ParameterDescriptor(read_only=True, dynamic_typing=type_ == 0)
    if type_:
        desc.type = type_
    desc.description = spec.doc + (f" [{spec.unit}]" if spec.unit else "")
    desc.additional_constraints = (spec.allowed() + "; read once, at start: restart the "
                                   "node with --params-file / -p to change it")
    return desc


class ReadOnlyConfig:
    """Mixin of a node whose configuration :func:`declare_config` declared (put before
    rclpy's ``Node`` in the bases): setting one of those parameters at run time is refused
    with :data:`READ_ONLY_REASON`, which says why and how to change the value; rclpy's own
    refusal ("Trying to set a read-only parameter: k.") says neither. Both entry points
    are covered: ``set_parameters_atomically`` (the parameter services, ``ros2 param
    set``) and ``set_parameters`` (in-process). Other parameters are rclpy's business."""

    def _config_refusal(self, parameter_list: list) -> Any:
        """The refusal of the first configuration parameter in ``parameter_list``, or None."""
        from rcl_interfaces.msg import SetParametersResult

        keys = _schema_keys()
        for param in parameter_list:
            if param.name in keys and self.has_parameter(param.name):
                return SetParametersResult(successful=False,
                                           reason=READ_ONLY_REASON.format(key=param.name))
        return None

    def set_parameters_atomically(self, parameter_list: list) -> Any:
        refusal = self._config_refusal(parameter_list)
        return super().set_parameters_atomically(parameter_list) if refusal is None \
            else refusal

    def set_parameters(self, parameter_list: list) -> list:
        results = []
        for param in parameter_list:  # one by one, as rclpy sets them
            refusal = self._config_refusal([param])
            results.append(super().set_parameters([param])[0] if refusal is None
                           else refusal)
        return results


def _schema_keys() -> set[str]:
    """Every parameter name of the configuration schema."""
    from .. import config as config_mod
    return set(config_mod.default().to_flat())


def params_file_error(path: str | Path) -> str | None:
    """What is wrong with a parameter file that cannot be read as YAML (one line naming the
    file), or None. rcl's own message names neither the line's problem nor cleanly the file
    (``Couldn't parse params file: '--params-file x'. Error: Error parsing a event ...``).
    The file is read as the configuration reads it (:func:`..config.read_config_text`,
    :func:`..config.read_yaml`: a key given twice is refused too, which rcl would take
    silently, the last value winning)."""
    from ..config import read_config_text, read_yaml

    try:
        read_yaml(read_config_text(Path(path)), str(path))
    except ConfigError as err:
        return str(err)
    return None


def params_files(ros_args: list[str]) -> list[str]:
    """The files given with ``--params-file`` among ROS arguments."""
    return [ros_args[i + 1] for i, arg in enumerate(ros_args[:-1]) if arg == "--params-file"]


def given_with_p(ros_args: list[str]) -> dict[str, str]:
    """The ``-p NAME:=VALUE`` (``--param``) among ROS arguments: {NAME: VALUE text}, the
    last one of a name winning as in rcl. The one reading of ``-p`` (bringup's sim time and
    configuration, where a parameter came from, empty lists)."""
    out: dict[str, str] = {}
    for i, arg in enumerate(ros_args[:-1]):
        if arg in ("-p", "--param") and ":=" in ros_args[i + 1]:
            key, value = ros_args[i + 1].split(":=", 1)
            out[key.strip()] = value
    return out


def node_namespace(ros_args: list[str]) -> str:
    """The namespace ``-r __ns:=/robot1`` (``--remap``) among ROS arguments gives the nodes,
    '' for none; the last one wins, as in rcl."""
    out = ""
    for i, arg in enumerate(ros_args[:-1]):
        if arg in ("-r", "--remap") and ros_args[i + 1].startswith("__ns:="):
            out = ros_args[i + 1].split(":=", 1)[1].strip().strip("/")
    return out


def started_configuration(params_file: str | Path, ros_args: list[str],
                          nodes: tuple[str, ...] | list[str] = ()) -> config_mod.Config:
    """The configuration nodes started with ``--params-file params_file`` and ``ros_args``
    read: the file, then the further ``--params-file`` files among ``ros_args`` and their
    ``-p`` values (YAML, as rcl reads them) on top, in that order, validated as a node
    validates it, and the backbone's setup as the embedding node checks it at start
    (``setup_problems``: an ESANet without its checkpoint). With ``nodes`` (names, placed in
    the namespace of ``ros_args``), each node's own view of the files is checked, as rcl
    gives it /** and its own entries (another node's entry in a shared file is not
    refused), and the first node's configuration is returned. Bringup checks it before
    starting any node, so a bad value is one error naming where it was given, not one per
    node (or one node's death after the others have started)."""
    from .. import config as config_mod
    from ..core.backbone.backbone import setup_problems

    given = {key: config_mod.read_yaml(text, f"-p {key}:={text}")
             for key, text in given_with_p(ros_args).items()}  # -p: every node's
    views = [config_mod.node_name(node_namespace(ros_args), n) for n in nodes] or [None]
    first = None
    for view in views:
        overrides: dict[str, Any] = {}
        for path in params_files(ros_args):
            overrides.update((k, v) for k, v in _file_parameters(path, view).items()
                             if not isinstance(v, dict))
        overrides.update(given)
        overrides = {k: v for k, v in overrides.items() if not config_mod.ros_builtin(k)}
        named = f" (node {view})" if view else ""
        try:
            cfg = config_mod.load(params_file, overrides, node=view)
        except ConfigError as err:
            key = str(err).removeprefix("override ").split("=", 1)[0].split(":", 1)[0]
            raise ConfigError(f"{err}{named}{parameter_origin(key + ':', ros_args)}"
                              ) from None
        problems = setup_problems(cfg.backbone) if config_mod.checks_backbone(view) else []
        if problems:
            raise ConfigError(f"backbone: {problems[0]}{named}")
        first = cfg if first is None else first
    return first


def _file_parameters(path: str, node: str | None = None) -> dict[str, Any]:
    """Every parameter a params file gives (``node``: gives that node), by dotted name,
    sections included (``mapper`` and ``mapper.lr``), with its value; {} for a file the
    configuration cannot read (that is reported on its own, :func:`params_file_error`)."""
    from ..config import parameters_from_yaml, read_config_text

    try:
        nested = parameters_from_yaml(read_config_text(Path(path)), path, node)
    except ConfigError:
        return {}
    out: dict[str, Any] = {}
    stack = [("", nested)]
    while stack:
        prefix, values = stack.pop()
        for key, value in values.items():
            out[f"{prefix}{key}"] = value
            if isinstance(value, dict):
                stack.append((f"{prefix}{key}.", value))
    return out


def parameter_origin(message: str, ros_args: list[str]) -> str:
    """Where the parameter a ConfigError ``message`` names (its text up to the first ':')
    was given: ``" (given with -p)"``, ``" (given in params file F)"`` or ``""``. rcl
    merges the files and overrides before the node sees a value, so without this a wrong
    value in a file of many parameters (``mapper: 3`` in place of a section) is named
    without the file it is in."""
    key = message.split(":", 1)[0].strip()
    if not key or " " in key:
        return ""
    if key in given_with_p(ros_args):
        return " (given with -p)"
    found = [path for path in params_files(ros_args) if key in _file_parameters(path)]
    return f" (given in params file {', '.join(found)})" if found else ""


def empty_lists(ros_args: list[str]) -> str:
    """The parameters the params files among ``ros_args`` give as ``[]``, as a hint: rclpy
    cannot type an empty list and refuses it in the node's constructor with a message
    naming no key ("Cannot declare a statically typed parameter with default value of
    type PARAMETER_NOT_SET"). ``""`` if there are none."""
    found = [f"{key} in {path}" for path in params_files(ros_args)
             for key, value in _file_parameters(path).items() if value == []]
    found += [f"{key} given with -p" for key, value in given_with_p(ros_args).items()
              if value.replace(" ", "") == "[]"]
    if not found:
        return ""
    return (f"{', '.join(sorted(found))}: ROS cannot type an empty list; leave the key out "
            "to keep its default")


def ros_args_error(err: Exception) -> str:
    """rcl's refusal of the ROS arguments on one line, without its source locations."""
    text = str(err)
    if type(err).__name__ == "UnknownROSArgsError":
        return f"unknown ROS arguments: {text}"
    text = re.sub(r",? at /\S+:\d+", "", text)
    for prefix in ("Failed to parse ROS arguments: ", "failed to initialize rcl: "):
        text = text.removeprefix(prefix)
    return " ".join(text.split())
