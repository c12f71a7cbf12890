"""The online engine's stages, in one process: health, embedding, mapper, discovery, offline.

Real inputs throughout: synthetic RGB-D frames with ground truth, the shipped
default backbone and a real (small) Embedding-NeRF.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from neurncd_ros import config, synth
from neurncd_ros.core import classes, uncertainty
from neurncd_ros.core.backbone.backbone import BackboneConfig, load_backbone
from neurncd_ros.core.engine import health as H
from neurncd_ros.core.engine.discovery import DiscoveryStage, ViewInput
from neurncd_ros.core.engine.embedding import EmbeddingNodeConfig, EmbeddingStage
from neurncd_ros.core.engine.mapping import MapperStage
from neurncd_ros.core.engine.views import resize_to
from neurncd_ros.core.engine.offline import OfflineEngine, mapper_factory
from neurncd_ros.core.engine.records import EmbeddingRecord, EmbeddingSpec

from fakeclock import MS, Clock  # noqa: E402,F401


@pytest.fixture(scope="module")
def cfg():
    return config.load(None, {"mapper.fast.rays_per_iteration": 256})


@pytest.fixture(scope="module")
def backbone():
    return load_backbone(BackboneConfig(num_threads=1))


@pytest.fixture(scope="module")
def frames():
    """Two seconds of a held-out room at 30 Hz, 96x72."""
    return list(synth.generate(1002, 60, synth.SynthConfig(width=96, height=72)))


# ------------------------------------------------------------------ health

def test_health_throttles_each_kind_of_problem_on_its_own():
    clock, lines = Clock(), []
    h = H.Health("x", lambda level, text: lines.append((level, text)), throttle_s=5.0,
                 window_s=10.0, clock=clock)
    h.problem("bad_depth", "depth A")
    h.problem("bad_depth", "depth B")          # throttled
    h.problem("bad_pose", "pose A")            # another kind: logged at once
    clock.t = 6.0
    h.problem("bad_depth", "depth C")
    assert [t for _, t in lines] == ["depth A", "pose A",
                                     "depth C (1 more of this kind since the last report)"]
    assert h.problems == {"bad_depth": 3, "bad_pose": 1}
    assert h.snapshot()["level"] == H.WARN
    clock.t = 30.0
    snap = h.snapshot()
    assert snap["level"] == H.OK and snap["values"]["problem.bad_depth"] == "3"
    h.fail("training", "thread died")
    h.set_state("running")                     # an error is final
    snap = h.snapshot()
    assert snap["level"] == H.ERROR and "thread died" in snap["message"]
    assert lines[-1][0] == H.ERROR


def test_a_note_is_logged_at_info_and_leaves_the_diagnostics_ok():
    """A decision the stage took (the pose source chosen) is logged, not reported as a
    problem: a healthy run's diagnostics stay OK."""
    clock, lines = Clock(), []
    h = H.Health("x", lambda level, text: lines.append((level, text)), clock=clock)
    h.set_state("running")
    h.note("pose_source", "pose source: topic (pose_source auto)")
    h.note("pose_source", "pose source: topic (pose_source auto)")   # throttled
    assert lines == [(H.OK, "pose source: topic (pose_source auto)")]
    assert not h.problems and h.counts["note.pose_source"] == 2
    snap = h.snapshot()
    assert snap["level"] == H.OK and snap["message"] == "running"


def test_a_partner_refused_before_pairing_is_named_as_the_cause():
    """Colour that arrives and is refused (an encoding the node cannot read): a depth given
    up unpaired says so, not that nothing came and large images may be lost in DDS."""
    clock, lines = Clock(), []
    h = H.Health("x", lambda level, text: lines.append(text), throttle_s=0.0, clock=clock)
    report = H.sync_reporter(h)
    report("depth", "unpaired", 5, "color")
    assert "nothing came on color" in lines[-1] and "Fast DDS profile" in lines[-1]
    h.refuse("color", "bad_color", "colour image skipped", "colour must be rgb8, got 'rgba8'")
    report("depth", "unpaired", 6, "color")
    assert lines[-1] == ("depth: the frame stamped 6 is given up unpaired: color arrives but "
                         "is refused: colour must be rgb8, got 'rgba8': dropped")
    report("depth", "unpaired", 7, "pose")  # another stream: as before
    assert "nothing came on pose" in lines[-1]
    clock.t = 2 * h.window_s  # the refusal is old news
    report("depth", "unpaired", 8, "color")
    assert "nothing came on color" in lines[-1]


