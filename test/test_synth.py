"""Synthetic RGB-D generator: geometry, labels, determinism, sensor noise, config checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from neurncd_ros.core.camera import backproject, project, reproject_depth_error
from neurncd_ros.core.classes import CLASS_ID, NUM_CLASSES
from neurncd_ros.synth.generator import (SynthConfig, frames_at, generate, intrinsics_of,
                                         room_of, trajectory)
from neurncd_ros.synth.render import (DISPARITY_STEP, KINECT_BASELINE, KINECT_FX,
                                                SceneArrays, kinect_depth, point_clearance)
from neurncd_ros.synth.scene import BOX, CYL
from neurncd_ros.core.params import build

torch.set_num_threads(1)

SMALL = dict(width=96, height=72)


def _frames(seed: int, n: int, **kw) -> list:
    return list(generate(seed, n, SynthConfig(**{**SMALL, **kw})))


def _depth_edges(depth: np.ndarray) -> np.ndarray:
    """Depth discontinuities (far above what a plane gives), dilated by 2 pixels."""
    lap = np.abs(ndimage.laplace(depth.astype(np.float64)))
    return ndimage.binary_dilation(lap > 0.01 * depth, iterations=2)


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - u0, v - v0
    D = img.astype(np.float64)
    return (D[v0, u0] * (1 - fu) * (1 - fv) + D[v0, u0 + 1] * fu * (1 - fv)
            + D[v0 + 1, u0] * (1 - fu) * fv + D[v0 + 1, u0 + 1] * fu * fv)


# ------------------------------------------------------------------ config

def test_default_intrinsics_are_replica_like():
    cfg = SynthConfig()
    intr = intrinsics_of(cfg)
    assert (cfg.width, cfg.height, cfg.fps, cfg.depth_noise) == (320, 240, 30.0, "realistic")
    assert intr.fx == pytest.approx(160.0) and intr.fy == pytest.approx(160.0)
    kin = intrinsics_of(SynthConfig(camera="kinect"))
    # 58 deg horizontal fov at 640x480 (fx ~ 577) scaled to 320x240
    assert kin.fx == pytest.approx(320 / math.tan(math.radians(29)) / 2, rel=1e-6)
    assert (kin.width, kin.height) == (320, 240)


@pytest.mark.parametrize("bad", [
    dict(width=0), dict(height=-3), dict(camera="pinhole"), dict(depth_noise="gauss"),
    dict(fps=0.0), dict(hfov_deg=200.0), dict(rgb_noise_std=-1.0), dict(dropout=1.5),
    dict(cam_height_min=1.9, cam_height_max=1.3), dict(room_size_min=6.0, room_size_max=4.0),
    dict(clearance=0.1), dict(width=1.5), dict(speed=float("nan")),
    dict(cam_height_max=2.3, clearance=0.5),
])
def test_bad_config_values_raise(bad):
    with pytest.raises(ValueError) as err:
        SynthConfig(**bad)
    assert any(k in str(err.value) for k in bad)


def test_config_builds_from_dict_and_rejects_unknown_keys():
    cfg = build(SynthConfig, {"width": 64, "height": 48, "camera": "kinect"})
    assert (cfg.width, cfg.camera) == (64, "kinect")
    with pytest.raises(ValueError, match="colour_depth"):
        build(SynthConfig, {"colour_depth": 8})


@pytest.mark.parametrize("seed,frames,cfg", [(-1, 2, None), (1.5, 2, None), (0, -2, None),
                                              (0, 2.0, None), (0, 2, {"width": 64})])
def test_bad_arguments_raise(seed, frames, cfg):
    with pytest.raises(ValueError):
        generate(seed, frames, cfg)


# ------------------------------------------------------------------ frames

def test_frames_follow_the_contract():
    cfg = SynthConfig(**SMALL, fps=15.0, start_ns=5_000)
    frames = list(generate(2, 4, cfg))
    assert len(frames) == 4
    for i, f in enumerate(frames):
        f.validate()
        assert f.stamp_ns == 5_000 + round(i * 1e9 / 15.0)
        assert f.rgb.shape == (72, 96, 3) and f.depth.dtype == np.float32
        assert f.semantic.dtype == np.uint16 and f.instance.dtype == np.uint16
        assert f.semantic.max() <= NUM_CLASSES
        assert f.intrinsics == intrinsics_of(cfg)
    # The room is closed: every exact ray hits something labelled.
    exact = _frames(2, 2, depth_noise="none")
    assert all((f.semantic > 0).all() and (f.instance > 0).all() for f in exact)
    assert all((f.depth > 0).all() for f in exact)


def test_same_seed_same_arrays_and_prefix_runs_match():
    a = _frames(7, 3)
    b = _frames(7, 5)
    for fa, fb in zip(a, b[:3]):
        for name in ("rgb", "depth", "pose", "semantic", "instance"):
            np.testing.assert_array_equal(getattr(fa, name), getattr(fb, name))
        assert fa.stamp_ns == fb.stamp_ns


def test_frames_at_matches_the_full_walk():
    cfg = SynthConfig(**SMALL)
    walk = list(generate(4, 6, cfg))
    picked = list(frames_at(4, [5, 2], cfg))
    for f, i in zip(picked, (5, 2)):
        np.testing.assert_array_equal(f.rgb, walk[i].rgb)
        np.testing.assert_array_equal(f.depth, walk[i].depth)
        assert f.stamp_ns == walk[i].stamp_ns
    with pytest.raises(ValueError):
        list(frames_at(4, [-1], cfg))


def test_different_seeds_give_different_rooms_and_frames():
    a, b = _frames(1, 1)[0], _frames(2, 1)[0]
    assert not np.array_equal(a.rgb, b.rgb)
    assert not np.allclose(a.pose, b.pose)
    assert room_of(1).size != room_of(2).size


# ------------------------------------------------------------------ rooms

def _obb_intersect(p, q, shrink: float = 0.003) -> bool:
    """Separating-axis test of two yaw-rotated boxes (cylinders as their square)."""
    if p.centre[2] + p.half[2] - shrink <= q.centre[2] - q.half[2] + shrink or \
            q.centre[2] + q.half[2] - shrink <= p.centre[2] - p.half[2] + shrink:
        return False
    def axes(r):
        yaw = 0.0 if r.kind == CYL else r.yaw           # a cylinder's square is its AABB
        c, s = math.cos(yaw), math.sin(yaw)
        return [np.array([c, s]), np.array([-s, c])]

    def radius(r, ax):
        e = axes(r)
        return abs(e[0] @ ax) * (r.half[0] - shrink) + abs(e[1] @ ax) * (r.half[1] - shrink)
    d = np.array(q.centre[:2]) - np.array(p.centre[:2])
    for ax in axes(p) + axes(q):
        if abs(d @ ax) >= radius(p, ax) + radius(q, ax):
            return False
    return True


def test_rooms_are_in_range_and_hold_every_class():
    cfg = SynthConfig()
    full = 0
    seen = set()
    for seed in range(20):
        room = room_of(seed, cfg)
        W, D, H = room.size
        assert 3.0 <= W <= 8.0 and 3.0 <= D <= 8.0 and 2.4 <= H <= 3.2
        box = room.aabbs()
        assert (box[:, 0] >= -1e-6).all() and (box[:, 1] <= np.array(room.size) + 1e-6).all()
        classes = room.classes()
        seen |= classes
        full += classes == set(range(1, NUM_CLASSES + 1))
        counts = {c: sum(1 for v in room.instances.values() if v == c) for c in classes}
        assert counts.get(CLASS_ID["books"], 0) >= 3, f"seed {seed}: too few books"
    assert seen == set(range(1, NUM_CLASSES + 1))
    assert full >= 18, f"only {full}/20 rooms hold all 13 classes"


@pytest.mark.parametrize("seed", range(8))
def test_parts_of_different_instances_do_not_interpenetrate(seed):
    room = room_of(seed)
    parts = room.parts
    bad = [(p.inst, q.inst) for i, p in enumerate(parts) for q in parts[i + 1:]
           if p.inst != q.inst and _obb_intersect(p, q)]
    assert not bad, f"seed {seed}: interpenetrating instances {bad[:5]}"


def test_every_class_is_seen_across_20_seeds():
    # Low frame rate: a few frames sweep a long part of each walk.
    cfg = SynthConfig(width=64, height=48, fps=1.0, depth_noise="none", rgb_noise_std=0.0)
    seen = set()
    for seed in range(20):
        for f in generate(seed, 6, cfg):
            seen |= set(np.unique(f.semantic).tolist())
    assert seen == set(range(1, NUM_CLASSES + 1))


# ------------------------------------------------------------------ geometry

def test_noise_free_depth_reprojects_within_a_millimetre():
    """Exact depth of frame a, moved into frame b, meets frame b's depth.

    Compared at the exact (sub-pixel, bilinear) landing position and away from
    depth edges: median and 90th percentile < 1 mm (a few landings next to
    occlusions stay off, so not the max). ``reproject_depth_error`` looks up the
    nearest pixel, which on slanted surfaces is off by up to half a pixel's depth
    change (cm at 160x120), so it is bounded by that change plus 1 mm instead.
    """
    cfg = SynthConfig(width=160, height=120, depth_noise="none", rgb_noise_std=0.0)
    W, H = cfg.width, cfg.height
    for seed in (2, 8):
        frames = list(generate(seed, 3, cfg))
        for fa, fb in ((frames[0], frames[1]), (frames[0], frames[2])):
            ea, eb = _depth_edges(fa.depth), _depth_edges(fb.depth)
            da = np.where(ea, 0.0, fa.depth).astype(np.float32)
            pts, _ = backproject(da, fa.intrinsics, fa.pose)
            u, v, z = project(pts, fa.intrinsics, fb.pose)
            ok = (u >= 0) & (v >= 0) & (u < W - 1) & (v < H - 1) & (z > 0)
            u, v, z = u[ok], v[ok], z[ok]
            clear = _bilinear(eb.astype(np.float64), u, v) == 0
            assert clear.sum() > 3000
            err = np.abs(_bilinear(fb.depth, u, v) - z)[clear]
            assert np.median(err) < 1e-3 and np.percentile(err, 90) < 1e-3
            db = np.where(eb, 0.0, fb.depth).astype(np.float32)
            near = reproject_depth_error(da, fa.pose, db, fb.pose, fa.intrinsics)
            gy, gx = np.gradient(fb.depth.astype(np.float64))
            half_px = 0.5 * (np.abs(gx) + np.abs(gy))[~eb]
            assert np.median(near) < np.median(half_px) + 1e-3


def test_backprojected_depth_lies_on_the_scene_boxes():
    seed = 4
    cfg = SynthConfig(**SMALL, depth_noise="none")
    f = next(iter(generate(seed, 1, cfg)))
    sa = SceneArrays.from_scene(room_of(seed, cfg))
    pts, m = backproject(f.depth, f.intrinsics, f.pose)
    dist = np.abs(point_clearance(sa, pts))
    # Points on cylinders are off their bounding boxes; all others sit on a surface.
    assert np.median(dist) < 1e-5 and np.mean(dist < 1e-4) > 0.8
    assert (sa.kind == BOX).mean() > 0.5


def test_label_edges_are_instance_edges_and_instances_have_one_class():
    for seed in (6, 9):
        cls_of: dict[int, set] = {}
        for f in _frames(seed, 3, depth_noise="none"):
            for axis in (0, 1):
                sem_edge = np.diff(f.semantic.astype(np.int32), axis=axis) != 0
                inst_edge = np.diff(f.instance.astype(np.int32), axis=axis) != 0
                assert sem_edge.any()
                assert not (sem_edge & ~inst_edge).any()
            pairs = np.unique(np.stack([f.instance.ravel(), f.semantic.ravel()]), axis=1)
            for i, c in pairs.T.tolist():
                cls_of.setdefault(i, set()).add(c)
        assert all(len(c) == 1 for c in cls_of.values())
        room = room_of(seed)
        assert all(room.instances[i] == c.pop() for i, c in cls_of.items())


def test_colour_of_a_surface_point_is_the_same_from_every_view():
    """Textures live on 3D surfaces and shading is Lambertian: a surface point keeps
    its colour between views (windows show the outside by direction, so not them)."""
    cfg = SynthConfig(width=160, height=120, depth_noise="none", rgb_noise_std=0.0)
    fa, _, fb = list(generate(8, 3, cfg))
    keep = ~_depth_edges(fa.depth) & (fa.semantic != CLASS_ID["window"])
    da = np.where(keep, fa.depth, 0).astype(np.float32)
    pts, m = backproject(da, fa.intrinsics, fa.pose)
    u, v, z = project(pts, fa.intrinsics, fb.pose)
    ok = (u >= 0) & (v >= 0) & (u < 159) & (v < 119) & (z > 0)
    ok[ok] &= ~_depth_edges(fb.depth)[np.round(v[ok]).astype(int), np.round(u[ok]).astype(int)]
    assert ok.sum() > 1000
    ca = fa.rgb[m][ok].astype(np.float64)
    cb = np.stack([_bilinear(fb.rgb[..., k], u[ok], v[ok]) for k in range(3)], -1)
    diff = np.abs(ca - cb).mean(1)
    # control: the same pixels one row down in frame b differ much more often
    shifted = np.stack([_bilinear(fb.rgb[..., k], u[ok], np.minimum(v[ok] + 3, 118))
                        for k in range(3)], -1)
    assert np.median(diff) < 1.5
    assert np.median(diff) < 0.5 * np.median(np.abs(ca - shifted).mean(1))


def test_camera_stays_clear_of_geometry():
    for seed in (0, 10, 13):
        cfg = SynthConfig(**SMALL, depth_noise="none")
        room = room_of(seed, cfg)
        sa = SceneArrays.from_scene(room)
        poses = trajectory(seed, 600, cfg, room, sa)
        assert point_clearance(sa, poses[:, :3, 3]).min() >= cfg.clearance - 0.02
        assert (poses[:, 2, 3] >= cfg.cam_height_min - 0.05).all()
        steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
        assert steps.max() < 3 * cfg.speed / cfg.fps          # smooth, no jumps
        fwd = poses[:, :3, 2]
        turn = np.degrees(np.arccos(np.clip((fwd[1:] * fwd[:-1]).sum(1), -1, 1)))
        assert turn.max() < 5.0                                # < 150 deg/s
        for f in generate(seed, 3, cfg):
            assert f.depth.min() > 0.2


# ------------------------------------------------------------------ sensor model

def test_realistic_depth_has_noise_holes_and_quantisation_and_none_has_none():
    clean = _frames(3, 2, depth_noise="none", width=160, height=120)
    noisy = _frames(3, 2, depth_noise="realistic", width=160, height=120)
    for c, n in zip(clean, noisy):
        np.testing.assert_array_equal(c.semantic, n.semantic)
        assert (c.depth > 0).all()
        holes = n.depth == 0
        assert 0.005 < holes.mean() < 0.35
        valid = ~holes
        err = n.depth[valid] - c.depth[valid]
        z = c.depth[valid]
        assert np.abs(err).max() < 0.3
        near, far = np.abs(err[z < 1.5]), np.abs(err[z > 3.0])
        if len(near) > 50 and len(far) > 50:
            assert far.mean() > 2 * near.mean()
        # millimetre steps
        mm = n.depth[valid].astype(np.float64) * 1000
        assert np.abs(mm - np.round(mm)).max() < 1e-2
        # holes crowd at depth edges
        gy, gx = np.gradient(c.depth)
        edge = ndimage.binary_dilation(np.hypot(gx, gy) > 0.05 * c.depth, iterations=2)
        assert holes[edge].mean() > 3 * holes[~edge].mean()


@pytest.mark.parametrize("z", [0.8, 1.5, 2.5, 3.5])
def test_kinect_noise_follows_the_axial_model(z):
    """Flat wall at z: spread = Gaussian sigma(z) and disparity quantisation, unbiased."""
    rng = np.random.default_rng(0)
    depth = np.full((120, 160), z)
    out = kinect_depth(depth, np.ones_like(depth), rng, dropout=0.0, grazing_cos=0.12)
    assert (out > 0).all()
    err = out.astype(np.float64) - z
    sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
    step = z ** 2 / (KINECT_FX * KINECT_BASELINE) * DISPARITY_STEP
    expected = math.sqrt(sigma ** 2 + step ** 2 / 12 + 0.001 ** 2 / 12)
    assert 0.75 * expected < err.std() < 1.3 * expected
    assert abs(err.mean()) < 0.2 * expected + 2e-4
    # grazing views and random dropouts make holes
    graze = kinect_depth(depth, np.full_like(depth, 0.05), rng, dropout=0.0, grazing_cos=0.12)
    assert (graze == 0).mean() > 0.9
    drop = kinect_depth(depth, np.ones_like(depth), rng, dropout=0.1, grazing_cos=0.12)
    assert 0.08 < (drop == 0).mean() < 0.12


def test_max_depth_cuts_far_returns():
    f = _frames(2, 1, depth_noise="none", max_depth=2.0)[0]
    assert f.depth.max() <= 2.0 and (f.depth == 0).any()


def test_rgb_noise_is_applied_and_seeded():
    a = _frames(1, 1, rgb_noise_std=0.0)[0].rgb.astype(int)
    b = _frames(1, 1, rgb_noise_std=4.0)[0].rgb.astype(int)
    d = (b - a)[(a > 20) & (a < 235)]
    assert 2.5 < d.std() < 5.5


@pytest.mark.slow
def test_a_default_300_frame_walk_is_valid_and_covers_the_room():
    cfg = SynthConfig()
    seen, prev, path = set(), None, 0.0
    for f in generate(11, 300, cfg):
        f.validate()
        valid = f.depth > 0
        assert f.depth[valid].min() > 0.2 and valid.mean() > 0.6
        seen |= set(np.unique(f.semantic).tolist())
        if prev is not None:
            path += float(np.linalg.norm(f.pose[:3, 3] - prev))
        prev = f.pose[:3, 3]
    assert len(seen) >= 9
    assert 0.6 * cfg.speed * 10 < path < 1.4 * cfg.speed * 10
