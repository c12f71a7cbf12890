"""Embedding-NeRF: render maths, real RGB-D fit, synthetic-scene embedding, mapper API."""

from __future__ import annotations

import math
import os
import sys
import time

import cv2
import numpy as np
import pytest
import torch

from neurncd_ros.core import classes
from neurncd_ros.core.camera import camera_directions, pixel_grid
from neurncd_ros import synth
from neurncd_ros.core.data import formats
from neurncd_ros.core.field import losses, renderer, samplers
from neurncd_ros.core.field.backends.fast import FastConfig
from neurncd_ros.core.field.backends.reference import ReferenceConfig
from neurncd_ros.core.field.keyframes import KeyframeConfig
from neurncd_ros.core.field.mapper import Mapper, MapperConfig
from neurncd_ros.core.frame import Frame

torch.set_num_threads(1)


def _downscale(f: Frame, w: int, h: int) -> Frame:
    rgb = cv2.resize(f.rgb, (w, h), interpolation=cv2.INTER_AREA)
    depth = cv2.resize(f.depth, (w, h), interpolation=cv2.INTER_NEAREST)
    return Frame(f.stamp_ns, rgb, depth, f.pose, f.intrinsics.scaled(w, h))


def _heldout_rays(f: Frame, stride: int):
    """Rays and targets of the pixels with u, v multiples of ``stride`` (never trained on)."""
    u, v = pixel_grid(f.intrinsics.height, f.intrinsics.width)
    u, v = u[::stride, ::stride].ravel(), v[::stride, ::stride].ravel()
    d = camera_directions(f.intrinsics, u, v) @ f.pose[:3, :3].T
    o = np.broadcast_to(f.pose[:3, 3], d.shape)
    return o, d, f.rgb[v, u] / 255.0, f.depth[v, u]


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return -10.0 * math.log10(float(np.mean((a - b) ** 2)))


# ------------------------------------------------------------------ maths

def test_render_weights_stop_at_an_opaque_wall():
    t = torch.linspace(0.5, 4.0, 351)[None]
    sigma = torch.where(t > 2.0, torch.tensor(1e4), torch.tensor(0.0))
    w = renderer.render_weights(sigma, t, torch.ones(1))
    out = renderer.composite(w, t, {"e": torch.ones(1, 351, 2)})
    assert abs(float(out["depth"][0]) - 2.01) < 0.011
    assert abs(float(out["opacity"][0]) - 1.0) < 1e-4
    # a tilted ray (|d| = 2): metric spacing doubles, same z-depth
    w2 = renderer.render_weights(sigma * 0.5, t, torch.full((1,), 2.0))
    assert torch.allclose(w2, w, atol=1e-5)


def test_samplers_stay_in_range_and_follow_weights():
    near, far = torch.tensor([0.1, 1.0]), torch.tensor([5.0, 3.0])
    g = torch.Generator().manual_seed(0)
    t = samplers.stratified(near, far, 32, perturb=g)
    assert torch.all(t >= near[:, None]) and torch.all(t <= far[:, None])
    assert torch.all(t[:, 1:] >= t[:, :-1])
    w = torch.zeros(2, 32)
    w[:, 10] = 1.0
    tf = samplers.importance(t, w, 64, perturb=g)
    lo, hi = (t[:, 9] + t[:, 10]) / 2, (t[:, 10] + t[:, 11]) / 2
    inside = (tf >= lo[:, None] - 1e-5) & (tf <= hi[:, None] + 1e-5)
    assert inside.float().mean() > 0.95
    depth = torch.tensor([2.0, 0.0])
    tg = samplers.depth_guided(near, far, depth, 16, 8, 0.1, perturb=g)
    assert ((tg[0] - 2.0).abs() <= 0.1 + 1e-6).sum() >= 16  # band around the measurement
    assert torch.all(tg[1] >= 1.0) and torch.all(tg[1] <= 3.0)  # no depth: stratified
    o = torch.zeros(2, 3)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    n, f = samplers.aabb_near_far(o + torch.tensor([0.0, 0.0, -3.0]), d, -torch.ones(3),
                                  torch.ones(3), 0.05)
    assert torch.allclose(n, torch.tensor([2.0, 0.05])) and torch.allclose(f[0], torch.tensor(4.0))
    assert f[1] == n[1]  # the backward ray misses the box