def test_a_refusal_is_blamed_only_for_the_frame_it_was_the_partner_of():
    """A pose refused (its quaternion) 5 s of stamps before: a later frame given up for
    another reason (its pose stamped far from it) was said to lose its pose to that
    refusal. A refusal with a stamp is blamed only within REFUSED_NEAR_NS of the frame."""
    clock, lines = Clock(), []
    h = H.Health("x", lambda level, text: lines.append(text), throttle_s=0.0, clock=clock)
    report = H.sync_reporter(h)
    h.refuse("pose", "bad_pose", "pose skipped", "norm 2.000000", stamp_ns=1_000_000_000)
    report("color", "unpaired", 1_000_000_000 + H.REFUSED_NEAR_NS // 2, "pose")
    assert "pose arrives but is refused: norm 2.000000" in lines[-1]
    report("color", "unpaired", 6_000_000_000, "pose")  # another frame, another cause
    assert "refused" not in lines[-1] and "nothing came on pose" in lines[-1]
    assert h.refused() == {"pose": "norm 2.000000"}  # still what the stream does lately
    assert h.refused(6_000_000_000, H.REFUSED_NEAR_NS) == {}


def test_a_frame_names_a_camera_info_of_another_size():
    from neurncd_ros.core.camera import Intrinsics
    from neurncd_ros.core.frame import Frame
    rgb, depth = np.zeros((48, 64, 3), np.uint8), np.ones((48, 64), np.float32)
    small = Intrinsics.from_hfov(32, 24, 90.0)
    with pytest.raises(ValueError, match="^the camera info is for 32x24 but the colour and "
                                         "depth images are 64x48$"):
        Frame(1, rgb, depth, np.eye(4), small).validate()
    with pytest.raises(ValueError, match=r"^depth must be \(48, 64\) float32, got \(24, 32\)"):
        Frame(1, rgb, depth[:24, :32], np.eye(4), Intrinsics.from_hfov(64, 48, 90.0)).validate()
    Frame(1, rgb, depth, np.eye(4), Intrinsics.from_hfov(64, 48, 90.0)).validate()


def test_a_frame_says_what_is_wrong_with_its_arrays():
    """Arrays as a user's own data has them wrong: each a ValueError saying what to do,
    not an AttributeError from inside, nor a stamp in seconds taken as nanoseconds (30 s
    of stream in 30 ns: the rate gates let only the first frame through)."""
    from neurncd_ros.core.camera import Intrinsics
    from neurncd_ros.core.frame import Frame
    rgb, depth = np.zeros((48, 64, 3), np.uint8), np.ones((48, 64), np.float32)
    intr = Intrinsics.from_hfov(64, 48, 90.0)
    ok = Frame(1, rgb, depth, np.eye(4), intr)
    for change, match in (
            ({"depth": np.full((48, 64), 1500, np.uint16)},
             r"float32, got \(48, 64\) uint16 \(millimetres.*/ 1000\)"),
            ({"depth": -depth}, r"^depth must be >= 0 metres \(0 = no measurement\), min is -1"),
            ({"rgb": rgb.tolist()}, "^rgb must be a numpy array, got list$"),
            ({"semantic": [[0]]}, "^semantic must be a numpy array, got list$"),
            ({"intrinsics": intr.K}, r"^intrinsics must be an Intrinsics, got ndarray .*"
                                     r"Intrinsics.from_matrix\(K, width, height\)"),
            ({"stamp_ns": 1.5}, r"^stamp_ns must be an integer number of nanoseconds, got "
                                r"float 1.5 \(a stamp in seconds: int\(round\(seconds \* 1e9")):
        with pytest.raises(ValueError, match=match):
            dataclasses.replace(ok, **change).validate()
    nan = depth.copy()
    nan[0, :3] = [np.nan, np.inf, 0.0]  # holes, as 0 is
    dataclasses.replace(ok, depth=nan, stamp_ns=np.int64(1)).validate()


def test_health_rates_count_events_per_second():
    clock = Clock()
    h = H.Health("x", throttle_s=1.0, window_s=10.0, clock=clock)
    for i in range(21):
        clock.t = i * 0.5
        h.count("labelled")
    assert h.rate("labelled") == pytest.approx(2.1, rel=0.01)
    clock.t = 100.0
    assert h.rate("labelled") == 0.0 and h.counts["labelled"] == 21


# ------------------------------------------------------------------ embedding

def test_embedding_stage_pairs_keeps_the_newest_and_gates_by_stamp(backbone, frames):
    st = EmbeddingStage(backbone, EmbeddingNodeConfig(max_rate_hz=10.0, output_scale=0.5))
    assert st.spec.channel_to_id == tuple(classes.KNOWN_IDS)
    for f in frames[:3]:
        st.offer("depth", f.stamp_ns, f.depth)
        st.offer("color", f.stamp_ns, f.rgb)
    stamp, rgb, depth = st.take()
    assert stamp == frames[2].stamp_ns and st.take() is None
    assert st.health.counts["dropped_busy"] == 2
    rec = st.embed(stamp, rgb, depth)
    assert isinstance(rec, EmbeddingRecord) and rec.spec == st.spec
    assert rec.embedding.shape == (36, 48, 9) and rec.embedding.dtype == np.float32
    # 30 Hz stamps gated at 10 Hz: every third frame after the embedded one.
    picked = []
    for f in frames[3:12]:
        if st.wanted(f.stamp_ns):
            st.embed(f.stamp_ns, f.rgb, f.depth)
            picked.append(f)
    assert picked == frames[5:12:3]
    with pytest.raises(ValueError, match="registered to colour"):
        st.embed(stamp, rgb[:, :40], depth)


def test_a_diverged_backbone_is_named_not_stored_as_infinities(backbone, frames):
    """Logits of 1e9 (a checkpoint trained with too high a rate) became float16 infinities
    in the keyframes and an error 'logits contain NaN or inf' stages later: the embedding
    stage refuses them, saying what they mean."""

    class Diverged:
        def __getattr__(self, name):
            return getattr(backbone, name)

        def embed(self, *args, **kwargs):
            return backbone.embed(*args, **kwargs) * 1e8

    st = EmbeddingStage(Diverged(), EmbeddingNodeConfig(output_scale=0.5))
    f = frames[0]
    with pytest.raises(ValueError, match=r"logits reach .*default checkpoint looks diverged"):
        st.embed(f.stamp_ns, f.rgb, f.depth)
    ok = EmbeddingStage(backbone, EmbeddingNodeConfig(output_scale=0.5))
    assert np.isfinite(ok.embed(f.stamp_ns, f.rgb, f.depth).embedding).all()


def test_embedding_rate_gate_counts_from_the_pair_being_embedded(backbone, frames):
    """Online the backbone embeds a taken pair while the next ones arrive: those are
    gated against the taken pair's stamp, so a 30 Hz stream gated at 10 Hz is embedded
    every third frame, as offline, however long each embedding takes."""
    st = EmbeddingStage(backbone, EmbeddingNodeConfig(max_rate_hz=10.0, output_scale=0.5))
    taken, free_at = [], frames[0].stamp_ns
    for f in frames[:13]:
        st.offer("depth", f.stamp_ns, f.depth)
        st.offer("color", f.stamp_ns, f.rgb)
        if f.stamp_ns >= free_at:  # the backbone is free: it takes what waits...
            job = st.take()
            if job is not None:
                taken.append(job)
                free_at = f.stamp_ns + 50_000_000  # ... and embeds it for 50 ms
    for job in taken:
        st.embed(*job)
    assert [j[0] for j in taken] == [f.stamp_ns for f in frames[0:13:3]]
    assert st.health.counts["skipped_rate"] == 13 - len(taken)
    assert st.health.counts.get("dropped_busy", 0) == 0


@pytest.mark.parametrize("size, published", [((640, 480), (240, 320)),
                                               ((848, 480), (181, 320)),
                                               ((96, 72), (72, 96))])
def test_embedding_is_published_at_the_backbones_resolution(backbone, frames, size, published):
    """By default (output_scale 0) a frame wider than the network's input gets its embedding
    at the network's width, the frame's aspect kept: what the network saw, a quarter of the
    bytes of a 640x480 frame's. The values are the full-size embedding's, sampled there."""
    import cv2

    f = frames[0]
    rgb = cv2.resize(f.rgb, size, interpolation=cv2.INTER_LINEAR)
    depth = cv2.resize(f.depth, size, interpolation=cv2.INTER_NEAREST)
    st = EmbeddingStage(backbone, EmbeddingNodeConfig())
    assert st.input_width == 320
    emb = st.embed(f.stamp_ns, rgb, depth).embedding
    assert emb.shape == (*published, 9) and emb.dtype == np.float32
    full = EmbeddingStage(backbone, EmbeddingNodeConfig(output_scale=1.0)).embed(
        f.stamp_ns, rgb, depth).embedding
    assert full.shape == (size[1], size[0], 9)
    back = np.stack([cv2.resize(full[..., c], (published[1], published[0]),
                                interpolation=cv2.INTER_AREA) for c in range(9)], -1)
    assert np.mean(np.argmax(back, -1) == np.argmax(emb, -1)) > 0.97
    assert np.median(np.abs(back - emb)) < 0.1 * np.median(np.abs(full))


# ------------------------------------------------------------------ mapper

def _stage(cfg, **node) -> MapperStage:
    node_cfg = dataclasses.replace(cfg.mapper_node, **node)
    return MapperStage(node_cfg, mapper_factory(cfg), online=False)


def _record(backbone, f) -> EmbeddingRecord:
    return EmbeddingRecord(f.stamp_ns, backbone.embed(f.rgb, f.depth), backbone.spec)


def test_mapper_stage_serves_keyframes_first_then_the_newest_frame(cfg, backbone, frames):
    st = _stage(cfg, max_in_flight=2)
    jobs = [st.admit(f, _record(backbone, f)) for f in frames[:40:3]]
    kf = [j.frame.stamp_ns for j in jobs if j.keyframe]
    other = [j.frame.stamp_ns for j in jobs if not j.keyframe]
    assert kf[0] == frames[0].stamp_ns and len(kf) >= 2 and len(other) >= 2
    assert st.keyframe_stamps == kf
    # A frame is superseded by any newer one, keyframes too: the newest frame is served
    # only if no keyframe came after it (views reach discovery in stamp order).
    newest = [o for o in other if o > kf[-1]][-1:]
    assert st.health.counts["skipped_newer"] == len(other) - len(newest)
    first, second = st.next_view(), st.next_view()
    assert [first.frame.stamp_ns, second.frame.stamp_ns] == kf[:2]
    assert st.next_view() is None, "two views in flight: the renderer waits"
    st.labelled(first.frame.stamp_ns)
    rest = []
    while (job := st.next_view()) is not None:
        rest.append(job.frame.stamp_ns)
        st.labelled(job.frame.stamp_ns)
    assert rest == kf[2:] + newest, "every keyframe, then only the newest frame"
    assert rest == sorted(rest)
    assert st.pending == 1  # `second` is still unlabelled
    # A frame waiting when a keyframe arrives is not rendered after it (discovery would
    # drop it as older than a frame already paired, and hold its slot until the timeout).
    st = _stage(cfg, max_in_flight=8)
    jobs = [st.admit(f, _record(backbone, f)) for f in frames[:16:3]]
    assert [j.keyframe for j in jobs[-2:]] == [False, True]
    served = []
    while (job := st.next_view()) is not None:
        served.append(job.frame.stamp_ns)
    assert served == [j.frame.stamp_ns for j in jobs if j.keyframe] and served == sorted(served)


def test_views_are_the_backbone_until_the_field_has_learnt_the_scene(cfg, backbone, frames):
    st = _stage(cfg, mature_iterations=20, render_scale=0.5, fallback="backbone",
                field_views=True)
    jobs = [st.admit(f, _record(backbone, f)) for f in frames[:30:2]]
    job = jobs[-1]
    fresh = st.render_view(job)
    bb = resize_to(job.embedding.embedding, 36, 48)
    assert fresh.field_share == 0.0 and np.array_equal(fresh.embedding, bb)
    assert np.allclose(fresh.entropy, uncertainty.entropy(bb), atol=1e-6)
    st.mapper.step(40)
    view = st.render_view(job)
    assert view.embedding.shape == (36, 48, 9) and view.entropy.shape == (36, 48)
    assert view.field_share > 0.5, view.field_share
    assert not np.allclose(view.embedding, bb)
    # The field has learnt the backbone's classes on the keyframes it trained on.
    agree = (view.embedding.argmax(-1) == bb.argmax(-1)).mean()
    assert agree > 0.6, agree


def test_views_leave_a_learnt_field_out_unless_field_views(cfg, backbone, frames, monkeypatch):
    """By default (field_views off) a view is the keyframe fusion even where the field has
    trained long enough to count: the field is not rendered at all (its render costs ten
    times the fusion). With field_views the same stage blends the field in."""
    assert cfg.mapper_node.field_views is False
    views = {}
    for on in (False, True):
        st = _stage(cfg, mature_iterations=20, render_scale=0.5, fallback="keyframes",
                    field_views=on)
        jobs = [st.admit(f, _record(backbone, f)) for f in frames[:30:2]]
        fused = st.render_view(jobs[-1])  # before training: the fusion alone either way
        st.mapper.step(40)
        calls = []
        render = st.mapper.render_rays
        monkeypatch.setattr(st.mapper, "render_rays", lambda *a, **k: calls.append(1)
                            or render(*a, **k))
        views[on] = (fused, st.render_view(jobs[-1]), len(calls))
    (fused_off, learnt_off, calls_off), (fused_on, learnt_on, calls_on) = views[False], views[True]
    assert np.array_equal(fused_off.embedding, fused_on.embedding)
    assert calls_off == 0 and learnt_off.field_share == 0.0
    np.testing.assert_array_equal(learnt_off.embedding, fused_off.embedding)
    assert calls_on > 0 and learnt_on.field_share > 0.5
    assert not np.allclose(learnt_on.embedding, fused_on.embedding, atol=1e-3)


def test_a_learnt_field_reads_the_views_one_visibility_pass(cfg, backbone, frames,
                                                            monkeypatch):
    """At full size the coverage of a trained field reads the depth fusion's visibility
    test instead of testing its keyframes again, and blends the same field in."""
    from neurncd_ros.core.engine import views as V

    st = _stage(cfg, mature_iterations=20, render_scale=1.0, fallback="keyframes",
                depth_fusion=True, field_views=True)
    jobs = [st.admit(f, _record(backbone, f)) for f in frames[:30:2]]
    st.mapper.step(40)
    calls = []
    visible = V._visible
    monkeypatch.setattr(V, "_visible", lambda *a: calls.append(a[2]) or visible(*a))
    shared = st.render_view(jobs[-1])
    tested = len(calls)
    views = st._nearest_keyframes(jobs[-1].frame) + st._recent_views(jobs[-1].frame)
    assert tested == len(views) >= 2, "one test per stored view, none again for the coverage"
    monkeypatch.setattr(V.ViewVisibility, "first", lambda self, n: None)  # test anew
    again = st.render_view(jobs[-1])
    assert len(calls) - tested > tested, "without the shared pass the keyframes are tested twice"
    assert shared.field_share > 0.5 and abs(shared.field_share - again.field_share) < 1e-3
    assert np.allclose(shared.embedding, again.embedding, atol=1e-3)


def test_keyframe_fusion_averages_the_views_that_see_a_point_and_skips_occluded_ones():
    from types import SimpleNamespace

    from neurncd_ros.core.camera import Intrinsics
    from neurncd_ros.core.engine.views import fuse_keyframes

    intr = Intrinsics.from_hfov(8, 6, 60.0)
    pose = np.eye(4)

    def kf(depth_m, value, x=0.0):
        p = pose.copy()
        p[0, 3] = x
        emb = np.full((3, 4, 2), value, np.float16)  # half resolution, as stored
        return SimpleNamespace(pose=p, intrinsics=intr, depth=np.full((6, 8), depth_m,
                                                                     np.float32),
                               embedding=emb)

    points = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 9.0], [50.0, 0.0, 2.0]])
    own = np.zeros((3, 2), np.float32)
    # The first keyframe sees the wall at 2 m; the second sees it from 10 cm to the side;
    # the third measured 1 m there: something in front, so the point is occluded for it.
    fused, n, _ = fuse_keyframes(points, own, [kf(2.0, 3.0), kf(2.0, 6.0, x=0.1),
                                            kf(1.0, 100.0)], tolerance=0.05)
    assert n.tolist() == [3.0, 1.0, 1.0]  # the far and the off-image points: own view only
    assert np.allclose(fused[0], (0.0 + 3.0 + 6.0) / 3) and np.allclose(fused[1:], 0.0)
    # Probabilities: own softmax (1/2, 1/2), the keyframe's logits (ln 3, 0) -> (3/4, 1/4);
    # the mean (5/8, 3/8) comes back as log-probabilities.
    other = kf(2.0, 0.0)
    other.embedding[..., 0] = np.log(3.0)
    fused, n, h_views = fuse_keyframes(points[:1], own[:1], [other], 0.05, logit_channels=2,
                                       view_entropy=True)
    assert n.tolist() == [2.0] and np.allclose(fused, np.log([[5 / 8, 3 / 8]]), atol=1e-3)
    # The views' own entropies: ln 2 and H(3/4, 1/4); their mean lies below the entropy of
    # the mean (5/8, 3/8): the gap is the views' disagreement.
    h = lambda p: -sum(x * np.log(x) for x in p)  # noqa: E731
    assert np.allclose(h_views, [(np.log(2) + h((0.75, 0.25))) / 2], atol=1e-4)
    assert h((5 / 8, 3 / 8)) - h_views[0] > 0.03
    # The frame's own view counted twice: (2 (1/2, 1/2) + (3/4, 1/4)) / 3 = (7/12, 5/12);
    # still two views seen, and the mean entropy weighted alike.
    fused, n, h_views = fuse_keyframes(points[:1], own[:1], [other], 0.05, logit_channels=2,
                                       view_entropy=True, own_weight=2.0)
    assert n.tolist() == [2.0] and np.allclose(fused, np.log([[7 / 12, 5 / 12]]), atol=1e-3)
    assert np.allclose(h_views, [(2 * np.log(2) + h((0.75, 0.25))) / 3], atol=1e-4)
    # A point no other view sees keeps the frame's own embedding, whatever its weight.
    fused, n, _ = fuse_keyframes(points[1:2], own[1:2] + 1.0, [other], 0.05, own_weight=2.0)
    assert n.tolist() == [1.0] and np.allclose(fused, 1.0)


