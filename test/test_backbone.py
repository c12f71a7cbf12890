"""Backbone interface, the shipped default weights, entropy, training pieces."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
import torch

from neurncd_ros.core import classes, uncertainty
from neurncd_ros.core.backbone import backbone as bb
from neurncd_ros.core.backbone import data as train_data
from neurncd_ros.core.backbone import small, train
from neurncd_ros.core.params import ConfigError, build

HELD_OUT_SEED = 1007
"""A synthetic scene seed used neither for training (0-179) nor validation (1000-1004)."""


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="module")
def default_backbone() -> bb.Backbone:
    if not bb.DEFAULT_WEIGHTS.is_file():
        pytest.fail(f"shipped weights {bb.DEFAULT_WEIGHTS} missing")
    return bb.load_backbone(bb.BackboneConfig(num_threads=0))


@pytest.fixture(scope="module")
def held_out_frames():
    from neurncd_ros import synth
    return list(synth.generate(HELD_OUT_SEED, 2, synth.SynthConfig()))


def _rgbd(h: int, w: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    depth = (0.5 + 4 * rng.random((h, w))).astype(np.float32)
    depth[:5, :5] = 0.0
    return rgb, depth


# ----------------------------------------------------------------------------- shipped model
def test_default_backbone_shape_and_dtype(default_backbone):
    assert default_backbone.channels == 9
    assert default_backbone.channel_to_id.dtype == np.uint16
    assert default_backbone.channel_to_id.tolist() == list(classes.KNOWN_IDS)
    for h, w in ((240, 320), (150, 200)):
        rgb, depth = _rgbd(h, w)
        out = default_backbone.predict(rgb, depth)
        assert out.shape == (h, w, 9) and out.dtype == np.float32
        assert np.isfinite(out).all()


def test_loading_the_default_backbone_leaves_torchs_global_generator_alone():
    """The layers' throw-away initial weights are drawn from a forked generator, so
    building a backbone does not change what anyone else draws from torch's."""
    state = torch.random.get_rng_state()
    b = bb.load_backbone(bb.BackboneConfig(num_threads=0))
    assert torch.equal(torch.random.get_rng_state(), state)
    assert b.channels == len(classes.KNOWN_IDS)


@pytest.fixture(scope="module")
def float32_backbone() -> bb.Backbone:
    return bb.load_backbone(bb.BackboneConfig(num_threads=0, precision="float32"))


