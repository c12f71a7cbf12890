"""ESANet R34-NBt1D: checkpoint compatibility, safe loading, forward contract, preprocessing."""

from __future__ import annotations

import json
import os
import pickle

import cv2
import numpy as np
import pytest
import torch

from neurncd_ros.core.backbone import backbone as B
from neurncd_ros.core.backbone import esanet as E
from neurncd_ros.core.params import ConfigError, build

torch.set_num_threads(1)

NYU_MEAN, NYU_STD = 2841.94941272766, 1417.2594281672277
SUN_MEAN, SUN_STD = 19025.14930492213, 9880.916071806689


def _randomise_buffers(model: torch.nn.Module, seed: int) -> None:
    """Give BN running stats non-default values so a load that skipped buffers shows."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, buf in model.named_buffers():
            if name.endswith("running_mean"):
                buf.copy_(0.1 * torch.randn(buf.shape, generator=g))
            elif name.endswith("running_var"):
                buf.copy_(0.5 + torch.rand(buf.shape, generator=g))


@pytest.fixture(scope="module")
def model37() -> E.ESANet:
    """One 37-class model shared by the tests (building it takes about a second)."""
    torch.manual_seed(0)
    m = E.ESANet(37)
    _randomise_buffers(m, 1)
    return m.eval()


@pytest.fixture(scope="module")
def inputs() -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(2)
    return torch.randn(1, 3, 64, 96, generator=g), torch.randn(1, 1, 64, 96, generator=g)


@pytest.fixture(scope="module")
def public_ckpt(tmp_path_factory, model37) -> str:
    """model37 saved in the public release layout (with numpy scalars like a training log)."""
    path = tmp_path_factory.mktemp("ckpt") / "r34_NBt1D.pth"
    torch.save({"epoch": 499, "state_dict": model37.state_dict(),
                "optimizer": {"state": {}, "param_groups": [{"lr": 0.01}]},
                "best_miou": np.float64(0.4817), "best_miou_epoch": np.int64(480)}, path)
    return str(path)


# --- state_dict compatibility ------------------------------------------------

@pytest.mark.parametrize("head", ["sunrgbd", "nyuv2"])
def test_state_dict_matches_recorded_key_list(esanet_key_list, head):
    rec = json.loads(esanet_key_list.read_text())[head]
    m = E.ESANet(rec["num_classes"])
    got = [[k, list(v.shape), str(v.dtype).removeprefix("torch.")]
           for k, v in m.state_dict().items()]
    assert len(got) == rec["num_tensors"]
    first_diff = next((a, b) for a, b in zip(got, rec["keys"]) if a != b) \
        if got != rec["keys"] else None
    assert first_diff is None, f"first differing entry (ours, recorded): {first_diff}"
    assert sum(p.numel() for p in m.parameters()) == rec["num_parameters"]


# --- checkpoint loading -----------------------------------------------------

def test_public_layout_roundtrip_gives_identical_logits(public_ckpt, model37, inputs):
    loaded = E.load_esanet_checkpoint(public_ckpt)
    assert loaded.num_classes == 37 and not loaded.training
    with torch.no_grad():
        a, b = model37(*inputs), loaded(*inputs)
    assert a.shape == (1, 37, 64, 96)
    assert torch.equal(a, b)
    # A fresh model (different init) really differs, so equality above means the load worked.
    torch.manual_seed(123)
    with torch.no_grad():
        c = E.ESANet(37).eval()(*inputs)
    assert not torch.allclose(a, c)


def test_bare_state_dict_with_module_prefix_loads(tmp_path, model37, inputs):
    path = tmp_path / "bare.pth"
    torch.save({"module." + k: v for k, v in model37.state_dict().items()}, path)
    loaded = E.load_esanet_checkpoint(path, num_classes=37)
    with torch.no_grad():
        assert torch.equal(model37(*inputs), loaded(*inputs))


def test_wrong_head_size_lists_keys_with_shapes(public_ckpt):
    with pytest.raises(ValueError) as err:
        E.load_esanet_checkpoint(public_ckpt, num_classes=40)
    msg = str(err.value)
    assert "wrong shape" in msg
    assert "decoder.decoder_module_1.side_output.weight expected (40, 512, 1, 1) " \
           "found (37, 512, 1, 1)" in msg
    # The fix first: the head says which dataset the checkpoint was trained for.
    assert "its class head decoder.conv_out.weight has 37 classes, not 40: a SUN RGB-D " \
           "checkpoint (backbone.esanet_dataset sunrgbd)" in msg.split("wrong shape")[0], msg


def test_missing_and_unexpected_keys_are_named(tmp_path, model37):
    sd = dict(model37.state_dict())
    sd.pop("encoder_depth.layer3.2.bn1.running_var")
    sd["decoder.extra_head.weight"] = torch.zeros(3, 3)
    path = tmp_path / "broken.pth"
    torch.save({"state_dict": sd}, path)
    with pytest.raises(ValueError) as err:
        E.load_esanet_checkpoint(path)
    msg = str(err.value)
    assert "1 missing: encoder_depth.layer3.2.bn1.running_var expected (256,)" in msg
    assert "1 unexpected: decoder.extra_head.weight found (3, 3)" in msg


class _Payload:
    """Unpickling this runs a shell command that creates a marker file."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_code_executing_pickle_is_refused(tmp_path, model37):
    # The payload is real: a plain unpickler runs it.
    probe = tmp_path / "probe"
    pickle.loads(pickle.dumps(_Payload(str(probe))))
    assert probe.exists()
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.pth"
    torch.save({"state_dict": {"decoder.conv_out.weight": torch.zeros(37, 128, 3, 3)},
                "hook": _Payload(str(marker))}, path)
    with pytest.raises(ValueError, match="refusing checkpoint .*system"):
        E.load_esanet_checkpoint(path)
    assert not marker.exists()


