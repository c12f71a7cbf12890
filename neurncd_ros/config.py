"""The one configuration schema: every parameter of every node and of `neurncd`.

The schema is assembled from the parameter dataclasses the components declare
(``core.params.param``), one section each. A section class may declare
subsections (``subsections()``: name -> class), e.g. one per registered field
backend under ``mapper``. ``config/neurncd.yaml`` holds the values in ROS 2
parameter-file form::

    /**:
      ros__parameters:
        backbone:
          kind: default
        mapper:
          backend: fast
          fast:
            hidden: 32

so the same file is given to every node (``--ros-args --params-file``) and to
the offline tool (``neurncd run --config``). In ROS the nested keys become
dotted parameter names (``backbone.kind``, ``mapper.fast.hidden``); a
section's dotted name (``mapper.fast``) is what :meth:`Config.section` takes.

It stays one module (over 500 lines): reading a parameter file in the ROS form, its
dotted keys, the sections' validation, overrides and the report of every error
(:func:`problems`) share one parse of the file, and the schema is meant to be in one
place.
"""

from __future__ import annotations

import dataclasses
import importlib
import re
from pathlib import Path
from typing import Any

import yaml

from .core.params import ConfigError, ParamSpec, build, param, specs, to_dict
from .share import share_file


# ------------------------------------------------------- node / tool sections

@dataclasses.dataclass(frozen=True)
class ReplayConfig:
    """The replay node: plays a bag's messages on their topics at their recorded pace, as
    `ros2 bag play` does (no rosbag2 wheels exist)."""

    bag: str = param("", "bag to replay (mcap or sqlite3 folder/file)")
    rate: float = param(1.0, "playback speed relative to the recorded stamps", lo=0.01,
                        hi=100.0)
    loop: bool = param(False, "start again at the end of the bag (the node then runs until "
                       "stopped); otherwise it exits 0 at the end")
    start_offset_s: float = param(0.0, "skip this much of the bag's beginning", lo=0.0,
                                  hi=1e6, unit="s")
    delay_s: float = param(0.0, "extra wait before the first message", lo=0.0, hi=3600.0,
                           unit="s")
    wait_for_subscribers_s: float = param(30.0, "before playing, wait at most this long until "
                                          "every input topic of the contract that the bag "
                                          "holds (colour, depth, camera info, pose) has a "
                                          "subscriber; then play anyway, with a warning (0 = "
                                          "do not wait)", lo=0.0, hi=3600.0, unit="s")
    wait_for_graph: bool = param(False, "also wait (within wait_for_subscribers_s) until the "
                                 "embedding, mapper and discovery nodes report on "
                                 "topics.diagnostics that they are up and see their upstream "
                                 "node (and, with clock, until /clock has a subscriber), so "
                                 "that a replay started with the nodes (the launch file sets "
                                 "it) does not play the first frames before the mapper "
                                 "listens; bringup waits for them itself")
    clock: bool = param(False, "publish rosgraph_msgs/Clock on /clock at the bag's time as it "
                        "plays (ros2 bag play --clock), for nodes run with use_sim_time "
                        "(bringup sets it when given -p use_sim_time:=true)")
    settle_s: float = param(1.0, "then wait until the number of subscribers on those topics "
                            "has not changed for this long (within wait_for_subscribers_s): "
                            "a second node still matching, or one whose side of the match "
                            "is not complete yet, would miss the first frames", lo=0.0,
                            hi=60.0, unit="s")