def test_inference_net_is_the_trained_function_with_batch_norms_folded(float32_backbone,
                                                                        held_out_frames):
    """The backbone runs the shipped net with every batch norm folded into its
    convolution and in NHWC layout (for speed); in float32 it computes the same logits
    as the net rebuilt from the file as trained, on a real frame, and the argmax is
    identical."""
    net = float32_backbone.net
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())
    assert float32_backbone.channels_last
    assert all(p.dtype == torch.float32 for p in net.parameters())
    trained = small.load_weights(str(bb.DEFAULT_WEIGHTS))
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in trained.modules())
    fr = held_out_frames[0]
    ours = float32_backbone.predict(fr.rgb, fr.depth)
    rgb = torch.from_numpy(fr.rgb).permute(2, 0, 1)[None].float()
    with torch.inference_mode():
        ref = trained.predict_raw(rgb, torch.from_numpy(fr.depth)[None, None])
    ref = ref[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(ours, ref, atol=2e-4 * float(np.abs(ref).max()))
    assert (ours.argmax(-1) == ref.argmax(-1)).mean() > 0.9999


def test_graph_backbone_computes_what_the_eager_net_computes(float32_backbone,
                                                             held_out_frames):
    """backbone.graph (the default) runs the net as a frozen TorchScript graph traced per
    input shape: on real frames of two sizes in one batch, logits and penultimate
    features equal the eager net's, one graph is traced per shape and reused, and
    warm_up traces the input size before the first frame."""
    assert float32_backbone.graph
    eager = bb.load_backbone(bb.BackboneConfig(num_threads=0, precision="float32",
                                               graph=False, features=True))
    graph = bb.load_backbone(bb.BackboneConfig(num_threads=0, precision="float32",
                                               features=True))
    assert not eager.graph and not graph._graphs
    graph.warm_up()
    assert len(graph._graphs) == 1
    a, b = held_out_frames
    small_rgb, small_depth = b.rgb[::2, ::2].copy(), b.depth[::2, ::2].copy()
    for features in (False, True):
        ours = graph.predict_batch([a.rgb, small_rgb], [a.depth, small_depth], features)
        ref = eager.predict_batch([a.rgb, small_rgb], [a.depth, small_depth], features)
        for o, r in zip(ours, ref):
            assert o.shape == r.shape
            np.testing.assert_allclose(o, r, rtol=1e-5, atol=1e-5 * float(np.abs(r).max()))
    assert len(graph._graphs) == 3  # warm-up (batch 1, features), batch 2 without and with
    graph.embed(a.rgb, a.depth)
    assert len(graph._graphs) == 3  # the camera's size maps to the traced input shape
    assert not eager._graphs


def test_bfloat16_net_labels_real_frames_as_the_float32_net(float32_backbone, held_out_frames):
    """backbone.precision bfloat16 runs the encoder and decoder in bfloat16 and keeps the
    class heads in float32: on real held-out frames it returns float32 logits whose
    argmax is the float32 net's on at least 99.5 % of pixels and whose normalised
    entropy (what discovery thresholds) differs by under 0.01 on average."""
    from neurncd_ros.core.uncertainty import entropy

    low = bb.load_backbone(bb.BackboneConfig(num_threads=0, precision="bfloat16"))
    assert low.input_dtype == torch.bfloat16
    assert low.net.rgb_stem[0].weight.dtype == torch.bfloat16
    for head in small.HEADS:
        assert getattr(low.net, head).weight.dtype == torch.float32
    for fr in held_out_frames:
        ref = float32_backbone.predict(fr.rgb, fr.depth)
        ours = low.predict(fr.rgb, fr.depth)
        assert ours.dtype == np.float32 and ours.shape == ref.shape
        assert not np.array_equal(ours, ref)  # it does run in another precision
        assert (ours.argmax(-1) == ref.argmax(-1)).mean() >= 0.995
        h_ref, h_ours = (entropy(x) / np.log(x.shape[-1]) for x in (ref, ours))
        assert np.abs(h_ours - h_ref).mean() < 0.01
    # The penultimate features come back in float32 too (backbone.features).
    feat = bb.load_backbone(bb.BackboneConfig(num_threads=0, precision="bfloat16",
                                              features=True))
    emb = feat.embed(held_out_frames[0].rgb, held_out_frames[0].depth)
    assert emb.dtype == np.float32 and emb.shape[-1] == 9 + feat.feature_channels


def test_precision_auto_is_bfloat16_only_where_the_cpu_has_it():
    """auto resolves to bfloat16 exactly when oneDNN reports native bfloat16 (emulated
    bfloat16 is slower than float32), and a bad precision is refused by the schema."""
    from neurncd_ros.core.params import ConfigError, build

    native = bb.native_bfloat16("cpu")
    assert bb.compute_dtype(bb.BackboneConfig()) == (torch.bfloat16 if native
                                                     else torch.float32)
    assert bb.compute_dtype(bb.BackboneConfig(precision="float32")) == torch.float32
    assert bb.compute_dtype(bb.BackboneConfig(precision="bfloat16")) == torch.bfloat16
    assert not bb.native_bfloat16("cuda")
    with pytest.raises(ConfigError, match="precision"):
        build(bb.BackboneConfig, {"precision": "float16"})


def test_fold_batch_norm_keeps_the_function_of_any_layout():
    """Folding is exact for any batch-norm statistics (not only the shipped ones) and
    refuses a net in training mode, whose norms still learn."""
    torch.manual_seed(0)
    net = small.SmallRGBDNet(widths=(8, 8, 16, 16), novelty_branch=True)
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-1, 1)
            m.running_var.uniform_(0.2, 3)
            m.weight.data.uniform_(0.5, 2)
            m.bias.data.uniform_(-1, 1)
    with pytest.raises(ValueError, match="eval"):
        small.fold_batch_norm(net)
    net.eval()
    x_rgb, x_depth = torch.randn(2, 3, 40, 56), torch.randn(2, 2, 40, 56)
    with torch.inference_mode():
        ref = net(x_rgb, x_depth)
        folded = small.fold_batch_norm(net)
        out = folded.to(memory_format=torch.channels_last)(
            x_rgb.contiguous(memory_format=torch.channels_last),
            x_depth.contiguous(memory_format=torch.channels_last))
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    torch.testing.assert_close(out, ref, atol=1e-4, rtol=1e-4)


def test_features_need_the_default_net():
    with pytest.raises(ValueError, match="kind=default only"):
        bb.load_backbone(bb.BackboneConfig(kind="esanet", checkpoint="x.pth", features=True))


def test_predict_batch_matches_single(default_backbone):
    a = _rgbd(240, 320, 1)
    b = _rgbd(150, 200, 2)
    batch = default_backbone.predict_batch([a[0], b[0]], [a[1], b[1]])
    assert [x.shape for x in batch] == [(240, 320, 9), (150, 200, 9)]
    np.testing.assert_allclose(batch[1], default_backbone.predict(*b), atol=1e-3)
    assert default_backbone.predict_batch([], []) == []


def test_shipped_weights_segment_held_out_scene(default_backbone, held_out_frames):
    """The shipped weights must really segment a synthetic scene they never saw."""
    correct = total = 0
    for fr in held_out_frames:
        logits = default_backbone.predict(fr.rgb, fr.depth)
        pred_id = default_backbone.channel_to_id[logits.argmax(-1)]
        known = np.isin(fr.semantic, classes.KNOWN_IDS)
        correct += int((pred_id[known] == fr.semantic[known]).sum())
        total += int(known.sum())
    assert total > 1000, "held-out frames show almost no known-class pixels"
    acc = correct / total
    assert acc > 0.70, f"pixel accuracy on known pixels {acc:.3f} (chance ~ 0.11)"


