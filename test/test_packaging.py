"""Packaging: colcon builds an installable ament_python package whose nodes answer --help,
and package.xml, setup.py and requirements.txt agree."""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path


REPO = Path(__file__).resolve().parents[1]
NODES = ("embedding", "mapper", "discovery", "replay", "bringup")


def setup_py_literals() -> dict:
    """Module-level constants of setup.py, read without running it."""
    tree = ast.parse((REPO / "setup.py").read_text())
    out = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name):
            try:
                out[node.targets[0].id] = ast.literal_eval(node.value)
            except ValueError:
                pass
    return out


def test_package_xml_and_setup_py_agree():
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.attrib["format"] == "3"
    assert root.find("export/build_type").text == "ament_python"
    lit = setup_py_literals()
    assert root.find("name").text == lit["PACKAGE"] == "neurncd_ros"
    import neurncd_ros
    assert root.find("version").text == lit["VERSION"] == neurncd_ros.__version__
    exec_deps = {e.text for e in root.findall("exec_depend")}
    assert exec_deps == set(lit["RUNTIME_DEPENDENCIES"]) | set(lit["ROS_ONLY_DEPENDENCIES"])
    assert not set(lit["RUNTIME_DEPENDENCIES"]) & set(lit["ROS_ONLY_DEPENDENCIES"])
    pins = {}
    for line in (REPO / "requirements.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, version = line.split("==")
            pins[name.lower()] = version
    assert {v.lower() for v in lit["RUNTIME_DEPENDENCIES"].values()} == set(pins)
    assert pins["torch"] == "2.13.0"
    assert (REPO / "resource" / "neurncd_ros").is_file()
    assert "$base/lib/neurncd_ros" in (REPO / "setup.cfg").read_text()


def _copy_source(dst: Path) -> None:
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO,
                           capture_output=True, text=True, check=True).stdout.split()
    for rel in files:
        src = REPO / rel
        if src.is_file():
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst / rel)


def test_colcon_build_installs_nodes_that_answer_help(tmp_path):
    colcon = Path(sys.executable).parent / "colcon"
    assert colcon.exists(), "colcon is a pinned dev requirement (requirements-dev.txt)"
    src = tmp_path / "ws" / "src" / "neurncd_ros"
    _copy_source(src)
    ws = tmp_path / "ws"
    env = dict(os.environ, AMENT_PREFIX_PATH=sys.prefix, COLCON_HOME=str(tmp_path / "colcon"))
    r = subprocess.run([str(colcon), "build", "--packages-select", "neurncd_ros"], cwd=ws,
                       env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    lib = ws / "install" / "neurncd_ros" / "lib" / "neurncd_ros"
    share = ws / "install" / "neurncd_ros" / "share" / "neurncd_ros"
    assert (share / "package.xml").is_file()
    assert (share / "config" / "neurncd.yaml").is_file()
    assert (share / "config" / "fastdds_shm.xml").is_file()
    # ros2 launch neurncd_ros neurncd.launch.py finds it here.
    assert (share / "launch" / "neurncd.launch.py").is_file()
    assert (ws / "install" / "share" / "ament_index" / "resource_index" / "packages" /
            "neurncd_ros").exists() or (ws / "install" / "neurncd_ros" / "share" /
                                        "ament_index" / "resource_index" / "packages" /
                                        "neurncd_ros").exists()
    for node in NODES:
        exe = lib / node
        assert exe.is_file(), f"{exe} missing"
        # As a user would: source the workspace, then run the installed executable.
        cmd = f"source {ws}/install/setup.bash && {exe} --help"
        r = subprocess.run(["bash", "-c", cmd], env=env, capture_output=True, text=True,
                           timeout=120, cwd=tmp_path)
        assert r.returncode == 0, f"{node} --help failed:\n{r.stdout}\n{r.stderr}"
        assert re.search(rf"usage: {node}\b", r.stdout), r.stdout
    # The offline tool reads the installed share/ parameter file by default: the package's
    # folder in site-packages has no config/ beside it (ros2 run neurncd_ros neurncd ...).
    cmd = f"source {ws}/install/setup.bash && {lib / 'neurncd'} params"
    r = subprocess.run(["bash", "-c", cmd], env=env, capture_output=True, text=True,
                       timeout=120, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert re.search(r"^      field_views: false$", r.stdout, re.M), r.stdout
    # The installed copy is the one that runs, not the source tree, and its files (the
    # DDS profile, the parameter file) are its own prefix's.
    r = subprocess.run(["bash", "-c", f"source {ws}/install/setup.bash && {sys.executable} -c "
                        "'import neurncd_ros; print(neurncd_ros.__file__); "
                        "from neurncd_ros.share import share_file; "
                        "print(share_file(\"config\", \"fastdds_shm.xml\"))'"],
                       env=env, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    lines = r.stdout.splitlines()
    assert len(lines) == 2 and str(ws / "install") in lines[0], r.stdout + r.stderr
    assert lines[1] == str(share / "config" / "fastdds_shm.xml"), r.stdout
