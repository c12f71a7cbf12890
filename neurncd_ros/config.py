"""The one configuration schema: every parameter of every node and of `neurncd`.

The schema is assembled from the parameter dataclasses the components declare
(``core.params.param``), one section each. ``config/neurncd.yaml`` holds the
values in ROS 2 parameter-file form::

    /**:
      ros__parameters:
        backbone:
          kind: default

so the same file is given to every node (``--ros-args --params-file``) and to
the offline tool (``neurncd run --config``). In ROS the nested keys become
dotted parameter names (``backbone.kind``).
"""

from __future__ import annotations

import dataclasses
import importlib
from pathlib import Path
from typing import Any

import yaml

from .core.params import ConfigError, ParamSpec, build, param, specs, to_dict


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


# Section name -> (module, class). Core sections are imported lazily so this
# module stays cheap to import.
SECTIONS: dict[str, tuple[str, str]] = {
    "topics": ("neurncd_ros.core.topics", "Topics"),
    "sync": ("neurncd_ros.core.data.bag", "SyncConfig"),
    "convert": ("neurncd_ros.core.data.formats", "FolderConfig"),
    "synth": ("neurncd_ros.synth.generator", "SynthConfig"),
    "backbone": ("neurncd_ros.core.backbone.backbone", "BackboneConfig"),
    "mapper": ("neurncd_ros.core.field.mapper", "MapperConfig"),
    "segmentation": ("neurncd_ros.core.discovery.geoseg", "GeoSegConfig"),
    "modulation": ("neurncd_ros.core.discovery.modulation", "ModulationConfig"),
    "mcl": ("neurncd_ros.core.discovery.mcl", "MCLConfig"),
    "discovery": ("neurncd_ros.core.discovery.labeller", "DiscoveryConfig"),
    "embedding_node": ("neurncd_ros.core.engine.embedding", "EmbeddingNodeConfig"),
    "mapper_node": ("neurncd_ros.core.engine.mapping", "MapperNodeConfig"),
    "discovery_node": ("neurncd_ros.core.engine.discovery", "DiscoveryNodeConfig"),
    "replay": (__name__, "ReplayConfig"),
    "run": ("neurncd_ros.core.engine.offline", "RunConfig"),
}

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "config" / "neurncd.yaml"


def section_class(name: str) -> type:
    mod, cls = SECTIONS[name]
    return getattr(importlib.import_module(mod), cls)


def schema() -> dict[str, list[ParamSpec]]:
    """Every parameter, by section, in declaration order."""
    return {name: specs(section_class(name)) for name in SECTIONS}


@dataclasses.dataclass(frozen=True)
class Config:
    """A validated configuration: one attribute per section."""

    sections: dict[str, Any]

    def __getattr__(self, name: str) -> Any:
        try:
            return self.__dict__["sections"][name]
        except KeyError:
            raise AttributeError(name) from None

    def to_nested(self) -> dict[str, dict[str, Any]]:
        return {name: to_dict(obj) for name, obj in self.sections.items()}

    def to_flat(self) -> dict[str, Any]:
        """Dotted ROS parameter names -> values."""
        return {f"{s}.{k}": v for s, d in self.to_nested().items() for k, v in d.items()}


def from_nested(values: dict[str, Any] | None) -> Config:
    """Validate nested ``{section: {key: value}}``; unknown sections or keys fail by name."""
    values = values or {}
    if not isinstance(values, dict):
        raise ConfigError(f"parameters must be a mapping of sections, got "
                          f"{type(values).__name__}")
    for name, sec in values.items():
        if name not in SECTIONS:
            raise ConfigError(f"{name}: unknown section; known: " + ", ".join(SECTIONS))
        if not isinstance(sec, dict):
            raise ConfigError(f"{name}: section must be a mapping of parameters, got "
                              f"{sec!r}")
    return Config({name: build(section_class(name), values.get(name), prefix=f"{name}.")
                   for name in SECTIONS})


def from_flat(values: dict[str, Any]) -> Config:
    """Validate dotted names (``section.key``), as ROS parameters arrive."""
    nested: dict[str, dict[str, Any]] = {}
    for key, value in values.items():
        if "." not in key:
            raise ConfigError(f"{key}: unknown parameter; parameters are named "
                              "<section>.<name>, sections: " + ", ".join(SECTIONS))
        sec, name = key.split(".", 1)
        nested.setdefault(sec, {})[name] = value
    return from_nested(nested)


def parameters_from_yaml(text: str, source: str = "<yaml>") -> dict[str, Any]:
    """The ``ros__parameters`` mapping of a ROS 2 parameter file (``/**`` or any node)."""
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise ConfigError(f"{source}: not valid YAML: {err}") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{source}: expected a mapping with '/**: ros__parameters:'")
    merged: dict[str, Any] = {}
    for node_name, body in doc.items():
        if not isinstance(body, dict) or set(body) != {"ros__parameters"}:
            raise ConfigError(f"{source}: entry {node_name!r} must hold exactly "
                              "'ros__parameters:' (ROS 2 parameter-file form)")
        params = body["ros__parameters"] or {}
        if not isinstance(params, dict):
            raise ConfigError(f"{source}: {node_name}.ros__parameters must be a mapping")
        for sec, vals in params.items():
            if isinstance(vals, dict) and isinstance(merged.get(sec), dict):
                merged[sec] = {**merged[sec], **vals}
            else:
                merged[sec] = vals
    return merged


def load(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> Config:
    """Read and validate a parameter file (default: the shipped config/neurncd.yaml).

    ``overrides`` are dotted names applied on top (as from the command line).
    """
    path = Path(path) if path else DEFAULT_CONFIG
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    nested = parameters_from_yaml(path.read_text(), str(path))
    for key, value in (overrides or {}).items():
        if "." not in key:
            raise ConfigError(f"{key}: override must be <section>.<name>")
        sec, name = key.split(".", 1)
        if sec in nested and not isinstance(nested[sec], dict):
            raise ConfigError(f"{sec}: section must be a mapping")
        nested.setdefault(sec, {})[name] = value
    try:
        return from_nested(nested)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None


def default() -> Config:
    """All defaults, without reading any file."""
    return from_nested({})


def to_yaml(cfg: Config, with_docs: bool = True) -> str:
    """The configuration as a ROS 2 parameter file, each value with its doc."""
    lines = ["/**:", "  ros__parameters:"]
    sch = schema()
    for sec, values in cfg.to_nested().items():
        cls = section_class(sec)
        doc = (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""
        if with_docs and doc:
            lines.append(f"    # {doc}")
        lines.append(f"    {sec}:")
        for spec in sch[sec]:
            if with_docs:
                lines.append(f"      # {spec.doc} ({spec.allowed()})")
            dumped = yaml.safe_dump({spec.name: values[spec.name]}, default_flow_style=True,
                                    width=10_000).strip()
            # ROS cannot type an empty list from a parameter file ("not set"), so an
            # empty default is written commented out: absent means the default.
            empty = isinstance(values[spec.name], list) and not values[spec.name]
            lines.append(f"      {'# ' if empty else ''}{dumped[1:-1]}")
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