def test_nan_depth_is_a_hole(default_backbone):
    rgb, depth = _rgbd(120, 160, 3)
    holes = depth.copy()
    holes[40:60, 50:90] = 0.0
    nans = depth.copy()
    nans[40:60, 50:90] = np.nan
    nans[0, 100] = np.inf
    holes[0, 100] = 0.0
    np.testing.assert_allclose(default_backbone.predict(rgb, nans),
                               default_backbone.predict(rgb, holes), atol=1e-4)


@pytest.mark.parametrize("rgb, depth, match", [
    (np.zeros((60, 80, 3), np.float32), np.ones((60, 80), np.float32), "uint8"),
    (np.zeros((60, 80), np.uint8), np.ones((60, 80), np.float32), r"\(H, W, 3\)"),
    (np.zeros((60, 80, 3), np.uint8), np.ones((60, 80), np.uint16), "float32"),
    (np.zeros((60, 80, 3), np.uint8), np.ones((60, 81), np.float32), "differ"),
    (np.zeros((60, 80, 3), np.uint8), -np.ones((60, 80), np.float32), ">= 0"),
    (np.zeros((4, 80, 3), np.uint8), np.ones((4, 80), np.float32), "smaller"),
    ([[0]], np.ones((60, 80), np.float32), "numpy"),
])
def test_bad_inputs_raise(default_backbone, rgb, depth, match):
    with pytest.raises(ValueError, match=match):
        default_backbone.predict(rgb, depth)


def test_batch_length_mismatch(default_backbone):
    rgb, depth = _rgbd(60, 80)
    with pytest.raises(ValueError, match="rgb images"):
        default_backbone.predict_batch([rgb, rgb], [depth])


# ----------------------------------------------------------------------------- config
def test_config_validation(tmp_path):
    with pytest.raises(ConfigError, match="kind"):
        build(bb.BackboneConfig, {"kind": "resnet"})
    with pytest.raises(ConfigError, match="input_width"):
        build(bb.BackboneConfig, {"input_width": -3})
    with pytest.raises(ValueError, match="does not exist"):
        bb.load_backbone(bb.BackboneConfig(checkpoint=str(tmp_path / "missing.pt")))
    with pytest.raises(ValueError, match="needs checkpoint"):
        bb.load_backbone(bb.BackboneConfig(kind="esanet"))
    with pytest.raises(ValueError, match="multiples of 32"):
        bb.load_backbone(bb.BackboneConfig(kind="esanet", checkpoint="x",
                                           input_width=320, input_height=240))
    bad = tmp_path / "bad.pt"
    torch.save({"weights": 1}, bad)
    with pytest.raises(ValueError, match="SmallRGBDNet"):
        bb.load_backbone(bb.BackboneConfig(checkpoint=str(bad)))
    # Not a torch file at all (random bytes, a truncated copy of the shipped weights, the
    # weights' JSON record): one clear line naming the file, not torch's traceback.
    shipped = bb.DEFAULT_WEIGHTS.read_bytes()
    noise = np.random.default_rng(3).integers(0, 256, 4096, dtype=np.uint8).tobytes()
    # A line of text, seeded noise and a small YAML file failed inside the weights-only
    # unpickler as KeyError / IndexError: a traceback from every tool and node.
    for name, blob in (("random.pt", bytes(range(256)) * 12), ("cut.pt", shipped[:5000]),
                       ("record.json", bb.DEFAULT_WEIGHTS.with_suffix(".json").read_bytes()),
                       ("text.pth", b"this is not a checkpoint\n"), ("noise.pt", noise),
                       ("cfg.pt", b"backbone:\n  kind: esanet\n")):
        (tmp_path / name).write_bytes(blob)
        with pytest.raises(ValueError, match=f"^cannot read checkpoint {tmp_path / name}: "):
            bb.load_backbone(bb.BackboneConfig(checkpoint=str(tmp_path / name)))


def test_esanet_channel_to_id():
    nyu = bb.esanet_channel_to_id("nyuv2")
    sun = bb.esanet_channel_to_id("sunrgbd")
    assert len(nyu) == 40 and len(sun) == 37 and nyu.dtype == np.uint16
    np.testing.assert_array_equal(sun, nyu[:37])
    # NYU-40: 1 wall, 2 floor, 22 ceiling, 25 television.
    assert nyu[0] == classes.CLASS_ID["wall"] and nyu[1] == classes.CLASS_ID["floor"]
    assert nyu[21] == classes.CLASS_ID["ceiling"] and nyu[24] == classes.CLASS_ID["tv"]