def test_fusion_inputs_reuse_each_views_probabilities_and_forget_views_no_longer_read():
    from types import SimpleNamespace

    from neurncd_ros.core.camera import Intrinsics
    from neurncd_ros.core.engine.views import FusionInputs, fuse_keyframes

    rng = np.random.default_rng(3)
    intr = Intrinsics.from_hfov(16, 12, 60.0)

    def view(stamp, x):
        pose = np.eye(4)
        pose[0, 3] = x
        return SimpleNamespace(stamp_ns=stamp, pose=pose, intrinsics=intr,
                               depth=np.full((12, 16), 2.0, np.float32),
                               embedding=rng.normal(size=(12, 16, 5)).astype(np.float16))

    views = [view(i, 0.02 * i) for i in range(4)]
    points = np.stack([rng.uniform(-0.5, 0.5, 50), rng.uniform(-0.4, 0.4, 50),
                       np.full(50, 2.0)], 1)
    own = rng.normal(size=(50, 5)).astype(np.float32)
    cache = FusionInputs()
    for kept in (views[:3], views[1:]):  # the second rendering reads two views again
        plain = fuse_keyframes(points, own, kept, 0.05, logit_channels=3, view_entropy=True)
        cached = fuse_keyframes(points, own, kept, 0.05, logit_channels=3,
                                view_entropy=True, inputs=cache)
        for a, b in zip(plain, cached):
            assert np.array_equal(a, b)
        assert plain[1].max() == 4.0  # every view saw some of the points
        cache.keep(kept)
        assert len(cache) == 3
    # After a map reset a new view may come with an old stamp: it is converted anew.
    fresh = view(2, 0.04)
    again = fuse_keyframes(points, own, views[1:2] + [fresh] + views[3:], 0.05,
                           logit_channels=3, inputs=cache)[0]
    plain = fuse_keyframes(points, own, views[1:2] + [fresh] + views[3:], 0.05,
                           logit_channels=3)[0]
    assert np.array_equal(again, plain)


def _plane_depth(intr, pose, normal, offset):
    """Exact z-depth of the plane normal . p = offset seen from a camera (camera-to-world)."""
    from neurncd_ros.core.camera import camera_directions, pixel_grid

    u, v = pixel_grid(intr.height, intr.width)
    rays = camera_directions(intr, u, v) @ pose[:3, :3].T  # camera z = 1
    t = (offset - normal @ pose[:3, 3]) / (rays @ normal)
    return t.astype(np.float32)


