"""The default small RGB-D segmentation network (the project's own ESANet-lite).

Why a small net: no public weights can be downloaded here, so the project
trains its own model on its synthetic scenes, and it must run online on a
2-core CPU (budget 40 ms per 320x240 frame). The layout follows ESANet in
miniature: two light encoders (RGB and depth) built from factorised
NonBottleneck-1D blocks, depth fused into RGB after every stage with
squeeze-and-excitation ("SE-add"), a pyramid pooling context module, and a
decoder with skip connections. The output has S = 9 channels, channel k being
the pre-softmax logit (the semantic embedding) of NYU-13 id
``classes.KNOWN_IDS[k]``.

Inputs are produced by :func:`prepare_inputs`: RGB normalised with ImageNet
statistics, and depth as two channels (normalised metric depth, 0 at holes; a
validity mask), so the net is told where the sensor gave no measurement.

Optional *novelty branch* (issue 11, direction 2): a second copy of the last
decoder stage and of the classifier, trained with outlier exposure on the
frozen network (``train_backbone(..., novelty_branch=True)``). Its normalised
entropy h sets a per-pixel temperature: the output logits are the known-class
head's logits times ``max(1 - h, NOVELTY_FLOOR)``. Scaling by a positive factor
keeps every pixel's argmax, so the known classes are labelled exactly as
without the branch, while the softmax flattens (its entropy rises) where the
branch sees something it was taught is no known class. At inference h is taken
at the decoder's half resolution and the factor upsampled (:meth:`SmallRGBDNet.
_temperature`, cheaper); training scores the branch's full-size logits. Why not
outlier exposure of the whole net: it costs known-class accuracy
(bench/results/backbone_oe_wholenet.json).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .. import classes
from ..torchfile import read_torch_file
from ..uncertainty import entropy

RGB_MEAN = (0.485, 0.456, 0.406)
RGB_STD = (0.229, 0.224, 0.225)
DEPTH_MEAN_M = 2.8
"""Typical indoor depth (m): centre of the depth normalisation."""
DEPTH_STD_M = 1.4
"""Spread of indoor depth (m): scale of the depth normalisation."""

DEFAULT_WIDTHS = (20, 40, 80, 160)
"""Channels of the stem and the three encoder stages of the shipped model (small
enough for the frame budget on one core; timings in bench/results/backbone.json)."""

ARCH_VERSION = 1
"""Bumped whenever the layout changes, so stale weights fail loudly."""

NOVELTY_FLOOR = 0.05
"""Smallest temperature factor of the novelty branch (keeps the argmax defined)."""


def prepare_inputs(rgb: torch.Tensor, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalise a batch: rgb (B, 3, H, W) in [0, 255], depth (B, 1, H, W) metres, 0 = hole.

    Returns the (B, 3, H, W) RGB tensor and the (B, 2, H, W) depth tensor
    (normalised depth zeroed at holes, validity mask).
    """
    mean = rgb.new_tensor(RGB_MEAN).view(1, 3, 1, 1) * 255.0
    std = rgb.new_tensor(RGB_STD).view(1, 3, 1, 1) * 255.0
    x_rgb = (rgb - mean) / std
    valid = (depth > 0).to(depth.dtype)
    x_depth = torch.cat([(depth - DEPTH_MEAN_M) / DEPTH_STD_M * valid, valid], dim=1)
    return x_rgb, x_depth


