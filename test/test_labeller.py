"""Discoverer: known/novel naming, stable novel ids, full labelling, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neurncd_ros.core.camera import Intrinsics
from neurncd_ros.core.classes import CHANNEL_TO_ID, CLASS_ID, NOVEL_ID_START
from neurncd_ros.core.discovery.labeller import Discoverer, DiscoveryConfig
from neurncd_ros.core.discovery.mcl import MCLConfig
from neurncd_ros.core.discovery.modulation import ModulationConfig, segment_descriptors, \
    segment_stats, simulate_embedding, softmax

torch.set_num_threads(1)

H, W, S = 60, 80, len(CHANNEL_TO_ID)
# Object "kinds": known classes by NYU-13 id, and two novel objects with their own
# consistent low-contrast channel mixes (what a backbone does with unseen classes).
NOVEL_MIX = {"A": {0: 1.2, 1: 1.0}, "B": {4: 1.1, 6: 1.3, 7: 0.9}}


def _logits(kind, rng, n):
    out = rng.normal(0, 0.3, (n, S)).astype(np.float32)
    if kind in NOVEL_MIX:
        for ch, v in NOVEL_MIX[kind].items():
            out[:, ch] += v
    else:
        out[:, list(CHANNEL_TO_ID).index(CLASS_ID[kind])] += 5.0
    return out


def _frame(layout, seed):
    """layout: list of (kind, (r0, r1, c0, c1)) boxes in segment-id order; rest unsegmented."""
    rng = np.random.default_rng(seed)
    segments = np.full((H, W), -1, np.int32)
    emb = _logits("wall", rng, H * W).reshape(H, W, S)
    kinds = np.full((H, W), "", dtype=object)
    for i, (kind, (r0, r1, c0, c1)) in enumerate(layout):
        segments[r0:r1, c0:c1] = i
        emb[r0:r1, c0:c1] = _logits(kind, rng, (r1 - r0) * (c1 - c0)).reshape(r1 - r0,
                                                                              c1 - c0, S)
        kinds[r0:r1, c0:c1] = kind
    p = softmax(emb)
    ent = -(p * np.log(p)).sum(-1).astype(np.float32)
    return segments, emb, ent, kinds


LAYOUT = [("wall", (0, 20, 0, 80)), ("A", (22, 32, 0, 12)), ("A", (22, 32, 14, 26)),
          ("floor", (45, 60, 0, 80)), ("B", (22, 34, 40, 52)), ("B", (22, 34, 54, 66)),
          ("chair", (34, 44, 68, 80))]


# The hand-built logits above have their own entropy scale (known ~0.15 log S, novel
# ~0.9 log S): the thresholds the tests use are fixed here, not the shipped defaults
# (tuned on the default backbone's rendered entropy, bench/ncd.py).
STAND_IN = dict(entropy_threshold=0.6, min_cluster_segments=2, segment_novelty=False)


def _discoverer(**kw):
    cfg = DiscoveryConfig(min_cluster_pixels=50, **{**STAND_IN, **kw})
    return Discoverer(cfg, CHANNEL_TO_ID, mcl_cfg=MCLConfig(k=10))


def _label_of(labels, kinds, kind):
    vals, counts = np.unique(labels[kinds == kind], return_counts=True)
    return int(vals[np.argmax(counts)]), float(counts.max() / counts.sum())


def test_known_and_novel_labels_and_stable_ids_across_frames():
    d = _discoverer()
    seg, emb, ent, kinds = _frame(LAYOUT, 0)
    lab = d.process_segments(seg, emb, ent)
    assert lab.dtype == np.uint16 and lab.shape == (H, W)
    for kind in ("wall", "floor", "chair"):
        got, share = _label_of(lab, kinds, kind)
        assert got == CLASS_ID[kind] and share == 1.0
    a, sa = _label_of(lab, kinds, "A")
    b, sb = _label_of(lab, kinds, "B")
    assert a >= NOVEL_ID_START and b >= NOVEL_ID_START and a != b and sa == sb == 1.0
    assert {a, b} == {NOVEL_ID_START, NOVEL_ID_START + 1}
    # The same objects seen again, elsewhere and with segments listed in another order.
    rng = np.random.default_rng(1)
    for frame in range(2, 6):
        layout = [LAYOUT[i] for i in rng.permutation(len(LAYOUT))]
        seg, emb, ent, kinds = _frame(layout, frame)
        lab = d.process_segments(seg, emb, ent)
        assert _label_of(lab, kinds, "A") == (a, 1.0)
        assert _label_of(lab, kinds, "B") == (b, 1.0)
    cls = d.classes()
    assert cls[a]["kind"] == "novel" and cls[CLASS_ID["wall"]]["kind"] == "known"
    assert cls[CLASS_ID["wall"]]["name"] == "wall"
    assert cls[a]["pixels"] == int((lab == a).sum()) > 0
    assert sum(v["pixels"] for v in cls.values()) == H * W


def test_new_novel_object_gets_a_fresh_id_and_ids_are_never_reused():
    d = _discoverer()
    seg, emb, ent, kinds = _frame(LAYOUT, 0)
    lab = d.process_segments(seg, emb, ent)
    first = {_label_of(lab, kinds, "A")[0], _label_of(lab, kinds, "B")[0]}
    # B leaves the view for good; a new novel kind C appears.
    NOVEL_MIX["C"] = {5: 1.4, 2: 0.5}
    try:
        layout = [k for k in LAYOUT if k[0] != "B"] + [("C", (22, 34, 40, 52)),
                                                      ("C", (22, 34, 54, 66))]
        ids_c = set()
        for frame in range(1, 4):
            seg, emb, ent, kinds = _frame(layout, frame)
            lab = d.process_segments(seg, emb, ent)
            c, share = _label_of(lab, kinds, "C")
            assert c >= NOVEL_ID_START and share == 1.0
            ids_c.add(c)
        assert len(ids_c) == 1 and not ids_c & first
        assert _label_of(lab, kinds, "A")[0] in first
    finally:
        del NOVEL_MIX["C"]


def test_cluster_numbering_does_not_change_ids():
    d = _discoverer()
    for frame in range(3):
        seg, emb, ent, kinds = _frame(LAYOUT, frame)
        d.process_segments(seg, emb, ent)
    from neurncd_ros.core.discovery.mcl import markov_cluster
    clusters = markov_cluster(d._mem.desc, d.mcl_cfg)
    before = d.name_clusters(clusters)
    perm = np.random.default_rng(3).permutation(clusters.max() + 1)
    after = d.name_clusters(perm[clusters])
    assert after.tolist() == before.tolist()
    assert (before >= NOVEL_ID_START).any()


def test_segment_novelty_keeps_uncertain_segments_out_of_a_confident_cluster(monkeypatch):
    """Segments that lean to "wall" but are uncertain (a picture the backbone half
    calls wall) join the wall cluster; with segment_novelty they form a novel class."""
    wall_ch = list(CHANNEL_TO_ID).index(CLASS_ID["wall"])
    monkeypatch.setitem(NOVEL_MIX, "C", {wall_ch: 1.6})
    layout = [("wall", (r, r + 10, c, c + 40)) for r in (0, 10) for c in (0, 40)]
    layout += [("C", (22, 34, c, c + 14)) for c in (0, 16, 32, 48)]
    layout += [("floor", (45, 60, 0, 80))]
    seg, emb, ent, kinds = _frame(layout, 0)
    assert ent[kinds == "C"].mean() > 0.6 * np.log(S) > ent[kinds == "wall"].mean()
    merged = _discoverer().process_segments(seg, emb, ent)
    split = _discoverer(segment_novelty=True).process_segments(seg, emb, ent)
    assert _label_of(merged, kinds, "C") == (CLASS_ID["wall"], 1.0)
    assert _label_of(split, kinds, "C") == (NOVEL_ID_START, 1.0)
    for kind in ("wall", "floor"):
        assert _label_of(split, kinds, kind) == (CLASS_ID[kind], 1.0)


def test_every_pixel_labelled_and_unsegmented_pixels_use_embedding_argmax():
    d = _discoverer()
    seg, emb, ent, kinds = _frame(LAYOUT, 0)
    lab = d.process_segments(seg, emb, ent)
    assert (lab > 0).all()
    free = seg < 0
    assert free.any()
    assert (lab[free] == CHANNEL_TO_ID[emb[free].argmax(-1)]).all()
    # A non-finite embedding: inside a segment the segment's label still holds, outside
    # it the pixel is the only kind that stays 0.
    fy, fx = np.argwhere(free)[0]
    emb[fy, fx] = np.nan
    emb[0, 0] = np.nan
    lab2 = _discoverer().process_segments(seg, emb, ent)
    assert lab2[fy, fx] == 0 and lab2[0, 0] == lab[0, 0]
    assert (lab2 > 0).sum() == H * W - 1


def test_confident_pixels_keep_their_own_known_class_inside_a_known_segment():
    """A chair segment that took in a strip of floor (one depth segment over both):
    the floor strip's pixels, confidently floor, stay floor with pixel_known; without
    it the whole segment is chair. Uncertain pixels follow the segment."""
    seg, emb, ent, kinds = _frame(LAYOUT, 0)
    strip = (seg == 6) & (np.arange(W)[None, :] >= 76)  # the chair box's right edge
    rng = np.random.default_rng(5)
    emb[strip] = _logits("floor", rng, int(strip.sum()))
    p = softmax(emb)
    ent = -(p * np.log(p)).sum(-1).astype(np.float32)
    lab = _discoverer().process_segments(seg, emb, ent)
    assert (lab[strip] == CLASS_ID["floor"]).all()
    assert (lab[(seg == 6) & ~strip] == CLASS_ID["chair"]).all()
    off = _discoverer(pixel_known=False).process_segments(seg, emb, ent)
    assert (off[seg == 6] == CLASS_ID["chair"]).all()
    unsure = ent.copy()
    unsure[strip] = np.log(S)  # as uncertain as it gets: no longer its own
    lab = _discoverer().process_segments(seg, emb, unsure)
    assert (lab[strip] == CLASS_ID["chair"]).all()


def test_recluster_period_assigns_between_reclusterings():
    d = _discoverer(recluster_period=3)
    seg, emb, ent, kinds = _frame(LAYOUT, 0)
    lab0 = d.process_segments(seg, emb, ent)
    a = _label_of(lab0, kinds, "A")[0]
    seg, emb, ent, kinds = _frame(LAYOUT[::-1], 1)  # not a re-clustering frame
    lab1 = d.process_segments(seg, emb, ent)
    assert _label_of(lab1, kinds, "A") == (a, 1.0)
    assert _label_of(lab1, kinds, "floor") == (CLASS_ID["floor"], 1.0)


def test_large_memory_reclusters_less_often(monkeypatch):
    from neurncd_ros.core.discovery import labeller

    calls = []
    real = labeller.markov_cluster

    def counted(desc, cfg):
        calls.append(len(desc))
        return real(desc, cfg)

    monkeypatch.setattr(labeller, "markov_cluster", counted)
    d = _discoverer(recluster_segments=20)  # 7 segments per frame
    a = None
    for frame in range(6):
        seg, emb, ent, kinds = _frame(LAYOUT if frame % 2 == 0 else LAYOUT[::-1], frame)
        lab = d.process_segments(seg, emb, ent)
        # Re-clustered or not, every frame is labelled and the novel id is kept.
        assert _label_of(lab, kinds, "floor") == (CLASS_ID["floor"], 1.0)
        a = a or _label_of(lab, kinds, "A")[0]
        assert a >= NOVEL_ID_START and _label_of(lab, kinds, "A") == (a, 1.0)
    # Memory before frames 0..5: 0, 7, 14, 21, 28, 35 segments, so a re-clustering
    # every 1, 1, 1, ceil(1.05^2) = 2, ceil(1.4^2) = 2, ceil(1.75^2) = 4 frames:
    # at frames 0, 1, 2 and 4 (with 7, 14, 21 and 35 segments).
    assert calls == [7, 14, 21, 35]
    assert d.memory_len == 42 and d.recluster_every() == 5  # ceil(2.1^2)
    off = _discoverer(recluster_segments=0)
    for frame in range(6):
        seg, emb, ent, _ = _frame(LAYOUT, frame)
        off.process_segments(seg, emb, ent)
    assert len(calls) == 4 + 6 and off.recluster_every() == 1


def test_memory_is_bounded_and_keeps_recent_frames():
    d = _discoverer(memory_size=20, recent_frames=2)
    for frame in range(8):
        seg, emb, ent, _ = _frame(LAYOUT, frame)
        d.process_segments(seg, emb, ent)
    assert d.memory_len <= 20
    assert (d._mem.frame >= 6).sum() == 2 * len(LAYOUT)


def test_descriptor_modes_and_pooling():
    seg, emb, ent, _ = _frame(LAYOUT, 0)
    both = segment_descriptors(seg, emb, ent,
                               ModulationConfig(pooling="softmax", colour_weight=0.0))
    assert both.shape == (len(LAYOUT), S + 2) and both.dtype == np.float32
    assert np.allclose(both[:, :S].sum(1), 1.0, atol=1e-5)
    emb_only = segment_descriptors(seg, emb, ent, ModulationConfig(
        mode="embedding", colour_weight=0.0, pooling="softmax"))
    assert np.allclose(emb_only, both[:, :S])
    ent_only = segment_descriptors(seg, emb, ent, ModulationConfig(
        mode="entropy", colour_weight=0.0, entropy_weight=1.0))
    stats, _ = segment_stats(seg, emb, ent, ModulationConfig().entropy_interior)
    assert np.allclose(ent_only[:, 0], stats.mean_entropy / np.log(S), atol=1e-6)
    logit = segment_descriptors(seg, emb, ent, ModulationConfig(pooling="logits", colour_weight=0.0,
                                                                mode="embedding"))
    assert np.allclose(np.linalg.norm(logit, axis=1), 1.0, atol=1e-5)
    # Novel-object segments carry more entropy than the known ones.
    assert stats.mean_entropy[[1, 2, 4, 5]].min() > stats.mean_entropy[[0, 3, 6]].max()
    assert stats.pixels.tolist() == [int((seg == i).sum()) for i in range(len(LAYOUT))]


def test_interior_entropy_ignores_the_boundary_band():
    """A segment whose border pixels carry high entropy (as rendered boundaries do):
    interior pooling sees only the flat inside; a segment too thin for an interior
    keeps its all-pixel statistics."""
    from neurncd_ros.core.discovery.modulation import interior

    seg = np.full((20, 30), -1, np.int64)
    seg[2:18, 2:20] = 0
    seg[2:18, 22:24] = 1  # 2 px wide: no interior at radius 2
    ent = np.full(seg.shape, 0.1, np.float32)
    border = (seg == 0) & ~interior(seg, 2)
    ent[border] = 2.0
    ent[seg == 1] = 1.5
    emb = np.zeros(seg.shape + (S,), np.float32)
    core = interior(seg, 2)
    assert core[4:16, 4:18].all() and not core[2, 5] and not core[(seg == 1)].any()
    plain, _ = segment_stats(seg, emb, ent)
    inner, _ = segment_stats(seg, emb, ent, entropy_interior=2)
    assert plain.mean_entropy[0] > 0.5 and abs(inner.mean_entropy[0] - 0.1) < 1e-6
    assert inner.std_entropy[0] < 1e-3
    assert abs(inner.mean_entropy[1] - 1.5) < 1e-6 and inner.pixels[1] == 32


def test_process_end_to_end_on_a_synthetic_frame():
    from neurncd_ros import synth
    from neurncd_ros.core.discovery.metrics import evaluate
    d = Discoverer(DiscoveryConfig(**STAND_IN), CHANNEL_TO_ID)
    preds, gts = [], []
    for i, f in enumerate(synth.generate(0, 7, synth.SynthConfig())):
        if i % 3:
            continue
        emb = simulate_embedding(f.semantic, f.instance, seed=i)
        p = softmax(emb)
        ent = -(p * np.log(np.maximum(p, 1e-12))).sum(-1).astype(np.float32)
        lab = d.process(f.depth, f.intrinsics, emb, ent, f.stamp_ns, f.rgb)
        assert lab.shape == f.depth.shape and lab.dtype == np.uint16 and (lab > 0).all()
        preds.append(lab)
        gts.append(f.semantic)
    r = evaluate(preds, gts)
    # Known classes are mostly right with a clean stand-in embedding.
    assert r["miou_known"] > 40.0, r


def test_bad_inputs_raise_value_error():
    d = _discoverer()
    intr = Intrinsics.from_hfov(W, H)
    depth = np.full((H, W), 2.0, np.float32)
    with pytest.raises(ValueError, match="channel_to_id"):
        d.process(depth, intr, np.zeros((H, W, S + 1), np.float32), np.zeros((H, W)))
    with pytest.raises(ValueError, match="depth"):
        d.process(depth[:10], intr, np.zeros((H, W, S), np.float32), np.zeros((H, W)))
    with pytest.raises(ValueError, match="entropy"):
        d.process_segments(np.zeros((H, W), np.int32), np.zeros((H, W, S), np.float32),
                           np.zeros((H, 3)))
    with pytest.raises(ValueError, match="NYU-13"):
        Discoverer(DiscoveryConfig(), np.array([0, 50]))


def _paint(kinds, colours):
    """uint8 RGB image: each kind's colour (from an RGB triple), small pixel noise."""
    rng = np.random.default_rng(7)
    img = np.zeros((H, W, 3), np.float64)
    for kind, rgb in colours.items():
        img[kinds == kind] = rgb
    img += rng.normal(0, 2.0, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def test_colour_and_mode_split_find_a_picture_the_logits_call_wall():
    """A picture whose logits are confidently "wall" differs from the wall only in
    colour: with the colour descriptor and mode_split it is a novel class; without
    either it is wall. A wall of two similar shades and a floor of two different
    colours of comparable size (known classes that vary) stay one known class each."""
    layout = [("wall", (r, r + 10, c, c + 40)) for r in (0, 10, 20, 30) for c in (0, 40)]
    layout += [("picture", (2, 10, 2 + c, 12 + c)) for c in (0, 20)]
    layout += [("floor", (45, 60, 0, 40)), ("floor2", (45, 60, 40, 80))]
    seg = np.full((H, W), -1, np.int32)
    kinds = np.full((H, W), "", dtype=object)
    for i, (kind, (r0, r1, c0, c1)) in enumerate(layout):
        seg[r0:r1, c0:c1] = i
        kinds[r0:r1, c0:c1] = kind
    kinds[(kinds == "wall") & (np.arange(W)[None, :] >= 40)] = "wall2"
    rng = np.random.default_rng(0)
    emb = _logits("wall", rng, H * W).reshape(H, W, S)
    emb[45:] = _logits("floor", rng, 15 * W).reshape(15, W, S)
    p = softmax(emb)
    ent = -(p * np.log(p)).sum(-1).astype(np.float32)
    rgb = _paint(kinds, {"wall": (220, 210, 190), "wall2": (205, 196, 178),
                         "picture": (30, 40, 120), "floor": (120, 80, 40),
                         "floor2": (90, 90, 95)})
    kinds[kinds == "wall2"] = "wall"
    kinds[kinds == "floor2"] = "floor"
    cfg = dict(STAND_IN, min_cluster_segments=1)
    with_both = _discoverer(**cfg, mode_split=True).process_segments(seg, emb, ent, rgb)
    assert _label_of(with_both, kinds, "picture") == (NOVEL_ID_START, 1.0)
    for kind in ("wall", "floor"):
        assert _label_of(with_both, kinds, kind) == (CLASS_ID[kind], 1.0)
    no_split = _discoverer(**cfg, mode_split=False).process_segments(seg, emb, ent, rgb)
    assert _label_of(no_split, kinds, "picture") == (CLASS_ID["wall"], 1.0)
    d = Discoverer(DiscoveryConfig(min_cluster_pixels=50, mode_split=True, **cfg), CHANNEL_TO_ID,
                   mcl_cfg=MCLConfig(k=10), mod_cfg=ModulationConfig(colour_weight=0.0))
    assert _label_of(d.process_segments(seg, emb, ent, rgb), kinds, "picture") == \
        (CLASS_ID["wall"], 1.0)


def test_colour_stats_and_bad_colour():
    seg = np.zeros((H, W), np.int32)
    seg[:, W // 2:] = 1
    emb = np.zeros((H, W, S), np.float32)
    ent = np.zeros((H, W), np.float32)
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:, W // 2:] = 255
    stats, _ = segment_stats(seg, emb, ent, colour=rgb)
    np.testing.assert_allclose(stats.mean_lab[:, 0], [0.0, 1.0], atol=1e-3)
    np.testing.assert_allclose(stats.std_lab, 0.0, atol=1e-3)
    d = segment_descriptors(seg, emb, ent, ModulationConfig(colour_weight=2.0, colour_std=True),
                            colour=rgb)
    assert d.shape == (2, S + 2 + 6)
    np.testing.assert_allclose(d[1, S + 2], 2.0, atol=1e-3)
    # No colour image: same width, zero colour part.
    d0 = segment_descriptors(seg, emb, ent, ModulationConfig(colour_weight=2.0))
    assert d0.shape == (2, S + 2 + 3) and not d0[:, S + 2:].any()
    with pytest.raises(ValueError, match="colour must be"):
        segment_stats(seg, emb, ent, colour=rgb[:10])
    with pytest.raises(ValueError, match="uint8"):
        segment_stats(seg, emb, ent, colour=rgb.astype(np.float32))


def test_area_part_is_the_segments_metric_size():
    intr = Intrinsics.from_hfov(W, H, 90.0)
    seg = np.zeros((H, W), np.int32)
    seg[:, W // 2:] = 1
    seg[:2, :2] = -1
    emb = np.zeros((H, W, S), np.float32)
    ent = np.zeros((H, W), np.float32)
    depth = np.full((H, W), 2.0, np.float32)
    depth[:, -3:] = 0.0  # no measurement: adds nothing to segment 1's area
    stats, _ = segment_stats(seg, emb, ent, depth=depth, intrinsics=intr)
    px = 4.0 / (intr.fx * intr.fy)  # one pixel's footprint at 2 m
    np.testing.assert_allclose(stats.area, [((seg == 0).sum()) * px,
                                            ((seg == 1) & (depth > 0)).sum() * px], rtol=1e-5)
    cfg = ModulationConfig(area_weight=0.5, colour_weight=0.0)
    near = segment_descriptors(seg, emb, ent, cfg, depth=depth, intrinsics=intr)
    far = segment_descriptors(seg, emb, ent, cfg, depth=2 * depth, intrinsics=intr)
    # Twice as far, the same pixels cover four times the area.
    np.testing.assert_allclose(far[:, -1] - near[:, -1], 0.5 * np.log10(4.0), atol=1e-3)
    # Without depth the part keeps its width and is zero; weight 0 has no part.
    nodepth = segment_descriptors(seg, emb, ent, cfg)
    assert nodepth.shape == near.shape and not nodepth[:, -1].any()
    assert segment_descriptors(seg, emb, ent, ModulationConfig(colour_weight=0.0),
                               depth=depth, intrinsics=intr).shape[1] == near.shape[1] - 1
    with pytest.raises(ValueError, match="depth must be"):
        segment_stats(seg, emb, ent, depth=depth[:10], intrinsics=intr)
    # The Discoverer gives its frame's depth to the descriptor.
    d = Discoverer(DiscoveryConfig(), CHANNEL_TO_ID, mod_cfg=cfg)
    d.process(depth + 0.0, intr, emb, ent)
    areas = 10 ** (d._mem.desc[:, -1] / 0.5)
    assert d._mem.desc.shape[1] == near.shape[1] and areas.sum() > 0.5 * (depth > 0).sum() * px


def test_novel_clusters_close_in_descriptor_space_share_one_id():
    """Markov clustering may split one novel object into clusters (here A's two
    segments, split by hand); with novel_merge_distance they are one novel class,
    while the distinct novel object B keeps an id of its own; 0 turns it off."""
    seg, emb, ent, kinds = _frame(LAYOUT, 0)

    def named(distance):
        d = _discoverer(min_cluster_segments=1, novel_merge_distance=distance)
        d.process_segments(seg, emb, ent)
        mem = d._mem
        seg_of = {int(u): i for i, u in enumerate(mem.uid)}  # one frame: uid = segment id
        clusters = np.array([{0: 0, 1: 1, 2: 2, 3: 3, 4: 4, 5: 4, 6: 5}[int(u)]
                             for u in mem.uid])
        lab = d.name_clusters(clusters)
        return {kind: {int(lab[seg_of[i]]) for i, (k, _) in enumerate(LAYOUT) if k == kind}
                for kind in ("A", "B")}, d

    merged, d = named(0.4)
    a_desc = d._mem.desc[[1, 2]]
    assert np.linalg.norm(a_desc[0] - a_desc[1]) < 0.4  # A's segments are alike ...
    assert len(merged["A"]) == 1 and len(merged["B"]) == 1  # ... so one id for A
    assert merged["A"] != merged["B"] and min(merged["A"] | merged["B"]) >= NOVEL_ID_START
    apart, _ = named(0.0)
    assert len(apart["A"]) == 2 and apart["A"].isdisjoint(apart["B"])


def test_uncertain_pixels_without_segment_join_the_nearest_novel_label():
    """The band between two pieces of a novel object (no segment, uncertain) takes the
    object's novel id within novel_fill_px; confident or far pixels keep their argmax."""
    layout = [("wall", (0, 20, 0, 80)), ("A", (22, 32, 0, 12)), ("A", (22, 32, 16, 28)),
              ("floor", (45, 60, 0, 80)), ("A", (22, 32, 40, 52))]
    seg, emb, ent, kinds = _frame(layout, 0)
    rng = np.random.default_rng(5)
    # An uncertain gap between the first two pieces, and an uncertain patch far away.
    for r0, r1, c0, c1 in ((22, 32, 12, 16), (38, 43, 70, 76)):
        emb[r0:r1, c0:c1] = _logits("A", rng, (r1 - r0) * (c1 - c0)).reshape(r1 - r0,
                                                                              c1 - c0, S)
    p = softmax(emb)
    ent = -(p * np.log(p)).sum(-1).astype(np.float32)
    # W = 80 px: 80 px at the 640 px reference width reach 10 px here.
    lab = _discoverer(novel_fill_px=80).process_segments(seg, emb, ent)
    a, share = _label_of(lab, kinds, "A")
    assert a >= NOVEL_ID_START and share == 1.0
    assert (lab[22:32, 12:16] == a).all()
    far = lab[38:43, 70:76]
    assert (far == CHANNEL_TO_ID[emb[38:43, 70:76].argmax(-1)]).all()
    # Confident pixels without a segment next to the object keep the argmax (wall).
    assert (lab[20:22, 0:28] == CLASS_ID["wall"]).all()
    off = _discoverer(novel_fill_px=0).process_segments(seg, emb, ent)
    assert (off[22:32, 12:16] < NOVEL_ID_START).all()


def test_uncertain_pixels_inside_a_known_segment_join_the_adjacent_novel_label():
    """With novel_fill_known (default) the fill also reaches uncertain pixels that a
    known segment holds (a picture's frame cut into the wall segment): next to the novel
    object they take its id; uncertain pixels far from it, and confident ones next to
    it, stay wall; off, the wall segment keeps them all."""
    layout = [("wall", (0, 20, 0, 80)), ("A", (22, 32, 0, 12)), ("A", (22, 32, 14, 26)),
              ("floor", (45, 60, 0, 80))]
    seg, emb, ent, kinds = _frame(layout, 0)
    rng = np.random.default_rng(7)
    band, far = (slice(17, 20), slice(0, 12)), (slice(2, 5), slice(60, 66))
    for r, c in (band, far):
        n = (r.stop - r.start) * (c.stop - c.start)
        emb[r, c] = _logits("A", rng, n).reshape(r.stop - r.start, c.stop - c.start, S)
    p = softmax(emb)
    ent = -(p * np.log(p)).sum(-1).astype(np.float32)
    assert ent[band].mean() > 0.6 * np.log(S)  # uncertain, inside the wall segment
    lab = _discoverer(novel_fill_px=80).process_segments(seg, emb, ent)
    a, _ = _label_of(lab, kinds, "A")
    assert a >= NOVEL_ID_START
    assert (lab[band] == a).mean() > 0.9
    assert (lab[far] == CLASS_ID["wall"]).all()
    assert (lab[17:20, 30:50] == CLASS_ID["wall"]).all()  # confident, near A's second piece
    off = _discoverer(novel_fill_px=80, novel_fill_known=False).process_segments(seg, emb, ent)
    assert (off[band] == CLASS_ID["wall"]).all()


def test_uncertain_region_without_depth_becomes_a_novel_segment():
    """A large region the segmentation leaves out (here: no depth, as on glass) whose
    embedding is unsure gets a novel id of its own; a small one, or the feature off,
    keeps the per-pixel argmax."""
    rng = np.random.default_rng(3)
    depth = np.full((H, W), 2.0, np.float32)
    emb = _logits("wall", rng, H * W).reshape(H, W, S)
    hole, speck = (slice(22, 34), slice(40, 66)), (slice(50, 53), slice(5, 8))
    for r, c in (hole, speck):
        depth[r, c] = 0.0
        n = (r.stop - r.start) * (c.stop - c.start)
        emb[r, c] = _logits("A", rng, n).reshape(r.stop - r.start, c.stop - c.start, S)
    p = softmax(emb)
    ent = -(p * np.log(p)).sum(-1).astype(np.float32)
    assert ent[hole].mean() > 0.6 * np.log(S) > ent[:20].mean()
    intr = Intrinsics.from_hfov(W, H)
    # W = 80: 1200 px at the 640 px reference width are 19 px here.
    kw = dict(min_cluster_segments=1, uncertain_region_entropy=0.6)
    lab = _discoverer(uncertain_region_px=1200, **kw).process(depth, intr, emb, ent)
    vals, counts = np.unique(lab[hole], return_counts=True)
    assert vals[np.argmax(counts)] >= NOVEL_ID_START and counts.max() == lab[hole].size
    assert (lab[speck] == CHANNEL_TO_ID[emb[speck].argmax(-1)]).all()
    assert (lab[:20] == CLASS_ID["wall"]).mean() > 0.95
    off = _discoverer(uncertain_region_px=0, **kw).process(depth, intr, emb, ent)
    assert (off[hole] < NOVEL_ID_START).all()


def _flush_picture(picture=(slice(20, 34), slice(30, 50))):
    """A wall at 2 m with a picture flush with it (no depth step) and a band of
    uncertainty two pixels wide along the floor's edge: the embedding is unsure on both
    although its argmax is "wall". Returns depth, embedding, entropy, picture, band."""
    rng = np.random.default_rng(5)
    depth = np.full((H, W), 2.0, np.float32)
    emb = _logits("wall", rng, H * W).reshape(H, W, S)
    band = (slice(45, 47), slice(5, 75))
    wall_ch = list(CHANNEL_TO_ID).index(CLASS_ID["wall"])
    for r, c in (picture, band):
        unsure = rng.normal(0, 0.3, (r.stop - r.start, c.stop - c.start, S))
        unsure[..., wall_ch] += 1.0
        emb[r, c] = unsure
    p = softmax(emb)
    ent = -(p * np.log(p)).sum(-1).astype(np.float32)
    assert (emb[picture].argmax(-1) == wall_ch).mean() > 0.9
    assert ent[picture].mean() > 0.8 * np.log(S) and ent.mean() < 0.6 * np.log(S)
    return depth, emb, ent, picture, band


def _label_flush(depth, emb, ent, **kw):
    """One frame through a Discoverer with the uncertain regions on, the picture's region
    carved (embedding edges off, so the segmentation leaves it in the wall's segment)."""
    from neurncd_ros.core.discovery.geoseg import GeoSegConfig
    cfg = DiscoveryConfig(**{**STAND_IN, "min_cluster_segments": 1, "segment_novelty": True,
                             "min_cluster_pixels": 50, "uncertain_region_px": 300,
                             "uncertain_region_entropy": 0.6,
                             "uncertain_region_opening": 24,  # 3 px at W = 80
                             **kw})
    d = Discoverer(cfg, CHANNEL_TO_ID, mcl_cfg=MCLConfig(k=10),
                   seg_cfg=GeoSegConfig(embedding_edges=False))
    return d.process(depth, Intrinsics.from_hfov(W, H), emb, ent)


def test_uncertain_region_inside_a_known_segment_is_carved_out():
    """A picture flush with a wall that the segmentation left inside the wall's segment,
    whose embedding is unsure although its argmax is "wall": with
    ``uncertain_region_carve`` it becomes a segment of its own and gets a novel id. A band
    of uncertain pixels two pixels wide (an object's border) stays wall, and without the
    carve so does the picture."""
    depth, emb, ent, picture, band = _flush_picture()
    lab = _label_flush(depth, emb, ent, uncertain_region_carve=True)
    vals, counts = np.unique(lab[picture], return_counts=True)
    assert vals[np.argmax(counts)] >= NOVEL_ID_START and counts.max() > 0.9 * lab[picture].size
    assert (lab[band] == CLASS_ID["wall"]).mean() > 0.9
    assert (lab[:15] == CLASS_ID["wall"]).all()
    off = _label_flush(depth, emb, ent, uncertain_region_carve=False)
    assert (off[picture] == CLASS_ID["wall"]).mean() > 0.9


def test_a_small_very_uncertain_cluster_is_novel_before_min_cluster_pixels():
    """An object in the first frame it appears in: its carved region (280 px) is below
    ``min_cluster_pixels`` (500), but its mean entropy is above
    ``uncertain_region_entropy``, so from ``uncertain_cluster_pixels`` (scaled from the
    640 px reference width: 6400 -> 100 px at W = 80) it is novel already. Above its size,
    off, or with the entropy bar above the cluster's mean entropy it is undecided, and
    painted with its argmax, "wall"."""
    depth, emb, ent, picture, _ = _flush_picture()
    assert emb[picture].shape[0] * emb[picture].shape[1] == 280

    def novel_share(**kw):
        lab = _label_flush(depth, emb, ent, min_cluster_pixels=500, **kw)
        return float((lab[picture] >= NOVEL_ID_START).mean())

    assert novel_share(uncertain_cluster_pixels=6400) > 0.9
    assert novel_share(uncertain_cluster_pixels=32000) < 0.1  # 500 px at W = 80
    assert novel_share(uncertain_cluster_pixels=0) < 0.1


@pytest.mark.parametrize("entropy, age, novel", [(0.95, 0, True), (0.7, 0, False),
                                                 (0.95, 3, True), (0.95, 4, False)])
def test_uncertain_cluster_pixels_needs_the_region_entropy_and_a_new_cluster(entropy, age,
                                                                           novel):
    """A cluster of 100 px, below ``min_cluster_pixels``, is novel at the smaller
    ``uncertain_cluster_pixels`` only if its mean entropy is above
    ``uncertain_region_entropy`` (0.9 log S; one merely above the known/novel threshold,
    0.7 log S, stays undecided) and its segments are at most ``uncertain_cluster_frames``
    (3) frames old: an object that has just come into view, not an old fragment."""
    from neurncd_ros.core.discovery.labeller import UNDECIDED, _Memory
    d = Discoverer(DiscoveryConfig(min_cluster_pixels=500, uncertain_cluster_pixels=64,
                                   uncertain_region_entropy=0.9, uncertain_cluster_frames=3),
                   CHANNEL_TO_ID)
    hist = np.zeros((1, S), np.int64)
    hist[0, list(CHANNEL_TO_ID).index(CLASS_ID["wall"])] = 100
    d._mem = _Memory(uid=np.zeros(1, np.int64), frame=np.zeros(1, np.int64),
                     desc=np.zeros((1, 4), np.float32), pixels=np.array([100]),
                     ent_sum=np.array([entropy * np.log(S) * 100]), hist=hist,
                     cluster=np.zeros(1, np.int64))
    d._frames = age  # the frame being labelled; the segment came in frame 0
    label = int(d.name_clusters(np.zeros(1, np.int64))[0])
    assert (label >= NOVEL_ID_START) if novel else (label == UNDECIDED)


def _uncertain_memory(d, desc):
    """Put segments with descriptors ``desc`` into ``d``'s memory, every one uncertain
    (mean entropy 0.9 log S, 100 pixels), as if they came from earlier frames, beside 20
    confident wall segments far from them."""
    from neurncd_ros.core.discovery.labeller import _Memory
    noise = np.random.default_rng(0).normal(0, 0.02, (20, desc.shape[1]))
    wall = np.full((20, desc.shape[1]), -1.0) + noise
    desc = np.concatenate([desc, wall])
    n, k = len(desc), len(desc) - 20
    hist = np.zeros((n, S), np.int64)
    hist[:, list(CHANNEL_TO_ID).index(CLASS_ID["wall"])] = 100
    ent = np.where(np.arange(n) < k, 0.9, 0.05) * np.log(S) * 100
    d._mem = _Memory(uid=np.arange(n, dtype=np.int64), frame=np.zeros(n, np.int64),
                     desc=desc.astype(np.float32), pixels=np.full(n, 100, np.int64),
                     ent_sum=ent, hist=hist, cluster=np.full(n, -1, np.int64))


def test_uncertain_segments_of_three_novel_classes_keep_three_ids():
    """Three novel classes' uncertain segments, a few hundred pixels apart in descriptor
    space (0.49, beyond novel_merge_distance): at novel_inflation 2 (the default) they are
    three novel ids; at the memory's inflation 1.4 Markov clustering flows them into one
    (what made a long run give the picture, window and ceiling one id)."""
    rng = np.random.default_rng(3)
    centres = np.eye(12)[:3] * 0.35
    desc = np.concatenate([c + rng.normal(0, 0.06, (20, 12)) for c in centres])
    truth = np.repeat(np.arange(3), 20)

    def ids(**kw):
        d = Discoverer(DiscoveryConfig(segment_novelty=True, min_cluster_pixels=50, **kw),
                       CHANNEL_TO_ID)
        _uncertain_memory(d, desc)
        d._recluster()
        assert (d._mem.cluster[60:] == CLASS_ID["wall"]).all()
        assert (d._mem.cluster[:60] >= NOVEL_ID_START).all()  # the uncertain ones: novel
        return d._mem.cluster[:60]

    lab = ids()
    for c in range(3):
        assert len(set(lab[truth == c].tolist())) == 1  # one id per class ...
    assert len(set(lab.tolist())) == 3  # ... and three ids
    assert len(set(ids(novel_inflation=1.4).tolist())) == 1


def test_novel_merge_does_not_chain_across_classes():
    """Novel clusters on a chain, each within novel_merge_distance of the next, as pieces
    between two objects put them: average link joins the close pairs but not the chain's
    ends (single link made them one id); two far groups stay apart, 0 turns merging off."""
    d = Discoverer(DiscoveryConfig(novel_merge_distance=0.4), CHANNEL_TO_ID)
    chain = np.outer([0.0, 0.3, 0.65, 0.95, 1.3], np.eye(4)[0])
    g = d._novel_groups(chain)
    assert g[0] == g[1] and g[2] == g[3] and len({g[0], g[2], g[4]}) == 3
    far = np.concatenate([np.zeros((2, 4)), np.full((2, 4), 2.0)]) + np.eye(4)[:, :] * 0.05
    g = d._novel_groups(far)
    assert g[0] == g[1] and g[2] == g[3] and g[0] != g[2]
    off = Discoverer(DiscoveryConfig(novel_merge_distance=0.0), CHANNEL_TO_ID)
    assert off._novel_groups(chain).tolist() == [0, 1, 2, 3, 4]


def test_segments_between_reclusterings_join_clusters_of_their_own_kind():
    """Between re-clusterings an uncertain segment joins the novel cluster, not the
    confident wall cluster whose mean descriptor is nearer to it; a confident segment
    joins the wall although the novel cluster's mean is nearer (as a re-clustering with
    segment_novelty would place them). Without segment_novelty the nearest wins."""
    from neurncd_ros.core.discovery.labeller import _Memory

    rng = np.random.default_rng(1)
    novel = np.eye(12)[0] * 0.35 + rng.normal(0, 0.02, (20, 12))
    d = Discoverer(DiscoveryConfig(segment_novelty=True, min_cluster_pixels=50), CHANNEL_TO_ID)
    _uncertain_memory(d, novel)
    d._recluster()
    wall, nov = CLASS_ID["wall"], int(d._mem.cluster[0])
    assert (d._mem.cluster[20:] == wall).all() and nov >= NOVEL_ID_START
    # Two arrivals: the first halfway but nearer the wall and uncertain, the second
    # nearer the novel class and confident.
    desc = np.stack([0.45 * np.eye(12)[0] * 0.35 + 0.55 * np.full(12, -1.0),
                     0.6 * np.eye(12)[0] * 0.35 + 0.4 * np.full(12, -1.0)])
    ent = np.array([0.9, 0.05]) * np.log(S) * 100
    new = _Memory(uid=np.array([100, 101]), frame=np.ones(2, np.int64),
                  desc=desc.astype(np.float32), pixels=np.full(2, 100, np.int64),
                  ent_sum=ent, hist=np.zeros((2, S), np.int64), cluster=np.full(2, -1))
    assert d._nearest_cluster(new).tolist() == [nov, wall]
    d_plain = Discoverer(DiscoveryConfig(segment_novelty=False), CHANNEL_TO_ID)
    d_plain._mem = d._mem
    assert d_plain._nearest_cluster(new).tolist() == [wall, nov]


def test_a_long_walk_keeps_the_novel_classes_apart():
    """Tuning seed 500 walked for 50 s (one labelled frame per second, the default
    backbone's embedding): by the last ten frames the memory holds about 1000 segments,
    hundreds of them uncertain, and the ceiling, the picture and the TV still get three
    different novel ids (at the memory's inflation with single-link merging and cosine
    assignment, all three took one id there; bench/discovery_memory.py measures the
    whole walk)."""
    from neurncd_ros import synth
    from neurncd_ros.core.backbone.backbone import BackboneConfig, load_backbone
    from neurncd_ros.core.uncertainty import entropy

    backbone = load_backbone(BackboneConfig(num_threads=0, precision="float32"))
    d = Discoverer(DiscoveryConfig(), CHANNEL_TO_ID)
    seen: dict[int, dict[int, int]] = {}
    frames = synth.generate(500, 50, synth.SynthConfig(fps=1.0))
    for i, fr in enumerate(frames):
        emb = backbone.embed(fr.rgb, fr.depth)
        lab = d.process(fr.depth, fr.intrinsics, emb, entropy(emb), fr.stamp_ns, fr.rgb,
                        None, fr.pose)
        if i < 40:
            continue
        for name in ("ceiling", "picture", "tv"):
            ids, counts = np.unique(lab[fr.semantic == CLASS_ID[name]], return_counts=True)
            for j, n in zip(ids.tolist(), counts.tolist()):
                if j >= NOVEL_ID_START:
                    seen.setdefault(CLASS_ID[name], {}).setdefault(j, 0)
                    seen[CLASS_ID[name]][j] += n
    assert d.memory_len > 800
    top = {c: max(ids, key=ids.get) for c, ids in seen.items()}
    assert len(top) == 3, f"a novel class got no novel id: {top}"
    assert len(set(top.values())) == 3, f"novel classes share an id: {top}"