def test_entropy_and_kl():
    rng = np.random.default_rng(0)
    logits = rng.normal(0, 5, (1000, 9)).astype(np.float32)
    logits[0] = 0.0
    logits[1] = [100.0] + [0.0] * 8
    h = losses.entropy(logits)
    assert h.dtype == np.float32 and np.all(h >= 0) and np.all(h <= math.log(9) + 1e-6)
    assert abs(h[0] - math.log(9)) < 1e-5 and h[1] < 1e-6
    e = torch.from_numpy(logits)
    assert float(losses.embedding_kl(e, e)) < 1e-6
    assert float(losses.embedding_kl(e, e + 3.0)) < 1e-6  # shift invariant: it is softmax
    assert float(losses.embedding_kl(e, e.flip(-1))) > 0.5
    # Confidence weighting: a uniform (maximally unsure) target ray has weight 0.
    t = torch.tensor([[0.0] * 9, [4.0] + [0.0] * 8])
    r = torch.tensor([[0.0] * 8 + [3.0], [0.0] * 9])
    per_ray = [float(losses.embedding_kl(t[i:i + 1], r[i:i + 1])) for i in range(2)]
    assert min(per_ray) > 0.1
    assert abs(float(losses.embedding_kl(t, r)) - sum(per_ray) / 2) < 1e-6
    assert abs(float(losses.embedding_kl(t, r, 2.0)) - per_ray[1]) < 1e-6


# ------------------------------------------------------------------ real data

@pytest.fixture(scope="module")
def redwood(real_data_dir):
    frames = list(formats.read_folder(real_data_dir / "redwood_livingroom"))
    assert len(frames) == 5
    return [_downscale(f, 160, 120) for f in frames]


def test_fast_field_fits_real_rgbd_heldout_pixels(redwood):
    """5 real Redwood frames at 160x120; every 4th pixel (both axes) is never trained on."""
    m = Mapper(MapperConfig(seed=1), channels=3, keyframes=KeyframeConfig(holdout_stride=4))
    for f in redwood:
        assert m.add_keyframe(f, np.zeros((60, 80, 3), np.float32), force=True)
    m.step(150)
    psnrs, errs = [], []
    for f in redwood[::2]:
        o, d, rgb, depth = _heldout_rays(f, 4)
        out = m.render_rays(o, d)
        psnrs.append(_psnr(out["rgb"], rgb))
        ok = depth > 0
        errs.append(np.abs(out["depth"][ok] - depth[ok]))
    psnr, med = float(np.mean(psnrs)), float(np.median(np.concatenate(errs)))
    # measured (seeds 1, 2): 26.8 dB and 0.8-1.1 cm after 150 iterations
    assert psnr >= 24.0, psnr
    assert med <= 0.025, med


@pytest.mark.slow
def test_reference_field_learns_real_rgbd(redwood):
    """The paper's MLP (few rays so it stays minutes): held-out PSNR improves clearly."""
    m = Mapper(MapperConfig(backend="reference", seed=3), channels=3,
               keyframes=KeyframeConfig(holdout_stride=4),
               backend_cfg=ReferenceConfig(rays_per_iteration=256))
    for f in redwood:
        m.add_keyframe(f, np.zeros((120, 160, 3), np.float32), force=True)
    o, d, rgb, _ = _heldout_rays(redwood[2], 8)
    before = _psnr(m.render_rays(o, d)["rgb"], rgb)
    m.step(40)
    after = _psnr(m.render_rays(o, d)["rgb"], rgb)
    assert after > before + 3.0 and after > 15.0, (before, after)


