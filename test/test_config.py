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
    assert set(sch) == set(config.section_classes())
    assert {"mapper", "mapper.fast", "mapper.reference", "keyframes"} <= set(sch)
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
        sec, name = key.rsplit(".", 1)
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
    # A plain YAML of sections, as a user writes one first: where the sections go (the
    # message alone told them to put 'ros__parameters:' under 'discovery:').
    bad.write_text("discovery:\n  entropy_threshold: 0.5\n")
    with pytest.raises(ConfigError, match=r"'discovery' is a section of parameters: put the "
                                          r"sections under '/\*\*:' then 'ros__parameters:'"):
        config.load(bad)
    bad.write_text("bringup:\n  x: 1\n")  # not a section: the ROS form alone
    with pytest.raises(ConfigError, match=r"ROS 2 parameter-file form\)$"):
        config.load(bad)
    bad.write_text("/**:\n  ros__parameters:\n    mapper_node: {max_in_flight: -3}\n")
    with pytest.raises(ConfigError, match=rf"{re.escape(str(bad))}: mapper_node\.max_in_flight"):
        config.load(bad)
    # A bad override is named as such, not blamed on the (valid) file it is applied to.
    with pytest.raises(ConfigError, match=r"^override synth\.width=-5 \(on .*\): synth\.width: "
                                          r"-5 is out of range"):
        config.load(SHIPPED, {"synth.width": -5})
    with pytest.raises(ConfigError, match=r"^override mapper\.lr=1 .*mapper\.lr: unknown"):
        config.load(SHIPPED, {"mapper.lr": 1})
    # Overrides are applied together: a check tying two parameters sees both.
    both = config.load(SHIPPED, {"synth.room_size_min": 9.0, "synth.room_size_max": 10.0})
    assert (both.synth.room_size_min, both.synth.room_size_max) == (9.0, 10.0)
    with pytest.raises(ConfigError, match=r"^override synth\.room_size_min=9\.0 \(on "):
        config.load(SHIPPED, {"synth.room_size_min": 9.0})
    # The file's own error wins over the overrides' and names the file.
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(bad))}: mapper_node\.max_in_flight"):
        config.load(bad, {"synth.width": -5})
    bad.write_text("/**: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        config.load(bad)
    bad.write_text("x:\n  a: 1\n   b: [\n")  # PyYAML's own text spans lines, with a caret
    with pytest.raises(ConfigError) as err:
        config.load(bad)
    assert str(err.value) == (f"{bad}: not valid YAML: line 3, column 5: mapping values "
                              "are not allowed here")


def test_rclpys_own_parameters_in_a_shared_file_are_left_to_ros(tmp_path):
    """One parameter file serves the nodes, bringup and neurncd: use_sim_time (a bag
    replayed with /clock) and qos_overrides are rclpy's and pass through, while the
    schema's values in the same file apply and a typo is still an error."""
    path = tmp_path / "sim.yaml"
    path.write_text("/**:\n  ros__parameters:\n    use_sim_time: true\n    qos_overrides:\n"
                    "      /camera/depth/image_raw:\n        subscription:\n"
                    "          depth: 5\n    run:\n      overlays: 2\n")
    assert config.load(path).run.overlays == 2
    path.write_text("/**:\n  ros__parameters:\n    use_sim_tme: true\n")
    with pytest.raises(ConfigError, match="use_sim_tme: unknown section"):
        config.load(path)


def test_a_nodes_view_of_a_shared_file_is_what_rcl_gives_it(tmp_path):
    """A file shared with other nodes, or with entries per robot: each node is given /**
    and the entries that name it, in file order (rclpy's matching: '/*' one name token,
    '/**' any), so another node's keys are not this node's errors; the offline tool's
    view (no node) merges every entry."""
    path = tmp_path / "shared.yaml"
    path.write_text("/**:\n  ros__parameters:\n    mapper:\n      lambda_embedding: 0.5\n"
                    "camera_driver:\n  ros__parameters:\n    fps: 30\n"
                    "/robot1/*:\n  ros__parameters:\n    mapper:\n      lambda_embedding: 2.0\n"
                    "/robot2/mapper:\n  ros__parameters:\n    mapper:\n"
                    "      lambda_embedding: -1.0\n")
    with pytest.raises(ConfigError, match="fps: unknown section"):
        config.load(path)
    assert config.load(path, node="/mapper").mapper.lambda_embedding == 0.5
    assert config.load(path, node="/robot1/mapper").mapper.lambda_embedding == 2.0
    with pytest.raises(ConfigError, match="lambda_embedding: -1.0 is out of range"):
        config.load(path, node="/robot2/mapper")
    assert config.problems(path, node="/robot1/discovery") == []
    assert len(config.problems(path)) == 2  # fps and the -1.0
    for entry, node, applies in (("/**", "/a/b/mapper", True), ("mapper", "/mapper", True),
                                 ("mapper", "/robot1/mapper", False),
                                 ("/*", "/robot1/mapper", False),
                                 ("/**/mapper", "/mapper", True),
                                 ("/robot1/*", "/robot1/mapper", True)):
        assert config.node_entry_applies(entry, node) is applies, (entry, node)


def test_the_default_file_is_the_running_packages_own(tmp_path, monkeypatch):
    """Another install of the package on AMENT_PREFIX_PATH (a stale workspace) does not
    lend the running code its parameter file: the source tree's comes first here, and an
    installed package reads its own prefix's share/ (test_packaging)."""
    share = tmp_path / "prefix" / "share" / "neurncd_ros"
    (share / "config").mkdir(parents=True)
    (share / "config" / "neurncd.yaml").write_text(
        "/**:\n  ros__parameters:\n    mapper:\n      old_param_removed: 1\n")
    (tmp_path / "prefix" / "share" / "ament_index" / "resource_index" / "packages").mkdir(
        parents=True)
    (tmp_path / "prefix" / "share" / "ament_index" / "resource_index" / "packages" /
     "neurncd_ros").write_text("")
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path / "prefix"))
    assert config.default_config() == REPO / "config" / "neurncd.yaml"
    config.load()