def test_depth_fusion_averages_what_the_keyframes_measured_of_each_point():
    from types import SimpleNamespace

    from neurncd_ros.core.camera import Intrinsics, look_at
    from neurncd_ros.core.engine.views import fuse_depth

    intr = Intrinsics.from_hfov(64, 48, 60.0)
    normal = np.array([0.3, 0.1, 1.0]) / np.linalg.norm([0.3, 0.1, 1.0])  # a slanted wall
    offset = 2.0
    view_pose = look_at(np.zeros(3), np.array([0.0, 0.0, 1.0]), up=np.array([0.0, -1.0, 0.0]))
    kf_poses = [look_at(np.array(e), np.array([0.1, 0.0, 2.0]), up=np.array([0.0, -1.0, 0.0]))
                for e in ([0.15, 0, 0], [-0.15, 0, 0], [0, 0.12, 0.1], [0, -0.12, -0.1])]
    truth = _plane_depth(intr, view_pose, normal, offset)
    exact = [_plane_depth(intr, p, normal, offset) for p in kf_poses]
    kfs = [SimpleNamespace(pose=p, intrinsics=intr, depth=d) for p, d in zip(kf_poses, exact)]

    # Geometry: exact depths in, the view's exact depth out, up to each keyframe's pixel
    # rounding on the slanted wall (its nearest pixel is up to half a pixel, 2 cm here,
    # beside the point).
    fused, n = fuse_depth(truth, intr, view_pose, kfs, 0.05)
    assert n.max() == 5 and (n >= 3).mean() > 0.9
    assert np.abs(fused - truth).mean() < 0.0015 and np.abs(fused - truth).max() < 0.01

    # Noise: 1 cm per view, independent; five views shrink it about as 1 / sqrt(5).
    rng = np.random.default_rng(0)
    noisy = lambda d: (d + rng.normal(0.0, 0.01, d.shape)).astype(np.float32)  # noqa: E731
    view = noisy(truth)
    view[5, 7], view[9, 9] = 0.0, np.nan  # no measurement: stays none
    noisy_kfs = [SimpleNamespace(pose=k.pose, intrinsics=intr, depth=noisy(k.depth))
                 for k in kfs]
    fused, n = fuse_depth(view, intr, view_pose, noisy_kfs, 0.05)
    ok = np.isfinite(view) & (view > 0)
    assert fused[5, 7] == 0.0 and fused[9, 9] == 0.0 and n[5, 7] == 0.0
    rms = lambda d: float(np.sqrt(np.mean((d[ok] - truth[ok]) ** 2)))  # noqa: E731
    assert rms(fused) < 0.6 * rms(view), (rms(fused), rms(view))

    # Occlusion: a keyframe that measured something 1 m in front does not see the wall
    # there, and is left out of those pixels' mean.
    blocked = noisy_kfs[0].depth.copy()
    blocked[:, :32] = 1.0
    occluded = [SimpleNamespace(pose=kf_poses[0], intrinsics=intr, depth=blocked)]
    fused, n = fuse_depth(truth, intr, view_pose, occluded, 0.05)
    assert 0.3 < (n == 2).mean() < 0.7 and (n[ok] >= 1).all()
    assert np.abs(fused - truth)[ok].max() < 0.05  # nothing pulled towards 1 m


def test_one_visibility_pass_serves_both_fusions_of_a_view():
    """The depth fusion's visibility test (in the view's camera) read by the keyframe
    fusion of the same pixels gives what the keyframe fusion's own test (world points)
    gives; a test made for other keyframes is refused, not silently misread."""
    from types import SimpleNamespace

    from neurncd_ros.core.camera import Intrinsics, backproject, look_at
    from neurncd_ros.core.engine.views import (coverage, fuse_depth, fuse_keyframes,
                                               view_visibility)

    rng = np.random.default_rng(5)
    intr = Intrinsics.from_hfov(64, 48, 60.0)
    normal = np.array([0.3, 0.1, 1.0]) / np.linalg.norm([0.3, 0.1, 1.0])
    up = np.array([0.0, -1.0, 0.0])
    view_pose = look_at(np.zeros(3), np.array([0.0, 0.0, 1.0]), up=up)
    kf_poses = [look_at(np.array(e), np.array([0.1, 0.0, 2.0]), up=up)
                for e in ([0.15, 0, 0], [-0.15, 0, 0], [0, 0.12, 0.1])]
    noisy = lambda d: (d + rng.normal(0.0, 0.01, d.shape)).astype(np.float32)  # noqa: E731
    kfs = [SimpleNamespace(pose=p, intrinsics=intr, depth=noisy(_plane_depth(intr, p, normal, 2.0)),
                           embedding=rng.normal(size=(48, 64, 4)).astype(np.float16))
           for p in kf_poses]
    kfs[0].depth[:, :20] = 1.0  # something in front: that keyframe does not see those points
    depth = noisy(_plane_depth(intr, view_pose, normal, 2.0))
    depth[3, 4] = 0.0
    seen = view_visibility(depth, intr, view_pose, kfs, 0.05)
    assert seen.mask.sum() == depth.size - 1 and len(seen.seen) == 3
    assert 0 < seen.seen[0][0].size < seen.seen[1][0].size  # the occluded part is left out
    assert all(np.array_equal(a, b) for a, b in zip(
        fuse_depth(depth, intr, view_pose, kfs, 0.05, seen),
        fuse_depth(depth, intr, view_pose, kfs, 0.05)))
    points, mask = backproject(depth, intr, view_pose)
    own = rng.normal(size=(len(points), 4)).astype(np.float32)
    shared = fuse_keyframes(points, own, kfs, 0.05, logit_channels=3, visibility=seen)
    alone = fuse_keyframes(points, own, kfs, 0.05, logit_channels=3)
    assert np.array_equal(mask, seen.mask)
    # Two float32 roundings of the same test: a few points on the tolerance's edge may differ.
    assert (shared[1] == alone[1]).mean() > 0.999 and shared[1].max() == 4.0
    same = shared[1] == alone[1]
    assert np.allclose(shared[0][same], alone[0][same], atol=1e-5)
    with pytest.raises(ValueError, match="other keyframes"):
        fuse_keyframes(points, own, kfs[:2], 0.05, logit_channels=3, visibility=seen)
    with pytest.raises(ValueError, match="other keyframes"):
        fuse_depth(depth, intr, view_pose, kfs[::-1], 0.05, seen)
    # The coverage of the first keyframes reads the same pass (the mapper stage tests its
    # keyframes, then its recent frames); a count that is not a prefix is refused.
    maturity = np.array([0.5, 1.0])
    cov_shared = coverage(points, kfs[:2], maturity, 0.05, seen.first(2))
    cov_alone = coverage(points, kfs[:2], maturity, 0.05)
    assert (cov_shared == cov_alone).mean() > 0.999 and {0.5, 1.0} <= set(np.unique(cov_shared))
    assert np.array_equal(cov_shared, coverage(points, kfs[:2], maturity, 0.05,
                                               seen.first(3).first(2)))
    with pytest.raises(ValueError, match="holds 3 keyframes, not 4"):
        seen.first(4)
    with pytest.raises(ValueError, match="other keyframes"):
        coverage(points, kfs[:2], maturity, 0.05, seen)


def test_mapper_stage_gives_discovery_the_fused_depth(cfg, backbone, frames):
    """The view's depth is the measured one averaged with the keyframes': closer to the
    exact depth of the synthetic room than the Kinect-like measurement itself."""
    clean_cfg = synth.SynthConfig(width=96, height=72, depth_noise="none")
    views = {}
    for on in (True, False):
        st = _stage(cfg, fallback="keyframes", render_scale=0.5, depth_fusion=on)
        jobs = [st.admit(f, _record(backbone, f)) for f in frames[:30:2]]
        views[on] = st.render_view(jobs[-1])
    f = jobs[-1].frame
    off, fused = views[False], views[True]
    assert off.depth is None and off.view_depth is f.depth
    assert ViewInput.of(off).depth is f.depth and ViewInput.of(fused).depth is fused.depth
    assert fused.depth.shape == f.depth.shape and fused.depth.dtype == np.float32
    assert np.array_equal(fused.depth > 0, f.depth > 0)  # no hole filled, none made
    assert np.array_equal(fused.embedding, off.embedding)  # only the depth changes
    index = frames.index(f)
    exact = next(synth.frames_at(1002, [index], clean_cfg)).depth
    ok = (f.depth > 0) & (exact > 0)
    err = lambda d: float(np.mean(np.abs(d[ok] - exact[ok])))  # noqa: E731
    assert err(fused.depth) < 0.85 * err(f.depth), (err(fused.depth), err(f.depth))