def test_unreadable_or_foreign_files_give_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        E.load_esanet_checkpoint(tmp_path / "nope.pth")
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"\x00not a checkpoint" * 8)
    with pytest.raises(ValueError, match="cannot read checkpoint"):
        E.load_esanet_checkpoint(junk)
    other = tmp_path / "other.pth"
    torch.save({"fc.weight": torch.zeros(2, 2)}, other)
    with pytest.raises(ValueError, match="no class head"):
        E.load_esanet_checkpoint(other)


# --- forward contract -------------------------------------------------------

def test_forward_256x320_gives_full_size_float_logits(model37):
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        out = model37(torch.randn(1, 3, 256, 320, generator=g),
                      torch.randn(1, 1, 256, 320, generator=g))
    assert out.shape == (1, 37, 256, 320) and out.dtype == torch.float32
    assert torch.isfinite(out).all()


def test_size_not_divisible_by_32_is_rejected(model37):
    with pytest.raises(ValueError, match="divisible by 32.*240x320"):
        model37(torch.zeros(1, 3, 240, 320), torch.zeros(1, 1, 240, 320))
    with pytest.raises(ValueError, match=r"depth must be \(N, 1, H, W\)"):
        model37(torch.zeros(1, 3, 64, 64), torch.zeros(1, 3, 64, 64))


def test_side_outputs_only_in_training_mode(inputs):
    torch.manual_seed(5)
    m = E.ESANet(37)
    with torch.no_grad():
        # Training BN needs > 1 value per channel after the 1x1 pooling bin: batch 2.
        batch = [torch.cat([x, x.flip(-1)]) for x in inputs]
        out, s8, s16, s32 = m.train()(*batch)  # pyramid supervision, strides 8/16/32
        assert out.shape == (2, 37, 64, 96)
        assert [s.shape[-2:] for s in (s8, s16, s32)] == [(8, 12), (4, 6), (2, 3)]
        ref = m.eval()(*inputs)
        for i in (1, 2, 3):
            getattr(m.decoder, f"decoder_module_{i}").side_output.weight.fill_(float("nan"))
        assert torch.equal(m(*inputs), ref)


def test_learned_upsampling_is_nearest_then_zero_padded_bilinear_kernel():
    up = E.LearnedUpsample(2)
    x = torch.ones(1, 2, 4, 5)
    with torch.no_grad():
        y = up(x)
    assert y.shape == (1, 2, 8, 10)
    # Interior: kernel sums to 1; borders lose one kernel row (0.75), corners two (0.5625).
    assert torch.allclose(y[..., 1:-1, 1:-1], torch.ones(1, 2, 6, 8))
    assert torch.allclose(y[..., 0, 1:-1], torch.full((1, 2, 8), 0.75))
    assert torch.allclose(y[..., 0, 0], torch.full((1, 2), 0.5625))
    # A single hot pixel spreads as the 2x2 nearest block blurred by [1,2,1]x[1,2,1]/16.
    x = torch.zeros(1, 1, 3, 3)
    x[..., 1, 1] = 1
    with torch.no_grad():
        y = E.LearnedUpsample(1)(x)[0, 0]
    assert torch.isclose(y[2, 2], torch.tensor(9 / 16))
    assert torch.isclose(y[1, 1], torch.tensor(1 / 16))


