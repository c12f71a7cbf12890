"""What a user of the offline tool sees on real inputs: `neurncd run` on a bag without
ground truth, `neurncd convert` on an ICL-NUIM folder, and configuration files that
are wrong in ways YAML itself accepts."""

from __future__ import annotations

import itertools
import json
import re
import subprocess
import sys

import cv2
import numpy as np
import pytest

from neurncd_ros import config
from neurncd_ros.core import classes
from neurncd_ros.core.camera import Intrinsics, reproject_depth_error
from neurncd_ros.core.data import formats
from neurncd_ros.core.data.bag import FrameReader
from neurncd_ros.core.data.formats import FormatError, opencv_axes, read_folder
from neurncd_ros.core.params import ConfigError

from rosutil import REPO


def neurncd(*args: object, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run the offline tool (``python -m neurncd_ros.cli ARGS``) from the repository root."""
    return subprocess.run([sys.executable, "-m", "neurncd_ros.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=REPO)


# ------------------------------------------------------------ run without ground truth

@pytest.fixture(scope="module")
def kinect_run(real_data_dir, tmp_path_factory):
    """The real Kinect dining room (no semantic ground truth) as a bag, run once."""
    tmp = tmp_path_factory.mktemp("kinect")
    bag = tmp / "kinect_dining.mcap"
    assert formats.convert(real_data_dir / "kinect_dining", bag) == 5
    out = tmp / "out"
    (out / "labels").mkdir(parents=True)
    # A label image an earlier run left behind: not one of this run's frames.
    cv2.imwrite(str(out / "labels" / "42.png"), np.ones((4, 4), np.uint16))
    r = neurncd("run", "--bag", bag, "--out", out, "--set", "run.overlays=1")
    assert r.returncode == 0, r.stdout + r.stderr
    return r, out, json.loads((out / "metrics.json").read_text())


def test_run_without_ground_truth_says_so_and_flags_it(kinect_run):
    r, out, result = kinect_run
    assert "no ground truth in the bag: labels written, nothing evaluated" in r.stdout
    assert result["evaluated"] is False and result["frames_evaluated"] == 0
    assert "metrics" not in result
    # The overlays have no ground-truth tile, and the summary says which tiles they have.
    (ov,) = (out / "overlays").glob("*.png")
    assert cv2.imread(str(ov)).shape == (480, 4 * 640, 3)
    assert "(1: rgb | backbone | NeurNCD labels | entropy)" in r.stdout
    assert "ground truth |" not in r.stdout


def test_run_writes_every_published_label_image_as_16_bit_png(kinect_run):
    r, out, result = kinect_run
    pngs = sorted((out / "labels").glob("*.png"))
    assert len(pngs) == result["labelled"] == result["label_images"] >= 1
    assert "42.png" not in {p.name for p in pngs}  # the earlier run's file is gone
    pixels: dict[int, int] = {}
    for p in pngs:
        lab = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert lab.dtype == np.uint16 and lab.shape == (480, 640)
        ids, counts = np.unique(lab, return_counts=True)
        # The ids of /neurncd/labels: 0 unlabelled, NYU-13, novel from 100.
        assert all(i == 0 or 1 <= i <= classes.NUM_CLASSES or i >= classes.NOVEL_ID_START
                   for i in ids.tolist())
        for i, c in zip(ids.tolist(), counts.tolist()):
            if i:
                pixels[i] = pixels.get(i, 0) + c
    # The class table is exactly what the label images show: no class without pixels.
    assert {int(k): v["pixels"] for k, v in result["classes"].items()} == pixels
    assert all(v["pixels"] > 0 and v["frames"] >= 1 for v in result["classes"].values())
    assert not set(result["class_ids_not_in_labels"]) & set(pixels)
    assert f"{out}/labels/<stamp>.png ({len(pngs)} label images, 16-bit" in r.stdout
    shown = [k for k, v in result["classes"].items() if "merged_into" not in v]
    assert f"classes in the labels: {len(shown)} (" in r.stdout


def test_run_with_ground_truth_is_flagged_evaluated(tmp_path):
    from neurncd_ros import synth
    from neurncd_ros.core.data.bag import write_bag

    bag = tmp_path / "scene.mcap"
    write_bag(bag, synth.generate(1002, 12, synth.SynthConfig(width=160, height=120)))
    out = tmp_path / "out"
    r = neurncd("run", "--bag", bag, "--out", out, "--set", "run.overlays=1")
    assert r.returncode == 0, r.stdout + r.stderr
    result = json.loads((out / "metrics.json").read_text())
    assert result["evaluated"] is True and result["frames_evaluated"] == result["labelled"]
    assert "nothing evaluated" not in r.stdout and "NeurNCD: mIoU all" in r.stdout
    (ov,) = (out / "overlays").glob("*.png")
    assert cv2.imread(str(ov)).shape == (120, 5 * 160, 3)
    assert "(1: rgb | ground truth | backbone | NeurNCD labels | entropy)" in r.stdout
    assert len(list((out / "labels").glob("*.png"))) == result["labelled"]


def test_run_saves_the_map_and_the_next_run_continues_it(tmp_path):
    """mapper_node.map_path and discovery_node.state_path offline as on the nodes: loaded
    if they exist, saved at the end (the map was ignored by neurncd run without a word)."""
    from neurncd_ros import synth
    from neurncd_ros.core.data.bag import write_bag

    frames = list(synth.generate(1002, 16, synth.SynthConfig(width=160, height=120)))
    write_bag(tmp_path / "a.mcap", frames[:8])
    write_bag(tmp_path / "b.mcap", frames[8:])
    map_file = tmp_path / "maps" / "room.pt"
    state_file = tmp_path / "maps" / "discovery.pt"
    common = ("--set", f"mapper_node.map_path={map_file}", "--set", "run.training_rate_hz=60",
              "--set", "run.overlays=0", "--set", f"discovery_node.state_path={state_file}")
    r = neurncd("run", "--bag", tmp_path / "a.mcap", "--out", tmp_path / "a", *common)
    assert r.returncode == 0, r.stdout + r.stderr
    first = json.loads((tmp_path / "a" / "metrics.json").read_text())["map"]
    assert first["loaded"] is None and first["saved"] and first["iterations"] > 0
    assert map_file.is_file() and map_file.with_name("room.pt.spec.json").is_file()
    assert f"no map at {map_file} yet" in r.stdout
    r = neurncd("run", "--bag", tmp_path / "b.mcap", "--out", tmp_path / "b", *common)
    assert r.returncode == 0, r.stdout + r.stderr
    second = json.loads((tmp_path / "b" / "metrics.json").read_text())["map"]
    assert second["loaded"]["iterations"] == first["iterations"]
    assert second["loaded"]["keyframes"] >= 1
    assert second["iterations"] > first["iterations"]
    assert f"continued map {map_file} ({first['iterations']} iterations" in r.stdout
    assert second["loaded"]["kept_settings"] == {} and "keeps the settings" not in r.stdout
    # a setting changed for a map that exists: the map keeps its own, and the run says so
    r = neurncd("run", "--bag", tmp_path / "b.mcap", "--out", tmp_path / "c", *common,
                "--set", "mapper.near=0.1")
    assert r.returncode == 0, r.stdout + r.stderr
    third = json.loads((tmp_path / "c" / "metrics.json").read_text())["map"]
    assert third["loaded"]["kept_settings"] == {"mapper.near": [0.05, 0.1]}
    assert "it keeps the settings it was built with: mapper.near 0.05 (configured 0.1)" \
        in r.stdout
    first_state = json.loads((tmp_path / "a" / "metrics.json").read_text())["discovery_state"]
    second_state = json.loads((tmp_path / "b" / "metrics.json").read_text())["discovery_state"]
    assert first_state["continued_novel_ids"] is None and first_state["saved"]
    assert second_state["continued_novel_ids"] == first_state["novel_ids"]
    assert f"continued discovery state {state_file}" in r.stdout


def test_info_gives_the_depth_and_warns_when_it_is_no_indoor_scene(tmp_path):
    """`neurncd info` is where a user checks a bag: it gives the median depth, and a bag
    whose depth was written at the wrong scale (here five times too far, as ICL-NUIM read
    as millimetres) is named as such."""
    import dataclasses

    from neurncd_ros import synth
    from neurncd_ros.core.data.bag import write_bag

    frames = list(synth.generate(1002, 3, synth.SynthConfig(width=80, height=60)))
    good, bad = tmp_path / "good.mcap", tmp_path / "bad.mcap"
    write_bag(good, frames)
    write_bag(bad, [dataclasses.replace(f, depth=f.depth * 5) for f in frames])
    r = neurncd("info", good, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    med = float(np.median([np.median(f.depth[f.depth > 0]) for f in frames]))
    assert f"depth: median {med:.2f} m" in r.stdout and "warning" not in r.stdout
    r = neurncd("info", bad, timeout=120)
    assert r.returncode == 0 and "is no indoor scene" in r.stdout, r.stdout
    # A bag without poses: its frames, and that the poses will be estimated.
    nopose = tmp_path / "nopose.mcap"
    write_bag(nopose, frames, pose_mode="none")
    r = neurncd("info", nopose, timeout=120)
    assert r.returncode == 0 and "3 synchronised frames" in r.stdout, r.stdout + r.stderr
    assert "no pose in the bag (/camera/pose" in r.stdout and "odometry" in r.stdout
    # The engine's advice is one plain line, not a Python warning with file and source.
    r = neurncd("run", "--bag", good, "--out", tmp_path / "out", "--set",
                "backbone.novelty_branch=false", timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "neurncd run: warning: " in r.stderr and "no novelty branch" in r.stderr, r.stderr
    assert "UserWarning" not in r.stderr and "warnings.warn" not in r.stderr, r.stderr


def test_run_help_states_the_output_layout():
    r = neurncd("run", "--help", timeout=120)
    assert r.returncode == 0
    for text in ("metrics.json", "labels/<stamp>.png", "16-bit", "/neurncd/labels",
                 "overlays/<stamp>.png", '"evaluated"'):
        assert text in r.stdout, text


# ------------------------------------------------------------ ICL-NUIM

def test_icl_folder_read_as_millimetres_is_refused_naming_the_preset(real_data_dir,
                                                                      tmp_path):
    icl = real_data_dir / "icl_livingroom"
    with pytest.raises(FormatError, match=r"median of 15\.\d m.*preset=icl"):
        next(read_folder(icl))
    out = tmp_path / "icl.mcap"
    r = neurncd("convert", icl, "--out", out, timeout=120)
    assert r.returncode == 1 and "--opt preset=icl" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and not out.exists()
    # A scale the user chose is not second-guessed (the geometry then shows it is wrong).
    f = next(read_folder(icl, depth_scale=1000.0))
    assert np.median(f.depth[f.depth > 0]) > 14.0
    # The millimetre folders of the same layout read as before.
    f = next(read_folder(real_data_dir / "kinect_dining"))
    assert 2.5 < np.median(f.depth[f.depth > 0]) < 3.3


def test_icl_preset_gives_an_opencv_camera_and_poses_that_agree(real_data_dir, tmp_path):
    icl = real_data_dir / "icl_livingroom"
    frames = list(read_folder(icl, preset="icl"))
    for f in frames:
        assert (f.intrinsics.fx, f.intrinsics.fy) == (481.2, 480.0)
        assert abs(np.linalg.det(f.pose[:3, :3]) - 1.0) < 1e-6
        # Upright images: the image's down direction is the same world direction in all
        # frames (ICL-NUIM's y-up world mirrored to y-down).
        assert f.pose[1, 1] > 0.9
    # Back-projected points land on the next frame's depth (the dataset README: ~4 cm)
    # for the overlapping pairs; the fy sign flipped without the poses would not.
    for a, b in ((frames[0], frames[1]), (frames[3], frames[4])):
        err = reproject_depth_error(a.depth, a.pose, b.depth, b.pose, a.intrinsics)
        assert err.size > 50_000 and np.median(err) < 0.06
    raw = list(itertools.islice(read_folder(icl, depth_scale=5000.0,
                                            intrinsics=[481.2, 480.0, 319.5, 239.5]), 2))
    naive = reproject_depth_error(raw[0].depth, raw[0].pose, raw[1].depth, raw[1].pose,
                                  raw[0].intrinsics)
    assert np.median(naive) > 0.2
    # The bag's CameraInfo carries the OpenCV camera too.
    out = tmp_path / "icl.mcap"
    r = neurncd("convert", icl, "--out", out, "--opt", "preset=icl", timeout=120)
    assert r.returncode == 0, r.stderr
    back = list(FrameReader(out))
    assert [f.intrinsics.fy for f in back] == [480.0] * 5
    err = reproject_depth_error(back[0].depth, back[0].pose, back[1].depth, back[1].pose,
                                back[0].intrinsics)
    assert np.median(err) < 0.06


def test_negative_focal_lengths_become_an_opencv_camera():
    """Points back-projected with the dataset's camera and pose are the points of the
    converted camera and pose, in a frame mirrored the same way (or rolled, when both
    focal lengths are negative)."""
    rng = np.random.default_rng(0)
    u, v, z = rng.uniform(0, 640, 50), rng.uniform(0, 480, 50), rng.uniform(0.5, 4, 50)
    a = np.radians(30)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = [0.3, -0.2, 1.0]

    def world(intr: Intrinsics, pose: np.ndarray) -> np.ndarray:
        p = np.stack([(u - intr.cx) * z / intr.fx, (v - intr.cy) * z / intr.fy, z,
                      np.ones_like(z)])
        return (pose @ p)[:3]

    for fx, fy, mirror in ((481.2, -480.0, [1, -1, 1]), (-481.2, 480.0, [-1, 1, 1]),
                           (-481.2, -480.0, [1, 1, 1])):
        intr = Intrinsics(fx, fy, 319.5, 239.5, 640, 480)
        fixed, pose = opencv_axes(intr, T)
        assert fixed.fx > 0 and fixed.fy > 0
        assert abs(np.linalg.det(pose[:3, :3]) - 1.0) < 1e-9
        np.testing.assert_allclose(world(fixed, pose),
                                   np.array(mirror)[:, None] * world(intr, T), atol=1e-9)
    plain = Intrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)
    assert opencv_axes(plain, T)[1] is T


def test_a_bag_never_gets_a_negative_focal_length(real_data_dir, tmp_path):
    import dataclasses

    from neurncd_ros.core.data.bag import BagError, write_bag

    f = next(read_folder(real_data_dir / "icl_livingroom", preset="icl"))
    i = f.intrinsics
    flipped = dataclasses.replace(f, intrinsics=Intrinsics(i.fx, -i.fy, i.cx, i.cy, i.width,
                                                           i.height))
    with pytest.raises(BagError, match=r"fy -480\.0; the topic contract needs OpenCV axes"):
        write_bag(tmp_path / "bad.mcap", [flipped])
    assert not (tmp_path / "bad.mcap").exists()


# ------------------------------------------------------------ configuration files

PARAMS = "/**:\n  ros__parameters:\n"


def test_a_key_given_twice_is_a_configuration_error_naming_file_and_key(tmp_path):
    dup = tmp_path / "my.yaml"
    dup.write_text(PARAMS + "    run:\n      overlays: 2\n      out_dir: a\n"
                   "      overlays: 3\n")
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(dup))}: parameter "
                                          r"'run\.overlays' .* given twice \(lines 4 and 6\)"):
        config.load(dup)
    dup.write_text(PARAMS + "    run:\n      overlays: 2\n    mapper:\n      backend: fast\n"
                   "    run:\n      out_dir: a\n")
    with pytest.raises(ConfigError, match=r"section 'run' .* twice \(lines 3 and 7\)"):
        config.load(dup)
    r = neurncd("params", "--config", dup, timeout=120)
    assert r.returncode == 2 and f"configuration error: {dup}: section 'run'" in r.stderr
    r = neurncd("check-config", dup, timeout=120)
    assert r.returncode == 2 and str(dup) in r.stderr and "twice" in r.stderr
    # Not duplicates: the same parameter for two nodes (the node's wins, as in ROS 2),
    # and a key overriding one brought in by a YAML merge.
    ok = tmp_path / "ok.yaml"
    ok.write_text(PARAMS + "    run: {overlays: 2}\nneurncd_mapper:\n  ros__parameters:\n"
                  "    run: {overlays: 3}\n")
    assert config.load(ok).run.overlays == 3
    assert config.strict_yaml_load("a: &x {k: 1}\nb: {<<: *x, k: 2}\n")["b"] == {"k": 2}


def test_a_config_that_is_not_utf8_is_named(tmp_path):
    bad = tmp_path / "latin1.yaml"
    bad.write_bytes(b"\xff\xfe" + (PARAMS + "    run: {out_dir: caf\xe9}\n").encode("utf-16-le"))
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(bad))}: not UTF-8 text "
                                          r"\(byte 0xff at line 1"):
        config.load(bad)
    r = neurncd("params", "--config", bad, timeout=120)
    assert r.returncode == 2, r.stderr
    assert f"neurncd params: configuration error: {bad}: not UTF-8" in r.stderr
    bad.write_bytes((PARAMS + "    run: {out_dir: caf\xe9}\n").encode("latin-1"))
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(bad))}: not UTF-8 text "
                                          r"\(byte 0xe9 at line 3"):
        config.load(bad)


# ------------------------------------------------------------ a camera's own bag

RS_TOPICS = {"color": "/camera/camera/color/image_raw",
             "depth": "/camera/camera/aligned_depth_to_color/image_raw",
             "camera_info": "/camera/camera/color/camera_info"}
"""A RealSense driver's topic names (realsense2_camera 4.x), not the contract's."""

RS_TF = ("odom", "camera_color_optical_frame")


@pytest.fixture(scope="module")
def realsense_bag(tmp_path_factory):
    """A bag as a RealSense with odometry records it: the driver's topic names, the pose
    on /tf as odom -> base_link (dynamic) -> camera_link -> camera_color_optical_frame
    (static); and the frames it carries."""
    from neurncd_ros import synth
    from neurncd_ros.core.camera import look_at
    from neurncd_ros.core.data import bag
    from neurncd_ros.core.topics import Topics

    frames = list(synth.generate(1002, 4, synth.SynthConfig(width=80, height=60)))
    tp = Topics(**RS_TOPICS, camera_frame=RS_TF[1], world_frame=RS_TF[0])
    T_bl = look_at([0.1, 0.0, 0.2], [1.0, 0.1, 0.1])   # base_link -> camera_link
    T_lo = look_at([0.0, 0.02, 0.0], [0.0, 0.02, 1.0])  # camera_link -> optical frame
    s0 = frames[0].stamp_ns - 10
    items = [(tp.tf_static, bag.TF_MESSAGE, s0, bag.tf_msg(
        s0, [("base_link", "camera_link", T_bl), ("camera_link", RS_TF[1], T_lo)]))]
    for f in frames:
        for topic, typ, s, msg in bag.frame_messages(f, tp, pose_mode="tf"):
            if topic == tp.tf:
                msg = bag.tf_msg(s, [("odom", "base_link",
                                      f.pose @ np.linalg.inv(T_bl @ T_lo))])
            items.append((topic, typ, s, msg))
    path = tmp_path_factory.mktemp("realsense") / "rs.mcap"
    bag.write_messages(path, items)
    return path, frames


def _set_topics() -> list[str]:
    return [a for role, name in RS_TOPICS.items() for a in ("--set", f"topics.{role}={name}")]


def test_convert_reads_a_bags_topics_from_the_configuration(realsense_bag, tmp_path):
    """`neurncd convert` reads a bag's topic names from --set / --config as info and run
    do, with the source's poses and with odometry; the bag it writes has the contract's
    default names, so info and run read it without overrides."""
    from neurncd_ros.core.data.bag import bag_topics
    from neurncd_ros.core.topics import Topics

    src, frames = realsense_bag
    tf = ["--tf-parent", RS_TF[0], "--tf-child", RS_TF[1]]
    yaml = tmp_path / "topics.yaml"
    yaml.write_text(PARAMS + "    topics:\n" + "".join(f"      {role}: {name}\n" for role, name
                                                     in RS_TOPICS.items()))
    runs = {"set": [*tf, *_set_topics()], "config": [*tf, "--config", yaml],
            "odometry": ["--poses", "odometry", *_set_topics()]}
    for name, extra in runs.items():
        out = tmp_path / f"{name}.mcap"
        r = neurncd("convert", src, "--kind", "bag", "--out", out, *extra, timeout=300)
        assert r.returncode == 0, (name, r.stderr)
        assert f"converted {len(frames)} frames" in r.stdout, (name, r.stdout)
        contract = Topics()
        assert {contract.color, contract.depth, contract.camera_info, contract.pose} <= \
            set(bag_topics(out)) and RS_TOPICS["color"] not in bag_topics(out)
        got = list(FrameReader(out))
        assert [g.stamp_ns for g in got] == [f.stamp_ns for f in frames]
        if name != "odometry":  # the /tf chain composed is the camera's pose
            for f, g in zip(frames, got):
                np.testing.assert_allclose(g.pose, f.pose, atol=1e-9)
    # without the topic names, the error names the topic looked for and the bag's
    r = neurncd("convert", src, "--out", tmp_path / "none.mcap", *tf, timeout=300)
    assert r.returncode == 1 and "no color topic '/camera/color/image_raw'" in r.stderr
    assert RS_TOPICS["color"] in r.stderr
    r = neurncd("convert", "--help", timeout=120)
    assert "topics.*" in r.stdout and "default names" in r.stdout


def test_a_tf_frame_the_bag_has_not_is_named_by_info_run_and_convert(realsense_bag,
                                                                      tmp_path):
    """A wrong /tf frame (map where the bag has odom) is one line naming the bag's frames
    from info, run and convert, not 'N dropped (missing pose: N)' or 'no frames to run on';
    so are two frames of separate trees."""
    src, _ = realsense_bag
    frames = "(frames: odom, base_link, camera_link, camera_color_optical_frame)"
    missing = f"tf frame 'map' (tf_parent) is not in the bag's /tf tree {frames}"
    sync = ["--set", "sync.tf_parent=map", "--set", f"sync.tf_child={RS_TF[1]}"]
    for cmd in (["info", src, *sync], ["run", "--bag", src, "--out", tmp_path / "run", *sync],
                ["convert", src, "--out", tmp_path / "c.mcap", "--tf-parent", "map",
                 "--tf-child", RS_TF[1]]):
        r = neurncd(*cmd, *_set_topics(), timeout=300)
        assert r.returncode == 1, (cmd[0], r.stdout, r.stderr)
        assert f"neurncd {cmd[0]}: error: {src}: {missing}" in r.stderr, (cmd[0], r.stderr)
    assert not (tmp_path / "c.mcap").exists()
    r = neurncd("info", src, *_set_topics(), "--set", "sync.tf_parent=camera_link",
                "--set", "sync.tf_child=base_footprint", timeout=120)
    assert r.returncode == 1
    assert "tf frame 'base_footprint' (tf_child) is not in the bag's /tf tree" in r.stderr


def test_the_cli_logs_warnings_as_whole_lines_above_its_progress_bars(capsys):
    """A frame the odometry loses is logged while `run`'s progress bar is drawn: the line
    goes through tqdm.write (above the bar, not glued to it), once per record however
    often main() runs in the process."""
    import logging

    from tqdm import tqdm

    from neurncd_ros import cli

    for _ in range(2):
        assert cli.main(["params"]) == 0
    root = logging.getLogger()
    assert [h.get_name() for h in root.handlers].count("neurncd-tqdm") == 1
    capsys.readouterr()
    with tqdm(range(3), file=sys.stderr, desc="run") as bar:
        for i in bar:
            if i == 1:
                logging.getLogger("neurncd_ros.core.odometry").warning(
                    "frame 7: tracking lost against keyframe 2: too few inliers")
    err = capsys.readouterr().err
    # The bar's line is cleared (carriage return) before the record is written whole.
    assert "\rframe 7: tracking lost against keyframe 2: too few inliers\n" in err, err


def test_progress_bars_in_a_log_file_are_lines_with_messages_between(tmp_path):
    """stderr redirected to a file (CI, nohup, `2> log`): tqdm's carriage returns and cursor
    codes made one endless line with the messages glued into it. Through ProgressLines
    each bar state is a line (throttled per bar, the final n/n always), nested bars too,
    and a message written between bar updates is a line of its own."""
    import io

    from tqdm import tqdm

    from neurncd_ros.core.text import ProgressLines

    now = [0.0]
    log = io.StringIO()
    out = ProgressLines(log, interval=10.0, clock=lambda: now[0])
    with tqdm(total=3, file=out, desc="sweep", mininterval=0) as outer:
        for _ in range(3):
            # a description with brackets, as eval's stages name their bag
            for j in tqdm(range(4), file=out, desc="scenes [a.mcap]", leave=False,
                          mininterval=0):
                now[0] += 1.0
                if j == 2:
                    tqdm.write("scene lost a frame", file=out)
            outer.update()
    text = log.getvalue()
    assert "\r" not in text and "\x1b" not in text, repr(text)
    lines = text.splitlines()
    assert all(line.startswith(("sweep:", "scenes [a.mcap]:", "scene lost"))
               for line in lines), lines
    assert lines.count("scene lost a frame") == 3
    assert sum(line.startswith("scenes [a.mcap]: 100%") and "4/4" in line
               for line in lines) == 3, lines
    assert lines[-1].startswith("sweep: 100%") and "3/3" in lines[-1]
    # throttled: 12 inner updates over 12 s of fake clock give a handful of lines, not 12
    assert sum(line.startswith("scenes") and "4/4" not in line for line in lines) <= 3

    # A bar without a total (frames of a dataset folder, not counted first): its text
    # never says n/n, so its last count is shown when it closes, once.
    log = io.StringIO()
    out = ProgressLines(log, interval=10.0, clock=lambda: now[0])
    for _ in tqdm(iter(range(30)), file=out, desc="write rep.mcap", mininterval=0,
                  unit="frame"):
        now[0] += 0.01
    lines = log.getvalue().splitlines()
    assert lines[0].startswith("write rep.mcap: 0frame"), lines
    assert lines[-1].startswith("write rep.mcap: 30frame") and len(lines) == 2, lines

    r = neurncd("synth", "--seed", 3, "--frames", 4, "--out", tmp_path / "s.db3", timeout=120)
    assert r.returncode == 0, r.stderr
    assert "\r" not in r.stderr and r.stderr.startswith("synth seed 3:"), repr(r.stderr)
    assert r.stderr.splitlines()[-1].startswith("synth seed 3: 100%"), repr(r.stderr)
    assert "4/4" in r.stderr.splitlines()[-1], repr(r.stderr)
    assert "as sqlite3" in r.stdout
    assert sorted(p.suffix for p in (tmp_path / "s.db3").iterdir()) == [".db3", ".yaml"]


def test_wrong_arguments_get_the_commands_usage_and_a_hint(real_data_dir, tmp_path):
    """What a user typing the commands wrongly reads: the subcommand's own usage for an
    unknown option, a hint to convert a dataset folder given as a bag, the reader options
    beside the convert.* parameters, no empty scene, and an error on a line of its own."""
    r = neurncd("run", "--bag", tmp_path / "x.mcap", "--frobnicate")
    assert r.returncode == 2 and "usage: neurncd run" in r.stderr
    assert "unrecognized arguments: --frobnicate" in r.stderr
    folder = real_data_dir / "kinect_dining"
    r = neurncd("run", "--bag", folder, "--out", tmp_path / "o")
    assert r.returncode == 1
    assert f"convert it into a bag first (neurncd convert {folder}" in r.stderr
    r = neurncd("convert", folder, "--out", tmp_path / "k.mcap", "--opt", "idmap=m.json")
    assert r.returncode == 2 and "idmap: unknown parameter" in r.stderr
    assert "id_map, class_info" in r.stderr
    r = neurncd("bench", "nosuch", "--quick")
    assert r.returncode == 2 and "no benchmark matched ['nosuch']; there are" in r.stderr
    assert "ncd" in r.stderr.split("there are", 1)[1]
    r = neurncd("bench", "synth", "odometri", "--quick")  # a typo beside a name: nothing runs
    assert r.returncode == 2 and "no benchmark matched ['odometri']" in r.stderr, r.stderr
    assert "== bench/" not in r.stdout
    # graph has no quick mode: named with --quick it is refused before anything runs (in
    # `neurncd bench --quick` it is left out, and the summary says so).
    r = neurncd("bench", "graph", "--quick")
    assert r.returncode == 2 and "graph has no --quick mode" in r.stderr, r.stderr
    r = neurncd("synth", "--seed", 1, "--frames", 0, "--out", tmp_path / "s.mcap")
    assert r.returncode == 2 and "--frames: must be at least 1" in r.stderr
    assert not (tmp_path / "s.mcap").exists()
    r = neurncd("convert", folder, "--out", tmp_path / "k.mcap")
    assert r.returncode == 0 and "converted 5 frames" in r.stdout
    r = neurncd("convert", folder, "--out", tmp_path / "k.mcap")
    assert r.returncode == 1
    assert r.stderr.startswith("neurncd convert: error:") and "exists already" in r.stderr


def test_check_config_names_every_error_of_a_file(tmp_path):
    """One run shows everything to fix: a choice not allowed, a wrong type, a value out of
    range and an unknown section, each named with its file (it stopped at the first)."""
    bad = tmp_path / "multi.yaml"
    bad.write_text("/**:\n  ros__parameters:\n    mapper_node:\n      fusion: bogus\n"
                   "      coverage_depth_tolerance: abc\n      own_view_weight: 1000.0\n"
                   "    bogus_section:\n      x: 1\n")
    r = neurncd("check-config", bad, timeout=120)
    assert r.returncode == 2 and f"{bad}: 4 errors" in r.stderr, r.stderr
    for what in ("mapper_node.fusion: 'bogus' is not allowed",
                 "mapper_node.coverage_depth_tolerance: 'abc' has type str",
                 "mapper_node.own_view_weight: 1000.0 is out of range",
                 "bogus_section: unknown section"):
        assert f"configuration error: {bad}: {what}" in r.stderr, r.stderr
    good = neurncd("check-config", REPO / "config" / "neurncd.yaml", timeout=120)
    assert good.returncode == 0 and "valid (" in good.stdout
    # Parameters that must agree (checked without loading a model): they were called
    # valid, and the embedding node, `run` and bringup refused them later.
    esanet = tmp_path / "esanet.yaml"
    esanet.write_text("/**:\n  ros__parameters:\n    backbone:\n      kind: esanet\n"
                      "      input_width: 320\n      input_height: 240\n")
    r = neurncd("check-config", esanet, timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    for what in ("multiples of 32", "kind=esanet needs checkpoint"):
        assert f"configuration error: {esanet}: backbone: " in r.stderr and what in r.stderr, \
            r.stderr
    esanet.write_text("/**:\n  ros__parameters:\n    backbone:\n      kind: esanet\n"
                      f"      checkpoint: {tmp_path / 'absent.pth'}\n")
    r = neurncd("check-config", esanet, timeout=120)
    assert r.returncode == 2 and "ESANet checkpoint" in r.stderr and "does not exist" \
        in r.stderr, r.stderr
    # A file shared with another node and with another robot's entry: --node checks what
    # each named node is given (the backbone's setup for the embedding node alone).
    shared = tmp_path / "shared.yaml"
    shared.write_text("/**:\n  ros__parameters:\n    discovery:\n      entropy_threshold: 0.4\n"
                      "camera_driver:\n  ros__parameters:\n    fps: 30\n"
                      "/robot2/mapper:\n  ros__parameters:\n    mapper:\n"
                      "      lambda_embedding: -1.0\n"
                      "/robot1/mapper:\n  ros__parameters:\n    backbone:\n"
                      "      kind: esanet\n")
    views = ["--node", "/robot1/embedding", "--node", "/robot1/mapper"]
    r = neurncd("check-config", shared, *views, timeout=120)
    assert r.returncode == 0 and "for /robot1/embedding, /robot1/mapper" in r.stdout, \
        r.stdout + r.stderr
    r = neurncd("check-config", shared, "--node", "robot2/mapper", timeout=120)
    assert r.returncode == 2 and "lambda_embedding: -1.0 is out of range" in r.stderr \
        and "(node /robot2/mapper)" in r.stderr and "fps" not in r.stderr, r.stderr
    r = neurncd("check-config", shared, timeout=120)  # every entry: neurncd run's view
    assert r.returncode == 2 and "fps: unknown section" in r.stderr, r.stderr