def test_mapper_stage_fuses_a_wide_frame_at_its_work_width(cfg, backbone, frames):
    """Frames wider than mapper_node.work_width are fused at that width (the frame's
    aspect): the embedding comes at the working size, the fused depth at the frame's size
    (nearest), still closer to the exact depth than the measurement at that size; a
    work_width not below the frame's width changes nothing."""
    clean_cfg = synth.SynthConfig(width=96, height=72, depth_noise="none")
    views = {}
    for work in (0, 96, 48):
        st = _stage(cfg, fallback="keyframes", work_width=work)
        jobs = [st.admit(f, _record(backbone, f)) for f in frames[:30:2]]
        views[work] = st.render_view(jobs[-1])
    f = jobs[-1].frame
    for name in ("embedding", "entropy", "depth"):
        assert np.array_equal(getattr(views[96], name), getattr(views[0], name)), name
    wide = views[48]
    assert wide.embedding.shape[:2] == (36, 48) and wide.entropy.shape == (36, 48)
    assert wide.depth.shape == f.depth.shape and wide.depth.dtype == np.float32
    coarse = cv2.resize(cv2.resize(f.depth, (48, 36), interpolation=cv2.INTER_NEAREST),
                        (96, 72), interpolation=cv2.INTER_NEAREST)
    assert np.array_equal(wide.depth > 0, coarse > 0)  # the working grid's holes, no more
    exact = next(synth.frames_at(1002, [frames.index(f)], clean_cfg)).depth
    ok = (coarse > 0) & (exact > 0)
    err = lambda d: float(np.mean(np.abs(d[ok] - exact[ok])))  # noqa: E731
    assert err(wide.depth) < 0.9 * err(coarse), (err(wide.depth), err(coarse))


def test_disagreement_weight_adds_the_views_disagreement_to_the_entropy(cfg, backbone, frames):
    plain = _stage(cfg, fallback="keyframes", render_scale=0.5)
    extra = _stage(cfg, fallback="keyframes", render_scale=0.5, disagreement_weight=3.0)
    for st in (plain, extra):
        jobs = [st.admit(f, _record(backbone, f)) for f in frames[:30:2]]
    a, b = plain.render_view(jobs[-1]), extra.render_view(jobs[-1])
    assert np.array_equal(a.embedding, b.embedding)  # the embedding is the same fusion
    assert np.allclose(a.entropy, uncertainty.entropy(a.embedding), atol=1e-5)
    gain = b.entropy - a.entropy
    assert gain.min() >= -1e-6 and (gain > 1e-3).mean() > 0.01  # higher where views differ
    assert b.entropy.max() <= np.log(a.embedding.shape[-1]) + 1e-6


def test_keyframe_fallback_fuses_the_stored_views_before_the_field_has_learnt(cfg, backbone,
                                                                              frames):
    st = _stage(cfg, fallback="keyframes", fusion="logits", render_scale=0.5)
    jobs = [st.admit(f, _record(backbone, f)) for f in frames[:30:2]]
    job = jobs[-1]
    view = st.render_view(job)
    bb = resize_to(job.embedding.embedding, 36, 48)
    assert view.field_share == 0.0  # nothing rendered from the field yet
    assert view.embedding.shape == bb.shape and not np.allclose(view.embedding, bb)
    # The fused view still names what the frame's own logits name almost everywhere.
    agree = (view.embedding.argmax(-1) == bb.argmax(-1)).mean()
    assert agree > 0.8, agree
    assert np.allclose(view.entropy, uncertainty.entropy(view.embedding), atol=1e-5)


def test_keyframe_fusion_also_reads_the_recent_frames_when_asked(cfg, backbone, frames):
    records = {f.stamp_ns: _record(backbone, f) for f in frames[:30:2]}
    views = {}
    for recent in (0, 4):
        st = _stage(cfg, fallback="keyframes", fusion_recent=recent, render_scale=0.5)
        jobs = [st.admit(f, records[f.stamp_ns]) for f in frames[:30:2]]
        others = [j for j in jobs if not j.keyframe]
        assert len(others) >= 2
        assert len(st._recent) == (min(4, len(others)) if recent else 0)
        views[recent] = st.render_view(jobs[-1]).embedding
    # The frames not admitted as keyframes see the same points, so they change the mean.
    assert not np.allclose(views[0], views[4])


def test_a_stopped_training_thread_stops_the_views(cfg, backbone, frames):
    st = MapperStage(cfg.mapper_node, mapper_factory(cfg), online=True)
    job = st.admit(frames[0], _record(backbone, frames[0]))
    assert job is not None and st.mapper.running
    st.mapper.stop()                               # as if the training thread had died
    assert not st.check_training() and st.health.failed
    assert st.admit(frames[5], _record(backbone, frames[5])) is None
    with pytest.raises(RuntimeError, match="training thread"):
        st.render_view(job)
    assert st.health.snapshot()["level"] == H.ERROR


def test_mapper_stage_pairs_messages_and_reports_bad_frames(cfg, backbone, frames):
    st = _stage(cfg)
    f = frames[0]
    rec = _record(backbone, f)
    assert st.offer("embedding", f.stamp_ns, rec) == []
    st.offer("color", f.stamp_ns, f.rgb)
    st.offer("depth", f.stamp_ns, f.depth)
    assert st.offer("pose", f.stamp_ns + 3 * MS, f.pose) == []     # no camera info yet
    assert st.health.problems["no_camera_info"] == 1
    g = frames[3]
    st.offer_info(g.intrinsics)
    for stream, value in (("color", g.rgb), ("depth", g.depth[:, :50]), ("pose", g.pose),
                          ("embedding", _record(backbone, g))):
        st.offer(stream, g.stamp_ns, value)
    assert st.health.problems["frame_mismatch"] == 1               # depth of the wrong size
    h = frames[6]
    jobs = []
    for stream, value in (("pose", h.pose), ("color", h.rgb), ("embedding",
                                                              _record(backbone, h)),
                          ("depth", h.depth)):
        jobs += st.offer(stream, h.stamp_ns, value)
    assert len(jobs) == 1 and jobs[0].keyframe and jobs[0].frame.stamp_ns == h.stamp_ns


def test_mapper_stage_saves_atomically_and_restores(cfg, backbone, frames, tmp_path):
    from neurncd_ros.core.field.mapper import Mapper

    st = _stage(cfg)
    path = tmp_path / "map.pt"
    assert st.save(path) is False
    for f in frames[:20:4]:
        st.admit(f, _record(backbone, f))
    st.mapper.step(3)
    assert st.save(path) and not list(tmp_path.glob("*.tmp"))
    back = _stage(cfg)
    back.load(path, Mapper.load)
    assert back.spec == backbone.spec and back.mapper.iterations == 3
    assert len(back.mapper.buffer) == len(st.mapper.buffer)
    # A mistyped path is no map there (it was "no spec.json: not saved by the mapper").
    with pytest.raises(ValueError, match=r"^no map at .*mpa\.pt \(the file a "
                                         r"mapper_node\.map_path names\)$"):
        _stage(cfg).load(tmp_path / "mpa.pt", Mapper.load)
    # A map that fails to load leaves the stage with the map it had (it kept the other
    # file's spec beside its own field, which refused every embedding after it).
    other = tmp_path / "other.pt"
    other.write_bytes(b"not a map")
    (tmp_path / "other.pt.spec.json").write_text(
        EmbeddingSpec((1, 2, 3), 0, "other").to_json())
    mapper = back.mapper
    with pytest.raises(ValueError, match="other.pt"):
        back.load(other, Mapper.load)
    assert back.spec == backbone.spec and back.mapper is mapper
    (tmp_path / "map.pt.spec.json").unlink()
    with pytest.raises(ValueError, match="spec.json is missing"):
        _stage(cfg).load(path, Mapper.load)


# ------------------------------------------------------------------ discovery