# ----------------------------------------------------------------------------- entropy
def test_entropy_matches_hand_computation():
    logits = np.array([[[0.0, 0.0, 0.0], [2.0, 1.0, -1.0]]], dtype=np.float32)
    h = uncertainty.entropy(logits)
    p = np.exp([2.0, 1.0, -1.0]) / np.exp([2.0, 1.0, -1.0]).sum()
    assert h.shape == (1, 2) and h.dtype == np.float32
    assert h[0, 0] == pytest.approx(math.log(3), abs=1e-6)
    assert h[0, 1] == pytest.approx(float(-(p * np.log(p)).sum()), abs=1e-6)


def test_entropy_range_and_stability():
    rng = np.random.default_rng(0)
    logits = (rng.normal(size=(30, 40, 9)) * 50).astype(np.float32)
    logits[0, 0] = 1e30  # all equal, huge: uniform
    logits[0, 1] = [1e30] + [-1e30] * 8  # one-hot
    h = uncertainty.entropy(logits)
    assert np.isfinite(h).all()
    assert h.min() >= 0.0 and h.max() <= math.log(9) + 1e-6
    assert h[0, 0] == pytest.approx(math.log(9), abs=1e-5)
    assert h[0, 1] == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(ValueError, match="NaN"):
        uncertainty.entropy(np.array([[np.nan, 1.0]], np.float32))


def test_entropy_over_the_channel_axis_of_a_tensor():
    """A network's (B, S, H, W) output: entropy over dim 1 equals moving channels last."""
    x = torch.randn(2, 9, 5, 7) * 4
    torch.testing.assert_close(uncertainty.entropy(x, dim=1),
                               uncertainty.entropy(x.movedim(1, -1)))
    with pytest.raises(ValueError, match="channels last"):
        uncertainty.entropy(np.zeros((9, 4), np.float32), dim=0)


# ----------------------------------------------------------------------------- training pieces
def test_targets_ignore_novel_and_void():
    sem = np.arange(14, dtype=np.uint16)[None]
    tgt = train_data.semantic_to_target(sem)[0]
    for cid in range(14):
        if cid in classes.KNOWN_IDS:
            assert tgt[cid] == classes.ID_TO_CHANNEL[cid]
        else:
            assert tgt[cid] == train_data.IGNORE


def test_miou_definition():
    # 2 known classes on 4 known pixels; novel pixel (IGNORE) must not count.
    target = np.array([0, 0, 1, 1, train_data.IGNORE], np.uint8)
    pred = np.array([0, 1, 1, 1, 0], np.int64)
    s = train.scores_from_confusion(train.confusion(pred, target))
    # IoU(0) = 1/2, IoU(1) = 2/3, other classes absent from GT are excluded.
    assert s["miou_known"] == pytest.approx((0.5 + 2 / 3) / 2 * 100)
    assert s["pixel_accuracy"] == pytest.approx(0.75)


def test_augment_keeps_labels_aligned():
    gen = torch.Generator().manual_seed(0)
    # Image whose colour encodes the label: the warp must move both together.
    lab = torch.zeros(2, 48, 64, dtype=torch.long)
    lab[:, :, 32:] = 1
    rgb = (lab[:, None].float() * 200).repeat(1, 3, 1, 1)
    depth = torch.ones(2, 1, 48, 64)
    r, d, t = train_data.augment(rgb, depth, lab, gen, jitter=0.0)
    inside = t != train_data.IGNORE
    assert inside.float().mean() > 0.5
    bright = r.mean(1) > 100
    agree = (bright == (t == 1))[inside].float().mean()
    assert agree > 0.95
    assert ((d[:, 0] == 0) == ~inside).float().mean() > 0.95
    r, d, t = train_data.augment(rgb, depth, lab, gen, crop=(32, 40))
    assert r.shape == (2, 3, 32, 40) and d.shape == (2, 1, 32, 40) and t.shape == (2, 32, 40)
    inside = t != train_data.IGNORE
    assert ((r.mean(1) > 100) == (t == 1))[inside].float().mean() > 0.95


def test_outlier_paste_takes_only_known_colour_and_marks_it_outlier():
    """Outlier exposure pastes another sample's known-class colour onto the destination's
    geometry as OUTLIER; novel (IGNORE) sources are never pasted, IGNORE stays IGNORE."""
    gen = torch.Generator().manual_seed(0)
    b, h, w = 4, 40, 48
    tgt = torch.zeros(b, h, w, dtype=torch.long)          # wall-ish class 0 everywhere
    tgt[1] = 3                                            # sample 1 is another class
    tgt[2] = train_data.IGNORE                                 # sample 2 is all novel
    rgb = torch.stack([torch.full((3, h, w), float(v)) for v in (10, 120, 250, 60)])
    r, t = train_data.paste_outliers(rgb, tgt, gen, prob=1.0)
    out = t == train_data.OUTLIER
    # Sample 0 takes sample 1's colour (class 3 on class 0): pasted, marked outlier.
    assert out[0].any() and (r[0, 0][out[0]] == 120).all() and (r[0, 0][~out[0]] == 10).all()
    # Sample 1 would take sample 2's colour, which is all novel: never pasted.
    assert not out[1].any() and torch.equal(r[1], rgb[1])
    # Sample 2's destination pixels are IGNORE and stay so (the colour may change).
    assert (t[2] == train_data.IGNORE).all()
    # Sample 3 would take sample 0's class-0 colour onto class 0: same class, not pasted.
    assert not out[3].any()
    # Nothing pasted without the option; the input tensors are not modified.
    r0, t0 = train_data.paste_outliers(rgb, tgt, gen, prob=0.0)
    assert torch.equal(r0, rgb) and torch.equal(t0, tgt)
    assert (tgt != train_data.OUTLIER).all()