def test_problems_are_not_values_the_rest_of_the_file_makes_consistent(tmp_path):
    """A check that ties two parameters (min below max) judged each value against the
    other's default: a file raising both was listed as two errors that load() accepts."""
    path = tmp_path / "room.yaml"
    path.write_text("/**:\n  ros__parameters:\n    synth:\n      room_height_min: 4.0\n"
                    "      room_height_max: 5.0\n      room_size_min: 10.0\n"
                    "      room_size_max: 15.0\n")
    assert config.load(path).synth.room_height_min == 4.0
    assert config.problems(path) == []
    path.write_text("/**:\n  ros__parameters:\n    synth:\n      room_height_min: 4.0\n"
                    "      room_height_max: 3.5\n      room_size_min: -1.0\n")
    found = config.problems(path)
    assert any("room_height_min" in f for f in found), found  # still refused, with -1.0
    assert any("room_size_min: -1.0" in f for f in found), found


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


def test_backend_and_keyframe_sections_nested_in_file_dotted_in_ros(tmp_path):
    from neurncd_ros.core.field.backends.fast import FastConfig
    from neurncd_ros.core.field.backends.reference import ReferenceConfig
    from neurncd_ros.core.field.keyframes import KeyframeConfig

    params = yaml.safe_load(SHIPPED.read_text())["/**"]["ros__parameters"]
    assert params["mapper"]["backend"] == "fast"
    assert set(params["mapper"]["fast"]) == {s.name for s in config.schema()["mapper.fast"]}
    assert "reference" in params["mapper"] and "max_keyframes" in params["keyframes"]
    cfg = config.default()
    assert cfg.section("mapper.fast") == FastConfig()
    assert cfg.section("mapper.reference") == ReferenceConfig()
    assert cfg.section("keyframes") == cfg.keyframes == KeyframeConfig()
    assert cfg.section("mapper") is cfg.mapper
    with pytest.raises(KeyError, match="mapper.gpu: unknown section"):
        cfg.section("mapper.gpu")
    flat = cfg.to_flat()
    assert flat["mapper.fast.hidden"] == 32 and flat["mapper.reference.lr"] == 5e-4
    assert flat["keyframes.max_keyframes"] == 64 and "mapper.max_keyframes" not in flat
    got = config.from_flat({"mapper.fast.hidden": 64, "mapper.reference.rays_per_iteration": 512,
                            "keyframes.max_keyframes": 8})
    assert got.section("mapper.fast").hidden == 64 and got.keyframes.max_keyframes == 8
    assert got.section("mapper.reference").rays_per_iteration == 512
    assert got.to_nested()["mapper"]["fast"]["hidden"] == 64
    assert config.from_nested(got.to_nested()).to_flat() == got.to_flat()
    with pytest.raises(ConfigError, match=r"mapper\.fast\.no_such: unknown parameter"):
        config.from_flat({"mapper.fast.no_such": 1})
    with pytest.raises(ConfigError, match=r"mapper\.gpu\.hidden: unknown parameter"):
        config.from_flat({"mapper.gpu.hidden": 1})
    over = config.load(SHIPPED, {"mapper.reference.lr": 1e-3, "keyframes.recent_window": 5})
    assert over.section("mapper.reference").lr == 1e-3 and over.keyframes.recent_window == 5
    # Several node entries merge at every depth.
    two = tmp_path / "two.yaml"
    two.write_text("/**:\n  ros__parameters:\n    mapper: {fast: {hidden: 16}}\n"
                   "mapper:\n  ros__parameters:\n    mapper: {fast: {plane_channels: 4}}\n")
    fast = config.load(two).section("mapper.fast")
    assert (fast.hidden, fast.plane_channels) == (16, 4)
    # Dotted keys, which ROS 2 takes beside the nested form (the nodes read either), mean
    # the same to neurncd and bringup; a parameter given both ways is given twice.
    dotted = tmp_path / "dotted.yaml"
    dotted.write_text("/**:\n  ros__parameters:\n    discovery.entropy_threshold: 0.5\n"
                      "    mapper.fast: {hidden: 16}\n    mapper:\n      fast.plane_channels: 4\n")
    got = config.load(dotted)
    assert got.discovery.entropy_threshold == 0.5
    assert (got.section("mapper.fast").hidden, got.section("mapper.fast").plane_channels) == \
        (16, 4)
    for body, name in (("    discovery.entropy_threshold: 0.5\n    discovery:\n"
                        "      entropy_threshold: 0.4\n", "discovery.entropy_threshold"),
                       ("    mapper.fast: {hidden: 16}\n    mapper:\n      fast:\n"
                        "        hidden: 8\n", "mapper.fast.hidden"),
                       ("    mapper.fast: 3\n    mapper.fast.hidden: 8\n", "mapper.fast")):
        twice = tmp_path / "twice.yaml"
        twice.write_text("/**:\n  ros__parameters:\n" + body)
        with pytest.raises(ConfigError, match=f"{name} is given twice"):
            config.load(twice)


