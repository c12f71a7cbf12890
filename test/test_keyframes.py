"""Keyframe buffer: admission, bounded size under a long stream, eviction, sampling, threads."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from neurncd_ros.core.camera import Intrinsics, look_at, pose_distance, project
from neurncd_ros.core.field.keyframes import KeyframeBuffer, KeyframeConfig
from neurncd_ros.core.frame import Frame

INTR = Intrinsics.from_hfov(16, 12, 90.0)


def _frame(pose: np.ndarray, stamp_ns: int, depth: float = 2.0) -> Frame:
    rng = np.random.default_rng(stamp_ns % 1000)
    rgb = rng.integers(0, 255, (12, 16, 3), dtype=np.uint8)
    return Frame(stamp_ns, rgb, np.full((12, 16), depth, np.float32), pose, INTR)


def _walk(i: int) -> np.ndarray:
    """A camera walking around a 2 m radius circle, 1 cm per frame, facing the centre."""
    a = 0.005 * i
    eye = np.array([2.0 * np.cos(a), 2.0 * np.sin(a), 1.5])
    return look_at(eye, np.array([0.0, 0.0, 1.0]))


def test_bounded_over_long_stream_and_first_kept():
    cfg = KeyframeConfig(max_keyframes=12, min_translation=0.1, min_rotation=10.0,
                         max_interval=0.0)
    buf = KeyframeBuffer(cfg)
    emb = np.zeros((6, 8, 4), np.float32)
    admitted = 0
    for i in range(10_000):
        admitted += buf.add(_frame(_walk(i), i * 33_000_000), emb)
        assert len(buf) <= cfg.max_keyframes
    kfs = buf.keyframes()
    assert len(kfs) == cfg.max_keyframes
    # 1 cm per frame, a keyframe each 0.1 m (chord) or 10 deg: about every 11th frame.
    assert 800 < admitted < 1100
    assert buf.admitted == admitted and buf.evicted == admitted - cfg.max_keyframes
    assert kfs[0].id == 0  # the first keyframe is protected
    assert kfs[-1].stamp_ns == max(k.stamp_ns for k in kfs)
    # Eviction by redundancy keeps the views spread out: no two kept keyframes
    # closer than the admission thresholds allow.
    gaps = [pose_distance(a.pose, b.pose)[0] for j, a in enumerate(kfs) for b in kfs[j + 1:]]
    assert min(gaps) >= 0.09


def test_admission_by_motion_and_time():
    cfg = KeyframeConfig(min_translation=0.2, min_rotation=15.0, max_interval=1.0)
    buf = KeyframeBuffer(cfg)
    emb = np.zeros((12, 16, 3), np.float32)
    pose = look_at(np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 1.0]))
    assert buf.add(_frame(pose, 0), emb)  # first frame always
    assert not buf.add(_frame(pose, 100_000_000), emb)  # no motion, 0.1 s
    moved = pose.copy()
    moved[:3, 3] += [0.0, 0.25, 0.0]
    assert buf.add(_frame(moved, 200_000_000), emb)  # 0.25 m
    turned = moved.copy()
    c, s = np.cos(np.radians(20)), np.sin(np.radians(20))
    turned[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ moved[:3, :3]
    assert buf.add(_frame(turned, 300_000_000), emb)  # 20 deg
    assert not buf.add(_frame(turned, 1_200_000_000), emb)  # 0.9 s
    assert buf.add(_frame(turned, 1_400_000_000), emb)  # 1.1 s since last keyframe
    assert len(buf) == 4


def test_bad_embedding_rejected():
    buf = KeyframeBuffer()
    f = _frame(_walk(0), 0)
    with pytest.raises(ValueError, match="embedding"):
        buf.add(f, np.zeros((12, 16), np.float32))
    with pytest.raises(ValueError, match="at most"):
        buf.add(f, np.zeros((24, 32, 3), np.float32))
    with pytest.raises(ValueError, match="non-finite"):
        buf.add(f, np.full((12, 16, 3), np.nan, np.float32))


def test_rays_hit_measured_depth_and_lookup_low_res_embedding():
    buf = KeyframeBuffer(KeyframeConfig(min_translation=0.01, holdout_stride=2))
    pose = _walk(0)
    f = _frame(pose, 0, depth=2.5)
    # Embedding at half resolution whose channel 0 holds the coarse column index.
    emb = np.zeros((6, 8, 2), np.float32)
    emb[..., 0] = np.arange(8)[None, :]
    buf.add(f, emb)
    rays = buf.sample_rays(500, np.random.default_rng(0))
    pts = rays["origins"] + rays["dirs"] * rays["depth"][:, None]
    u, v, z = project(pts, INTR, pose)
    assert np.allclose(z, 2.5, atol=1e-6)
    ui, vi = np.round(u).astype(int), np.round(v).astype(int)
    assert np.allclose(u, ui, atol=1e-6)
    assert np.all(rays["embedding"][:, 0] == ui // 2)  # same image area at half resolution
    assert np.allclose(rays["rgb"], f.rgb[vi, ui] / 255.0)
    assert not np.any((ui % 2 == 0) & (vi % 2 == 0))  # held-out pixels never drawn


def test_recent_bias_and_ready_once():
    cfg = KeyframeConfig(min_translation=0.01, recent_bias=0.5, recent_window=1,
                         max_keyframes=10)
    buf = KeyframeBuffer(cfg)
    for i in range(5):
        buf.add(_frame(_walk(10 * i), i), np.zeros((12, 16, 2), np.float32))
    p = buf.keyframe_weights()
    assert np.isclose(p.sum(), 1.0) and np.isclose(p[-1], 0.5 + 0.5 / 5)
    rays = buf.sample_rays(4000, np.random.default_rng(1))
    newest = np.isclose(rays["origins"], buf.keyframes()[-1].pose[:3, 3]).all(axis=1)
    assert abs(newest.mean() - p[-1]) < 0.03
    buf.tick(3)
    buf.add(_frame(_walk(100), 9), np.zeros((12, 16, 2), np.float32))
    ready = buf.ready(3)
    assert [k.id for k in ready] == [0, 1, 2, 3, 4]
    assert buf.ready(3) == []
    buf.tick(3)
    assert [k.id for k in buf.ready(3)] == [5]


def test_thread_safe_concurrent_add_and_sample():
    buf = KeyframeBuffer(KeyframeConfig(max_keyframes=8, min_translation=0.01))
    emb = np.zeros((12, 16, 3), np.float32)
    errors = []

    def producer():
        try:
            for i in range(400):
                buf.add(_frame(_walk(3 * i), i), emb)
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    t = threading.Thread(target=producer)
    t.start()
    rng = np.random.default_rng(0)
    while t.is_alive():
        if len(buf):
            r = buf.sample_rays(64, rng)
            assert r["rgb"].shape == (64, 3) and np.isfinite(r["dirs"]).all()
        buf.tick(1)
        buf.ready(5)
    t.join()
    assert not errors and len(buf) == 8
