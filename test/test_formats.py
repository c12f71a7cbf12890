"""Real-format readers: units and geometry on the real fixtures, exact writer round trips."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from neurncd_ros.core.camera import Intrinsics, look_at, reproject_depth_error
from neurncd_ros.core import sync
from neurncd_ros.core.data import bag, formats
from neurncd_ros.core.data.formats import FormatError, read_folder
from neurncd_ros.core.frame import Frame
from neurncd_ros.core.params import ConfigError

torch.set_num_threads(1)

# (folder, read_folder options, frame 1 median depth m, README frame 1->2 reprojection median m)
SEQUENCES = [
    ("kinect_dining", {}, 2.9, 0.10),
    ("icl_livingroom", {"preset": "icl"}, 3.0, 0.04),
    ("redwood_livingroom", {}, 1.86, 0.005),
]


def first_two(folder: Path, **opts) -> list[Frame]:
    return list(itertools.islice(read_folder(folder, **opts), 2))


@pytest.mark.parametrize("name,opts,median,reproj", SEQUENCES)
def test_sequences_units_and_reprojection(real_data_dir, name, opts, median, reproj):
    f1, f2 = first_two(real_data_dir / name, **opts)
    for f in (f1, f2):
        assert f.rgb.shape == (480, 640, 3) and f.depth.dtype == np.float32
        assert np.count_nonzero(f.depth) > 0.5 * f.depth.size
    # frame 1's median depth in metres (a unit error is a factor of 5 or 1000)
    assert abs(np.median(f1.depth[f1.depth > 0]) - median) < 0.1 * median
    assert f2.stamp_ns > f1.stamp_ns
    err = reproject_depth_error(f1.depth, f1.pose, f2.depth, f2.pose, f1.intrinsics)
    assert err.size > 50_000
    assert np.median(err) < 1.5 * reproj
    # the inverse pose direction is clearly worse: poses are camera-to-world
    bad = reproject_depth_error(f1.depth, np.linalg.inv(f1.pose), f2.depth,
                                np.linalg.inv(f2.pose), f1.intrinsics)
    assert bad.size == 0 or np.median(bad) > 2 * np.median(err)


def test_kinds_detected_and_camera_files(real_data_dir):
    assert formats.detect_kind(real_data_dir / "kinect_dining") == "posetxt"
    assert formats.detect_kind(real_data_dir / "redwood_livingroom") == "redwood"
    red = first_two(real_data_dir / "redwood_livingroom")[0]
    assert red.intrinsics == Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    icl = first_two(real_data_dir / "icl_livingroom", preset="icl")[0]
    assert icl.intrinsics.fy == 480.0  # OpenCV axes: the poses are mirrored to match
    # a wrong depth scale is visible in the geometry: ICL read as millimetres
    f1, f2 = first_two(real_data_dir / "icl_livingroom", preset="icl", depth_scale=1000.0)
    err = reproject_depth_error(f1.depth, f1.pose, f2.depth, f2.pose, f1.intrinsics)
    assert np.median(err) > 0.2


@pytest.mark.parametrize("prefix,preset,median", [("NYU", "nyu", 3.3), ("TUM", "tum", 2.4),
                                                  ("SUN", "sun", 2.7)])
def test_single_frames_units(real_data_dir, prefix, preset, median):
    folder = real_data_dir / "single_frames"
    color = next(folder.glob(f"{prefix}_color.*"))
    depth = next(folder.glob(f"{prefix}_depth.*"))
    f = formats.read_single(color, depth, preset)
    valid = f.depth[f.depth > 0]
    assert valid.size > 0.5 * f.depth.size
    assert abs(np.median(valid) - median) < 0.1 * median
    assert valid.max() <= 10.0 + 1e-6
    if preset == "tum":
        assert f.intrinsics.fx == 517.3


def test_depth_decoders_on_known_values():
    # NYU: big-endian disparity as OpenCV returns it (byte-swapped); 2047 = no measurement
    disp = np.array([[839, 1000, 2047]], dtype=np.uint16).byteswap()
    z = formats.nyu_disparity_to_metres(disp)
    np.testing.assert_allclose(z[0, :2], [351.3 / (1092.5 - 839), 351.3 / 92.5], rtol=1e-6)
    assert z[0, 2] == 0
    # SUN: stored value is the 16-bit rotation of depth in mm
    mm = np.array([[2700, 1, 0]], dtype=np.uint16)
    stored = (mm << np.uint16(3)) | (mm >> np.uint16(13))
    np.testing.assert_array_equal(formats.sun_rotated_to_raw(stored), mm)
    np.testing.assert_allclose(formats.decode_depth(stored, "sun_rotated", 1000.0)[0],
                               [2.7, 0.001, 0.0], rtol=1e-6)


def make_frames(n: int = 3, w: int = 32, h: int = 24, seed: int = 1,
                intr: Intrinsics | None = None) -> list[Frame]:
    rng = np.random.default_rng(seed)
    intr = intr or Intrinsics(30.5, 29.0, 15.25, 11.75, w, h)
    out = []
    for i in range(n):
        depth = (rng.integers(200, 9000, (h, w)) / 1000.0).astype(np.float32)
        depth[rng.random((h, w)) < 0.1] = 0.0
        out.append(Frame(1_600_000_000_000_000_000 + i * 50_000_123,
                         rng.integers(0, 256, (h, w, 3), dtype=np.uint8), depth,
                         look_at(rng.uniform(-3, 3, 3) + [0, 0, 1], rng.uniform(-1, 1, 3)),
                         intr, rng.integers(0, 14, (h, w)).astype(np.uint16),
                         rng.integers(0, 1000, (h, w)).astype(np.uint16)))
    return out


def assert_same(a: list[Frame], b: list[Frame], pose_atol: float = 0.0,
                gt: bool = True) -> None:
    assert len(a) == len(b)
    for fa, fb in zip(a, b):
        assert fa.stamp_ns == fb.stamp_ns and fa.intrinsics == fb.intrinsics
        np.testing.assert_array_equal(fa.rgb, fb.rgb)
        np.testing.assert_array_equal(fa.depth, fb.depth)
        np.testing.assert_allclose(fa.pose, fb.pose, rtol=0, atol=pose_atol)
        if gt:
            np.testing.assert_array_equal(fa.semantic, fb.semantic)
            np.testing.assert_array_equal(fa.instance, fb.instance)


def test_replica_round_trip_exact(tmp_path):
    frames = make_frames()
    assert formats.write_replica(tmp_path / "r", frames) == 3
    assert (tmp_path / "r/rgb/rgb_0.png").is_file()
    assert (tmp_path / "r/semantic_class/semantic_class_2.png").is_file()
    assert formats.detect_kind(tmp_path / "r") == "replica"
    got = list(read_folder(tmp_path / "r"))
    assert_same(frames, got)  # poses bit-exact through the text file
    # Replica ids remapped on read
    lut = np.arange(14, dtype=np.uint16)[::-1]
    remapped = list(read_folder(tmp_path / "r", id_map=lut))
    np.testing.assert_array_equal(remapped[0].semantic, 13 - frames[0].semantic)
    (tmp_path / "map.json").write_text(json.dumps({"3": 7, "5": 1}))
    by_file = next(read_folder(tmp_path / "r", id_map=tmp_path / "map.json"))
    # A folder of NYU-13 ids: the ids id_map does not list keep their meaning.
    want = np.select([frames[0].semantic == 3, frames[0].semantic == 5], [7, 1],
                     frames[0].semantic.astype(np.int64))
    np.testing.assert_array_equal(by_file.semantic, want)


def test_replica_default_camera_is_90_deg_hfov(tmp_path):
    intr = Intrinsics.from_hfov(32, 24, 90.0)
    frames = make_frames(2, intr=intr)
    for f in frames:
        f.semantic = f.instance = None
    formats.write_replica(tmp_path / "r", frames)
    assert not (tmp_path / "r/intrinsics.json").exists()
    assert not (tmp_path / "r/semantic_class").exists()
    (tmp_path / "r/timestamps.txt").unlink()  # Semantic-NeRF folders have no stamps
    got = list(read_folder(tmp_path / "r", fps=10.0, start_stamp_ns=5))
    assert got[0].intrinsics == intr and got[0].intrinsics.fx == pytest.approx(16.0)
    assert [g.stamp_ns for g in got] == [5, 5 + 100_000_000]
    assert got[0].semantic is None


def test_tum_round_trip(tmp_path):
    frames = make_frames()
    formats.write_tum(tmp_path / "t", frames)
    assert formats.detect_kind(tmp_path / "t") == "tum"
    i = frames[0].intrinsics
    got = list(read_folder(tmp_path / "t", intrinsics=[i.fx, i.fy, i.cx, i.cy]))
    assert_same(frames, got, pose_atol=1e-9, gt=False)
    # The camera goes with the folder (intrinsics.json; TUM has none of its own), so the
    # round trip needs no option; the /5000 depth scale is TUM's.
    assert_same(frames, list(read_folder(tmp_path / "t")), pose_atol=1e-9, gt=False)
    # Without it, the TUM fr1 preset's camera (640x480) is refused for these 32x24 images,
    # naming the option to set, rather than placing every point wrongly.
    (tmp_path / "t/intrinsics.json").unlink()
    with pytest.raises(FormatError, match=r"the 'tum' preset's camera \(fx 517.3, fy 516.5, "
                                          r"cx 318.6, cy 255.3\) does not fit these 32x24 "
                                          r"images .*--opt intrinsics="):
        next(read_folder(tmp_path / "t"))
    dflt = next(read_folder(tmp_path / "t", intrinsics=[i.fx, i.fy, i.cx, i.cy]))
    np.testing.assert_array_equal(dflt.depth, frames[0].depth)
    # association tolerance: dropping one depth leaves that colour frame without a partner
    lines = (tmp_path / "t/depth.txt").read_text().splitlines()
    (tmp_path / "t/depth.txt").write_text("\n".join(lines[:2] + lines[3:]) + "\n")
    got = list(read_folder(tmp_path / "t", kind="tum", intrinsics=[i.fx, i.fy, i.cx, i.cy],
                           max_time_diff_s=0.01))
    assert [g.stamp_ns for g in got] == [frames[0].stamp_ns, frames[2].stamp_ns]


def test_convert_folder_and_tf_bag(real_data_dir, tmp_path):
    src = real_data_dir / "kinect_dining"
    n = formats.convert(src, tmp_path / "k", max_frames=2, storage="sqlite3")
    assert n == 2
    want = list(read_folder(src, max_frames=2))
    assert_same(want, list(bag.FrameReader(tmp_path / "k")), pose_atol=1e-12, gt=False)
    # a bag whose pose is on /tf converts to a bag with the pose topic
    bag.write_bag(tmp_path / "tf", want, pose_mode="tf")
    assert formats.convert(tmp_path / "tf", tmp_path / "out", tf_parent="world",
                           tf_child="camera") == 2
    assert_same(want, list(bag.FrameReader(tmp_path / "out")), pose_atol=1e-12, gt=False)
    # bag -> Replica folder
    assert formats.convert(tmp_path / "out", tmp_path / "rep", to="replica") == 2
    assert_same(want, list(read_folder(tmp_path / "rep")), pose_atol=1e-12, gt=False)


def test_convert_reads_a_bag_with_the_configured_topics_and_sync(tmp_path):
    """A bag source is read with ``topics`` and ``sync`` (the configuration's, as info and
    run read it); --tf-parent / --tf-child replace sync's frames one by one; the output
    bag has the contract's default names."""
    from neurncd_ros.core.topics import Topics

    frames = make_frames(3)
    theirs = Topics(color="/rgb", depth="/d", camera_info="/info", tf="/tf2",
                    camera_frame="cam", world_frame="odom")
    bag.write_bag(tmp_path / "src", frames, topics=theirs, pose_mode="tf")
    with pytest.raises(bag.BagError, match="no color topic '/camera/color/image_raw'"):
        formats.convert(tmp_path / "src", tmp_path / "x", tf_parent="odom", tf_child="cam")
    sync = bag.SyncConfig(tf_parent="odom", tf_child="wrong")
    assert formats.bag_sync(sync, None, "cam") == bag.SyncConfig(tf_parent="odom",
                                                                 tf_child="cam")
    assert formats.bag_sync(None, None, None) == bag.SyncConfig()
    n = formats.convert(tmp_path / "src", tmp_path / "out", topics=theirs, sync=sync,
                        tf_child="cam")
    assert n == 3 and set(bag.bag_topics(tmp_path / "out")) == {
        getattr(Topics(), k) for k in ("color", "depth", "camera_info", "pose", "semantic",
                                       "instance")}
    assert_same(frames, list(bag.FrameReader(tmp_path / "out")), pose_atol=1e-12)