@pytest.mark.parametrize("values, match", [
    ({"mapper": {"fast": {"no_such": 1}}}, r"mapper\.fast\.no_such: unknown parameter; known: "),
    ({"mapper": {"fast": {"hidden": "x"}}}, r"mapper\.fast\.hidden: 'x' has type str"),
    ({"mapper": {"reference": {"lr": 2.0}}}, r"mapper\.reference\.lr: 2\.0 is out of range"),
    ({"mapper": {"fast": 3}}, r"mapper\.fast: section must be a mapping"),
    ({"mapper": {"gpu": {"x": 1}}}, r"mapper\.gpu: unknown section; known: fast, reference"),
    ({"mapper": {"max_keyframes": 8}}, r"mapper\.max_keyframes: unknown parameter"),
    ({"keyframes": {"max_keyframes": 1}}, r"keyframes\.max_keyframes: 1 is out of range"),
])
def test_bad_values_in_subsections_name_the_dotted_key(values, match):
    with pytest.raises(ConfigError, match=match):
        config.from_nested(values)


def test_readme_parameter_table_matches_schema():
    readme = (REPO / "README.md").read_text()
    start = readme.index("<!-- params:start -->") + len("<!-- params:start -->\n")
    end = readme.index("<!-- params:end -->")
    assert readme[start:end] == config.markdown_table(), \
        "regenerate with: neurncd params --format markdown"
