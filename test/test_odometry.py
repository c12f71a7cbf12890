"""RGB-D odometry: accuracy on synthetic and real sequences, loss, relocalisation, segments."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from neurncd_ros import synth
from neurncd_ros.core import odometry as odo_mod
from neurncd_ros.core.camera import Intrinsics, invert_pose
from neurncd_ros.core.data import bag, formats
from neurncd_ros.core.odometry import OdometryConfig, RGBDOdometry, with_odometry

REAL = Path(__file__).parent / "data" / "real"


@pytest.fixture(scope="module")
def walk() -> list:
    """40 frames (1.3 s) of a held-out tuning scene with realistic depth noise."""
    return list(synth.generate(500, 40, synth.SynthConfig()))


def _track_all(odo, frames):
    return [odo.track(f.stamp_ns, f.rgb, f.depth, f.intrinsics) for f in frames]


def _errors_cm(results, frames):
    return np.array([np.linalg.norm(r.pose[:3, 3] - f.pose[:3, 3]) * 100
                     for r, f in zip(results, frames) if r.pose is not None])


def test_synthetic_walk_is_tracked_within_a_centimetre(walk):
    odo = RGBDOdometry(OdometryConfig(), initial_pose=walk[0].pose)
    res = _track_all(odo, walk)
    assert [r.status for r in res] == ["ok"] * len(walk)
    err = _errors_cm(res, walk)
    path = sum(np.linalg.norm(b.pose[:3, 3] - a.pose[:3, 3]) for a, b in zip(walk, walk[1:]))
    assert path > 0.3  # the camera really moves (about 40 cm)
    assert err.max() < 1.5, err
    rot = max(odo_mod.rotation_deg(invert_pose(r.pose) @ f.pose) for r, f in zip(res, walk))
    assert rot < 1.0
    assert res[0].keyframe and sum(r.keyframe for r in res) >= 2
    assert all(r.fitness > 0.8 and r.inliers > 1000 for r in res)


def test_redwood_fixture_matches_its_ground_truth():
    frames = list(formats.read_folder(REAL / "redwood_livingroom"))
    odo = RGBDOdometry(OdometryConfig(), initial_pose=frames[0].pose)
    res = _track_all(odo, frames)
    assert all(r.status == "ok" for r in res)
    assert _errors_cm(res, frames).max() < 1.0


def test_mirrored_camera_with_negative_focal_length_gives_the_same_poses(walk):
    """ICL-NUIM's y-up images (fy < 0) are mirrored pixels of an ordinary camera."""
    frames = walk[:12]
    plain = _track_all(RGBDOdometry(), frames)
    odo = RGBDOdometry()
    flipped = []
    for f in frames:
        i = f.intrinsics
        intr = Intrinsics(i.fx, -i.fy, i.cx, i.height - 1 - i.cy, i.width, i.height)
        flipped.append(odo.track(f.stamp_ns, f.rgb[::-1].copy(), f.depth[::-1].copy(), intr))
    for a, b in zip(plain, flipped):
        assert b.status == "ok"
        assert np.abs(a.pose - b.pose).max() < 1e-6


def test_loss_is_reported_and_the_walk_is_relocalised(walk, caplog):
    cfg = OdometryConfig(new_segment_after=0)
    odo = RGBDOdometry(cfg, initial_pose=walk[0].pose)
    res = _track_all(odo, walk[:15])
    assert all(r.status == "ok" for r in res)
    # A covered lens: no depth, a black image. Tracking is lost, loudly.
    f = walk[15]
    black = odo.track(f.stamp_ns, np.zeros_like(f.rgb), np.zeros_like(f.depth), f.intrinsics)
    assert black.status == "lost" and black.pose is None and "lost" in black.reason
    assert any("lost" in rec.message for rec in caplog.records)
    # Another room entirely (a different seed): still lost, never a made-up pose.
    other = next(iter(synth.generate(2001, 1, synth.SynthConfig())))
    r = odo.track(f.stamp_ns + 1, other.rgb, other.depth, other.intrinsics)
    assert r.status == "lost" and r.pose is None
    # The lens uncovered: relocalised against a stored keyframe, pose right again.
    back = _track_all(odo, walk[16:])
    assert back[0].status == "relocalised" and "keyframe" in back[0].reason
    assert all(r.status == "ok" for r in back[1:])
    assert _errors_cm(back, walk[16:]).max() < 2.0
    assert odo.counts["lost"] == 2 and odo.counts["relocalised"] == 1


