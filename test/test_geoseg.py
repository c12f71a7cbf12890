"""Geometric depth segmentation on hand-built, synthetic and real sensor depth."""

from __future__ import annotations


import cv2
import numpy as np
import pytest

from neurncd_ros.core.camera import Intrinsics
from neurncd_ros.core.discovery.geoseg import GeoSegConfig, scaled_sizes, segment_depth, \
    surface_normals, points_image

cv2.setNumThreads(1)


def _purity(seg: np.ndarray, instance: np.ndarray) -> tuple[float, float]:
    """(pixel-weighted share of segment pixels in their segment's majority instance, n)."""
    m = (seg >= 0) & (instance > 0)
    _, inst = np.unique(instance[m], return_inverse=True)
    table = np.zeros((seg.max() + 1, inst.max() + 1))
    np.add.at(table, (seg[m], inst), 1)
    return float(table.max(axis=1).sum()), float(table.sum())


def _jump_pairs(seg: np.ndarray, depth: np.ndarray, rel: float) -> tuple[int, int]:
    """(4-neighbour pairs inside one segment whose depth differs by > rel * depth, all pairs)."""
    bad = total = 0
    for a, b, da, db in ((seg[:, 1:], seg[:, :-1], depth[:, 1:], depth[:, :-1]),
                         (seg[1:], seg[:-1], depth[1:], depth[:-1])):
        same = (a == b) & (a >= 0)
        jump = np.abs(da - db) > rel * np.minimum(da, db)
        bad += int((same & jump).sum())
        total += int(same.sum())
    return bad, total


def _box_scene(h: int = 120, w: int = 160):
    """A wall at 3 m, a floor 1 m below the camera, and a box face at 2 m."""
    intr = Intrinsics.from_hfov(w, h, 70.0)
    v = np.arange(h, dtype=np.float64)[:, None] - intr.cy
    wall = np.full((h, w), 3.0)
    floor = np.where(v > 0, 1.0 * intr.fy / np.maximum(v, 1e-9), np.inf) * np.ones((1, w))
    depth = np.minimum(wall, floor)
    truth = np.where(floor < wall, 1, 2)
    box = (slice(20, 60), slice(50, 110))
    depth[box] = 2.0
    truth[box] = 3
    return depth.astype(np.float32), intr, truth


def test_hand_built_scene_separates_wall_floor_and_box():
    depth, intr, truth = _box_scene()
    seg = segment_depth(depth, intr, GeoSegConfig())
    assert seg.dtype == np.int32 and seg.shape == depth.shape
    assert (seg >= 0).mean() > 0.95
    good, total = _purity(seg, truth)
    assert good / total > 0.97
    # Each region is mostly one segment, and no segment id is shared across regions.
    for region in (1, 2, 3):
        ids, counts = np.unique(seg[(truth == region) & (seg >= 0)], return_counts=True)
        assert counts.max() / counts.sum() > 0.9
    owners = {int(s): set(np.unique(truth[seg == s]).tolist()) for s in np.unique(seg[seg >= 0])}
    major = [s for s in owners if (seg == s).sum() > 100]
    assert all(len(owners[s]) == 1 or (seg == s).sum() * 0.02 > 0 for s in major)
    bad, _ = _jump_pairs(seg, depth, 0.1)
    assert bad == 0


def test_ids_are_compact_and_invalid_depth_is_minus_one():
    depth, intr, _ = _box_scene()
    depth[:, :10] = 0.0
    depth[5, 20] = np.nan
    seg = segment_depth(depth, intr)
    assert (seg[:, :10] == -1).all() and seg[5, 20] == -1
    ids = np.unique(seg[seg >= 0])
    assert ids.tolist() == list(range(len(ids)))