# Top-level section name -> (module, class). Core sections are imported lazily so
# this module stays cheap to import.
SECTIONS: dict[str, tuple[str, str]] = {
    "topics": ("neurncd_ros.core.topics", "Topics"),
    "sync": ("neurncd_ros.core.data.bag", "SyncConfig"),
    "convert": ("neurncd_ros.core.data.formats", "FolderConfig"),
    "odometry": ("neurncd_ros.core.odometry", "OdometryConfig"),
    "synth": ("neurncd_ros.synth.generator", "SynthConfig"),
    "backbone": ("neurncd_ros.core.backbone.backbone", "BackboneConfig"),
    "mapper": ("neurncd_ros.core.field.mapper", "MapperConfig"),
    "keyframes": ("neurncd_ros.core.field.keyframes", "KeyframeConfig"),
    "segmentation": ("neurncd_ros.core.discovery.geoseg", "GeoSegConfig"),
    "modulation": ("neurncd_ros.core.discovery.modulation", "ModulationConfig"),
    "mcl": ("neurncd_ros.core.discovery.mcl", "MCLConfig"),
    "discovery": ("neurncd_ros.core.discovery.labeller", "DiscoveryConfig"),
    "label_fusion": ("neurncd_ros.core.discovery.fusion", "LabelFusionConfig"),
    "embedding_node": ("neurncd_ros.core.engine.embedding", "EmbeddingNodeConfig"),
    "mapper_node": ("neurncd_ros.core.engine.mapping", "MapperNodeConfig"),
    "discovery_node": ("neurncd_ros.core.engine.discovery", "DiscoveryNodeConfig"),
    "replay": (__name__, "ReplayConfig"),
    "run": ("neurncd_ros.core.engine.offline", "RunConfig"),
    "semnerf": ("neurncd_ros.core.eval.semnerf", "SemanticNerfConfig"),
}


def default_config() -> Path:
    """The shipped parameter file: share/neurncd_ros/config/neurncd.yaml of a colcon
    install, else the source tree's config/neurncd.yaml (the nodes' default too)."""
    return share_file("config", "neurncd.yaml")


def _top_class(name: str) -> type:
    mod, cls = SECTIONS[name]
    return getattr(importlib.import_module(mod), cls)


def section_classes() -> dict[str, type]:
    """Every section by dotted name (``mapper``, ``mapper.fast``, ...), each followed by
    its subsections, in file order."""
    out: dict[str, type] = {}

    def add(name: str, cls: type) -> None:
        out[name] = cls
        sub = getattr(cls, "subsections", None)
        for child, child_cls in (sub() if callable(sub) else {}).items():
            add(f"{name}.{child}", child_cls)

    for name in SECTIONS:
        add(name, _top_class(name))
    return out


def section_class(name: str) -> type:
    """The config class of section ``name``; a ConfigError naming it if there is none."""
    try:
        return section_classes()[name]
    except KeyError:
        raise ConfigError(f"{name}: unknown section") from None


def schema() -> dict[str, list[ParamSpec]]:
    """Every parameter, by dotted section name, in declaration order."""
    return {name: specs(cls) for name, cls in section_classes().items()}


@dataclasses.dataclass(frozen=True)
class Config:
    """A validated configuration: one attribute per top-level section, :meth:`section` for
    any section by dotted name."""

    sections: dict[str, Any]

    def __getattr__(self, name: str) -> Any:
        try:
            return self.__dict__["sections"][name]
        except KeyError:
            raise AttributeError(name) from None

    def section(self, name: str) -> Any:
        """The section object of a dotted name, e.g. ``cfg.section("mapper.fast")``."""
        try:
            return self.sections[name]
        except KeyError:
            raise KeyError(f"{name}: unknown section; known: "
                           + ", ".join(self.sections)) from None

    def to_nested(self) -> dict[str, dict[str, Any]]:
        """``{section: {key: value, subsection: {...}}}``, as in the parameter file."""
        out: dict[str, Any] = {}
        for name, obj in self.sections.items():
            *parents, last = name.split(".")
            node = out
            for p in parents:
                node = node[p]
            node[last] = to_dict(obj)
        return out

    def to_flat(self) -> dict[str, Any]:
        """Dotted ROS parameter names -> values."""
        return {f"{s}.{k}": v for s, obj in self.sections.items()
                for k, v in to_dict(obj).items()}