def test_context_module_pools_to_fixed_bins_at_any_size():
    ppm = E.PyramidPooling(512, 512).eval()
    assert [f[0].output_size for f in ppm.features] == [1, 5]
    with torch.no_grad():
        for h, w in ((8, 10), (15, 20)):
            assert ppm(torch.randn(1, 512, h, w)).shape == (1, 512, h, w)


# --- preprocessing ----------------------------------------------------------

def _depth_input(depth: np.ndarray, dataset: str = "nyuv2", mode: str = "raw") -> np.ndarray:
    t = torch.from_numpy(np.asarray(depth, np.float32))[None, None]
    return E.preprocess_depth(t, dataset, mode)[0, 0].numpy()


def test_normalisation_matches_hand_computed_values():
    rgb = np.array([[[255, 0, 128], [10, 200, 30]]], dtype=np.uint8)  # 1 x 2
    out = E.preprocess_rgb(torch.from_numpy(rgb).permute(2, 0, 1)[None].float())[0].numpy()
    assert out.shape == (3, 1, 2) and out.dtype == np.float32
    np.testing.assert_allclose(out[:, 0, 0], [(1 - 0.485) / 0.229, (0 - 0.456) / 0.224,
                                              (128 / 255 - 0.406) / 0.225], rtol=1e-6)
    depth = np.array([[2.0, 0.0, 0.5]], dtype=np.float32)
    nyu = _depth_input(depth, "nyuv2", "raw")
    np.testing.assert_allclose(nyu, [[(2000 - NYU_MEAN) / NYU_STD, 0.0,
                                      (500 - NYU_MEAN) / NYU_STD]], rtol=1e-5)
    sun = _depth_input(depth, "sunrgbd", "raw")
    np.testing.assert_allclose(sun, [[(20000 - SUN_MEAN) / SUN_STD, 0.0,
                                      (5000 - SUN_MEAN) / SUN_STD]], rtol=1e-5)
    nan_hole = _depth_input(np.array([[np.nan, np.inf]], np.float32), "nyuv2", "raw")
    assert np.all(nan_hole == 0)
    refined = _depth_input(depth, "nyuv2", "refined")
    assert refined[0, 1] == pytest.approx(-NYU_MEAN / NYU_STD, rel=1e-5)
    with pytest.raises(ValueError, match="dataset"):
        _depth_input(depth, "kitti")


def _kinect_frame(real_data_dir):
    d = real_data_dir / "kinect_dining"
    bgr = cv2.imread(str(d / "color" / "1.png"), cv2.IMREAD_COLOR)
    depth_mm = cv2.imread(str(d / "depth" / "1.pgm"), cv2.IMREAD_UNCHANGED)
    assert bgr is not None and depth_mm is not None
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), depth_mm.astype(np.float32) / 1000.0


def _esanet(model, **cfg) -> B.Backbone:
    """An ESANet backbone; float32 unless ``precision`` is given, so the preprocessing
    tests compare the inputs at full precision."""
    return B.esanet_backbone(model, build(B.BackboneConfig,
                                          {"kind": "esanet", "precision": "float32", **cfg}))


def test_bfloat16_esanet_runs_a_copy_and_returns_float32_logits(real_data_dir, model37):
    """backbone.precision bfloat16 runs ESANet in bfloat16 (inputs included) on a copy:
    the caller's model keeps its float32 weights, predict() returns float32 logits close
    to the float32 run on a real Kinect frame (random weights, so the logits are compared,
    not the labels)."""
    rgb, depth = _kinect_frame(real_data_dir)
    size = {"esanet_dataset": "sunrgbd", "input_width": 320, "input_height": 256}
    low = _esanet(model37, precision="bfloat16", **size)
    assert low.input_dtype == torch.bfloat16
    assert all(p.dtype == torch.bfloat16 for p in low.net.parameters())
    assert all(p.dtype == torch.float32 for p in model37.parameters())
    assert low.inputs([rgb], [depth])[0].dtype == torch.bfloat16
    ours = low.predict(rgb, depth)
    ref = _esanet(model37, **size).predict(rgb, depth)
    assert ours.dtype == np.float32 and ours.shape == ref.shape == (*depth.shape, 37)
    assert not np.array_equal(ours, ref)
    assert np.abs(ours - ref).mean() < 0.05 * np.abs(ref).mean()