def test_outlier_loss_pushes_towards_uniform_and_leaves_ce_alone():
    logits = torch.randn(2, classes.NUM_KNOWN, 6, 5, generator=torch.Generator().manual_seed(1))
    tgt = torch.randint(0, classes.NUM_KNOWN, (2, 6, 5), generator=torch.Generator().manual_seed(2))
    w = torch.ones(classes.NUM_KNOWN)
    plain = train.loss_terms(logits, tgt, w)
    assert set(plain) == {"ce"}
    tgt_oe = tgt.clone()
    tgt_oe[:, :2] = train_data.OUTLIER
    terms = train.loss_terms(logits, tgt_oe, w, outlier_weight=0.5)
    # CE over the remaining pixels only; OE = 0.5 * cross-entropy from uniform.
    keep = tgt_oe != train_data.OUTLIER
    ce = torch.nn.functional.cross_entropy(logits.permute(0, 2, 3, 1)[keep], tgt_oe[keep])
    assert torch.isclose(terms["ce"], ce)
    logp = torch.log_softmax(logits.permute(0, 2, 3, 1)[~keep], dim=1)
    assert torch.isclose(terms["oe"], -0.5 * logp.mean())
    # Uniform logits are the minimum of the OE term (log S).
    flat = train.loss_terms(torch.zeros_like(logits), tgt_oe, w, outlier_weight=1.0)["oe"]
    assert torch.isclose(flat, torch.tensor(np.log(classes.NUM_KNOWN), dtype=flat.dtype))
    assert terms["oe"] > flat * 0.5


