"""The one `Backbone` interface: RGB-D frame in, semantic embedding out.

The semantic embedding is the per-pixel pre-softmax logit vector of a
segmentation network (the layer before the softmax, as in the paper). Two
kinds are available:

- ``default``: the project's small RGB-D net (:mod:`.small`), trained on the
  synthetic scenes with the 9 known NYU-13 classes; S = 9 and channel k
  predicts ``classes.KNOWN_IDS[k]``; weights ship in ``neurncd_ros/models``.
  Weights with a novelty branch (the shipped ones) scale each pixel's logits by
  a temperature factor from that outlier-exposed branch (``novelty_branch``):
  the argmax is the known-class head's, the entropy rises on what it never saw.
- ``esanet``: ESANet R34-NBt1D from a public checkpoint (:mod:`.esanet`);
  S = 40 (NYUv2) or 37 (SUN RGB-D), channel k predicts the NYU-40 class
  k + 1, mapped to NYU-13 by ``channel_to_id``.

Input contract of :meth:`Backbone.predict`: ``rgb`` (H, W, 3) uint8 RGB,
``depth`` (H, W) float32 metres. Depth holes are 0; NaN and +-inf (the ROS
REP 118 encodings of "no measurement") are treated as holes too; negative
depth is an error. The frame is resized to the model's input size and the
logits are resized back (bilinear) to H x W.
"""

from __future__ import annotations

import copy
import dataclasses
import warnings
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from .. import classes
from ..engine.records import EmbeddingSpec
from ..params import param

MODELS_DIR = Path(__file__).resolve().parents[2] / "models"
DEFAULT_WEIGHTS = MODELS_DIR / "default_backbone.pt"
"""Shipped weights of the default small model (see default_backbone.json)."""

NATIVE_SIZE = {"default": (320, 240), "esanet": (640, 480)}
"""(width, height) used when input_width/input_height are 0: the training size of
the default net, and the 480x640 resolution ESANet's authors run at."""

MIN_SIDE = 8
"""Smallest accepted image side (pixels): anything smaller has no usable content."""


@dataclasses.dataclass(frozen=True)
class BackboneConfig:
    """Which segmentation network produces the semantic embedding, and how it runs."""

    kind: str = param("default", "segmentation network: the shipped small RGB-D net or "
                      "ESANet R34-NBt1D from a checkpoint", choices=("default", "esanet"))
    checkpoint: str = param("", "weight file; empty = shipped default weights "
                            "(kind=esanet needs a path)")
    esanet_dataset: str = param("nyuv2", "dataset the ESANet checkpoint was trained on: "
                                "sets class count (40/37) and depth statistics",
                                choices=("nyuv2", "sunrgbd"))
    input_width: int = param(0, "model input width in pixels; 0 = native (320 default, "
                             "640 esanet); esanet needs a multiple of 32", lo=0, hi=4096,
                             unit="px")
    input_height: int = param(0, "model input height in pixels; 0 = native (240 default, "
                              "480 esanet); esanet needs a multiple of 32", lo=0, hi=4096,
                              unit="px")
    esanet_depth_mode: str = param("raw", "ESANet depth holes: raw = a hole (0) stays 0 "
                                   "after normalisation, as the public raw-sensor inference "
                                   "does; refined = 0 is normalised like any depth (hole-free "
                                   "depth only)", choices=("raw", "refined"))
    novelty_branch: bool = param(True, "kind=default: use the weights' novelty branch when "
                                 "they have one (an outlier-exposed head whose entropy flattens "
                                 "the logits where it sees no known class; argmax unchanged); "
                                 "false = the known-class logits alone")
    features: bool = param(False, "kind=default: append the net's penultimate feature map "
                           "(the last decoder stage's 20 channels) to the embedding after "
                           "the logits (issue 11, direction 1: the field distils them, "
                           "mapper.distill_features, the mapper's keyframe fusion averages "
                           "them, discovery pools them per segment, "
                           "modulation.feature_weight); the embedding topic grows 29/9 times, "
                           "so pair it with embedding_node.output_scale 0.5")
    device: str = param("cpu", "torch device the network runs on", choices=("cpu", "cuda"))
    precision: str = param("auto", "arithmetic of the network's convolutions: bfloat16 is "
                           "about 1.4x faster on a CPU with native bfloat16 (AVX512-BF16) and "
                           "moves the argmax of a fraction of a percent of pixels, at class "
                           "borders; the default net keeps its class heads, so logits and "
                           "entropy, in float32; auto = bfloat16 where the CPU has it "
                           "natively, else float32 (bench/results/backbone.json)",
                           choices=("auto", "float32", "bfloat16"))
    graph: bool = param(True, "run the network as a frozen TorchScript graph, traced on "
                         "first use for each input shape (under 1 s, once; the embedding "
                         "node does it at start): the same outputs without PyTorch's "
                         "per-layer Python dispatch, less time per frame (on 2 cores: "
                         "bench/results/backbone.json, default_graph_speedup); "
                         "false = eager PyTorch, e.g. to debug or profile the net")
    num_threads: int = param(1, "torch CPU threads the executable running the backbone sets "
                             "(0 = leave torch's setting); 1 because the "
                             "nodes share the cores and more threads than free cores stall "
                             "(see bench/results/graph.json)", lo=0, hi=256)