def test_preprocess_real_kinect_frame(real_data_dir, model37):
    rgb, depth = _kinect_frame(real_data_dir)
    holes = depth == 0
    assert holes.any() and (~holes).any()
    bb = _esanet(model37, esanet_dataset="sunrgbd")  # native 640x480
    x_rgb, x_depth = bb.inputs([rgb], [depth])
    assert x_rgb.shape == (1, 3, 480, 640) and x_depth.shape == (1, 1, 480, 640)
    d = x_depth[0, 0].numpy()
    # Same frame size: no resize; depth in 1/10 mm standardised, holes kept at exactly 0.
    np.testing.assert_allclose(d[~holes], (depth[~holes] * 10000.0 - SUN_MEAN) / SUN_STD,
                               rtol=1e-5, atol=1e-5)
    assert np.all(d[holes] == 0)
    np.testing.assert_allclose(x_rgb[0, 1].numpy(), (rgb[..., 1] / 255 - 0.456) / 0.224,
                               rtol=1e-5, atol=1e-5)
    # refined mode (from the one config schema): holes are normalised like any depth.
    refined = _esanet(model37, esanet_dataset="sunrgbd", esanet_depth_mode="refined")
    d = refined.inputs([rgb], [depth])[1][0, 0].numpy()
    assert np.allclose(d[holes], -SUN_MEAN / SUN_STD)
    # NaN (ROS "no return") is a hole too; negative depth is an error.
    bad = depth.copy()
    bad[0, 0] = np.nan
    assert bb.inputs([rgb], [bad])[1][0, 0, 0, 0] == 0
    bad[0, 0] = -1.0
    with pytest.raises(ValueError, match=">= 0"):
        bb.inputs([rgb], [bad])


def test_resized_run_on_real_frame_returns_logits_at_frame_size(real_data_dir, model37):
    rgb, depth = _kinect_frame(real_data_dir)
    bb = _esanet(model37, esanet_dataset="sunrgbd", input_width=320, input_height=256)
    x_rgb, x_depth = bb.inputs([rgb], [depth])
    assert x_rgb.shape == (1, 3, 256, 320)
    # Nearest resizing never invents depth: every value is one of the input's values.
    src = np.unique(_depth_input(depth, "sunrgbd"))
    assert np.isin(np.unique(x_depth.numpy()), src).all()
    logits = bb.predict(rgb, depth)
    assert logits.shape == (480, 640, 37) and logits.dtype == np.float32
    assert np.isfinite(logits).all()


def test_config_rejects_sizes_not_divisible_by_32(model37):
    with pytest.raises(ValueError, match="multiples of 32"):
        _esanet(model37, esanet_dataset="sunrgbd", input_width=320, input_height=240)
    bb = _esanet(model37, esanet_dataset="sunrgbd", input_width=320, input_height=256)
    with pytest.raises(ValueError, match="rgb must be"):
        bb.predict(np.zeros((4, 4), np.uint8), np.zeros((4, 4), np.float32))
    with pytest.raises(ConfigError, match="esanet_depth_mode"):
        build(B.BackboneConfig, {"esanet_depth_mode": "filled"})


@pytest.mark.slow
def test_forward_at_native_480x640(esanet_key_list):
    rec = json.loads(esanet_key_list.read_text())["nyuv2"]
    m = E.ESANet(rec["num_classes"]).eval()
    with torch.no_grad():
        out = m(torch.randn(1, 3, 480, 640), torch.randn(1, 1, 480, 640))
    assert list(out.shape) == rec["eval_output_shape"]


def test_esanet_graph_computes_what_the_eager_net_computes(real_data_dir, model37):
    """backbone.graph runs ESANet as a frozen TorchScript graph too: on a real Kinect
    frame its logits equal the eager model's, and the caller's model stays a module."""
    rgb, depth = _kinect_frame(real_data_dir)
    size = {"esanet_dataset": "sunrgbd", "input_width": 320, "input_height": 256}
    graph, eager = _esanet(model37, **size), _esanet(model37, graph=False, **size)
    assert graph.graph and not eager.graph
    ours, ref = graph.predict(rgb, depth), eager.predict(rgb, depth)
    assert len(graph._graphs) == 1 and isinstance(graph.net, torch.nn.Module)
    np.testing.assert_allclose(ours, ref, rtol=1e-5, atol=1e-5 * float(np.abs(ref).max()))