# ------------------------------------------------------------------ synthetic scene

def _gt_embedding(semantic: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Backbone stand-in: 5 x one-hot of known classes + N(0, 1); novel/void: noise only."""
    emb = rng.normal(0.0, 1.0, semantic.shape + (classes.NUM_KNOWN,)).astype(np.float32)
    for cid, k in classes.ID_TO_CHANNEL.items():
        emb[..., k] += 5.0 * (semantic == cid)
    return emb


@pytest.fixture(scope="module")
def synthetic():
    cfg = synth.SynthConfig(width=80, height=60, fps=3.0, depth_noise="realistic")
    return list(synth.generate(5, 36, cfg))


def _fit_synthetic(frames, steps: int, **cfg) -> Mapper:
    rng = np.random.default_rng(0)
    m = Mapper(MapperConfig(seed=2, **cfg), classes.NUM_KNOWN,
               backend_cfg=FastConfig(rays_per_iteration=1024))
    for i, f in enumerate(frames):
        if i % 6 != 3:
            m.add_keyframe(f, _gt_embedding(f.semantic, rng), force=True)
    m.step(steps)
    return m


def _known_agreement(m: Mapper, frames) -> float:
    agree, total = 0, 0
    for i, f in enumerate(frames):
        if i % 6 != 3:
            continue
        out = m.render(f.pose, f.intrinsics)
        known = np.isin(f.semantic, classes.KNOWN_IDS)
        target = np.vectorize(classes.ID_TO_CHANNEL.get, otypes=[np.int64])(
            np.where(known, f.semantic, classes.KNOWN_IDS[0]))
        logits = out["embedding"][..., : classes.NUM_KNOWN]  # any features follow
        agree += int((logits.argmax(-1) == target)[known].sum())
        total += int(known.sum())
        h = out["entropy"]
        assert h.dtype == np.float32 and h.min() >= 0 and h.max() <= math.log(9) + 1e-5
    return agree / total


def test_embedding_argmax_agrees_on_heldout_synthetic_frames(synthetic):
    """Held-out views (every 6th frame, never admitted) render the right known class."""
    m = _fit_synthetic(synthetic, 200)
    assert _known_agreement(m, synthetic) > 0.9  # measured 0.97


def test_depth_guided_render_on_heldout_views(synthetic):
    """With the view's measured depth the fast field samples where it trained (24 samples,
    no search pass): held-out known-class agreement at least as good as without it, the
    rendered depth close to the measurement; pixels without depth fall back to the
    field-only render exactly; a depth of the wrong size is refused."""
    m = _fit_synthetic(synthetic, 200)
    held = [f for i, f in enumerate(synthetic) if i % 6 == 3]
    hits = {"free": 0, "depth": 0}
    total = 0
    for f in held:
        known = np.isin(f.semantic, classes.KNOWN_IDS)
        target = np.vectorize(classes.ID_TO_CHANNEL.get, otypes=[np.int64])(
            np.where(known, f.semantic, classes.KNOWN_IDS[0]))
        free = m.render(f.pose, f.intrinsics)
        guided = m.render(f.pose, f.intrinsics, depth=f.depth)
        for name, out in (("free", free), ("depth", guided)):
            hits[name] += int((out["embedding"].argmax(-1) == target)[known].sum())
        total += int(known.sum())
        ok = f.depth > 0
        assert np.median(np.abs(guided["depth"][ok] - f.depth[ok])) < 0.03
        # no measurement -> exactly the field-only render of that pixel
        assert (~ok).any()
        np.testing.assert_allclose(guided["embedding"][~ok], free["embedding"][~ok],
                                   rtol=1e-4, atol=1e-4)
    assert hits["depth"] / total >= hits["free"] / total - 0.005, hits
    assert hits["depth"] / total > 0.9
    f = held[0]
    half = m.render(f.pose, f.intrinsics, 30, 40, depth=f.depth)  # depth resampled
    assert half["embedding"].shape == (30, 40, 9)
    with pytest.raises(ValueError, match="depth has shape"):
        m.render(f.pose, f.intrinsics, depth=f.depth[:-1])
    with pytest.raises(ValueError, match="values for"):
        m.render_rays(np.zeros((4, 3)), np.ones((4, 3)), np.ones(3))
    # The reference backend (faithful to the paper) ignores the depth.
    r = Mapper(MapperConfig(backend="reference"), classes.NUM_KNOWN,
               backend_cfg=ReferenceConfig(rays_per_iteration=32, coarse_samples=8,
                                           fine_samples=8))
    r.add_keyframe(f, _gt_embedding(f.semantic, np.random.default_rng(0)))
    a = r.render(f.pose, f.intrinsics, 6, 8)
    b = r.render(f.pose, f.intrinsics, 6, 8, depth=f.depth)
    assert np.array_equal(a["embedding"], b["embedding"])


def test_save_load_renders_identically_and_resumes(synthetic, tmp_path):
    m = _fit_synthetic(synthetic[:8], 5, min_iterations_before_publish=3)
    f = synthetic[3]
    before = m.render(f.pose, f.intrinsics, 30, 40)
    m.save(tmp_path / "map.pt")
    m2 = Mapper.load(tmp_path / "map.pt")
    after = m2.render(f.pose, f.intrinsics, 30, 40)
    for k in before:
        assert after[k].shape == before[k].shape
        assert np.array_equal(after[k], before[k]), k
    assert m2.iterations == m.iterations == 5
    assert [k.id for k in m2.ready_keyframes()] == [k.id for k in m.ready_keyframes()]
    emb, ent = m2.query(np.array([[0.5, 0.5, 0.5], [1.0, 1.0, 0.1]]))
    assert emb.shape == (2, 9) and ent.shape == (2,)
    assert np.isfinite(m2.step(2)["total"]) and m2.iterations == 7


FEATURES = 6  # feature channels of the stand-in backbone's penultimate map


def _class_features() -> np.ndarray:
    """A fixed non-negative feature vector per NYU-13 id (0 = void), as a ReLU layer's."""
    return np.abs(np.random.default_rng(7).normal(0.0, 3.0, (classes.NUM_CLASSES + 1,
                                                             FEATURES))).astype(np.float32)