def test_a_long_loss_starts_a_new_segment_on_a_frame_with_depth(walk):
    """Lost for new_segment_after frames: a new segment starts, but not on a frame
    without depth (a keyframe with no points would lose every frame after it)."""
    odo = RGBDOdometry(OdometryConfig(new_segment_after=3), initial_pose=walk[0].pose)
    _track_all(odo, walk[:5])
    f = walk[5]
    dark = [odo.track(f.stamp_ns + k, np.zeros_like(f.rgb), np.zeros_like(f.depth),
                      f.intrinsics) for k in range(4)]
    assert [r.status for r in dark] == ["lost"] * 4 and odo.segment == 0
    assert "no new segment yet" in dark[3].reason and "min_inliers" in dark[3].reason
    # Then another room: a new segment there, tracked on from its first frame.
    room = list(synth.generate(2001, 4, synth.SynthConfig()))
    res = [odo.track(f.stamp_ns + 10 + k, r.rgb, r.depth, r.intrinsics)
           for k, r in enumerate(room)]
    assert res[0].status == "new_segment" and res[0].segment == 1 and res[0].keyframe
    assert [r.status for r in res[1:]] == ["ok"] * 3 and odo.segment == 1
    rel = [invert_pose(res[0].pose) @ r.pose for r in res]
    true = [invert_pose(room[0].pose) @ r.pose for r in room]
    assert max(np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in zip(rel, true)) < 0.015


def test_tracking_does_not_start_on_a_frame_without_depth(walk):
    odo = RGBDOdometry()
    f = walk[0]
    r = odo.track(f.stamp_ns, f.rgb, np.zeros_like(f.depth), f.intrinsics)
    assert r.status == "lost" and r.pose is None and "no tracking started" in r.reason
    r = odo.track(walk[1].stamp_ns, walk[1].rgb, walk[1].depth, walk[1].intrinsics)
    assert r.status == "ok" and r.keyframe and np.allclose(r.pose, np.eye(4))


def test_jump_is_refused(walk):
    """A frame far along the path is not accepted as the next step."""
    cfg = OdometryConfig(new_segment_after=0, max_step_m=0.05, features=0)
    odo = RGBDOdometry(cfg, initial_pose=walk[0].pose)
    _track_all(odo, walk[:3])
    r = odo.track(walk[39].stamp_ns, walk[39].rgb, walk[39].depth, walk[39].intrinsics)
    assert r.status == "lost" and r.pose is None
    assert "jump" in r.reason or "fitness" in r.reason or "converge" in r.reason


def test_camera_change_and_reset(walk):
    odo = RGBDOdometry()
    _track_all(odo, walk[:3])
    f = walk[3]
    small = f.intrinsics.scaled(160, 120)
    import cv2
    r = odo.track(f.stamp_ns, cv2.resize(f.rgb, (160, 120)),
                  cv2.resize(f.depth, (160, 120), interpolation=cv2.INTER_NEAREST), small)
    assert r.status == "new_segment" and "camera changed" in r.reason
    odo.reset()
    assert odo.segment == -1 and not odo.keyframes
    r = odo.track(f.stamp_ns, f.rgb, f.depth, f.intrinsics)
    assert r.status == "ok" and np.allclose(r.pose, np.eye(4))


def test_bad_input_is_refused_by_name(walk):
    odo = RGBDOdometry()
    f = walk[0]
    with pytest.raises(ValueError, match="rgb must be"):
        odo.track(0, f.rgb[..., 0], f.depth, f.intrinsics)
    with pytest.raises(ValueError, match="depth must be"):
        odo.track(0, f.rgb, f.depth[:10], f.intrinsics)
    with pytest.raises(ValueError, match="intrinsics are"):
        odo.track(0, f.rgb, f.depth, f.intrinsics.scaled(160, 120))
    with pytest.raises(ValueError, match="min_depth"):
        RGBDOdometry(OdometryConfig(min_depth=5.0, max_depth=4.0))


def test_with_odometry_replaces_the_poses(walk):
    stripped = [dataclasses.replace(f, pose=None) for f in walk[:10]]
    results: list = []
    out = list(with_odometry(stripped, OdometryConfig(), results,
                             initial_pose=walk[0].pose))
    assert len(out) == 10 and len(results) == 10
    assert all(o.pose is not None for o in out)
    assert _errors_cm(results, walk[:10]).max() < 1.5


def test_convert_writes_poses_into_a_bag_that_has_none(walk, tmp_path):
    """A bag without /camera/pose cannot be read as it is, and converts with odometry."""
    items = [it for f in walk[:12] for it in bag.frame_messages(f)
             if it[1] != bag.POSE_STAMPED]
    src = tmp_path / "nopose.mcap"
    bag.write_messages(src, items)
    with pytest.raises(bag.BagError, match="no pose topic"):
        bag.FrameReader(src)
    report: dict = {}
    out = tmp_path / "posed.mcap"
    n = formats.convert(src, out, poses="odometry", report=report)
    assert n == 12 and report == {"frames_in": 12, "lost": 0, "relocalised": 0,
                                  "segments": 1}
    back = list(bag.FrameReader(out))
    assert len(back) == 12 and np.allclose(back[0].pose, np.eye(4))
    # Poses relative to the first frame match the true relative motion.
    T0 = walk[0].pose
    for f, b in zip(walk[:12], back):
        rel = invert_pose(T0) @ f.pose
        assert np.linalg.norm(rel[:3, 3] - b.pose[:3, 3]) < 0.015
    with pytest.raises(formats.FormatError, match="poses must be"):
        formats.convert(src, tmp_path / "x.mcap", poses="guess")


