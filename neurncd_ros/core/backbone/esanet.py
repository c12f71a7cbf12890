"""ESANet R34-NBt1D: the public RGB-D segmentation network, and safe checkpoint loading.

(One module, over 500 lines: the network's layers, its checkpoint-name
mapping and the safe loader must change together to keep the state_dict
matching the released checkpoints.)

A re-implementation of the ESANet model of Seichter et al. (ICRA 2021,
TUI-NICR/ESANet, Apache-2.0) in its published R34-NBt1D configuration, written
so that its ``state_dict`` matches the released checkpoints name for name,
shape for shape and in order (the recorded key list, in the repository at
``test/data/esanet/r34_nbt1d_state_dict.json`` with its README):

- two ResNet34 encoders (blocks 3/4/6/3) built from NonBottleneck1D blocks
  (3x1 / 1x3 convolution pairs with bias, BatchNorm eps 1e-3); the depth
  encoder takes 1 channel;
- ``SE-add`` fusion after the stem and after every stage: squeeze-excitation
  re-weights the RGB and the depth features, then they are added; the sum
  continues in the RGB branch, the depth branch continues on its own;
- skip connections at strides 4/8/16: 1x1 conv + BN + ReLU to the decoder width;
- context module ``ppm``: pyramid pooling with fixed adaptive bins (1, 5)
  (independent of the input size), each bin 1x1 conv + BN + ReLU, upsampled
  back with *nearest* interpolation (learned upsampling needs a factor of 2),
  concatenated with the input and fused by a 1x1 conv + BN + ReLU;
- decoder: 3 stages of widths 512/256/128, each 3x3 conv + BN + ReLU, three
  NonBottleneck1D blocks, x2 ``learned-3x3-zeropad`` upsampling, then the skip
  is *added*; a 3x3 conv to the class logits at stride 4 and two more x2
  learned upsamplings to the input size. The side outputs (pyramid
  supervision) exist only for training and are not evaluated in eval mode.

``learned-3x3-zeropad`` upsampling is nearest x2 followed by a depthwise 3x3
convolution with zero padding, initialised with the kernel
[[1,2,1],[2,4,2],[1,2,1]]/16 (which mimics bilinear interpolation) and zero bias.

Preprocessing follows the public test-time pipeline: RGB / 255 then ImageNet
mean/std; depth in the unit of the training dataset (NYUv2: millimetres,
SUN RGB-D: 1/10 mm) standardised with the dataset's depth mean/std. In the
public ``raw`` depth mode (used by its sample inference with raw sensor depth)
missing depth (0) is set back to 0 *after* normalisation, i.e. a hole looks
like a pixel at the mean depth; in ``refined`` mode a 0 would be normalised
like any value (-mean/std), which only makes sense for hole-free depth.
Resizing a frame to the network size and the logits back is the job of the one
``Backbone`` interface (``backbone.py``), which calls these functions.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..torchfile import TorchFileError, read_torch_file

__all__ = [
    "ESANet", "DepthStats", "DEPTH_STATS", "DEPTH_MODES",
    "CheckpointError", "load_esanet_checkpoint", "preprocess_rgb", "preprocess_depth", "STRIDE",
]

STRIDE = 32
"""Height and width of the input must be multiples of this (5 stride-2 stages)."""

ENCODER_BLOCKS = (3, 4, 6, 3)
"""ResNet34 stage depths."""
ENCODER_WIDTHS = (64, 128, 256, 512)
"""Output channels of the four encoder stages (strides 4, 8, 16, 32)."""
DECODER_WIDTHS = (512, 256, 128)
"""Channels of the three decoder stages (strides 16, 8, 4)."""
DECODER_BLOCKS = 3
"""NonBottleneck1D blocks per decoder stage."""
PPM_BINS = (1, 5)
"""Adaptive average-pooling output sizes of the ``ppm`` context module."""
SE_REDUCTION = 16
"""Squeeze-excitation channel reduction."""

RGB_MEAN = (0.485, 0.456, 0.406)
RGB_STD = (0.229, 0.224, 0.225)


# ---------------------------------------------------------------------------
# building blocks


class ConvBNAct(nn.Sequential):
    """conv (no bias) -> BatchNorm -> ReLU; child names ``conv``/``bn`` as in the checkpoints."""

    def __init__(self, c_in: int, c_out: int, kernel_size: int) -> None:
        super().__init__()
        self.add_module("conv", nn.Conv2d(c_in, c_out, kernel_size, padding=kernel_size // 2,
                                          bias=False))
        self.add_module("bn", nn.BatchNorm2d(c_out))
        self.add_module("act", nn.ReLU(inplace=True))


class NonBottleneck1D(nn.Module):
    """ERFNet block: two factorised (3x1, 1x3) convolutions with a residual connection.

    The stride acts on the 3x1 (rows) and the 1x3 (columns) convolution of the
    first pair; the BatchNorms use eps 1e-3 like ERFNet.
    """

    def __init__(self, c_in: int, c_out: int, stride: int = 1,
                 downsample: nn.Module | None = None) -> None:
        super().__init__()
        self.conv3x1_1 = nn.Conv2d(c_in, c_out, (3, 1), stride=(stride, 1), padding=(1, 0))
        self.conv1x3_1 = nn.Conv2d(c_out, c_out, (1, 3), stride=(1, stride), padding=(0, 1))
        self.bn1 = nn.BatchNorm2d(c_out, eps=1e-3)
        self.conv3x1_2 = nn.Conv2d(c_out, c_out, (3, 1), padding=(1, 0))
        self.conv1x3_2 = nn.Conv2d(c_out, c_out, (1, 3), padding=(0, 1))
        self.bn2 = nn.BatchNorm2d(c_out, eps=1e-3)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.conv3x1_1(x))
        y = F.relu(self.bn1(self.conv1x3_1(y)))
        y = F.relu(self.conv3x1_2(y))
        y = self.bn2(self.conv1x3_2(y))
        identity = x if self.downsample is None else self.downsample(x)
        return F.relu(y + identity)


class ResNet34NBt1D(nn.Module):
    """ResNet34 encoder with NonBottleneck1D blocks; the stem's max-pool is applied by ESANet."""

    def __init__(self, input_channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(input_channels, 64, 7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        c_in = 64
        for i, (n, c) in enumerate(zip(ENCODER_BLOCKS, ENCODER_WIDTHS)):
            stride = 1 if i == 0 else 2
            down = None
            if stride != 1 or c_in != c:
                down = nn.Sequential(nn.Conv2d(c_in, c, 1, stride=stride, bias=False),
                                     nn.BatchNorm2d(c))
            blocks = [NonBottleneck1D(c_in, c, stride, down)]
            blocks += [NonBottleneck1D(c, c) for _ in range(n - 1)]
            self.add_module(f"layer{i + 1}", nn.Sequential(*blocks))
            c_in = c
        self._init_weights()

    def _init_weights(self) -> None:
        """He (fan-out) init for convolutions, unit/zero BN, as the public encoder."""
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def stem(self, x: torch.Tensor) -> torch.Tensor:
        """7x7 stride-2 conv + BN + ReLU (stride 2, before the max-pool)."""
        return F.relu(self.bn1(self.conv1(x)))

    def stage(self, i: int, x: torch.Tensor) -> torch.Tensor:
        """Run encoder stage ``i`` (1..4)."""
        return getattr(self, f"layer{i}")(x)


class SqueezeExcitation(nn.Module):
    """Channel re-weighting by a sigmoid gate computed from the global average."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        hidden = channels // SE_REDUCTION
        self.fc = nn.Sequential(nn.Conv2d(channels, hidden, 1), nn.ReLU(inplace=True),
                                nn.Conv2d(hidden, channels, 1), nn.Sigmoid())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.fc(F.adaptive_avg_pool2d(x, 1))


class SEFusionAdd(nn.Module):
    """``SE-add`` fusion: squeeze-excite RGB and depth features separately, then add."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.se_rgb = SqueezeExcitation(channels)
        self.se_depth = SqueezeExcitation(channels)

    def forward(self, rgb: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        return self.se_rgb(rgb) + self.se_depth(depth)


class PyramidPooling(nn.Module):
    """``ppm`` context module: fixed pooling bins, nearest upsampling, concat, 1x1 fuse."""

    def __init__(self, c_in: int, c_out: int, bins: tuple[int, ...] = PPM_BINS) -> None:
        super().__init__()
        reduced = c_in // len(bins)
        self.features = nn.ModuleList(
            nn.Sequential(nn.AdaptiveAvgPool2d(b), ConvBNAct(c_in, reduced, 1)) for b in bins)
        self.final_conv = ConvBNAct(c_in + reduced * len(bins), c_out, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        size = x.shape[-2:]
        pooled = [F.interpolate(f(x), size=size, mode="nearest") for f in self.features]
        return self.final_conv(torch.cat([x, *pooled], dim=1))


class LearnedUpsample(nn.Module):
    """x2 nearest upsampling then a depthwise 3x3 conv (zero padding), bilinear-initialised."""

    KERNEL = (0.0625, 0.125, 0.0625, 0.125, 0.25, 0.125, 0.0625, 0.125, 0.0625)

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1, groups=channels)
        with torch.no_grad():
            k = torch.tensor(self.KERNEL, dtype=torch.float32).reshape(1, 1, 3, 3)
            self.conv.weight.copy_(k.expand(channels, 1, 3, 3))
            self.conv.bias.zero_()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        return self.conv(F.interpolate(x, size=(2 * h, 2 * w), mode="nearest"))


class DecoderModule(nn.Module):
    """One decoder stage: 3x3 conv, NBt1D blocks, learned x2 upsampling, then + skip."""

    def __init__(self, c_in: int, c_dec: int, n_blocks: int, num_classes: int) -> None:
        super().__init__()
        self.conv3x3 = ConvBNAct(c_in, c_dec, 3)
        self.decoder_blocks = nn.Sequential(*[NonBottleneck1D(c_dec, c_dec)
                                              for _ in range(n_blocks)])
        self.upsample = LearnedUpsample(c_dec)
        # Pyramid supervision head: used in training mode only.
        self.side_output = nn.Conv2d(c_dec, num_classes, 1)

    def forward(self, x: torch.Tensor, skip: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """-> (upsampled features + skip, side logits before upsampling or None in eval)."""
        y = self.decoder_blocks(self.conv3x3(x))
        side = self.side_output(y) if self.training else None
        return self.upsample(y) + skip, side


class Decoder(nn.Module):
    """Three decoder stages (strides 32->16->8->4), class conv, two x2 learned upsamplings."""

    def __init__(self, c_in: int, num_classes: int) -> None:
        super().__init__()
        widths = (c_in, *DECODER_WIDTHS)
        for i in range(3):
            self.add_module(f"decoder_module_{i + 1}",
                            DecoderModule(widths[i], widths[i + 1], DECODER_BLOCKS, num_classes))
        self.conv_out = nn.Conv2d(DECODER_WIDTHS[-1], num_classes, 3, padding=1)
        self.upsample1 = LearnedUpsample(num_classes)
        self.upsample2 = LearnedUpsample(num_classes)

    def forward(self, x: torch.Tensor, skips: list[torch.Tensor]
                ) -> torch.Tensor | tuple[torch.Tensor, ...]:
        """``skips``: stride 16, 8, 4 features, in that order.

        Eval: logits at input size. Training (as the public code): also the side
        logits at strides 8, 16, 32 for pyramid supervision.
        """
        sides = []
        for i, skip in enumerate(skips):
            x, side = getattr(self, f"decoder_module_{i + 1}")(x, skip)
            sides.append(side)
        out = self.upsample2(self.upsample1(self.conv_out(x)))
        if self.training:
            return (out, *sides[::-1])
        return out


# ---------------------------------------------------------------------------
# the network


class ESANet(nn.Module):
    """ESANet R34-NBt1D (RGB-D, SE-add fusion, ppm, learned-3x3-zeropad upsampling).

    ``forward(rgb (N,3,H,W), depth (N,1,H,W))`` -> logits (N, num_classes, H, W)
    in eval mode (in training mode a tuple: logits, then the side logits at
    strides 8, 16, 32, as the public code); H and W must be multiples of 32.
    Inputs are expected already normalised (:func:`preprocess_rgb`,
    :func:`preprocess_depth`).
    """

    def __init__(self, num_classes: int = 37) -> None:
        super().__init__()
        if not isinstance(num_classes, int) or num_classes < 1:
            raise ValueError(f"num_classes must be a positive int, got {num_classes!r}")
        self.num_classes = num_classes
        self.encoder_rgb = ResNet34NBt1D(3)
        self.encoder_depth = ResNet34NBt1D(1)
        self.se_layer0 = SEFusionAdd(64)
        for i, c in enumerate(ENCODER_WIDTHS):
            self.add_module(f"se_layer{i + 1}", SEFusionAdd(c))
        # Skips at strides 4, 8, 16 projected to the decoder stage they join.
        for i in range(3):
            self.add_module(f"skip_layer{i + 1}", nn.Sequential(
                ConvBNAct(ENCODER_WIDTHS[i], DECODER_WIDTHS[2 - i], 1)))
        self.context_module = PyramidPooling(ENCODER_WIDTHS[-1], DECODER_WIDTHS[0])
        self.decoder = Decoder(DECODER_WIDTHS[0], num_classes)

    def forward(self, rgb: torch.Tensor, depth: torch.Tensor
                ) -> torch.Tensor | tuple[torch.Tensor, ...]:
        check_input(rgb, depth)
        d = self.encoder_depth.stem(depth)
        x = self.se_layer0(self.encoder_rgb.stem(rgb), d)
        # Stride 4: the fused stem continues in the RGB branch, depth on its own.
        x = F.max_pool2d(x, 3, stride=2, padding=1)
        d = F.max_pool2d(d, 3, stride=2, padding=1)
        skips = []
        for i in range(1, 5):
            x = self.encoder_rgb.stage(i, x)
            d = self.encoder_depth.stage(i, d)
            x = getattr(self, f"se_layer{i}")(x, d)
            if i < 4:
                skips.append(getattr(self, f"skip_layer{i}")(x))
        out = self.context_module(x)
        return self.decoder(out, skips[::-1])


def check_input(rgb: torch.Tensor, depth: torch.Tensor) -> None:
    """Raise ValueError naming the problem if the network cannot take these tensors."""
    if not isinstance(rgb, torch.Tensor) or not isinstance(depth, torch.Tensor):
        raise ValueError("rgb and depth must be torch tensors")
    if rgb.ndim != 4 or rgb.shape[1] != 3:
        raise ValueError(f"rgb must be (N, 3, H, W), got {tuple(rgb.shape)}")
    if depth.ndim != 4 or depth.shape[1] != 1:
        raise ValueError(f"depth must be (N, 1, H, W), got {tuple(depth.shape)}")
    if rgb.shape[0] != depth.shape[0] or rgb.shape[-2:] != depth.shape[-2:]:
        raise ValueError(f"rgb {tuple(rgb.shape)} and depth {tuple(depth.shape)} differ "
                         "in batch or spatial size")
    h, w = rgb.shape[-2:]
    if h % STRIDE or w % STRIDE or h == 0 or w == 0:
        raise ValueError(f"ESANet needs height and width divisible by {STRIDE} (its decoder "
                         f"adds stride-32 features to the skips), got {h}x{w}; use 480x640 "
                         "or 256x320 and resize the logits")


# ---------------------------------------------------------------------------
# preprocessing


@dataclasses.dataclass(frozen=True)
class DepthStats:
    """Depth unit and training statistics of one dataset's checkpoints."""

    units_per_metre: float
    mean: float
    std: float


DEPTH_STATS = {
    # NYUv2: depth in millimetres.
    "nyuv2": DepthStats(1000.0, 2841.94941272766, 1417.2594281672277),
    # SUN RGB-D: depth in 1/10 millimetres.
    "sunrgbd": DepthStats(10000.0, 19025.14930492213, 9880.916071806689),
}
"""Per-dataset depth unit and mean/std (the public code uses the refined-depth stats
for both depth modes)."""

DEPTH_MODES = ("raw", "refined")


def _stats(dataset: str) -> DepthStats:
    if dataset not in DEPTH_STATS:
        raise ValueError(f"ESANet dataset must be one of {sorted(DEPTH_STATS)}, got {dataset!r}")
    return DEPTH_STATS[dataset]


def preprocess_rgb(rgb: torch.Tensor) -> torch.Tensor:
    """(N,3,H,W) float RGB in [0, 255] -> /255 then ImageNet mean/std."""
    if rgb.ndim != 4 or rgb.shape[1] != 3:
        raise ValueError(f"rgb must be (N, 3, H, W), got {tuple(rgb.shape)}")
    x = rgb.float() / 255.0
    mean = torch.tensor(RGB_MEAN, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    std = torch.tensor(RGB_STD, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    return (x - mean) / std


def preprocess_depth(depth: torch.Tensor, dataset: str = "nyuv2",
                     depth_mode: str = "raw") -> torch.Tensor:
    """(N,1,H,W) depth in metres (0 = hole) -> dataset unit, standardised.

    ``raw``: holes stay exactly 0 after normalisation (public raw-depth mode);
    ``refined``: every value, 0 included, is standardised. NaN/inf count as holes.
    """
    if depth.ndim != 4 or depth.shape[1] != 1:
        raise ValueError(f"depth must be (N, 1, H, W), got {tuple(depth.shape)}")
    if depth_mode not in DEPTH_MODES:
        raise ValueError(f"depth_mode must be one of {DEPTH_MODES}, got {depth_mode!r}")
    s = _stats(dataset)
    d = depth.float() * s.units_per_metre
    d = torch.where(torch.isfinite(d), d, torch.zeros_like(d))
    out = (d - s.mean) / s.std
    if depth_mode == "raw":
        out = torch.where(d == 0, torch.zeros_like(out), out)
    return out


# ---------------------------------------------------------------------------
# checkpoints


class CheckpointError(ValueError):
    """A checkpoint cannot be used: unsafe, unreadable, or not an ESANet R34-NBt1D."""


class CheckpointNotFound(CheckpointError, FileNotFoundError):
    """The checkpoint path does not name a file."""


HEAD_KEY = "decoder.conv_out.weight"
"""The class head: its first dimension is the number of classes."""

def _read_checkpoint(path: Path, device: str) -> Any:
    """torch.load with weights_only=True (:mod:`..torchfile`); anything that would run
    code is refused."""
    try:
        return read_torch_file(path, device, "checkpoint")
    except TorchFileError as e:
        raise CheckpointError(str(e)) from None


def _state_dict_of(obj: Any, path: Path) -> dict[str, torch.Tensor]:
    """The tensor dict inside a checkpoint ({'state_dict': ...} or bare), without 'module.'."""
    if isinstance(obj, Mapping) and isinstance(obj.get("state_dict"), Mapping):
        obj = obj["state_dict"]
    if not isinstance(obj, Mapping) or not obj:
        raise CheckpointError(f"checkpoint {path} holds {type(obj).__name__}, not a state dict "
                              "(expected {'state_dict': {...}} or a bare name -> tensor dict)")
    bad = [k for k, v in obj.items() if not isinstance(k, str) or not isinstance(v, torch.Tensor)]
    if bad:
        raise CheckpointError(f"checkpoint {path}: entries that are not name -> tensor: "
                              f"{bad[:5]!r}")
    if all(k.startswith("module.") for k in obj):
        obj = {k[len("module."):]: v for k, v in obj.items()}
    return dict(obj)


def _mismatch_report(expected: Mapping[str, torch.Tensor], found: Mapping[str, torch.Tensor],
                     limit: int = 5) -> str:
    """Human-readable list of missing/unexpected/wrong-shape keys ('' if they agree)."""
    missing = [k for k in expected if k not in found]
    unexpected = [k for k in found if k not in expected]
    shapes = [k for k in expected if k in found and expected[k].shape != found[k].shape]
    parts = []
    if shapes:
        parts.append(f"{len(shapes)} with wrong shape: " + "; ".join(
            f"{k} expected {tuple(expected[k].shape)} found {tuple(found[k].shape)}"
            for k in shapes[:limit]))
    if missing:
        parts.append(f"{len(missing)} missing: " + "; ".join(
            f"{k} expected {tuple(expected[k].shape)}" for k in missing[:limit]))
    if unexpected:
        parts.append(f"{len(unexpected)} unexpected: " + "; ".join(
            f"{k} found {tuple(found[k].shape)}" for k in unexpected[:limit]))
    return " | ".join(parts)


def load_esanet_checkpoint(path: str | os.PathLike, num_classes: int | None = None,
                           device: str = "cpu") -> ESANet:
    """Build ESANet R34-NBt1D from a checkpoint, strictly, in eval mode on ``device``.

    Accepts the public layout ``{'state_dict': sd, ...}`` or a bare state dict,
    with or without a leading ``module.``; ``num_classes`` defaults to the
    head's size. Refuses pickles that need code (weights_only load); raises
    CheckpointError (a ValueError) listing offending keys on any mismatch.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointNotFound(f"ESANet checkpoint {path} does not exist or is not a file")
    sd = _state_dict_of(_read_checkpoint(path, device), path)
    if num_classes is None:
        head = sd.get(HEAD_KEY)
        if head is None or head.ndim != 4:
            raise CheckpointError(f"checkpoint {path} has no class head {HEAD_KEY!r} "
                                  "(4-D conv weight); is it an ESANet R34-NBt1D state dict? "
                                  f"first keys: {list(sd)[:5]}")
        num_classes = int(head.shape[0])
    with torch.random.fork_rng(devices=[]):  # initial weights replaced below: global RNG kept
        model = ESANet(num_classes)
    report = _mismatch_report(model.state_dict(), sd)
    if report:
        head = sd.get(HEAD_KEY)
        found = int(head.shape[0]) if head is not None and head.ndim == 4 else None
        # The class count first: a SUN RGB-D checkpoint read as NYUv2 lists five
        # side-output shapes before its head, and the fix is one parameter.
        hint = "" if found in (None, num_classes) else (
            f"; its class head {HEAD_KEY} has {found} classes, not {num_classes}"
            + {40: ": an NYUv2 checkpoint (backbone.esanet_dataset nyuv2)",
               37: ": a SUN RGB-D checkpoint (backbone.esanet_dataset sunrgbd)"}.get(found, ""))
        raise CheckpointError(f"checkpoint {path} does not fit ESANet R34-NBt1D with "
                              f"{num_classes} classes{hint}: {report}")
    model.load_state_dict(sd, strict=True)
    return model.to(device).eval()