def test_discovery_waits_for_the_spec_and_labels_at_depth_size(cfg, backbone, frames):
    clock = Clock()
    st = DiscoveryStage(cfg, cfg.discovery_node, clock=clock)
    f = frames[10]
    emb = resize_to(backbone.embed(f.rgb, f.depth), 36, 48)
    ent = uncertainty.entropy(emb)
    for stream, value in (("embedding", emb), ("info", f.intrinsics), ("entropy", ent),
                          ("color", f.rgb), ("pose", f.pose)):
        assert st.offer(stream, f.stamp_ns, value) is False
    assert st.offer("depth", f.stamp_ns, f.depth) is True
    assert st.take() is None, "no spec yet: the view waits"
    st.set_spec(backbone.spec)
    view = st.take()
    rec = st.label(view)
    assert rec.labels.shape == f.depth.shape and rec.labels.dtype == np.uint16
    assert (rec.labels > 0).mean() > 0.9
    assert all(v["kind"] in ("known", "novel") for v in rec.classes.values())
    bad = ViewInput(f.stamp_ns, f.depth, f.intrinsics, emb[..., :5], ent, f.rgb)
    with pytest.raises(ValueError, match="spec says"):
        st.label(bad)
    bad = ViewInput(f.stamp_ns, f.depth[:, :10], f.intrinsics, emb, ent, f.rgb)
    with pytest.raises(ValueError, match="camera info"):
        st.label(bad)
    bad = ViewInput(f.stamp_ns, f.depth, f.intrinsics, emb, ent, f.rgb,
                    pose=np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="view pose"):
        st.label(bad)


def test_discovery_labels_a_wide_view_at_its_work_width_and_returns_the_views_size(
        cfg, backbone, frames):
    """With discovery_node.work_width below the view's width, the view is segmented and
    clustered at that width, and its labels come back at the view's own size: the same
    classes as at full size, nearly everywhere."""
    f = frames[10]
    emb = backbone.embed(f.rgb, f.depth)
    ent = uncertainty.entropy(emb)
    view = ViewInput(f.stamp_ns, f.depth, f.intrinsics, emb, ent, f.rgb, pose=f.pose)
    seen = []
    recs = {}
    for width in (0, 48):
        st = DiscoveryStage(cfg, dataclasses.replace(cfg.discovery_node, work_width=width))
        st.set_spec(backbone.spec)
        process = st.discoverer.process
        st.discoverer.process = lambda depth, *a, **k: (seen.append(depth.shape),
                                                        process(depth, *a, **k))[1]
        recs[width] = st.label(view).labels
    assert seen == [f.depth.shape, (36, 48)]
    assert recs[48].shape == f.depth.shape and recs[48].dtype == np.uint16
    known = (recs[0] > 0) & (recs[0] < 100)
    assert np.mean(recs[48][known] == recs[0][known]) > 0.9
    # The class table counts the pixels of the labels as published, at the view's size.
    rec = st.label(dataclasses.replace(view, stamp_ns=view.stamp_ns + 1))
    ids, counts = np.unique(rec.labels, return_counts=True)
    shown = {int(i): int(c) for i, c in zip(ids, counts) if i}
    assert {i: rec.classes[i]["pixels"] for i in shown} == shown


def test_discovery_drops_views_that_never_get_a_spec(cfg, frames):
    clock = Clock()
    node_cfg = dataclasses.replace(cfg.discovery_node, spec_wait_s=5.0)
    st = DiscoveryStage(cfg, node_cfg, clock=clock)
    f = frames[0]
    emb = np.zeros((72, 96, 9), np.float32)
    for stream, value in (("embedding", emb), ("info", f.intrinsics), ("color", f.rgb),
                          ("entropy", emb[..., 0]), ("depth", f.depth), ("pose", f.pose)):
        st.offer(stream, f.stamp_ns, value)
    clock.t = 10.0
    assert st.take() is None and st.pending == 0
    assert st.health.problems["no_spec"] == 1


# ------------------------------------------------------------------ offline engine

def test_offline_engine_renders_keyframes_and_the_label_rate_in_stream_time(cfg, backbone,
                                                                          frames):
    c = config.load(None, {"mapper.fast.rays_per_iteration": 256, "run.view_rate_hz": 5.0,
                           "run.training_rate_hz": 20.0, "embedding_node.max_rate_hz": 10.0})
    engine = OfflineEngine(c, backbone)
    outs = list(engine.run(frames, progress=False))
    stamps = [o.frame.stamp_ns for o in outs]
    assert set(engine.mapping.keyframe_stamps) <= set(stamps), "every keyframe is labelled"
    # The label rate counts the keyframes: a frame that is not one is labelled only
    # where the last label of any kind is at least 1 / 5.0 s old.
    others = [i for i, o in enumerate(outs) if not o.view.keyframe]
    assert others and all(stamps[i] - stamps[i - 1] >= 0.199e9 for i in others if i > 0)
    # The embedding stage's gate: only every third 30 Hz frame reaches the mapper.
    assert all((s - frames[0].stamp_ns) % 100_000_000 < 2 * MS for s in stamps)
    duration = (frames[-1].stamp_ns - frames[0].stamp_ns) * 1e-9
    assert engine.mapper.iterations == int(20.0 * 1.9)  # the last embedded frame, 1.9 s
    assert duration > 1.9
    for o in outs:
        assert o.labels.labels.shape == o.frame.depth.shape
        assert o.backbone_ids().shape == o.frame.depth.shape
    again = list(OfflineEngine(c, backbone).run(frames, progress=False))
    assert all(np.array_equal(a.labels.labels, b.labels.labels) for a, b in zip(outs, again))


def test_a_refused_frame_leaves_the_offline_engine_as_it_was(backbone, frames):
    """A frame feed refuses (no pose, negative depth, a stamp in seconds, a stamp back in
    time) is a ValueError at once saying what is wrong, and the frames after it are
    labelled as if it had never come: a refused first frame set the training clock (more
    iterations), a frame without a pose failed inside the field's scene box with a
    TypeError, and a stamp back in time was taken in silence."""
    c = config.load(None, {"mapper.fast.rays_per_iteration": 256,
                           "run.training_rate_hz": 20.0})

    def labels(engine, stream):
        return [(o.frame.stamp_ns, o.labels.labels) for f in stream for o in engine.feed(f)]

    reference = OfflineEngine(c, backbone)
    ref = labels(reference, frames[:20])
    engine = OfflineEngine(c, backbone)
    f0, early = frames[0], frames[0].stamp_ns - 2_000_000_000
    for bad, match in ((dataclasses.replace(f0, stamp_ns=early, pose=None), "has no pose"),
                       (dataclasses.replace(f0, stamp_ns=early, depth=-f0.depth),
                        "depth must be >= 0"),
                       (dataclasses.replace(f0, stamp_ns=early * 1e-9), "nanoseconds")):
        with pytest.raises(ValueError, match=match):
            engine.feed(bad)
    got = labels(engine, frames[:10])
    with pytest.raises(ValueError, match=r"is 0.2 s before the previous frame .*stamp "
                                          "order"):
        engine.feed(frames[3])
    got += labels(engine, frames[10:20])
    assert engine.frames_in == 20 and engine.mapper.iterations == reference.mapper.iterations
    assert [s for s, _ in got] == [s for s, _ in ref]
    assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(got, ref))


def test_embedding_spec_round_trip_and_errors():
    spec = EmbeddingSpec(tuple(classes.KNOWN_IDS), 16, "default")
    assert EmbeddingSpec.from_json(spec.to_json()) == spec and spec.channels == 25
    for text, match in (("{", "not JSON"), ('{"x": 1}', "channel_to_id"),
                        ('{"channel_to_id": [1]}', "at least 2"),
                        ('{"channel_to_id": [1, 99]}', "NYU-13")):
        with pytest.raises(ValueError, match=match):
            EmbeddingSpec.from_json(text)
    with pytest.raises(ValueError, match="spec says"):
        spec.check(np.zeros((4, 4, 9), np.float32))


def test_discovery_stage_gives_the_colour_to_the_descriptor_without_colour_edges(
        cfg, backbone, frames, monkeypatch):
    """The colour descriptor (modulation.colour_weight) needs the view's colour even
    when the segmentation's colour edges are off."""
    from neurncd_ros.core.discovery.labeller import Discoverer
    seen = []
    orig = Discoverer._label_segments  # what process() labels the segments with

    def spy(self, segments, embedding, entropy, colour=None, features=None, *rest):
        seen.append(colour)
        return orig(self, segments, embedding, entropy, colour, features, *rest)

    monkeypatch.setattr(Discoverer, "_label_segments", spy)
    f = frames[10]
    emb = resize_to(backbone.embed(f.rgb, f.depth), 36, 48)
    view = ViewInput(f.stamp_ns, f.depth, f.intrinsics, emb, uncertainty.entropy(emb), f.rgb)
    for weight, wanted in ((2.0, True), (0.0, False)):
        c = config.from_nested({**cfg.to_nested(),
                                "segmentation": {**cfg.to_nested()["segmentation"],
                                                 "colour_edges": False},
                                "modulation": {**cfg.to_nested()["modulation"],
                                               "colour_weight": weight}})
        st = DiscoveryStage(c, c.discovery_node)
        st.set_spec(backbone.spec)
        st.label(view)
        assert (seen[-1] is not None) == wanted