def test_normals_of_a_plane_face_the_camera():
    depth, intr, truth = _box_scene()
    n = surface_normals(points_image(depth, intr), depth > 0, 5)
    # Wall pixels whose 5x5 window holds only wall (and stays inside the image).
    wall = cv2.erode((truth == 2).astype(np.uint8), np.ones((5, 5), np.uint8),
                     borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    assert wall.sum() > 5000
    assert np.allclose(n[2][wall], -1.0, atol=1e-4)
    assert np.allclose(n[0][wall], 0.0, atol=1e-3) and np.allclose(n[1][wall], 0.0, atol=1e-3)


def test_pixel_sizes_scale_with_resolution():
    cfg = GeoSegConfig()
    full, half = scaled_sizes(cfg, 640), scaled_sizes(cfg, 320)
    assert full["normals_window"] == 13 and half["normals_window"] == 7
    assert full["min_segment_size"] == 500 and half["min_segment_size"] == 125
    assert half["convexity_window"] % 2 == 1 and half["discontinuity_kernel"] >= 3


def test_bad_inputs_raise_value_error():
    depth, intr, _ = _box_scene()
    with pytest.raises(ValueError, match="intrinsics"):
        segment_depth(depth[:, :-1], intr)
    with pytest.raises(ValueError, match="float"):
        segment_depth((depth * 1000).astype(np.uint16), intr)
    with pytest.raises(ValueError, match="2-D"):
        segment_depth(depth[..., None], intr)


@pytest.fixture(scope="module")
def synth_frames():
    from neurncd_ros import synth
    out = []
    for noise in ("none", "realistic"):
        cfg = synth.SynthConfig(depth_noise=noise)
        for seed in (0, 1):
            out += [(noise, f) for f in synth.frames_at(seed, (0, 6, 12), cfg)]
    return out


def _appearance(f, i: int):
    """Embedding and entropy for a synthetic frame: the default backbone's logits when its
    weights exist, otherwise the ground-truth stand-in (modulation.simulate_embedding)."""
    from neurncd_ros.core.backbone.backbone import DEFAULT_WEIGHTS
    from neurncd_ros.core.uncertainty import entropy
    if DEFAULT_WEIGHTS.exists():
        from neurncd_ros.core.backbone.backbone import BackboneConfig, load_backbone
        emb = load_backbone(BackboneConfig(num_threads=1)).predict(f.rgb, f.depth)
    else:
        from neurncd_ros.core.discovery.modulation import simulate_embedding
        emb = simulate_embedding(f.semantic, f.instance, seed=i)
    return emb, entropy(emb)


def _check_frame(seg, f, noise):
    n = seg.max() + 1
    assert 3 <= n <= 80, f"{noise}: {n} segments"
    valid = f.depth > 0
    # Nearly every measured pixel is segmented (the rest: dissolved tiny fragments and
    # edge pixels whose normal disagrees with every neighbouring segment).
    assert ((seg >= 0) | ~valid).mean() > 0.7
    for rel in (0.3, 0.1):
        bad, _ = _jump_pairs(seg, np.where(valid, f.depth, np.nan), rel)
        assert bad == 0


def test_synthetic_segments_are_pure_and_respect_depth_edges(synth_frames):
    """Geometry only. Flush doors/pictures/TVs on walls cannot be cut by geometry, and
    window centroids (chosen for noisy depth, see geoseg) soften some room corners, hence
    not 1.0. Measured on these frames: 0.88 exact, 0.87 noisy (the raw-point variant:
    0.93 / 0.89 but far fewer pixels segmented); on 10 frames each of seeds 0-9 noisy
    0.92, held-out seeds 10-14 0.85."""
    for noise in ("none", "realistic"):
        good = total = 0.0
        for kind, f in synth_frames:
            if kind != noise:
                continue
            seg = segment_depth(f.depth, f.intrinsics)
            g, t = _purity(seg, f.instance)
            good, total = good + g, total + t
            _check_frame(seg, f, noise)
        need = 0.85 if noise == "none" else 0.84
        assert good / total >= need, f"{noise}: purity {good / total:.3f}"


def test_appearance_and_colour_edges_raise_purity_on_noisy_depth(synth_frames):
    """With the embedding, entropy and colour cues (as the discovery node runs it)
    realistic-noise purity reaches the 0.90 target. Measured here with the default
    backbone's logits: all cues 0.986, embedding and entropy only 0.882 (the backbone
    rightly calls doors "wall", so only colour cuts a flush door from its wall),
    geometry alone 0.87; held-out seeds 10-14: 0.98, tuning seeds 500-502: 0.96."""
    purity = {"all": [0.0, 0.0], "appearance": [0.0, 0.0], "geometry": [0.0, 0.0]}
    for i, (kind, f) in enumerate(synth_frames):
        if kind != "realistic":
            continue
        emb, ent = _appearance(f, i)
        runs = {"all": segment_depth(f.depth, f.intrinsics, GeoSegConfig(), emb, ent, f.rgb),
                "appearance": segment_depth(f.depth, f.intrinsics, GeoSegConfig(), emb, ent),
                "geometry": segment_depth(f.depth, f.intrinsics)}
        _check_frame(runs["all"], f, kind)
        for name, seg in runs.items():
            g, t = _purity(seg, f.instance)
            purity[name][0] += g
            purity[name][1] += t
    share = {k: g / t for k, (g, t) in purity.items()}
    assert share["all"] >= 0.90, share
    assert share["all"] > share["appearance"] >= share["geometry"] - 0.01, share


def test_flush_door_is_cut_only_by_colour():
    """A door flush with its wall, both confidently "wall" to the backbone: one segment
    from depth and embedding, two once the colour image is given (and not when the
    colour edges are switched off)."""
    h, w = 120, 160
    intr = Intrinsics.from_hfov(w, h, 70.0)
    depth = np.full((h, w), 2.5, np.float32)
    door = np.zeros((h, w), bool)
    door[20:, 40:90] = True
    emb = np.zeros((h, w, 9), np.float32)
    emb[..., 8] = 6.0
    ent = np.full((h, w), 0.05, np.float32)
    rng = np.random.default_rng(0)
    rgb = np.where(door[..., None], np.array([150, 110, 70]), np.array([200, 200, 195]))
    rgb = np.clip(rgb + rng.normal(0, 3, rgb.shape), 0, 255).astype(np.uint8)
    assert (segment_depth(depth, intr, GeoSegConfig(), emb, ent) == 0).all()
    off = segment_depth(depth, intr, GeoSegConfig(colour_edges=False), emb, ent, rgb)
    assert (off == 0).all()
    seg = segment_depth(depth, intr, GeoSegConfig(), emb, ent, rgb)
    assert seg.max() == 1
    good, total = _purity(seg, door.astype(np.int32) + 1)
    assert good / total > 0.99
    with pytest.raises(ValueError, match="uint8"):
        segment_depth(depth, intr, GeoSegConfig(), colour=rgb.astype(np.float32))
    with pytest.raises(ValueError, match="colour must be"):
        segment_depth(depth, intr, GeoSegConfig(), colour=rgb[:-1])


def test_flush_picture_is_cut_only_by_the_embedding():
    """A picture flush with a flat wall: one segment from depth alone, its own segment
    once its embedding differs from the wall's (and not when disabled)."""
    h, w = 120, 160
    intr = Intrinsics.from_hfov(w, h, 70.0)
    depth = np.full((h, w), 2.5, np.float32)
    picture = np.zeros((h, w), bool)
    picture[30:80, 50:120] = True
    emb = np.zeros((h, w, 9), np.float32)
    emb[..., 8] = 4.0                      # wall: confident on the wall channel
    emb[picture] = 0.0
    emb[picture, 4] = emb[picture, 5] = 1.5  # picture: an uncertain mix of two channels
    ent = np.ones((h, w), np.float32)
    alone = segment_depth(depth, intr)
    assert alone.max() == 0 and (alone == 0).all()
    seg = segment_depth(depth, intr, GeoSegConfig(), emb, ent)
    good, total = _purity(seg, picture.astype(np.int32) + 1)
    assert good / total > 0.99
    inner = seg[35:75, 55:115]
    assert np.unique(inner).size == 1 and inner[0, 0] >= 0
    assert (seg[5:20, 5:150] != inner[0, 0]).all()
    off = segment_depth(depth, intr, GeoSegConfig(embedding_edges=False), emb, ent)
    assert (off == 0).all()


def test_entropy_edges_cut_where_the_entropy_changes():
    h, w = 120, 160
    intr = Intrinsics.from_hfov(w, h, 70.0)
    depth = np.full((h, w), 2.5, np.float32)
    ent = np.full((h, w), 0.2, np.float32)
    ent[:, 80:] = 1.8
    seg = segment_depth(depth, intr, GeoSegConfig(entropy_edges=True), entropy=ent)
    assert seg.max() == 1
    assert np.unique(seg[:, :70]).tolist() == [seg[0, 0]] != [seg[0, -1]]
    assert segment_depth(depth, intr, entropy=ent).max() == 0  # off by default


def test_bad_appearance_inputs_raise_value_error():
    depth, intr, _ = _box_scene()
    h, w = depth.shape
    with pytest.raises(ValueError, match="embedding"):
        segment_depth(depth, intr, GeoSegConfig(), np.zeros((h, w - 1, 9), np.float32))
    with pytest.raises(ValueError, match="embedding"):
        segment_depth(depth, intr, GeoSegConfig(), np.zeros((h, w, 9), np.int32))
    with pytest.raises(ValueError, match="entropy"):
        segment_depth(depth, intr, GeoSegConfig(), np.zeros((h, w, 9), np.float32),
                      np.zeros((h, w, 1), np.float32))


def test_non_finite_embedding_is_no_edge():
    depth, intr, truth = _box_scene()
    emb = np.zeros(depth.shape + (9,), np.float32)
    emb[..., 8] = 4.0
    emb[10:20, 10:20] = np.nan
    emb[30:40, 100:110, 3] = np.inf
    ent = np.zeros(depth.shape, np.float32)
    ent[50:60, 20:30] = np.nan
    seg = segment_depth(depth, intr, GeoSegConfig(entropy_edges=True), emb, ent)
    assert (seg == segment_depth(depth, intr)).all()


def _kinect(real_data_dir, i: int, scale: float = 1.0):
    root = real_data_dir / "kinect_dining"
    raw = cv2.imread(str(root / "depth" / f"{i}.pgm"), cv2.IMREAD_UNCHANGED)
    assert raw is not None and raw.dtype == np.uint16
    depth = raw.astype(np.float32) / 1000.0
    intr = Intrinsics(518.0, 519.0, 325.5, 253.5, 640, 480)
    if scale != 1.0:
        w, h = int(640 * scale), int(480 * scale)
        depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
        intr = intr.scaled(w, h)
    return depth, intr


@pytest.mark.parametrize("scale", [0.5, 1.0])
def test_real_kinect_depth_gives_plausible_segments(real_data_dir, scale):
    for i in (1, 3, 5):
        depth, intr = _kinect(real_data_dir, i, scale)
        seg = segment_depth(depth, intr)
        n = seg.max() + 1
        # Measured 15-25 on these frames; a dining room has far more than 5 and far fewer
        # than 80 convex pieces once tiny fragments are dissolved.
        assert 8 <= n <= 60, n
        valid = depth > 0
        # Measured 0.73-0.87: far (4-5 m) Kinect depth breaks into dissolved fragments.
        assert (seg[valid] >= 0).mean() > 0.6
        assert (seg[~valid] == -1).all()
        bad, pairs = _jump_pairs(seg, np.where(valid, depth, np.nan), 0.3)
        assert bad == 0
        bad, pairs = _jump_pairs(seg, np.where(valid, depth, np.nan), 0.1)
        assert bad == 0


def test_real_kinect_with_appearance_cues_stays_plausible(real_data_dir):
    """As the discovery node runs it on a real room the default backbone never saw: its
    embedding edges plus real colour edges (textures, shading) keep the segment count
    plausible (measured 21/18/23 with both cues, 24/16/20 with the embedding only;
    segmented share of valid pixels 0.71-0.86) and still respect depth jumps."""
    from neurncd_ros.core.backbone.backbone import DEFAULT_WEIGHTS, BackboneConfig, load_backbone
    from neurncd_ros.core.uncertainty import entropy
    assert DEFAULT_WEIGHTS.exists(), "the shipped default backbone weights are missing"
    bb = load_backbone(BackboneConfig(num_threads=1))
    for i in (1, 3, 5):
        depth, intr = _kinect(real_data_dir, i, 0.5)
        path = next((real_data_dir / "kinect_dining" / "color").glob(f"{i}.*"))
        rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        rgb = cv2.resize(rgb, (intr.width, intr.height), interpolation=cv2.INTER_AREA)
        emb = bb.predict(rgb, depth)
        seg = segment_depth(depth, intr, GeoSegConfig(), emb, entropy(emb), rgb)
        n = seg.max() + 1
        assert 8 <= n <= 60, n
        valid = depth > 0
        assert (seg[valid] >= 0).mean() > 0.6
        bad, _ = _jump_pairs(seg, np.where(valid, depth, np.nan), 0.1)
        assert bad == 0
