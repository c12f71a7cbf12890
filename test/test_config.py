"""The one configuration schema: shipped YAML round trip, errors by name, README table."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from neurncd_ros import config
from neurncd_ros.core.params import ConfigError

REPO = Path(__file__).resolve().parents[1]
SHIPPED = REPO / "config" / "neurncd.yaml"


def test_every_parameter_is_documented_and_typed():
    sch = config.schema()
    assert set(sch) == set(config.SECTIONS)
    names = set()
    for sec, specs in sch.items():
        assert specs, f"section {sec} declares no parameters"
        for s in specs:
            assert s.doc and len(s.doc) > 8, f"{sec}.{s.name} has no real doc"
            assert s.type in (bool, int, float, str, list), f"{sec}.{s.name}: {s.type}"
            # The default itself must pass validation.
            config.from_flat({f"{sec}.{s.name}": s.default})
            names.add(f"{sec}.{s.name}")
    assert len(names) > 60


def test_shipped_yaml_is_ros_parameter_file_and_round_trips():
    doc = yaml.safe_load(SHIPPED.read_text())
    assert list(doc) == ["/**"] and list(doc["/**"]) == ["ros__parameters"]
    cfg = config.load(SHIPPED)
    assert cfg.to_nested() == config.default().to_nested()
    again = config.parameters_from_yaml(config.to_yaml(cfg))
    assert config.from_nested(again).to_nested() == cfg.to_nested()
    # Every parameter of the schema is written (and documented) in the shipped file.
    text = SHIPPED.read_text()
    for key in cfg.to_flat():
        sec, name = key.split(".", 1)
        assert re.search(rf"^\s+(# )?{re.escape(name)}:", text, re.M), key


def test_shipped_yaml_is_generated_from_schema():
    assert SHIPPED.read_text() == config.to_yaml(config.default()), \
        "regenerate with: neurncd params > config/neurncd.yaml"


@pytest.mark.parametrize("values, match", [
    ({"mapper": {"no_such_key": 1}}, r"mapper\.no_such_key: unknown parameter; known: "),
    ({"nosection": {}}, r"nosection: unknown section; known: topics"),
    ({"mapper": {"backend": "gpu"}}, r"mapper\.backend: 'gpu' is not allowed; allowed: one of "
                                     r"'fast', 'reference'"),
    ({"mapper_node": {"max_in_flight": 0}},
     r"mapper_node\.max_in_flight: 0 is out of range; allowed: int in \[1, 100\]"),
    ({"mapper_node": {"max_in_flight": "5"}},
     r"mapper_node\.max_in_flight: '5' has type str; allowed: int"),
    ({"mapper_node": {"max_in_flight": 2.5}},
     r"mapper_node\.max_in_flight: 2\.5 has type float"),
    ({"replay": {"loop": 1}}, r"replay\.loop: 1 has type int; allowed: bool"),
    ({"replay": {"rate": float("nan")}}, r"replay\.rate: nan is not finite"),
    ({"mapper": 3}, r"mapper: section must be a mapping"),
])
def test_bad_values_name_key_and_allowed(values, match):
    with pytest.raises(ConfigError, match=match):
        config.from_nested(values)


def test_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        config.load(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("mapper:\n  backend: fast\n")
    with pytest.raises(ConfigError, match="ros__parameters"):
        config.load(bad)
    bad.write_text("/**:\n  ros__parameters:\n    mapper_node: {max_in_flight: -3}\n")
    with pytest.raises(ConfigError, match=rf"{re.escape(str(bad))}: mapper_node\.max_in_flight"):
        config.load(bad)
    bad.write_text("/**: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        config.load(bad)


def test_overrides_and_flat_names():
    cfg = config.load(SHIPPED, {"mapper.backend": "reference", "mapper_node.max_in_flight": 3})
    assert cfg.mapper.backend == "reference" and cfg.mapper_node.max_in_flight == 3
    flat = cfg.to_flat()
    assert flat["mapper.backend"] == "reference"
    assert config.from_flat(flat).to_nested() == cfg.to_nested()
    with pytest.raises(ConfigError, match="<section>.<name>"):
        config.from_flat({"backend": "fast"})
    # Ints are accepted where floats are declared (YAML writes 1 for 1.0).
    assert config.from_flat({"replay.rate": 2}).replay.rate == 2.0


def test_readme_parameter_table_matches_schema():
    readme = (REPO / "README.md").read_text()
    start = readme.index("<!-- params:start -->") + len("<!-- params:start -->\n")
    end = readme.index("<!-- params:end -->")
    assert readme[start:end] == config.markdown_table(), \
        "regenerate with: neurncd params --format markdown"