def native_bfloat16(device: str) -> bool:
    """Whether ``device`` does bfloat16 convolutions natively: a CPU whose oneDNN has
    AVX512-BF16 (or AMX). Elsewhere bfloat16 is emulated and slower than float32."""
    if device != "cpu" or not torch.backends.mkldnn.is_available():
        return False
    return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


def compute_dtype(cfg: BackboneConfig) -> torch.dtype:
    """The dtype ``cfg.precision`` resolves to on ``cfg.device`` (auto: bfloat16 only
    where it is native, :func:`native_bfloat16`)."""
    if cfg.precision == "float32" or (cfg.precision == "auto"
                                      and not native_bfloat16(cfg.device)):
        return torch.float32
    if cfg.precision in ("auto", "bfloat16"):
        return torch.bfloat16
    raise ValueError(f"backbone precision must be auto, float32 or bfloat16, "
                     f"got {cfg.precision!r}")


def check_rgbd(rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Validate one RGB-D pair; return depth with NaN/inf replaced by 0 (hole)."""
    if not isinstance(rgb, np.ndarray) or not isinstance(depth, np.ndarray):
        raise ValueError("rgb and depth must be numpy arrays, got "
                         f"{type(rgb).__name__} and {type(depth).__name__}")
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if depth.dtype != np.float32 or depth.ndim != 2:
        raise ValueError(f"depth must be (H, W) float32 metres, got {depth.shape} {depth.dtype}")
    if depth.shape != rgb.shape[:2]:
        raise ValueError(f"depth {depth.shape} and rgb {rgb.shape[:2]} differ in size")
    if min(depth.shape) < MIN_SIDE:
        raise ValueError(f"image {depth.shape} is smaller than {MIN_SIDE} pixels on a side")
    finite = np.isfinite(depth)
    if not finite.all():
        depth = np.where(finite, depth, np.float32(0.0))
    if (depth < 0).any():
        raise ValueError(f"depth must be >= 0 metres (0 = hole), min is {float(depth.min())}")
    return depth


class Backbone:
    """A loaded segmentation network that turns RGB-D frames into embeddings.

    ``channels`` is S; ``channel_to_id`` (uint16, length S) is the NYU-13 id
    each channel predicts (0 where a channel has no NYU-13 class).
    """

    def __init__(self, net: torch.nn.Module, kind: str, channel_to_id: np.ndarray,
                 input_size: tuple[int, int], device: str, preprocess,
                 channels_last: bool = False, feature_channels: int = 0,
                 input_dtype: torch.dtype = torch.float32, graph: bool = False) -> None:
        self.net = net.eval()
        self.kind = kind
        self.channel_to_id = np.asarray(channel_to_id, dtype=np.uint16)
        self.channels = int(len(self.channel_to_id))
        self.input_size = input_size  # (width, height)
        self.device = torch.device(device)
        self._preprocess = preprocess
        self.channels_last = channels_last  # NHWC inputs for a net converted to NHWC
        # > 0: embed() appends this many channels of the net's penultimate feature map
        # (the net's ``forward_with_features``) after the logits.
        self.feature_channels = int(feature_channels)
        # The dtype the net's first layers take (bfloat16 under backbone.precision);
        # outputs are always returned as float32.
        self.input_dtype = input_dtype
        # Frozen TorchScript graphs of the net (backbone.graph), one per (features, input
        # shapes), traced on first use; empty and unused when graph is False.
        self.graph = bool(graph)
        self._graphs: dict[tuple, torch.jit.ScriptModule] = {}

    GRAPH_CACHE = 8
    """Traced graphs kept (input shapes seen: batch sizes, mostly); the oldest goes first."""

    def _forward(self, x_rgb: torch.Tensor, x_depth: torch.Tensor, features: bool):
        """The net on prepared inputs: (logits, features) with ``features``, else the
        logits (or the net's own output). Under ``graph`` the call goes through a frozen
        TorchScript graph of the same module, traced for these input shapes the first
        time they occur: same arithmetic, without the per-layer Python dispatch, which
        is a visible share of this small net's time on a CPU (default_graph_speedup in
        bench/results/backbone.json)."""
        fn = _WithFeatures(self.net).eval() if features else self.net
        if not self.graph:
            return fn(x_rgb, x_depth)
        key = (features, tuple(x_rgb.shape), tuple(x_depth.shape), x_rgb.dtype)
        graph = self._graphs.get(key)
        if graph is None:
            # Traced under no_grad (freezing under inference_mode fails on adaptive
            # pooling); the tracer's warnings are about Python constants (class counts
            # in the entropy) that are constants indeed.
            with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
                warnings.simplefilter("ignore", torch.jit.TracerWarning)
                graph = torch.jit.freeze(torch.jit.trace(fn, (x_rgb.clone(), x_depth.clone()),
                                                         check_trace=False))
            if len(self._graphs) >= self.GRAPH_CACHE:
                self._graphs.pop(next(iter(self._graphs)))
            self._graphs[key] = graph
        return graph(x_rgb, x_depth)

    def warm_up(self) -> None:
        """Run one blank frame at the input size, so a graph (``backbone.graph``) is
        traced now rather than on the first real frame (which the resize maps to the
        same input shape, whatever the camera's size)."""
        w, h = self.input_size
        self.predict_batch([np.zeros((h, w, 3), np.uint8)], [np.ones((h, w), np.float32)],
                           features=self.feature_channels > 0)

    def inputs(self, rgbs: Sequence[np.ndarray], depths: Sequence[np.ndarray]
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """The network's input tensors for some frames: validated, resized to the input
        size (RGB bilinear, depth nearest so holes stay holes), normalised by the
        network's own preprocessing."""
        w, h = self.input_size
        rgb_in, depth_in = [], []
        for rgb, depth in zip(rgbs, depths):
            depth = check_rgbd(rgb, depth)
            if depth.shape != (h, w):
                rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_LINEAR)
                depth = cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
            rgb_in.append(rgb)
            depth_in.append(depth)
        rgb_t = torch.from_numpy(np.stack(rgb_in)).permute(0, 3, 1, 2).float()
        depth_t = torch.from_numpy(np.stack(depth_in))[:, None]
        x_rgb, x_depth = self._preprocess(rgb_t.to(self.device), depth_t.to(self.device))
        x_rgb, x_depth = x_rgb.to(self.input_dtype), x_depth.to(self.input_dtype)
        if self.channels_last:
            x_rgb = x_rgb.contiguous(memory_format=torch.channels_last)
            x_depth = x_depth.contiguous(memory_format=torch.channels_last)
        return x_rgb, x_depth

    @property
    def precision(self) -> str:
        """'float32' or 'bfloat16': what the net computes in (``backbone.precision``
        resolved), for logs and records."""
        return str(self.input_dtype).removeprefix("torch.")

    @property
    def novelty_branch(self) -> bool:
        """Whether the embedding's entropy comes with a novelty branch's temperature
        (the shipped default weights, unless ``backbone.novelty_branch`` is false)."""
        return bool(getattr(self.net, "novelty_branch", False))

    @property
    def spec(self) -> EmbeddingSpec:
        """What the channels of :meth:`embed`'s output mean (travels with the embedding)."""
        return EmbeddingSpec(tuple(int(i) for i in self.channel_to_id), self.feature_channels,
                             self.kind)

    def embed(self, rgb: np.ndarray, depth: np.ndarray,
              size: tuple[int, int] | None = None) -> np.ndarray:
        """One frame -> (H, W, spec.channels) float32 semantic embedding: the logits, then
        the penultimate features when ``backbone.features`` is on. ``size`` (h, w): the
        output's size instead of the frame's (the network's output interpolated once)."""
        return self.predict_batch([rgb], [depth], features=self.feature_channels > 0,
                                  sizes=None if size is None else [size])[0]

    def predict(self, rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """One frame -> (H, W, S) float32 logits at the frame's own size."""
        return self.predict_batch([rgb], [depth])[0]

    def predict_batch(self, rgbs: Sequence[np.ndarray], depths: Sequence[np.ndarray],
                      features: bool = False,
                      sizes: Sequence[tuple[int, int]] | None = None) -> list[np.ndarray]:
        """Several frames (any sizes) -> list of (H_i, W_i, S) float32 logits
        (``features``: (H_i, W_i, S + feature_channels), the features after them).

        Frames are resized to the model input size, run as one batch, and the
        outputs resized back to each frame's size (or to ``sizes``, (h, w) per frame).
        """
        if len(rgbs) != len(depths):
            raise ValueError(f"got {len(rgbs)} rgb images but {len(depths)} depth images")
        if not rgbs:
            return []
        if sizes is None:
            sizes = [np.asarray(d).shape for d in depths]
        elif len(sizes) != len(rgbs):
            raise ValueError(f"got {len(sizes)} output sizes for {len(rgbs)} frames")
        with torch.inference_mode():
            x_rgb, x_depth = self.inputs(rgbs, depths)
            if features:
                logits, feats = self._forward(x_rgb, x_depth, True)
                logits = torch.cat([logits, F.interpolate(
                    feats, size=logits.shape[-2:], mode="bilinear", align_corners=False)], 1)
            else:
                logits = self._forward(x_rgb, x_depth, False)
            if isinstance(logits, (tuple, list)):  # some nets return side outputs
                logits = logits[0]
            logits = logits.float()
            out = []
            for i, (hh, ww) in enumerate(sizes):
                li = logits[i: i + 1]
                if (hh, ww) != tuple(li.shape[-2:]):
                    li = F.interpolate(li, size=(hh, ww), mode="bilinear", align_corners=False)
                out.append(np.ascontiguousarray(
                    li[0].permute(1, 2, 0).float().cpu().numpy(), dtype=np.float32))
        expected = self.channels + (self.feature_channels if features else 0)
        if expected != out[0].shape[-1]:
            raise RuntimeError(f"network returned {out[0].shape[-1]} channels, "
                               f"expected {expected}")
        return out


class _WithFeatures(torch.nn.Module):
    """A net's ``forward_with_features`` as a module's forward (what tracing records)."""

    def __init__(self, net: torch.nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, x_rgb: torch.Tensor, x_depth: torch.Tensor):
        return self.net.forward_with_features(x_rgb, x_depth)


def _input_size(cfg: BackboneConfig) -> tuple[int, int]:
    """(width, height) the network runs at, with 0 meaning the kind's native size."""
    nw, nh = NATIVE_SIZE[cfg.kind]
    w, h = cfg.input_width or nw, cfg.input_height or nh
    if w < MIN_SIDE or h < MIN_SIDE:
        raise ValueError(f"input size {w}x{h} is below {MIN_SIDE} pixels on a side")
    if cfg.kind == "esanet" and (w % 32 or h % 32):
        raise ValueError(f"esanet input_width/input_height must be multiples of 32 "
                         f"(its decoder joins stride-32 features), got {w}x{h}; "
                         f"use 640x480 or 320x256")
    return w, h


BRANCH_THRESHOLD = 0.3
"""Above this ``discovery.entropy_threshold`` is one tuned for a novelty branch."""


def threshold_warning(backbone: Backbone, entropy_threshold: float) -> str | None:
    """A warning when ``discovery.entropy_threshold`` was tuned for a novelty branch the
    backbone does not have, else None.

    Why: without the branch a net is confident on most novel objects (its normalised
    entropy there is about 0.1-0.3), so the default threshold (0.6, tuned for the shipped
    branch) calls nearly every novel object a known class, silently.
    """
    if backbone.novelty_branch or entropy_threshold <= BRANCH_THRESHOLD:
        return None
    return (f"the {backbone.kind} backbone has no novelty branch (or backbone.novelty_branch "
            f"is false), but discovery.entropy_threshold is {entropy_threshold:g}, a value "
            f"for the shipped weights' branch: few novel objects will be found. Without a "
            f"branch the tuned value for the default net is 0.15; tune it on your data "
            f"(README, 'Uncertainty on what your net never saw')")


def _load_default(cfg: BackboneConfig) -> Backbone:
    from . import small

    path = Path(cfg.checkpoint) if cfg.checkpoint else DEFAULT_WEIGHTS
    if not path.is_file():
        raise ValueError(f"backbone checkpoint {path} does not exist"
                         + ("" if cfg.checkpoint else " (shipped default weights missing; "
                            "run `neurncd train-backbone`)"))
    net = small.load_weights(str(path), device=cfg.device)
    if not cfg.novelty_branch:
        net.novelty_branch = False  # the branch's weights stay loaded but unused
    # Inference only from here: batch norms folded into their convolutions, and the
    # NHWC layout oneDNN's CPU convolutions prefer (the inputs follow, Backbone.inputs).
    # Same outputs to float rounding, 35-40 % less time on this CPU
    # (bench/results/backbone.json, default_unfolded_ms_320x240).
    net = small.fold_batch_norm(net).to(memory_format=torch.channels_last)
    dtype = compute_dtype(cfg)
    if dtype != torch.float32:  # after folding: the folded weights are rounded once
        net = small.lower_precision(net, dtype)
    return Backbone(net, "default", classes.CHANNEL_TO_ID.copy(), _input_size(cfg), cfg.device,
                    small.prepare_inputs, channels_last=True,
                    feature_channels=net.widths[0] if cfg.features else 0, input_dtype=dtype,
                    graph=cfg.graph)


def esanet_channel_to_id(dataset: str) -> np.ndarray:
    """NYU-13 id of each ESANet output channel: NYU-40 class k + 1 mapped to NYU-13.

    SUN RGB-D's 37 classes are the first 37 NYU-40 classes in the same order.
    """
    n = {"nyuv2": 40, "sunrgbd": 37}.get(dataset)
    if n is None:
        raise ValueError(f"esanet_dataset must be 'nyuv2' or 'sunrgbd', got {dataset!r}")
    return classes.NYU40_TO_NYU13[1: n + 1].astype(np.uint16)


def _load_esanet(cfg: BackboneConfig) -> Backbone:
    from . import esanet  # lazy: the R34 model is large and optional

    if not cfg.checkpoint:
        raise ValueError("kind=esanet needs checkpoint=<path to an ESANet R34-NBt1D .pth>; "
                         "no ESANet weights ship with the package")
    if not Path(cfg.checkpoint).is_file():
        raise ValueError(f"ESANet checkpoint {cfg.checkpoint} does not exist")
    n = len(esanet_channel_to_id(cfg.esanet_dataset))
    net = esanet.load_esanet_checkpoint(cfg.checkpoint, num_classes=n, device=cfg.device)
    return esanet_backbone(net, cfg)


def esanet_backbone(net: torch.nn.Module, cfg: BackboneConfig) -> Backbone:
    """Wrap an ESANet model in the Backbone interface with the public preprocessing of
    ``cfg.esanet_dataset`` (depth unit and statistics) and ``cfg.esanet_depth_mode``.

    The net is put in eval mode and NHWC layout in place; when ``cfg.precision``
    resolves to bfloat16 the backbone runs a bfloat16 copy, so the caller's net keeps
    its float32 weights."""
    from . import esanet

    channel_to_id = esanet_channel_to_id(cfg.esanet_dataset)
    dataset, mode = cfg.esanet_dataset, cfg.esanet_depth_mode

    def preprocess(rgb: torch.Tensor, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return esanet.preprocess_rgb(rgb), esanet.preprocess_depth(depth, dataset, mode)

    esanet_cfg = dataclasses.replace(cfg, kind="esanet")
    # NHWC for oneDNN's CPU convolutions: same outputs, 979 -> 757 ms at 480x640 on this
    # CPU (2 threads, random weights, interleaved runs at 1c87e47).
    dtype = compute_dtype(cfg)
    net = net.eval().to(memory_format=torch.channels_last)
    if dtype != torch.float32:
        net = copy.deepcopy(net).to(dtype=dtype)
    return Backbone(net, "esanet", channel_to_id, _input_size(esanet_cfg), cfg.device,
                    preprocess, channels_last=True, input_dtype=dtype, graph=cfg.graph)


def setup_problems(cfg: BackboneConfig) -> list[str]:
    """What :func:`load_backbone` would refuse in ``cfg`` before reading any weights (the
    parameters that must agree with each other, the checkpoint file present), each as one
    line: ``neurncd check-config`` and bringup report them without loading a model, so a
    file that says ``kind: esanet`` without a checkpoint is not called valid."""
    out = []
    if cfg.kind not in NATIVE_SIZE:
        out.append(f"backbone kind must be 'default' or 'esanet', got {cfg.kind!r}")
        return out
    if cfg.features and cfg.kind != "default":
        out.append("backbone.features (penultimate features in the embedding) is "
                   "implemented for kind=default only")
    if cfg.device == "cuda" and not torch.cuda.is_available():
        out.append("backbone device 'cuda' requested but torch sees no CUDA device")
    try:
        _input_size(cfg)
    except ValueError as err:
        out.append(str(err))
    if cfg.kind == "esanet" and not cfg.checkpoint:
        out.append("kind=esanet needs checkpoint=<path to an ESANet R34-NBt1D .pth>; no "
                   "ESANet weights ship with the package")
    elif cfg.checkpoint and not Path(cfg.checkpoint).is_file():
        what = "ESANet checkpoint" if cfg.kind == "esanet" else "backbone checkpoint"
        out.append(f"{what} {cfg.checkpoint} does not exist")
    return out


def load_backbone(cfg: BackboneConfig | None = None) -> Backbone:
    """Build the configured backbone on its device, in eval mode, ready to predict."""
    cfg = cfg or BackboneConfig()
    problems = setup_problems(cfg)
    if problems:
        raise ValueError(problems[0])
    return _load_esanet(cfg) if cfg.kind == "esanet" else _load_default(cfg)