def test_train_loop_learns_a_toy_task(tmp_path):
    """A few steps on a toy RGB-D task lower the loss and write weights + record."""
    rng = np.random.default_rng(0)

    def toy(n):
        sem = np.full((n, 48, 64), classes.CLASS_ID["wall"], np.uint16)
        sem[:, 24:] = classes.CLASS_ID["floor"]
        sem[:, :4] = classes.CLASS_ID["ceiling"]  # novel: ignored
        rgb = np.where(sem[..., None] == classes.CLASS_ID["floor"], 60, 200).repeat(3, -1)
        rgb = (rgb + rng.integers(0, 30, rgb.shape)).astype(np.uint8)
        depth = np.where(sem == classes.CLASS_ID["floor"], 1.5, 3.0).astype(np.float32)
        return {"rgb": rgb, "depth": depth, "semantic": sem}

    rec = train.train_backbone(tmp_path / "w.pt", toy(16), toy(4), {"trained_on": "toy"},
                               epochs=6, batch_size=4, progress=False,
                               command="test", crop=None)
    assert rec["history"][-1]["loss"] < rec["history"][0]["loss"]
    assert rec["val_miou_known"] > 60
    assert rec["trained_on"] == "toy" and rec["train_frames"] == 16
    assert json.loads((tmp_path / "w.json").read_text())["trained_on"] == "toy"
    net = small.load_weights(str(tmp_path / "w.pt"))
    assert isinstance(net, small.SmallRGBDNet)
    with pytest.raises(ValueError, match="validation data: semantic must be uint16"):
        bad = toy(4)
        bad["semantic"] = bad["semantic"].astype(np.int32)
        train.train_backbone(tmp_path / "x.pt", toy(4), bad, progress=False)
    # A learning rate that makes the loss NaN: refused, nothing written (a diverged net's
    # checkpoint was saved and every run with it ended in 'logits contain NaN or inf').
    with pytest.raises(ValueError, match="training diverged at step .*lower the learning"):
        train.train_backbone(tmp_path / "d.pt", toy(8), toy(4), epochs=3, batch_size=4,
                             progress=False, command="test", crop=None, lr=1e12)
    assert not (tmp_path / "d.pt").exists()
    # Fine-tuning from the weights just written keeps their record under "init".
    rec = train.train_backbone(tmp_path / "f.pt", toy(8), toy(4), epochs=1, batch_size=4,
                               progress=False, command="test", crop=None,
                               init=str(tmp_path / "w.pt"))
    assert rec["init"]["trained_on"] == "toy" and rec["trained_on"] == "arrays"
    # Outlier exposure: its term is logged per epoch and the record says so.
    rec = train.train_backbone(tmp_path / "o.pt", toy(8), toy(4), epochs=1, batch_size=4,
                               progress=False, command="test", crop=None,
                               init=str(tmp_path / "w.pt"), outlier_weight=0.5,
                               outlier_prob=1.0)
    assert rec["history"][0]["oe"] > 0 and rec["outlier_weight"] == 0.5
    assert "outlier exposure" in rec["loss"]
    with pytest.raises(ValueError, match="outlier_weight"):
        train.train_backbone(tmp_path / "x.pt", toy(4), toy(4), progress=False,
                             outlier_weight=-1.0)
    # Reproducible: the same options give the same weights, bit for bit.
    rng = np.random.default_rng(0)
    data = (toy(16), toy(4))
    for name in ("a.pt", "b.pt"):
        train.train_backbone(tmp_path / name, *data, epochs=2, batch_size=4,
                             progress=False, command="test", crop=(32, 48),
                             widths=(8, 8, 16, 16))
    a = small.load_weights(str(tmp_path / "a.pt")).state_dict()
    b = small.load_weights(str(tmp_path / "b.pt")).state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_novelty_branch_keeps_the_argmax_and_raises_entropy_on_outliers(tmp_path):
    """A novelty branch trained with outlier exposure on a frozen net: every pixel's
    argmax is the net's, the net's weights are untouched, and the entropy rises on
    colour that does not belong to its geometry while staying low on known classes."""
    rng = np.random.default_rng(0)

    def toy(n, paste=False):
        sem = np.full((n, 48, 64), classes.CLASS_ID["wall"], np.uint16)
        sem[:, 24:] = classes.CLASS_ID["floor"]
        rgb = np.where(sem[..., None] == classes.CLASS_ID["floor"], 60, 200).repeat(3, -1)
        rgb = (rgb + rng.integers(0, 30, rgb.shape)).astype(np.uint8)
        depth = np.where(sem == classes.CLASS_ID["floor"], 1.5, 3.0).astype(np.float32)
        if paste:  # floor colour on the wall's geometry, marked novel (a "picture")
            rgb[:, 6:16, 20:40] = 60
            sem[:, 6:16, 20:40] = classes.CLASS_ID["picture"]
        return {"rgb": rgb, "depth": depth, "semantic": sem}

    base = tmp_path / "base.pt"
    train.train_backbone(base, toy(16), toy(4), epochs=20, batch_size=4, progress=False,
                         command="test", crop=None, widths=(8, 8, 16, 16), lr=1e-2)
    with pytest.raises(ValueError, match="novelty_branch"):
        train.train_backbone(tmp_path / "x.pt", toy(4), toy(4), progress=False,
                             novelty_branch=True, init=str(base),
                             widths=(8, 8, 16, 16))  # no outlier weight
    rec = train.train_backbone(tmp_path / "nov.pt", toy(16), toy(4, paste=True), epochs=12,
                               batch_size=4, progress=False, command="test", crop=None,
                               init=str(base), outlier_weight=0.5, outlier_prob=1.0,
                               novelty_branch=True, lr=1e-2, widths=(8, 8, 16, 16))
    assert rec["novelty_branch"] and rec["init"]["weights"] == str(base)
    plain, nov = small.load_weights(str(base)), small.load_weights(str(tmp_path / "nov.pt"))
    assert nov.novelty_branch and not plain.novelty_branch
    for k, v in plain.state_dict().items():  # the frozen net is the same, bit for bit
        assert torch.equal(v, nov.state_dict()[k]), k
    val = toy(4, paste=True)
    rgb = torch.from_numpy(val["rgb"]).permute(0, 3, 1, 2).float()
    depth = torch.from_numpy(val["depth"])[:, None]
    with torch.no_grad():
        a, b = plain.predict_raw(rgb, depth), nov.predict_raw(rgb, depth)
    assert torch.equal(a.argmax(1), b.argmax(1))
    ent = {name: train.entropy_by_kind(m, val) for name, m in (("plain", plain), ("nov", nov))}
    assert rec["val_entropy_novel"] == pytest.approx(ent["nov"]["novel"], abs=1e-3)
    assert ent["nov"]["novel"] > ent["plain"]["novel"] + 0.2
    assert ent["nov"]["novel"] > 3 * ent["nov"]["known"]
    # Through the Backbone interface: backbone.novelty_branch false gives the frozen
    # net's own logits; true (the default) the scaled ones, with the same argmax.
    frame_rgb, frame_depth = val["rgb"][0], val["depth"][0]
    with_branch = bb.load_backbone(bb.BackboneConfig(checkpoint=str(tmp_path / "nov.pt")))
    without = bb.load_backbone(bb.BackboneConfig(checkpoint=str(tmp_path / "nov.pt"),
                                                 novelty_branch=False))
    ref = bb.load_backbone(bb.BackboneConfig(checkpoint=str(base))).predict(frame_rgb,
                                                                            frame_depth)
    np.testing.assert_array_equal(without.predict(frame_rgb, frame_depth), ref)
    scaled = with_branch.predict(frame_rgb, frame_depth)
    assert (scaled.argmax(-1) == ref.argmax(-1)).all() and not np.allclose(scaled, ref)