def test_bad_inputs_raise_clear_errors(real_data_dir, tmp_path):
    with pytest.raises(FormatError, match="no such file or folder"):
        list(read_folder(tmp_path / "absent"))
    with pytest.raises(FormatError, match="unknown folder kind"):
        read_folder(real_data_dir / "kinect_dining", kind="kitti")
    with pytest.raises(ConfigError, match="depth_scal"):
        read_folder(real_data_dir / "kinect_dining", depth_scal=1000.0)
    with pytest.raises(ConfigError, match="preset"):
        read_folder(real_data_dir / "kinect_dining", preset="nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FormatError, match="unknown layout"):
        read_folder(tmp_path / "empty")
    with pytest.raises(FormatError, match="intrinsics must be 4"):
        list(read_folder(real_data_dir / "kinect_dining", intrinsics=[1.0, 2.0]))
    with pytest.raises(FormatError, match="--tf-parent / --tf-child apply to a bag"):
        formats.convert(real_data_dir / "kinect_dining", tmp_path / "o.mcap", tf_parent="map",
                        tf_child="camera")
    assert not (tmp_path / "o.mcap").exists()
    # a broken pose file names the file and line
    formats.write_replica(tmp_path / "r", make_frames(2))
    traj = tmp_path / "r/traj_w_c.txt"
    traj.write_text(traj.read_text().replace(" ", " x", 1))
    with pytest.raises(FormatError, match="traj_w_c.txt:1"):
        list(read_folder(tmp_path / "r"))
    # mismatched colour / depth sizes in a folder
    formats.write_replica(tmp_path / "s", make_frames(1))
    small = formats.read_raw16(tmp_path / "s/depth/depth_0.png")[:10, :10]
    import cv2
    cv2.imwrite(str(tmp_path / "s/depth/depth_0.png"), small)
    with pytest.raises(FormatError, match="colour is 32x24 but depth is 10x10"):
        list(read_folder(tmp_path / "s"))
    # redwood json column-major is honoured
    cam = json.loads((real_data_dir / "redwood_livingroom/camera_primesense.json").read_text())
    assert cam["intrinsic_matrix"][6] == 319.5


def test_nyu_raw_sequence_as_tum(real_data_dir, tmp_path):
    """NYUv2 raw scene folder: r-<t>-<n>.ppm / d-<t>-<n>.pgm beside an offline trajectory."""
    import shutil
    src = real_data_dir / "single_frames"
    scene = tmp_path / "nyu"
    scene.mkdir()
    shutil.copy(src / "NYU_color.ppm", scene / "r-1294439283.377657-2863005480.ppm")
    shutil.copy(src / "NYU_depth.pgm", scene / "d-1294439283.384931-2863037524.pgm")
    (scene / "groundtruth.txt").write_text("1294439283.377 0.5 0 1 0 0 0 1\n")
    (f,) = list(read_folder(scene, preset="nyu"))
    assert f.stamp_ns == 1294439283_377657000
    assert f.intrinsics.fx == 518.86 and f.pose[0, 3] == 0.5
    assert abs(np.median(f.depth[f.depth > 0]) - 3.3) < 0.33
    # the depth_format alone selects the NYU file naming and disparity decoding
    (g,) = list(read_folder(scene, kind="tum", depth_format="nyu_disparity"))
    np.testing.assert_array_equal(g.depth, f.depth)


def test_pose_at_exact_interpolated_nearest():
    from neurncd_ros.core.camera import pose_from_tq
    a = pose_from_tq([0, 0, 0], [0, 0, 0, 1])
    b = pose_from_tq([2, 0, 0], [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])  # 90 deg about z
    times = np.array([100, 200], dtype=np.int64)
    assert sync.pose_at(times, [a, b], 200, 0) is b
    mid = sync.pose_at(times, [a, b], 150, 0, max_gap_ns=100)
    np.testing.assert_allclose(mid[:3, 3], [1, 0, 0], atol=1e-12)
    c = np.cos(np.pi / 4)
    np.testing.assert_allclose(mid[:2, :2], [[c, -c], [c, c]], atol=1e-12)
    assert sync.pose_at(times, [a, b], 190, 10) is b
    with pytest.raises(LookupError, match="within"):
        sync.pose_at(times, [a, b], 150, 10, max_gap_ns=99)
    with pytest.raises(LookupError, match="invalid sample: broken"):
        sync.pose_at(times, [a, "broken"], 201, 10)


def test_an_output_is_replaced_only_by_a_complete_one(tmp_path):
    """A conversion that fails leaves an existing output as it was and nothing beside it
    (a failed `convert --overwrite` deleted the old bag; a Replica folder was rewritten
    in place without --overwrite, and a failed one left empty folders)."""
    from neurncd_ros.core.data import bag

    frames = make_frames()
    bad = make_frames()
    bad[1].pose = None  # a frame the writers refuse, mid-stream
    for name, write, is_kind in (
            ("b.mcap", lambda p, fr, ow: bag.write_bag(p, fr, overwrite=ow), "metadata.yaml"),
            ("rep", lambda p, fr, ow: formats.write_replica(p, fr, overwrite=ow),
             "traj_w_c.txt"),
            ("tum", lambda p, fr, ow: formats.write_tum(p, fr, overwrite=ow), "rgb.txt")):
        out = tmp_path / name
        assert write(out, frames, False) == 3 and (out / is_kind).is_file()
        before = sorted(p.relative_to(out) for p in out.rglob("*"))
        with pytest.raises(ValueError, match="exists already; remove it, or overwrite it"):
            write(out, frames[:1], False)
        with pytest.raises(ValueError):
            write(out, bad, True)
        assert sorted(p.relative_to(out) for p in out.rglob("*")) == before, name
        assert sorted(x.name for x in tmp_path.iterdir() if x.name.startswith(".")) == []
        assert write(out, frames[:2], True) == 2  # a complete one replaces it
        fresh = tmp_path / f"new_{name}"
        with pytest.raises(ValueError):
            write(fresh, bad, False)
        assert not fresh.exists()
    (tmp_path / "mine").mkdir()
    with pytest.raises(ValueError, match="is not a Replica folder; not overwriting"):
        formats.write_replica(tmp_path / "mine", frames, overwrite=True)


def test_sun_depth_in_a_shared_layout_is_named_as_sun(real_data_dir, tmp_path):
    """A SUN RGB-D frame in slambook's color/ depth/ pose.txt layout, no preset: read as
    millimetres its rotated storage gives a 21 m room, and the check advised ICL-NUIM's
    1/5000 m (4.3 m, wrong) instead of SUN's own decoding (2.7 m)."""
    import shutil
    single = real_data_dir / "single_frames"
    for sub in ("color", "depth"):
        (tmp_path / sub).mkdir()
    shutil.copy(single / "SUN_color.jpg", tmp_path / "color" / "1.jpg")
    shutil.copy(single / "SUN_depth.png", tmp_path / "depth" / "1.png")
    (tmp_path / "pose.txt").write_text("0 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"multiples of 8.*2\.7 m.*preset=sun"):
        list(formats.read_posetxt(tmp_path))


def test_an_unknown_layout_with_rgb_and_depth_folders_names_kind_tum(tmp_path):
    """rgb/ and depth/ of timestamp-named files without rgb.txt read fine with --kind tum,
    but auto-detection said only 'unknown layout'."""
    (tmp_path / "rgb").mkdir()
    (tmp_path / "depth").mkdir()
    with pytest.raises(FormatError, match="unknown layout.*--kind tum"):
        formats.detect_kind(tmp_path)
    (tmp_path / "rgb").rmdir()
    with pytest.raises(FormatError, match=r"NYUv2 raw\)\)$"):
        formats.detect_kind(tmp_path)