class ConvBNReLU(nn.Sequential):
    """3x3 (or k x k) convolution, batch norm, ReLU: the stem and downsampling unit."""

    def __init__(self, cin: int, cout: int, k: int = 3, stride: int = 1) -> None:
        super().__init__(nn.Conv2d(cin, cout, k, stride, k // 2, bias=False),
                         nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class NonBottleneck1D(nn.Module):
    """ERFNet/ESANet residual block with 3x1 and 1x3 factorised convolutions.

    Factorising a 3x3 kernel into 3x1 + 1x3 keeps the receptive field at 2/3
    of the cost; the second pair is dilated to grow context cheaply.
    """

    def __init__(self, ch: int, dilation: int = 1) -> None:
        super().__init__()
        d = dilation
        self.conv3x1_1 = nn.Conv2d(ch, ch, (3, 1), padding=(1, 0))
        self.conv1x3_1 = nn.Conv2d(ch, ch, (1, 3), padding=(0, 1), bias=False)
        self.bn1 = nn.BatchNorm2d(ch)
        self.conv3x1_2 = nn.Conv2d(ch, ch, (3, 1), padding=(d, 0), dilation=(d, 1))
        self.conv1x3_2 = nn.Conv2d(ch, ch, (1, 3), padding=(0, d), dilation=(1, d), bias=False)
        self.bn2 = nn.BatchNorm2d(ch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.conv3x1_1(x), inplace=True)
        y = F.relu(self.bn1(self.conv1x3_1(y)), inplace=True)
        y = F.relu(self.conv3x1_2(y), inplace=True)
        y = self.bn2(self.conv1x3_2(y))
        return F.relu(y + x, inplace=True)


class SqueezeExcite(nn.Module):
    """Channel attention: global pooling -> bottleneck MLP -> sigmoid gate."""

    def __init__(self, ch: int, reduction: int = 4) -> None:
        super().__init__()
        hidden = max(ch // reduction, 4)
        self.fc1 = nn.Conv2d(ch, hidden, 1)
        self.fc2 = nn.Conv2d(hidden, ch, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        w = F.adaptive_avg_pool2d(x, 1)
        w = torch.sigmoid(self.fc2(F.relu(self.fc1(w), inplace=True)))
        return x * w


class SEFusion(nn.Module):
    """ESANet's SE-add: re-weight each modality's channels, then add depth into RGB."""

    def __init__(self, ch: int) -> None:
        super().__init__()
        self.se_rgb = SqueezeExcite(ch)
        self.se_depth = SqueezeExcite(ch)

    def forward(self, rgb: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        return self.se_rgb(rgb) + self.se_depth(depth)


def _stage(cin: int, cout: int, dilations: tuple[int, ...]) -> nn.Sequential:
    """Stride-2 downsampling followed by NonBottleneck-1D blocks."""
    return nn.Sequential(ConvBNReLU(cin, cout, 3, 2),
                         *[NonBottleneck1D(cout, d) for d in dilations])


class PyramidPooling(nn.Module):
    """PSPNet-style context: pool to several grids, project, upsample, concatenate."""

    def __init__(self, ch: int, bins: tuple[int, ...] = (1, 3, 5), branch: int = 32) -> None:
        super().__init__()
        self.bins = bins
        self.branches = nn.ModuleList(
            [nn.Sequential(nn.Conv2d(ch, branch, 1, bias=False), nn.BatchNorm2d(branch),
                           nn.ReLU(inplace=True)) for _ in bins])
        self.project = ConvBNReLU(ch + branch * len(bins), ch, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        size = x.shape[-2:]
        feats = [x]
        for b, branch in zip(self.bins, self.branches):
            y = branch(F.adaptive_avg_pool2d(x, b))
            feats.append(F.interpolate(y, size=size, mode="bilinear", align_corners=False))
        return self.project(torch.cat(feats, dim=1))


class DecoderStage(nn.Module):
    """Upsample x2, reduce channels, add the fused encoder skip, refine with one block."""

    def __init__(self, cin: int, cskip: int, cout: int) -> None:
        super().__init__()
        self.reduce = ConvBNReLU(cin, cout, 3)
        self.skip = nn.Conv2d(cskip, cout, 1, bias=False)
        self.block = NonBottleneck1D(cout)

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        x = F.interpolate(self.reduce(x), size=skip.shape[-2:], mode="bilinear",
                          align_corners=False)
        return self.block(x + self.skip(skip))


class SmallRGBDNet(nn.Module):
    """Two-branch RGB-D encoder with SE fusion, PPM context and a skip decoder.

    Resolutions for a 240x320 input: stem 1/2 (120x160), stages 1/4, 1/8, 1/16,
    decoder back to 1/2, logits bilinearly upsampled to the input size. Any
    input size works (sizes are matched by interpolation, no divisibility rule).
    """

    def __init__(self, num_classes: int = classes.NUM_KNOWN,
                 widths: tuple[int, int, int, int] = DEFAULT_WIDTHS,
                 novelty_branch: bool = False) -> None:
        super().__init__()
        c0, c1, c2, c3 = widths
        self.num_classes = num_classes
        self.widths = tuple(widths)
        self.novelty_branch = bool(novelty_branch)
        self.rgb_stem = ConvBNReLU(3, c0, 3, 2)
        self.depth_stem = ConvBNReLU(2, c0, 3, 2)
        self.rgb_stages = nn.ModuleList([_stage(c0, c1, (1,)), _stage(c1, c2, (1, 2)),
                                         _stage(c2, c3, (2, 4))])
        self.depth_stages = nn.ModuleList([_stage(c0, c1, ()), _stage(c1, c2, (1,)),
                                           _stage(c2, c3, (2,))])
        self.fusions = nn.ModuleList([SEFusion(c) for c in (c0, c1, c2, c3)])
        self.context = PyramidPooling(c3)
        self.decoder = nn.ModuleList([DecoderStage(c3, c2, c2), DecoderStage(c2, c1, c1),
                                      DecoderStage(c1, c0, c0)])
        self.classifier = nn.Conv2d(c0, num_classes, 1)
        if self.novelty_branch:
            self.novelty_decoder = DecoderStage(c1, c0, c0)
            self.novelty_classifier = nn.Conv2d(c0, num_classes, 1)

    def _decoder_input(self, x_rgb: torch.Tensor, x_depth: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor]:
        """(input of the last decoder stage, its 1/2-resolution skip): what the known-class
        head and the novelty branch both read. Inputs are cast to the encoder's dtype
        (bfloat16 after :func:`lower_precision`), so callers always pass float32."""
        dtype = self.rgb_stem[0].weight.dtype
        r = self.rgb_stem(x_rgb.to(dtype))
        d = self.depth_stem(x_depth.to(dtype))
        r = self.fusions[0](r, d)
        skips = [r]
        for i, (rs, ds) in enumerate(zip(self.rgb_stages, self.depth_stages)):
            r, d = rs(r), ds(d)
            r = self.fusions[i + 1](r, d)
            skips.append(r)
        x = self.context(skips[-1])
        for dec, skip in zip(self.decoder[:-1], reversed(skips[1:-1])):
            x = dec(x, skip)
        return x, skips[0]

    def _novelty(self, x: torch.Tensor, skip: torch.Tensor, size) -> torch.Tensor:
        return F.interpolate(self._head(self.novelty_classifier, self.novelty_decoder(x, skip)),
                             size=size, mode="bilinear", align_corners=False)

    @staticmethod
    def _head(classifier: nn.Conv2d, feats: torch.Tensor) -> torch.Tensor:
        """A 1x1 classifier on features cast to its own dtype: the heads stay float32
        under :func:`lower_precision`, so logits and entropies keep full precision."""
        return classifier(feats.to(classifier.weight.dtype))

    def _temperature(self, x: torch.Tensor, skip: torch.Tensor, size) -> torch.Tensor:
        """(B, 1, H, W) novelty temperature at the input size for inference: computed from
        the branch's logits at the decoder's half resolution, then the one-channel factor
        upsampled (bilinear, so it stays in [NOVELTY_FLOOR, 1]). Upsampling S logits and
        taking their entropy at full size instead cost about 7 of the net's 50 ms on
        this CPU and differ only along edges (bench/results/backbone.json)."""
        t = novelty_temperature(self._head(self.novelty_classifier,
                                           self.novelty_decoder(x, skip)))
        return F.interpolate(t, size=size, mode="bilinear", align_corners=False)

    def novelty_raw(self, rgb: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Un-normalised batch -> (B, S, H, W) novelty-branch logits, the rest of the
        network run without gradients (how the branch is trained on a frozen net)."""
        x_rgb, x_depth = prepare_inputs(rgb, depth)
        with torch.no_grad():
            x, skip = self._decoder_input(x_rgb, x_depth)
        return self._novelty(x, skip, x_rgb.shape[-2:])

    def forward_with_features(self, x_rgb: torch.Tensor, x_depth: torch.Tensor
                              ) -> tuple[torch.Tensor, torch.Tensor]:
        """As :meth:`forward`, plus the penultimate feature map: the last decoder stage's
        output (B, widths[0], H/2, W/2), what the known-class classifier reads. Both are
        float32 whatever the encoder's dtype."""
        size = x_rgb.shape[-2:]
        x, skip = self._decoder_input(x_rgb, x_depth)
        feats = self.decoder[-1](x, skip).to(self.classifier.weight.dtype)
        logits = F.interpolate(self.classifier(feats), size=size, mode="bilinear",
                               align_corners=False)
        if self.novelty_branch:
            logits = logits * self._temperature(x, skip, size)
        return logits, feats

    def forward(self, x_rgb: torch.Tensor, x_depth: torch.Tensor) -> torch.Tensor:
        """Normalised inputs (see :func:`prepare_inputs`) -> (B, S, H, W) logits (with the
        novelty branch: the known-class logits times its temperature factor)."""
        return self.forward_with_features(x_rgb, x_depth)[0]

    def predict_raw(self, rgb: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Un-normalised batch (rgb 0..255, depth metres) -> (B, S, H, W) logits."""
        return self(*prepare_inputs(rgb, depth))


def novelty_temperature(novelty: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) factor ``max(1 - h, NOVELTY_FLOOR)``, h the normalised entropy of the
    softmax of the novelty branch's (B, S, H, W) logits."""
    h = entropy(novelty, dim=1).unsqueeze(1) / math.log(novelty.shape[1])
    return (1.0 - h).clamp(min=NOVELTY_FLOOR)


def fold_batch_norm(model: nn.Module) -> nn.Module:
    """Fold every batch norm into the convolution right before it, in place, for inference.

    In eval mode a batch norm is a fixed per-channel scale and shift, so it can be
    merged into the preceding convolution's weights and bias: the same function
    (outputs equal to float rounding) without a memory pass per norm, which on a CPU
    costs about as much as a small convolution (bench/results/backbone.json,
    ``default_unfolded_ms_320x240``). Pairs are a ``Conv2d`` followed by a
    ``BatchNorm2d`` in a ``Sequential`` (:class:`ConvBNReLU`, the pyramid pooling
    branches) and the two conv/norm pairs of :class:`NonBottleneck1D`; each folded
    norm becomes an ``Identity``. Training needs the norms: only for a net in eval mode.
    """
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    if model.training:
        raise ValueError("fold_batch_norm is for inference: call model.eval() first")
    for module in list(model.modules()):
        if isinstance(module, nn.Sequential):
            for i in range(len(module) - 1):
                conv, bn = module[i], module[i + 1]
                if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                    module[i], module[i + 1] = fuse_conv_bn_eval(conv, bn), nn.Identity()
        elif isinstance(module, NonBottleneck1D):
            for conv_name, bn_name in (("conv1x3_1", "bn1"), ("conv1x3_2", "bn2")):
                bn = getattr(module, bn_name)
                if isinstance(bn, nn.BatchNorm2d):
                    setattr(module, conv_name,
                            fuse_conv_bn_eval(getattr(module, conv_name), bn))
                    setattr(module, bn_name, nn.Identity())
    left = [n for n, m in model.named_modules() if isinstance(m, nn.BatchNorm2d)]
    if left:
        raise RuntimeError(f"batch norms without a convolution to fold into: {left}")
    return model


HEADS = ("classifier", "novelty_classifier")
"""The 1x1 class heads, which :func:`lower_precision` leaves in float32."""


def lower_precision(model: SmallRGBDNet, dtype: torch.dtype = torch.bfloat16) -> SmallRGBDNet:
    """Run the encoder and decoder in ``dtype`` (bfloat16), in place, for inference.

    Why: on a CPU with native bfloat16 arithmetic (AVX512-BF16) oneDNN's convolutions
    run about 1.4x faster in bfloat16 than in float32 on this net, which is what
    brings a 320x240 frame within the 40 ms budget (bench/results/backbone.json,
    ``default_float32_ms_320x240``). The class heads stay float32 (:data:`HEADS`) and
    read features cast up, so logits, softmax and entropy are computed in full
    precision; only the features carry bfloat16 rounding (8 significant bits), which
    moves a pixel's argmax on a fraction of a percent of pixels, at class borders
    (``test_float32_*`` against ``test_*`` in the same file). Inputs stay float32: the
    net casts them. Only for a net in eval mode; training stays float32.
    """
    if model.training:
        raise ValueError("lower_precision is for inference: call model.eval() first")
    for name, child in model.named_children():
        if name not in HEADS:
            child.to(dtype)
    return model


def count_parameters(model: nn.Module) -> int:
    """Number of trainable scalars (the weight file holds this many floats)."""
    return sum(p.numel() for p in model.parameters())


def count_flops(model: nn.Module, height: int = 240, width: int = 320) -> int:
    """Floating-point operations (2 per multiply-add) of one forward pass at batch 1."""
    from torch.utils.flop_counter import FlopCounterMode

    x_rgb = torch.zeros(1, 3, height, width)
    x_depth = torch.zeros(1, 2, height, width)
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        model.eval()(x_rgb, x_depth)
    return int(counter.get_total_flops())


def save_weights(model: SmallRGBDNet, path: str, extra: dict | None = None,
                 half: bool = True) -> None:
    """Store the weights (fp16 by default, halves the file) with the layout they fit."""
    state = {k: (v.half() if half and v.is_floating_point() else v)
             for k, v in model.state_dict().items()}
    torch.save({"arch": "SmallRGBDNet", "arch_version": ARCH_VERSION,
                "num_classes": model.num_classes, "widths": list(model.widths),
                "novelty_branch": model.novelty_branch,
                "channel_to_id": np.asarray(classes.CHANNEL_TO_ID).tolist(),
                "state_dict": state, "extra": extra or {}}, path)


def load_weights(path: str, device: str = "cpu") -> SmallRGBDNet:
    """Rebuild the net from a file written by :func:`save_weights` (eval mode, fp32)."""
    blob = read_torch_file(path, device, "checkpoint")
    if not isinstance(blob, dict) or blob.get("arch") != "SmallRGBDNet":
        hint = ""
        if isinstance(blob, dict) and ("state_dict" in blob or "model" in blob):
            hint = "; an ESANet checkpoint (train-backbone --arch esanet) loads with " \
                   "backbone.kind esanet"
        raise ValueError(f"{path}: not a SmallRGBDNet weight file (no 'arch' = "
                         f"'SmallRGBDNet'){hint}")
    if blob.get("arch_version") != ARCH_VERSION:
        raise ValueError(f"{path}: weights are for layout version {blob.get('arch_version')}, "
                         f"this code builds version {ARCH_VERSION}; retrain the backbone")
    # The layers' initial weights are replaced by the file's; drawing them from a forked
    # generator leaves the process's global torch generator as it was (no hidden state).
    with torch.random.fork_rng(devices=[]):
        model = SmallRGBDNet(int(blob["num_classes"]), tuple(blob["widths"]),
                             bool(blob.get("novelty_branch", False)))
    state = {k: (v.float() if v.is_floating_point() else v) for k, v in blob["state_dict"].items()}
    model.load_state_dict(state, strict=True)
    return model.to(device).eval()