def test_backbone_features_ride_with_the_keyframes_into_each_segment_descriptor(
        frames, tmp_path, monkeypatch):
    """backbone.features (issue 11, direction 1): the embedding carries the net's 20
    penultimate feature channels after its 9 logits; the field learns both
    (mapper.distill_features), the keyframe fusion averages the features with the logits,
    a saved map restores them, and discovery pools them into each segment's descriptor
    (modulation.feature_weight)."""
    from neurncd_ros.core.discovery.labeller import Discoverer
    from neurncd_ros.core.field.mapper import Mapper

    c = config.load(None, {"mapper.fast.rays_per_iteration": 256, "backbone.features": True,
                           "backbone.num_threads": 1, "run.training_rate_hz": 10.0})
    b = load_backbone(c.backbone)
    assert b.spec.feature_channels == 20 and b.spec.channels == 29
    f = frames[10]
    emb = b.embed(f.rgb, f.depth)
    assert emb.shape == f.depth.shape + (29,)
    np.testing.assert_allclose(emb[..., :9], b.predict(f.rgb, f.depth), atol=1e-4)
    assert np.abs(emb[..., 9:]).max() > 0 and np.isfinite(emb).all()
    widths = []
    orig = Discoverer._label_segments  # what process() labels the segments with

    def spy(self, segments, embedding, entropy, colour=None, features=None, *rest):
        out = orig(self, segments, embedding, entropy, colour, features, *rest)
        widths.append((None if features is None else features.shape[-1],
                       self._mem.desc.shape[1]))
        return out

    monkeypatch.setattr(Discoverer, "_label_segments", spy)
    engine = OfflineEngine(c, b)
    outs = list(engine.run(frames[:30], progress=False))
    assert outs and all(o.view.embedding.shape[-1] == 29 for o in outs)
    assert engine.mapper.channels == 9 and engine.mapper.feature_channels == 20
    assert engine.mapper.field_channels == 29
    assert engine.mapper.iterations > 0
    # The descriptor: the default's parts plus the 20-wide feature part.
    plain = list(OfflineEngine(config.load(None, {"mapper.fast.rays_per_iteration": 256}),
                               load_backbone(BackboneConfig())).run(frames[:4],
                                                                    progress=False))
    assert plain and widths[0][0] == 20 and widths[-1][0] is None
    assert widths[0][1] == widths[-1][1] + 20
    path = tmp_path / "map.pt"
    assert engine.mapping.save(path)
    back = MapperStage(c.mapper_node, mapper_factory(c), online=False)
    back.load(path, Mapper.load)
    assert back.spec == b.spec and back.mapper.feature_channels == 20
    # A frame without features in a stream that had them is a clear error.
    d = Discoverer(c.discovery, mcl_cfg=c.mcl, seg_cfg=c.segmentation, mod_cfg=c.modulation)
    seg = np.zeros((8, 8), np.int64)
    seg[:, 4:] = 1
    e = np.zeros((8, 8, 9), np.float32)
    d.process_segments(seg, e, np.zeros((8, 8), np.float32), None, np.ones((8, 8, 20)))
    with pytest.raises(ValueError, match="features or none"):
        d.process_segments(seg, e, np.zeros((8, 8), np.float32))


def test_a_learnt_field_renders_the_features_it_distils(frames):
    """Where the field has learnt the scene, the view's feature channels are the field's
    rendering of the backbone's features (mapper.distill_features), close to the
    backbone's own; without distillation they stay the backbone's and only the logits
    come from the field."""
    c = config.load(None, {"mapper.fast.rays_per_iteration": 256, "backbone.features": True,
                           "backbone.num_threads": 1})
    b = load_backbone(c.backbone)
    views = {}
    for distill in (True, False):
        cd = config.load(None, {"mapper.fast.rays_per_iteration": 256,
                                "mapper.distill_features": distill})
        st = MapperStage(dataclasses.replace(cd.mapper_node, mature_iterations=20,
                                             render_scale=1.0, fallback="backbone",
                                             depth_fusion=False, field_views=True),
                         mapper_factory(cd), online=False)
        jobs = [st.admit(f, _record(b, f)) for f in frames[:30:2]]
        st.mapper.step(60)
        views[distill] = (st.render_view(jobs[-1]), jobs[-1].embedding.embedding)
    (learnt, own), (plain, own2) = views[True], views[False]
    assert np.array_equal(own, own2) and learnt.embedding.shape[-1] == 29
    assert learnt.field_share > 0.5 and plain.field_share > 0.5
    feats, target = learnt.embedding[..., 9:], own[..., 9:]
    assert not np.allclose(feats, target, atol=1e-3), "the features are the field's"
    rel = float(((feats - target) ** 2).sum() / (target ** 2).sum())
    assert rel < 0.5, rel  # measured 0.24 after 60 iterations: the field's, near the backbone's
    np.testing.assert_array_equal(plain.embedding[..., 9:], target)
    assert not np.allclose(plain.embedding[..., :9], own[..., :9], atol=1e-3)


def test_mapper_stage_names_the_stream_that_never_arrives(cfg, frames):
    """Colour, depth and pose come but no embedding: the stage says which stream it waits
    for and what to check, instead of rendering nothing in silence."""
    # A short horizon keeps the pairing's queues short (it holds sync_horizon_s of a 90 Hz
    # camera, 9 images, and of a 1 kHz pose topic): 16 frames fill them, as seconds of a
    # camera would.
    st = _stage(cfg, queue_size=4, sync_horizon_s=0.1)
    logged = []
    st.health._log = lambda level, text: logged.append(text)
    for f in frames[:16]:
        st.offer("color", f.stamp_ns, f.rgb)
        st.offer("depth", f.stamp_ns, f.depth)
        assert st.offer("pose", f.stamp_ns, f.pose) == []
    assert st.health.problems["starved"] >= 1
    text = next(t for t in logged if "waiting for" in t)
    assert text.startswith("waiting for embedding:") and "embedding node runs" in text


def test_mapper_stage_waits_for_poses_in_silence_while_their_source_is_chosen(cfg, backbone,
                                                                            frames):
    """pose_source auto (the default) with no pose topic: the mapper waits up to
    pose_auto_wait_s before it chooses odometry, and a 30 Hz camera fills its queues
    meanwhile. That wait is no missing pose topic: it warned 'waiting for pose
    (/camera/pose): nothing arrives there ... (check the topic names' every time, just
    before its line 'pose source: odometry (pose_source auto)'. Once the source is chosen,
    a pose that never comes is reported as before."""
    for choosing in (True, False):
        st = _stage(cfg, queue_size=4, sync_horizon_s=0.1)
        st.pose_choice_open = choosing
        logged = []
        st.health._log = lambda level, text: logged.append(text)
        for f in frames[:12]:
            st.offer("embedding", f.stamp_ns, _record(backbone, f))
            st.offer("color", f.stamp_ns, f.rgb)
            assert st.offer("depth", f.stamp_ns, f.depth) == []
        waits = [t for t in logged if "waiting for" in t]
        if choosing:
            assert "starved" not in st.health.problems, waits
        else:
            assert st.health.problems["starved"] >= 1
            assert waits[0].startswith("waiting for pose")