def _with_features(semantic: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Logits and features of the backbone stand-in: the class's feature vector + noise."""
    feats = _class_features()[semantic] + rng.normal(0.0, 0.3, semantic.shape + (FEATURES,))
    return np.concatenate([_gt_embedding(semantic, rng), feats.astype(np.float32)], axis=-1)


def _fit_features(frames, steps: int, distill: bool) -> Mapper:
    rng = np.random.default_rng(0)
    m = Mapper(MapperConfig(seed=2, distill_features=distill), classes.NUM_KNOWN,
               backend_cfg=FastConfig(rays_per_iteration=1024), feature_channels=FEATURES)
    for i, f in enumerate(frames):
        if i % 6 != 3:
            m.add_keyframe(f, _with_features(f.semantic, rng), force=True)
    if steps:
        assert "features" in m.step(steps)
    return m


def test_feature_error_is_relative_and_zero_without_features():
    f = torch.tensor([[1.0, 2.0], [0.0, 3.0]])
    assert float(losses.feature_error(f, torch.zeros_like(f))) == pytest.approx(1.0)
    assert float(losses.feature_error(f, f)) == 0.0
    # the same relative error whatever the features' scale
    assert float(losses.feature_error(100 * f, 100 * (f + 0.1))) == pytest.approx(
        float(losses.feature_error(f, f + 0.1)), rel=1e-5)
    none = torch.zeros(2, 0)
    out = losses.feature_error(none, torch.zeros(2, 0, requires_grad=True))
    assert float(out) == 0.0 and out.requires_grad


def test_field_distils_the_backbone_features_beside_the_logits(synthetic, tmp_path):
    """With feature channels in the keyframes' embedding (backbone.features) the field
    learns them too: held-out views render logits then features, the features near the
    class's feature vector (relative error far below the 1 of a field that renders
    zeros), the known classes as well as without features, the entropy of the logits
    alone. distill_features false renders the logits only; a map saved before the option
    existed loads as such."""
    m = _fit_features(synthetic, 150, distill=True)
    assert m.field_channels == classes.NUM_KNOWN + FEATURES
    table = _class_features()
    num = den = 0.0
    for i, f in enumerate(synthetic):
        if i % 6 != 3:
            continue
        out = m.render(f.pose, f.intrinsics, depth=f.depth)
        assert out["embedding"].shape == f.depth.shape + (classes.NUM_KNOWN + FEATURES,)
        np.testing.assert_allclose(out["entropy"], losses.entropy(
            out["embedding"][..., : classes.NUM_KNOWN]), atol=1e-5)
        sel = (f.semantic > 0) & (f.depth > 0)
        target = table[f.semantic[sel]]
        num += float(((out["embedding"][..., classes.NUM_KNOWN:][sel] - target) ** 2).sum())
        den += float((target ** 2).sum())
    assert num / den < 0.2, num / den  # measured 0.044
    assert _known_agreement(m, synthetic) > 0.9  # measured 0.96, as without features
    emb, ent = m.query(np.array([[0.5, 0.5, 0.5]]))
    assert emb.shape == (1, classes.NUM_KNOWN + FEATURES) and ent.shape == (1,)

    plain = _fit_features(synthetic[:8], 2, distill=False)
    assert plain.field_channels == classes.NUM_KNOWN
    f = synthetic[3]
    assert plain.render(f.pose, f.intrinsics, 6, 8)["embedding"].shape == (6, 8, 9)
    # A map file from before distill_features: its mapper section lacks the key.
    plain.save(tmp_path / "old.pt")
    state = torch.load(tmp_path / "old.pt", weights_only=True)
    del state["config"]["mapper"]["distill_features"]
    torch.save(state, tmp_path / "old.pt")
    old = Mapper.load(tmp_path / "old.pt")
    assert old.field_channels == classes.NUM_KNOWN and old.feature_channels == FEATURES
    m.save(tmp_path / "new.pt")
    back = Mapper.load(tmp_path / "new.pt")
    a = m.render(f.pose, f.intrinsics, 6, 8, depth=f.depth)
    b = back.render(f.pose, f.intrinsics, 6, 8, depth=f.depth)
    assert np.array_equal(a["embedding"], b["embedding"])


def test_background_training_while_adding_and_rendering(synthetic):
    m = Mapper(MapperConfig(min_iterations_before_publish=5), classes.NUM_KNOWN,
               keyframes=KeyframeConfig(min_translation=0.05),
               backend_cfg=FastConfig(rays_per_iteration=256))
    rng = np.random.default_rng(0)
    m.start()
    try:
        published = []
        for f in synthetic[:12]:
            m.add_keyframe(f, _gt_embedding(f.semantic, rng))
            out = m.render(f.pose, f.intrinsics, 15, 20)
            assert out["rgb"].shape == (15, 20, 3) and np.isfinite(out["depth"]).all()
            published += m.ready_keyframes()
            time.sleep(0.05)
        deadline = time.time() + 30
        while (m.iterations < 20 or min(k.iterations for k in m.buffer.keyframes()) < 5) \
                and time.time() < deadline:
            time.sleep(0.1)
    finally:
        m.stop()
    assert m.last_error is None
    assert m.iterations >= 20
    published += m.ready_keyframes()
    ids = [k.id for k in published]
    assert len(ids) == len(set(ids)) == len(m.buffer)  # each keyframe published once
    m.reset()
    assert m.iterations == 0 and len(m.buffer) == 0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a thread's own nice value")
def test_training_thread_alone_takes_train_nice(synthetic):
    """mapper.train_nice renices the training thread, not the process that renders."""
    own = os.getpriority(os.PRIO_PROCESS, 0)
    m = Mapper(MapperConfig(train_nice=7), classes.NUM_KNOWN,
               backend_cfg=FastConfig(rays_per_iteration=128))
    m.add_keyframe(synthetic[0], _gt_embedding(synthetic[0].semantic,
                                               np.random.default_rng(0)), force=True)
    m.start()
    try:
        deadline = time.time() + 60
        while m.iterations < 2 and time.time() < deadline and m.last_error is None:
            time.sleep(0.02)
        assert m.iterations >= 2, m.last_error
        assert os.getpriority(os.PRIO_PROCESS, m._thread.native_id) == min(19, own + 7)
        assert os.getpriority(os.PRIO_PROCESS, 0) == own
        out = m.render(synthetic[0].pose, synthetic[0].intrinsics, 15, 20)
        assert np.isfinite(out["embedding"]).all()
    finally:
        m.stop()


def test_bounds_grow_and_keep_what_was_learnt(synthetic):
    m = _fit_synthetic(synthetic[:4], 60)
    f = synthetic[1]
    before = m.render(f.pose, f.intrinsics, 30, 40)
    lo, hi = m.bounds
    far = Frame(f.stamp_ns + 1, f.rgb, f.depth, f.pose.copy(), f.intrinsics)
    far.pose[0, 3] += 0.5 * (hi - lo)[0]  # a view reaching past the box along x
    assert m.add_keyframe(far, _gt_embedding(f.semantic, np.random.default_rng(0)))
    lo2, hi2 = m.bounds
    assert hi2[0] > hi[0] and np.all(lo2 <= lo) and np.all(hi2 >= hi)
    after = m.render(f.pose, f.intrinsics, 30, 40)
    # the planes were resampled onto the larger box: the same view renders nearly the same
    assert _psnr(after["rgb"], before["rgb"]) > 25.0
    same = after["embedding"].argmax(-1) == before["embedding"].argmax(-1)
    assert same.mean() > 0.9
    assert np.isfinite(m.step(1)["total"])


def test_keyframe_extent_reads_a_large_frame_subsampled_to_the_same_box():
    """A 1280x720 frame's extent is read from every 4th pixel: the same 1st-99th
    percentile box as from every pixel within a centimetre; a 320x240 frame is read
    whole (the same box as before the subsampling)."""
    from neurncd_ros.core.field import scenebox

    big = next(synth.frames_at(2, [10], synth.SynthConfig(width=1280, height=720)))
    step = np.ceil(np.sqrt(big.depth.size / scenebox.EXTENT_PIXELS))
    assert step == 4
    lo, hi = scenebox.keyframe_extent(big, 8.0)
    # Every pixel, as keyframe_extent read it before (the reference here).
    d = np.where(big.depth <= 8.0, big.depth, 0.0).astype(np.float32)
    pts, _ = scenebox.backproject(d, big.intrinsics, big.pose)
    pts = np.concatenate([pts, big.pose[None, :3, 3]])
    assert np.abs(lo - np.percentile(pts, 1, axis=0)).max() < 0.01
    assert np.abs(hi - np.percentile(pts, 99, axis=0)).max() < 0.01
    small = next(synth.frames_at(2, [10], synth.SynthConfig(width=320, height=240)))
    d = np.where(small.depth <= 8.0, small.depth, 0.0).astype(np.float32)
    pts, _ = scenebox.backproject(d, small.intrinsics, small.pose)
    pts = np.concatenate([pts, small.pose[None, :3, 3]])
    lo, hi = scenebox.keyframe_extent(small, 8.0)
    assert np.array_equal(lo, np.percentile(pts, 1, axis=0))
    assert np.array_equal(hi, np.percentile(pts, 99, axis=0))


def test_a_keyframe_does_not_wait_for_a_training_step_to_grow_the_box(synthetic):
    """While a step holds the model, a keyframe past the box is admitted at once; the
    grown box waits and is applied before the next batch, and before a render."""
    import threading

    m = _fit_synthetic(synthetic[:4], 10)
    f = synthetic[1]
    lo, hi = m.bounds
    far = Frame(f.stamp_ns + 1, f.rgb, f.depth, f.pose.copy(), f.intrinsics)
    far.pose[0, 3] += 0.5 * (hi - lo)[0]
    emb = _gt_embedding(f.semantic, np.random.default_rng(0))
    admitted, done = [], threading.Event()
    with m._lock:  # a training step under way, as the background thread holds it
        worker = threading.Thread(target=lambda: (admitted.append(m.add_keyframe(far, emb)),
                                                  done.set()))
        worker.start()
        assert done.wait(60), "add_keyframe waited for the step"
        assert admitted == [True] and m._pending_box is not None
        assert np.array_equal(m._lo, lo) and np.array_equal(m._hi, hi)  # not applied yet
    worker.join()
    assert np.isfinite(m.step(1)["total"])  # applies the box, then draws the batch
    assert m._pending_box is None
    lo2, hi2 = m.bounds
    assert hi2[0] > hi[0] and np.all(lo2 <= lo) and np.all(hi2 >= hi)
    # A render applies a pending box too, and a second growth merges with the first.
    with m._lock:
        far2 = Frame(f.stamp_ns + 2, f.rgb, f.depth, far.pose.copy(), f.intrinsics)
        far2.pose[0, 3] += 0.5 * (hi2 - lo2)[0]
        t = threading.Thread(target=m.add_keyframe, args=(far2, emb))
        t.start()
        t.join(60)
        assert not t.is_alive() and m._pending_box is not None
    out = m.render(far2.pose, f.intrinsics, 15, 20)
    assert m._pending_box is None and m.bounds[1][0] > hi2[0]
    assert np.isfinite(out["embedding"]).all()


def test_reference_backend_smoke(synthetic):
    m = Mapper(MapperConfig(backend="reference"), classes.NUM_KNOWN,
               backend_cfg=ReferenceConfig(rays_per_iteration=32, coarse_samples=16,
                                           fine_samples=16))
    f = synthetic[0]
    m.add_keyframe(f, _gt_embedding(f.semantic, np.random.default_rng(0)))
    out = m.step(2)
    assert set(out) >= {"total", "photometric", "embedding"} and "depth" not in out
    r = m.render(f.pose, f.intrinsics, 6, 8)
    assert r["embedding"].shape == (6, 8, 9) and r["rgb"].min() >= 0 and r["rgb"].max() <= 1


def test_bad_inputs_raise_clear_errors(synthetic):
    m = Mapper(MapperConfig(), classes.NUM_KNOWN)
    f = synthetic[0]
    with pytest.raises(ValueError, match="nothing is mapped"):
        m.render(f.pose, f.intrinsics)
    with pytest.raises(ValueError, match="channels"):
        m.add_keyframe(f, np.zeros((60, 80, 4), np.float32))
    with pytest.raises(ValueError, match="embedding"):
        m.add_keyframe(f, np.zeros((60, 80), np.float32))
    assert m.step(1) == {}
    m.add_keyframe(f, np.zeros((30, 40, 9), np.float32))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        m.query(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="height and width"):
        m.render(f.pose, f.intrinsics, height=10)
    with pytest.raises(ValueError, match="4x4"):
        m.render(np.eye(3), f.intrinsics)
    with pytest.raises(ValueError):
        Mapper(MapperConfig(), 0)