def test_cli_convert_poses_odometry(walk, tmp_path, capsys):
    from neurncd_ros import cli

    items = [it for f in walk[:6] for it in bag.frame_messages(f)
             if it[1] != bag.POSE_STAMPED]
    src = tmp_path / "nopose.mcap"
    bag.write_messages(src, items)
    assert cli.main(["convert", str(src), "--out", str(tmp_path / "o.mcap"),
                     "--poses", "odometry"]) == 0
    text = capsys.readouterr().out
    assert "6 frames tracked, 0 lost" in text
    assert len(list(bag.FrameReader(tmp_path / "o.mcap"))) == 6


def test_icl_fixture_wide_baselines_are_reported_and_the_overlapping_pair_tracks():
    """ICL-NUIM's five frames turn 49, 91, 79 and 20 degrees between neighbours (two
    pairs share no view at all): those are losses, said so, and the last pair
    (20 degrees, 25 cm) is tracked. The default step limits are part of the test: read
    with OpenCV axes (fy > 0), the 79 degree pair is matched about 90 degrees wrong,
    a step those limits refuse."""
    frames = list(formats.read_folder(REAL / "icl_livingroom", "posetxt", preset="icl"))
    cfg = OdometryConfig(new_segment_after=1)
    odo = RGBDOdometry(cfg)
    res = _track_all(odo, frames)
    assert [r.status for r in res] == ["ok", "new_segment", "new_segment", "new_segment",
                                       "ok"]
    assert all("lost" in r.reason for r in res[1:4])
    assert res[4].segment == res[3].segment == 3
    est = invert_pose(res[3].pose) @ res[4].pose
    true = invert_pose(frames[3].pose) @ frames[4].pose
    assert np.linalg.norm(est[:3, 3] - true[:3, 3]) < 0.10
    assert odo_mod.rotation_deg(invert_pose(true) @ est) < 3.0


def _tum_folder_without_poses(dst: Path) -> Path:
    """The Redwood fixture's images in the TUM layout (rgb.txt, depth.txt), no groundtruth.txt."""
    import shutil

    src = REAL / "redwood_livingroom"
    for sub in ("rgb", "depth"):
        (dst / sub).mkdir(parents=True)
    lines = {"rgb": ["# colour"], "depth": ["# depth"]}
    for i, (c, d) in enumerate(zip(sorted((src / "color").iterdir()),
                                   sorted((src / "depth").iterdir()))):
        t = f"{1.0 + i / 30:.6f}"
        shutil.copy(c, dst / "rgb" / f"{t}.jpg")
        shutil.copy(d, dst / "depth" / f"{t}.png")
        lines["rgb"].append(f"{t} rgb/{t}.jpg")
        lines["depth"].append(f"{t} depth/{t}.png")
    for sub, text in lines.items():
        (dst / f"{sub}.txt").write_text("\n".join(text) + "\n")
    return dst


def test_cli_convert_of_a_folder_without_poses_fails_cleanly_then_converts(tmp_path, capsys):
    """A TUM folder without a trajectory: plain convert says what to do and leaves no
    half-written bag, so the suggested command then works on the same --out; the poses
    match the Redwood trajectory."""
    from neurncd_ros import cli

    src = _tum_folder_without_poses(tmp_path / "tum")
    out = tmp_path / "posed.mcap"
    opts = ["--opt", "depth_scale=1000", "--opt", "intrinsics=[525, 525, 319.5, 239.5]"]
    assert cli.main(["convert", str(src), "--out", str(out), *opts]) == 1
    assert "convert --poses odometry" in capsys.readouterr().err
    assert not out.exists()
    assert cli.main(["convert", str(src), "--out", str(out), "--poses", "odometry",
                     *opts]) == 0
    assert "5 frames tracked, 0 lost" in capsys.readouterr().out
    assert cli.main(["convert", str(src), "--out", str(out), "--poses", "odometry",
                     *opts]) == 1
    assert "--overwrite" in capsys.readouterr().err
    assert cli.main(["convert", str(src), "--out", str(out), "--poses", "odometry",
                     "--overwrite", *opts]) == 0
    got = list(bag.FrameReader(out))
    truth = list(formats.read_folder(REAL / "redwood_livingroom"))
    assert len(got) == 5
    for g, t in zip(got, truth):
        rel = invert_pose(truth[0].pose) @ t.pose
        assert np.linalg.norm(rel[:3, 3] - g.pose[:3, 3]) < 0.01