def test_synth_cache_is_keyed_by_the_generator_source(tmp_path, monkeypatch):
    """Cached frames are reused, but never across a change of the generator's code."""
    from neurncd_ros import synth
    from neurncd_ros.synth import training

    cfg = synth.SynthConfig(width=32, height=24)
    fresh = training.synth_frames(3, 2, tmp_path, cfg)
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1 and training.generator_hash() in files[0].name
    # The cache is read: a doctored file under the same key is what comes back.
    np.savez(files[0], rgb=np.zeros_like(fresh["rgb"]), depth=fresh["depth"],
             semantic=fresh["semantic"])
    assert training.synth_frames(3, 2, tmp_path, cfg)["rgb"].max() == 0
    # Another generator version does not see that file: the frames are rendered again.
    monkeypatch.setattr(training, "generator_hash", lambda: "0123456789")
    again = training.synth_frames(3, 2, tmp_path, cfg)
    assert np.array_equal(again["rgb"], fresh["rgb"])
    assert len(list(tmp_path.glob("*.npz"))) == 2


def test_record_command_reproduces_the_options():
    import argparse

    from neurncd_ros.tools import train_backbone

    p = argparse.ArgumentParser()
    train_backbone.add_arguments(p)

    def norm(ns):
        return {k: list(v) if isinstance(v, tuple) else v for k, v in vars(ns).items()}
    for extra in ([], ["--novelty-branch", "--outlier-weight", "0.2"]):
        args = p.parse_args(["--out", "w.pt", "--train-seeds", "0-3,7", "--epochs", "2",
                             "--widths", "8", "8", "16", "16", *extra])
        line = train_backbone.command_line(args)
        assert line.startswith("neurncd train-backbone ")
        assert ("--novelty-branch" in line) == bool(extra)
        again = p.parse_args(line.split()[2:])
        assert norm(again) == norm(args)


# ----------------------------------------------------------------------------- esanet
def test_esanet_checkpoint_loads_through_backbone(tmp_path):
    from neurncd_ros.core.backbone import esanet
    torch.manual_seed(0)
    net = esanet.ESANet(37)
    path = tmp_path / "ckpt_sunrgbd.pth"
    torch.save({"state_dict": net.state_dict(), "epoch": 0}, path)
    del net
    state = torch.random.get_rng_state()
    b = bb.load_backbone(bb.BackboneConfig(kind="esanet", checkpoint=str(path),
                                           esanet_dataset="sunrgbd", input_width=320,
                                           input_height=256, num_threads=0))
    assert torch.equal(torch.random.get_rng_state(), state), "loading drew from torch's RNG"
    assert b.channels == 37
    rgb, depth = _rgbd(240, 320)
    out = b.predict(rgb, depth)
    assert out.shape == (240, 320, 37) and out.dtype == np.float32 and np.isfinite(out).all()