def test_mapper_stage_drops_a_far_future_stamp_and_reports_a_frame_without_pose(
        cfg, backbone, frames):
    """One frame stamped 10^6 s ahead (a driver's glitch) is dropped and reported; the
    frames after it are paired and keyframes are still admitted by time, instead of every
    later frame being older than the bad one. A frame whose pose never comes is named in
    a problem report, not only counted."""
    clock = Clock()
    st = MapperStage(cfg.mapper_node, mapper_factory(cfg), online=False, clock=clock)
    logged = []
    st.health._log = lambda level, text: logged.append(text)
    st.offer_info(frames[0].intrinsics)
    sec = 1000 * MS

    def send(f, stamp, streams=("pose", "color", "depth", "embedding")):
        values = {"pose": f.pose, "color": f.rgb, "depth": f.depth,
                  "embedding": EmbeddingRecord(stamp, backbone.embed(f.rgb, f.depth),
                                               backbone.spec)}
        jobs = []
        for s in streams:
            jobs += st.offer(s, stamp, values[s])
        return jobs

    good = [sec + k * sec // 2 for k in range(10)]   # one frame every 0.5 s
    jobs = []
    for k, stamp in enumerate(good):
        clock.t = 0.1 * k
        if k == 3:
            assert send(frames[3], stamp + 10**6 * sec) == []
        jobs += send(frames[k], stamp)
    assert st.health.problems["jump"] == 4 and st.sync.resets == 0
    assert any("ahead of the last frame paired" in t for t in logged), logged
    assert st.health.counts["frames_paired"] == 10
    assert [j.frame.stamp_ns for j in jobs] == good
    assert [s for s in st.keyframe_stamps if s > good[3]], st.keyframe_stamps
    # A frame whose pose never comes: reported when the next frame pairs (a live stream)...
    send(frames[10], good[-1] + sec, streams=("color", "depth", "embedding"))
    assert len(send(frames[11], good[-1] + 2 * sec)) == 1
    assert st.health.problems["unpaired"] == 1
    assert any("nothing came on pose" in t for t in logged), logged
    # ... or when it expires (the stream stopped).
    send(frames[12], good[-1] + 3 * sec, streams=("color", "depth", "embedding"))
    clock.t += 2 * cfg.mapper_node.sync_horizon_s
    st.offer("color", good[-1] + 4 * sec, frames[13].rgb)
    assert st.health.problems["unpaired"] == 2


def test_mapper_stage_holds_the_embeddings_that_come_before_their_spec(cfg):
    """The embedding messages that came before their spec (the node cannot read them yet)
    are held as they came, in order, as long as their frames wait for them
    (sync_horizon_s) and as many as the pairing holds of an input; beyond either they are
    refused as no_spec, saying which. They were all refused."""
    clock, lines = Clock(), []
    node_cfg = dataclasses.replace(cfg.mapper_node, queue_size=2, sync_horizon_s=0.1,
                                   log_throttle_s=0.0)
    st = MapperStage(node_cfg, mapper_factory(cfg), online=False, clock=clock)
    st.health._log = lambda level, text: lines.append(text)
    st.spec_topic = "/neurncd/embedding/spec"
    assert st.sync.capacity == 9  # 0.1 s of a 90 Hz camera
    for k in range(11):
        st.hold_for_spec(k, f"message {k}")
    assert st.held_for_spec == 9 and st.health.problems["no_spec"] == 2
    assert lines[0] == ("embedding 0 skipped: its spec has not come on /neurncd/embedding/spec "
                        "yet, and more than 9 embeddings wait for it (the oldest is dropped)")
    clock.t = 0.05
    assert st.release_for_spec() == [f"message {k}" for k in range(2, 11)]
    assert st.held_for_spec == 0 and st.release_for_spec() == []
    # A spec that never comes: refused once their frames no longer wait for them.
    st.hold_for_spec(10, "late")
    clock.t = 0.1
    st.expire_held()
    assert st.held_for_spec == 1
    clock.t = 0.2
    st.expire_held()
    assert st.held_for_spec == 0 and st.health.problems["no_spec"] == 3
    assert lines[-1].startswith("embedding 10 skipped: its spec did not come on "
                                "/neurncd/embedding/spec within 0.1 s of it"), lines[-1]
    assert "embedding" in st.health.refused()  # a starved report names it refused


def test_a_bag_played_again_pairs_at_once_and_frees_the_views_in_flight(cfg, backbone,
                                                                        frames):
    """The same bag played a second time into a running mapper: the messages whose stamps
    went back before the restart was clear are paired on the new timeline (they were
    dropped: the first frames of every pass lost), and the old timeline's views in flight
    are no longer waited for (the renderer sat out in_flight_timeout_s for labels that
    never came)."""
    st = _stage(cfg, max_in_flight=1)
    st.offer_info(frames[0].intrinsics)
    shown = frames[:24:3]

    def play() -> list:
        paired = []
        for f in shown:
            for stream, value in (("color", f.rgb), ("depth", f.depth), ("pose", f.pose),
                                  ("embedding", _record(backbone, f))):
                paired += st.offer(stream, f.stamp_ns, value)
        return paired

    play()
    assert st.next_view() is not None and st.next_view() is None  # one in flight, unlabelled
    assert st.health.counts["frames_paired"] == len(shown)
    play()
    assert st.sync.resets == 1 and st.sync.drops["out_of_order"] == 0
    assert st.health.counts["frames_paired"] == 2 * len(shown), "every frame paired again"
    assert st.next_view() is not None, "the old timeline's view in flight still held a slot"


def test_reset_map_forgets_the_room_and_what_waits_to_be_fused(cfg, backbone, frames):
    """The mapper node's ~/reset: the field and keyframes, and the held recent frames and
    waiting keyframe views, so none of the old room is fused into the next one's views."""
    st = _stage(cfg, max_in_flight=4)
    for f in frames[:30:3]:
        st.admit(f, _record(backbone, f))
    assert len(st.mapper.buffer) and st.pending and st._recent_views(frames[40])
    st.reset_map()
    assert not len(st.mapper.buffer) and st.pending == 0 and not st._recent_views(frames[40])
    assert st.health.counts["resets"] == 1


def test_summary_says_what_was_left_unrendered(cfg, backbone, frames):
    """The mapper's exit line: keyframe views still queued at shutdown were never rendered
    nor labelled, and the line says so (it counted only what was done)."""
    st = _stage(cfg, max_in_flight=4)
    assert "not rendered or labelled" not in st.summary()
    for f in frames[:30:3]:
        st.admit(f, _record(backbone, f))
    queued = len(st._keyframe_jobs)
    assert queued and f"{queued} keyframe view" in st.summary()
    while st.next_view() is not None:
        pass
    assert "awaiting labels" in st.summary()


def test_a_run_skips_a_frame_stamped_before_the_previous_one(cfg, backbone, frames):
    """feed() refuses a frame older than the previous one (a library caller is told);
    run(), as neurncd run drives it over a bag of two recordings, skips it, warns once
    and counts it, and goes on with the frames after it."""
    from neurncd_ros.core.engine.offline import OfflineEngine
    engine = OfflineEngine(cfg, backbone=backbone)
    stream = list(frames[:6])
    stream.insert(4, dataclasses.replace(frames[1]))  # an old frame in the middle
    with pytest.warns(UserWarning, match="before the previous frame"):
        list(engine.run(stream, progress=False))
    assert engine.refused == 1 and engine.frames_in == 6


def test_depth_in_millimetres_is_refused_by_name(cfg, backbone, frames):
    """Depth in millimetres given as float32 (a 16UC1 PNG read without the / 1000) put
    every pixel beyond mapper.max_depth, and the frames were labelled, wrongly, without a
    word: the mapper stage refuses them naming the unit."""
    st = _stage(cfg)
    mm = dataclasses.replace(frames[0], depth=frames[0].depth * 1000)
    assert st.admit(mm, _record(backbone, mm)) is None
    assert st.health.problems["depth_not_metres"] == 1
    assert st.admit(frames[0], _record(backbone, frames[0])) is not None


def test_the_engine_saves_the_map_it_loads(cfg, backbone, frames, tmp_path):
    """OfflineEngine.save_map / load_map: a library caller saves and continues a map as
    the mapper node does (saving meant reaching into engine.mapping)."""
    from neurncd_ros.core.engine.offline import OfflineEngine
    engine = OfflineEngine(cfg, backbone=backbone)
    path = tmp_path / "room.pt"
    assert engine.save_map(path) is False  # no map before the first frame
    list(engine.run(frames[:12], progress=False))
    assert engine.save_map(path) and (tmp_path / "room.pt.spec.json").is_file()
    again = OfflineEngine(cfg, backbone=backbone)
    assert again.load_map(path) == {"iterations": engine.mapper.iterations,
                                    "keyframes": len(engine.mapper.buffer),
                                    "kept_settings": {}}
    # A configuration that differs: the map keeps what it was built with and says which;
    # how the mapper runs here (chunk sizes, threads) comes from the configuration.
    changed = config.load(None, {"mapper.fast.rays_per_iteration": 512, "mapper.near": 0.1,
                                 "keyframes.max_keyframes": 32, "mapper.train_chunk": 4096})
    third = OfflineEngine(changed, backbone=backbone)
    kept = third.load_map(path)["kept_settings"]
    assert kept == {"mapper.near": [0.05, 0.1], "keyframes.max_keyframes": [64, 32],
                    "mapper.fast.rays_per_iteration": [256, 512]}
    assert third.mapper.cfg.near == 0.05 and third.mapper.cfg.train_chunk == 4096