def _by_section(values: Any) -> dict[str, dict[str, Any]]:
    """Nested ``{section: {key: value, subsection: {...}}}`` -> values per dotted section."""
    if not isinstance(values, dict):
        raise ConfigError(f"parameters must be a mapping of sections, got "
                          f"{type(values).__name__}")
    known = section_classes()
    out: dict[str, dict[str, Any]] = {}

    def walk(name: str, mapping: Any) -> None:
        if not isinstance(mapping, dict):
            raise ConfigError(f"{name}: section must be a mapping of parameters, got "
                              f"{mapping!r}")
        children = [n.rpartition(".")[2] for n in known if n.rpartition(".")[0] == name]
        own = {}
        for key, value in mapping.items():
            if key in children:
                walk(f"{name}.{key}", value)
            elif isinstance(value, dict):
                raise ConfigError(f"{name}.{key}: unknown section; known: "
                                  + (", ".join(children) or "none"))
            else:
                own[key] = value
        out[name] = own

    for name, sec in values.items():
        if name not in SECTIONS:
            raise ConfigError(f"{name}: unknown section; known: " + ", ".join(SECTIONS))
        walk(name, sec)
    return out


def _set_dotted(by_section: dict[str, dict[str, Any]], key: str, value: Any) -> None:
    """Put a dotted parameter (``mapper.fast.hidden``) into its section's values."""
    if "." not in key:
        raise ConfigError(f"{key}: unknown parameter; parameters are named "
                          "<section>.<name>, sections: " + ", ".join(SECTIONS))
    known = section_classes()
    sec = max((n for n in known if key.startswith(n + ".")), key=len, default=None)
    if sec is None:
        top = key.split(".", 1)[0]
        raise ConfigError(f"{top}: unknown section; known: " + ", ".join(SECTIONS))
    by_section.setdefault(sec, {})[key[len(sec) + 1:]] = value


def _build(by_section: dict[str, dict[str, Any]]) -> Config:
    return Config({name: build(cls, by_section.get(name), prefix=f"{name}.")
                   for name, cls in section_classes().items()})


def from_nested(values: dict[str, Any] | None) -> Config:
    """Validate nested ``{section: {key: value}}``; unknown sections or keys fail by name."""
    return _build(_by_section(values or {}))


def from_flat(values: dict[str, Any]) -> Config:
    """Validate dotted names (``section.key``, ``section.sub.key``), as ROS parameters
    arrive."""
    by_section: dict[str, dict[str, Any]] = {}
    for key, value in values.items():
        _set_dotted(by_section, key, value)
    return _build(by_section)


def _merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """``extra`` over ``base``, mappings merged key by key at every depth."""
    out = dict(base)
    for k, v in extra.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) \
            else v
    return out


class DuplicateKeyError(yaml.YAMLError):
    """A YAML mapping names the same key twice (the key path and both lines)."""