def test_train_backbone_on_user_bags_with_a_validation_split(tmp_path, capsys):
    """`neurncd train-backbone --data` trains on bags with ground truth, splits off
    validation, records what it saw, and the embedding path loads the weights."""
    import json

    from neurncd_ros import cli, synth
    from neurncd_ros.core.data import bag

    cfg = synth.SynthConfig(width=64, height=48)
    paths = []
    for seed in (3, 4):
        paths.append(tmp_path / f"s{seed}.mcap")
        bag.write_bag(paths[-1], synth.generate(seed, 6, cfg))
    out = tmp_path / "mine.pt"
    common = ["train-backbone", "--out", str(out), "--size", "64", "48", "--epochs", "2",
              "--batch-size", "4", "--crop", "32", "48", "--widths", "8", "8", "16", "16",
              "--val-every", "0"]
    assert cli.main(common + ["--data", *map(str, paths)]) == 0
    rec = json.loads(out.with_suffix(".json").read_text())
    assert rec["trained_on"] == "data" and rec["val_split"] == "frames"
    assert rec["train_files"] == [str(p) for p in paths] and rec["train_frames"] == 10
    assert rec["val_frames"] == 2 and rec["train_size"] == [64, 48]
    assert "--data" in rec["command"] and "--train-seeds" not in rec["command"]
    # The record's command is one to run again (the CLI's own parser object once leaked
    # into it as --command-parser ArgumentParser(...)).
    assert "parser" not in rec["command"] and "--overwrite" not in rec["command"]
    printed = capsys.readouterr().out
    assert "validation 2 frames of" in printed
    assert f"wrote {out} and its record {out.with_suffix('.json')}" in printed
    # An existing weight file (the shipped weights were once the default --out) is
    # replaced only with --overwrite.
    assert cli.main(common + ["--data", *map(str, paths)]) == 1
    assert "exists already; name another --out, or pass --overwrite" in capsys.readouterr().err
    common = common + ["--overwrite"]
    b = bb.load_backbone(bb.BackboneConfig(checkpoint=str(out), num_threads=1))
    frame = next(iter(synth.generate(5, 1, cfg)))
    assert b.predict(frame.rgb, frame.depth).shape == (48, 64, 9)
    # By path in the engine, as `neurncd run --set backbone.checkpoint=...` and the
    # embedding node's `-p backbone.checkpoint:=...` give it.
    run = tmp_path / "run"
    assert cli.main(["run", "--bag", str(paths[0]), "--out", str(run), "--set",
                     f"backbone.checkpoint={out}", "--set", "run.overlays=0"]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["backbone_checkpoint"] == str(out) and metrics["labelled"] >= 1
    capsys.readouterr()
    # By files: the last file validates.
    assert cli.main(common + ["--data", *map(str, paths), "--val-split", "files"]) == 0
    rec = json.loads(out.with_suffix(".json").read_text())
    assert rec["val_files"] == [str(paths[1])] and rec["train_frames"] == 6
    # A bag without ground truth is refused by name.
    bare = tmp_path / "bare.mcap"
    bag.write_bag(bare, (_without_ground_truth(f) for f in synth.generate(6, 2, cfg)))
    assert cli.main(common + ["--data", str(bare), str(paths[0])]) == 1
    assert "bare.mcap: no frame with semantic ground truth" in capsys.readouterr().err
    missing = tmp_path / "no.pt"
    assert cli.main(common + ["--data", *map(str, paths), "--init", str(missing)]) == 1
    assert f"--init {missing}: no such weight file" in capsys.readouterr().err


def _without_ground_truth(frame):
    import dataclasses
    return dataclasses.replace(frame, semantic=None, instance=None)


def test_esanet_fine_tunes_on_known_classes_and_loads_as_esanet(tmp_path):
    """--arch esanet: a user's ESANet checkpoint, trained on the 9 known classes (its
    NYU-40 logits pooled per class), saved as an ESANet checkpoint the backbone loads."""
    from neurncd_ros.core.backbone import esanet

    torch.manual_seed(0)
    start = tmp_path / "user_esanet.pth"
    torch.save({"state_dict": esanet.ESANet(40).state_dict()}, start)
    rng = np.random.default_rng(0)
    sem = np.full((4, 64, 64), classes.CLASS_ID["wall"], np.uint16)
    sem[:, 32:] = classes.CLASS_ID["floor"]
    data = {"rgb": rng.integers(0, 256, (4, 64, 64, 3), dtype=np.uint8),
            "depth": np.full((4, 64, 64), 2.0, np.float32), "semantic": sem}
    with pytest.raises(ValueError, match="divisible by 32"):
        train.train_backbone(tmp_path / "x.pth", data, data, arch="esanet", init=str(start),
                             crop=(48, 48), progress=False)
    out = tmp_path / "mine.pth"
    rec = train.train_backbone(out, data, data, {"trained_on": "toy"}, epochs=1,
                               batch_size=2, crop=(64, 64), progress=False,
                               command="test", arch="esanet", init=str(start))
    assert rec["arch"] == "ESANet-R34-NBt1D" and rec["steps"] == 2
    assert rec["init"]["weights"] == str(start)
    b = bb.load_backbone(bb.BackboneConfig(kind="esanet", checkpoint=str(out),
                                           input_width=64, input_height=64, num_threads=1))
    assert b.channels == 40
    moved = any(not torch.equal(a, c) for a, c in zip(
        esanet.load_esanet_checkpoint(start).state_dict().values(),
        b.net.state_dict().values()))
    assert moved


def test_threshold_tuned_for_a_branch_warns_without_one():
    """The shipped weights carry a novelty branch and the default threshold is tuned for
    it; weights without one (or the branch off) with that threshold get a warning, in
    the offline engine as in the embedding node, naming the value to use instead."""
    from neurncd_ros import config
    from neurncd_ros.core.engine.offline import OfflineEngine

    shipped = bb.load_backbone(bb.BackboneConfig())
    assert shipped.novelty_branch
    default_threshold = config.load(None, {}).discovery.entropy_threshold
    assert bb.threshold_warning(shipped, default_threshold) is None
    off = bb.load_backbone(bb.BackboneConfig(novelty_branch=False))
    assert not off.novelty_branch
    advice = bb.threshold_warning(off, default_threshold)
    assert advice and "0.15" in advice and "novelty branch" in advice
    assert bb.threshold_warning(off, 0.15) is None
    cfg = config.load(None, config.parse_overrides(["backbone.novelty_branch=false"]))
    with pytest.warns(UserWarning, match="no novelty branch"):
        OfflineEngine(cfg)
    cfg = config.load(None, config.parse_overrides(["backbone.novelty_branch=false",
                                                     "discovery.entropy_threshold=0.15"]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        OfflineEngine(cfg)