class _StrictLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that rejects a key given twice in one mapping.

    PyYAML keeps the last value silently, so a parameter set twice in a file (an edit
    that added a line instead of changing one) would take effect without a word. The
    error names the key (as a dotted parameter name inside ``ros__parameters``) and the
    lines of both values. Keys brought in by a ``<<`` merge may be overridden, as YAML
    intends."""

    _root = None

    def construct_document(self, node):
        self._root = node
        return super().construct_document(node)

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, int] = {}
            for key_node, value_node in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.setdefault(key, key_node.start_mark.line)
                except TypeError:  # an unhashable key: the base class reports it
                    continue
                if first != key_node.start_mark.line:
                    what = self._describe(node, key, value_node)
                    raise DuplicateKeyError(f"{what} is given twice (lines {first + 1} and "
                                            f"{key_node.start_mark.line + 1}); give it once")
        return super().construct_mapping(node, deep)

    def _describe(self, mapping, key, value) -> str:
        """'parameter mapper.backend' (or 'section mapper') for a key under
        ros__parameters, else 'key a.b'."""
        def walk(node, path):
            if node is mapping:
                return path
            if isinstance(node, yaml.MappingNode):
                for k, v in node.value:
                    found = walk(v, path + [str(getattr(k, "value", k))])
                    if found is not None:
                        return found
            return None

        path = (walk(self._root, []) or []) + [str(key)]
        if len(path) > 2 and path[1] == "ros__parameters":
            what = "section" if isinstance(value, yaml.MappingNode) else "parameter"
            return f"{what} {'.'.join(path[2:])!r} (node {path[0]!r})"
        return f"key {'.'.join(path)!r}"


def yaml_problem(err: Exception) -> str:
    """A PyYAML error on one line: where, then what (its own text spans several lines, with
    a caret under the offending character, which a log line or an error line cannot hold)."""
    mark = getattr(err, "problem_mark", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    what = getattr(err, "problem", None) or str(err)
    return where + " ".join(str(what).split())


def strict_yaml_load(text: str) -> Any:
    """``yaml.safe_load`` that raises :class:`DuplicateKeyError` for a key given twice in
    one mapping instead of keeping the last value."""
    return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - a SafeLoader subclass


def read_yaml(text: str, source: str = "<yaml>") -> Any:
    """A YAML document read as every configuration file is (:func:`strict_yaml_load`); a
    ConfigError naming ``source`` on one line if it is not valid YAML or gives a key twice."""
    try:
        return strict_yaml_load(text)
    except DuplicateKeyError as err:
        raise ConfigError(f"{source}: {err}") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{source}: not valid YAML: {yaml_problem(err)}") from None


ROS_BUILTIN_PARAMETERS = ("use_sim_time", "start_type_description_service")


def ros_builtin(name: str) -> bool:
    """A parameter rclpy itself declares or reads (dotted name), not part of the schema."""
    return name in ROS_BUILTIN_PARAMETERS or name.split(".")[0] == "qos_overrides"


def node_entry_applies(entry: str, node: str) -> bool:
    """Whether a parameter file's node entry (``/**``, ``mapper``, ``/robot1/*``, ...)
    gives its parameters to the node of fully qualified name ``node``, as rclpy matches
    them: a leading ``/`` added, each ``/*`` one name token, ``/**`` any number of them."""
    name = entry if entry.startswith("/") else "/" + entry
    return re.fullmatch(name.replace("/*", r"(/\w+)"), node) is not None


def node_name(namespace: str, name: str) -> str:
    """The fully qualified name of node ``name`` in ``namespace`` (``robot1``, ``/robot1``,
    ``''`` for the root): ``/robot1/mapper``."""
    namespace = namespace.strip("/")
    return f"/{namespace}/{name}" if namespace else f"/{name}"


def checks_backbone(node: str | None) -> bool:
    """Whether the view of ``node`` (a fully qualified name; None: every entry, the offline
    tool's) is checked for the backbone's setup: the embedding node's refusal at start."""
    return node is None or node.rsplit("/", 1)[-1] == "embedding"


def parameters_from_yaml(text: str, source: str = "<yaml>", node: str | None = None
                         ) -> dict[str, Any]:
    """The ``ros__parameters`` mapping of a ROS 2 parameter file: every node entry's
    (``/**`` and any node's) merged in file order, the offline tool's view; with ``node``
    (a fully qualified name, ``/mapper``) only the entries rclpy gives that node
    (:func:`node_entry_applies`), the view the node itself starts with.

    A key given twice in one mapping is a ConfigError naming it (YAML would keep the
    last value silently). rclpy's own parameters (:func:`ros_builtin`: ``use_sim_time``
    for a bag replayed with /clock, ``qos_overrides``) are left to ROS: the same file
    serves the nodes, bringup and ``neurncd``."""
    doc = read_yaml(text, source)
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{source}: expected a mapping with '/**: ros__parameters:'")
    merged: dict[str, Any] = {}
    for node_name, body in doc.items():
        if not isinstance(body, dict) or set(body) != {"ros__parameters"}:
            # A plain YAML of sections (discovery: {entropy_threshold: 0.5}) reads as a
            # node named after the section: say where the sections go instead.
            section = str(node_name) in {name.split(".")[0] for name in section_classes()}
            raise ConfigError(f"{source}: entry {node_name!r} must hold exactly "
                              "'ros__parameters:' (ROS 2 parameter-file form)"
                              + (f"; {node_name!r} is a section of parameters: put the "
                                 "sections under '/**:' then 'ros__parameters:', as "
                                 "`neurncd params` prints them" if section else ""))
        params = body["ros__parameters"] or {}
        if not isinstance(params, dict):
            raise ConfigError(f"{source}: {node_name}.ros__parameters must be a mapping")
        if node is not None and not node_entry_applies(str(node_name), node):
            continue  # another node's: rcl gives it to that node only
        own = {k: v for k, v in params.items() if not ros_builtin(str(k))}
        merged = _merge(merged, _undotted(own, f"{source}: {node_name}.ros__parameters"))
    return merged


def _undotted(mapping: dict[str, Any], where: str, prefix: str = "") -> dict[str, Any]:
    """A ``ros__parameters`` mapping with dotted keys (``discovery.entropy_threshold: 0.5``,
    which ROS 2 accepts beside the nested form) nested as the schema reads them; a
    parameter given both ways (or twice by dots) is a ConfigError naming it."""
    out: dict[str, Any] = {}
    for key, value in mapping.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            value = _undotted(value, where, name + ".")
        *path, last = str(key).split(".")
        node, done = out, prefix
        for part in path:
            done += part
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{where}: {done} is given twice (as a value and as a "
                                  "section)")
            done += "."
        if last in node:
            if not (isinstance(node[last], dict) and isinstance(value, dict)):
                raise ConfigError(f"{where}: {name} is given twice (nested and dotted)")
            both = set(_leaves(node[last])) & set(_leaves(value))
            if both:
                raise ConfigError(f"{where}: {name}.{sorted(both)[0]} is given twice "
                                  "(nested and dotted)")
            value = _merge(node[last], value)
        node[last] = value
    return out


def _leaves(mapping: dict[str, Any], prefix: str = "") -> list[str]:
    """The dotted names of a nested mapping's non-mapping values."""
    out = []
    for k, v in mapping.items():
        out += _leaves(v, f"{prefix}{k}.") if isinstance(v, dict) else [f"{prefix}{k}"]
    return out


def parse_overrides(pairs: list[str] | None, option: str = "--set") -> dict[str, Any]:
    """``section.key=value`` strings (as from ``--set``) -> {dotted key: value}, each value
    parsed as YAML (a scalar or a list); a pair without "=" is a ConfigError naming it."""
    out = {}
    for pair in pairs or []:
        if "=" not in pair:
            form = "section.key=value" if option == "--set" else "key=value"
            raise ConfigError(f"{option} {pair!r}: expected {form}")
        key, raw = pair.split("=", 1)
        out[key.strip()] = yaml.safe_load(raw)
    return out


def read_config_text(path: Path) -> str:
    """A configuration file's text; a ConfigError naming the file if it is missing,
    unreadable or not UTF-8 (the encoding YAML and ROS 2 parameter files use)."""
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    try:
        data = path.read_bytes()
    except OSError as err:
        raise ConfigError(f"{path}: cannot read: {err.strerror or err}") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as err:
        line = data[:err.start].count(b"\n") + 1
        raise ConfigError(f"{path}: not UTF-8 text (byte 0x{data[err.start]:02x} at line "
                          f"{line}, byte offset {err.start}); save the file as UTF-8"
                          ) from None


def problems(path: str | Path, node: str | None = None) -> list[str]:
    """Every error of a parameter file, not only the first that :func:`load` stops at
    (``neurncd check-config``; ``node``: the view of that node, as in
    :func:`parameters_from_yaml`): each top-level section, then each parameter, checked on
    its own against the defaults; a value refused alone but not beside the rest of its
    section in the file (a check tying two parameters, both given) is no error. A file
    YAML or the ROS form refuses is its one error. Checks across sections are
    :func:`load`'s (run it as well)."""
    path = Path(path)
    try:
        nested = parameters_from_yaml(read_config_text(path), str(path), node)
    except ConfigError as err:
        return [str(err)]
    if not isinstance(nested, dict):
        return [f"{path}: parameters must be a mapping of sections"]
    out = []
    for name, section in nested.items():
        try:
            by_section = _by_section({name: section})
        except ConfigError as err:
            out.append(f"{path}: {err}")
            continue
        for sec, values in by_section.items():
            refused = {}
            for key, value in values.items():
                try:
                    _build({sec: {key: value}})
                except ConfigError as err:
                    refused[key] = err
            for key, err in refused.items():
                beside = {k: v for k, v in values.items() if k not in refused or k == key}
                try:
                    _build({sec: beside})
                except ConfigError:
                    out.append(f"{path}: {err}")
    return out


def load(path: str | Path | None = None, overrides: dict[str, Any] | None = None,
         node: str | None = None) -> Config:
    """Read and validate a parameter file (default: the shipped config/neurncd.yaml), in
    ROS 2 form: the sections under ``/**:`` then ``ros__parameters:`` (module doc); every
    node entry merged, or with ``node`` that node's view (:func:`parameters_from_yaml`).

    ``overrides`` are dotted names applied on top (as from the command line). An error
    names its source: the file when the file alone is invalid, else the first override
    that makes it so (a bad ``--set`` value is not blamed on the file).
    """
    path = Path(path) if path else default_config()
    nested = parameters_from_yaml(read_config_text(path), str(path), node)
    for key in overrides or {}:
        if "." not in key:
            raise ConfigError(f"{key}: override must be <section>.<name>")
    try:  # the file alone first, so an error names the file only when the file is wrong
        by_section = _by_section(nested)
        cfg = _build(by_section)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None
    if not overrides:
        return cfg
    try:  # then the overrides together (checks that tie two parameters see both)
        for key, value in overrides.items():
            _set_dotted(by_section, key, value)
        return _build(by_section)
    except ConfigError as err:
        named = [k for k in overrides if str(err).startswith(f"{k}:")]
        which = ", ".join(f"{k}={overrides[k]!r}" for k in (named or overrides))
        raise ConfigError(f"override {which} (on {path}): {err}") from None


def default() -> Config:
    """All defaults, without reading any file."""
    return from_nested({})


def to_yaml(cfg: Config, with_docs: bool = True) -> str:
    """The configuration as a ROS 2 parameter file, each value with its doc."""
    lines = ["/**:", "  ros__parameters:"]
    sch = schema()
    for sec, obj in cfg.sections.items():
        values, cls = to_dict(obj), type(obj)
        pad = "  " * (sec.count(".") + 2)
        doc = (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""
        if with_docs and doc:
            lines.append(f"{pad}# {doc}")
        lines.append(f"{pad}{sec.rsplit('.', 1)[-1]}:")
        for spec in sch[sec]:
            if with_docs:
                lines.append(f"{pad}  # {spec.doc} ({spec.allowed()})")
            dumped = yaml.safe_dump({spec.name: values[spec.name]}, default_flow_style=True,
                                    width=10_000).strip()
            # ROS cannot type an empty list from a parameter file ("not set"), so an
            # empty default is written commented out: absent means the default.
            empty = isinstance(values[spec.name], list) and not values[spec.name]
            lines.append(f"{pad}  {'# ' if empty else ''}{dumped[1:-1]}")
    return "\n".join(lines) + "\n"


def markdown_table() -> str:
    """The README's parameter table, generated from the schema."""
    rows = ["| parameter | type | default | allowed | description |",
            "|---|---|---|---|---|"]
    for sec, sp in schema().items():
        for s in sp:
            tname = s.type.__name__ if s.elem_type is None else f"list[{s.elem_type.__name__}]"
            default = repr(s.default) if isinstance(s.default, str) else str(s.default)
            unit = f" ({s.unit})" if s.unit else ""
            rows.append(f"| `{sec}.{s.name}` | {tname} | `{default}` | {s.allowed()} | "
                        f"{s.doc}{unit} |")
    return "\n".join(rows) + "\n"
