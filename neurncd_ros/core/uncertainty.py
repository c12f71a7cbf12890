"""The one softmax and the one entropy, for numpy arrays and torch tensors alike.

The entropy of the softmax of an embedding's logits is the uncertainty the
paper fuses in the field and the discovery thresholds: natural log, in
[0, ln S], computed from log-sum-exp with the maximum subtracted so very
large logits neither overflow nor give NaN.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def _channel_max(x: np.ndarray) -> np.ndarray:
    """Maximum over the last axis, keeping it: for an embedding's few channels a loop of
    element-wise maxima over the channel planes is about 6x faster than numpy's reduction
    along a short, innermost axis (the same values)."""
    if x.shape[-1] > 64:
        return x.max(axis=-1, keepdims=True)
    m = x[..., 0].copy()
    for k in range(1, x.shape[-1]):
        np.maximum(m, x[..., k], out=m)
    return m[..., None]


def _channel_sum(x: np.ndarray) -> np.ndarray:
    """Sum over the last axis, keeping it (einsum's loop: about 3x faster than numpy's
    reduction along a short innermost axis, and no BLAS threads)."""
    return np.einsum("...i->...", x)[..., None]


def softmax(logits: Any, axis: int = -1) -> Any:
    """softmax over ``axis``: float32 numpy array in, float32 out; a tensor gives a tensor."""
    if _is_torch(logits):
        import torch
        return torch.softmax(logits, dim=axis)
    z = np.asarray(logits, dtype=np.float32)
    if axis not in (-1, z.ndim - 1):
        z = z - z.max(axis=axis, keepdims=True)
        e = np.exp(z)
        return e / e.sum(axis=axis, keepdims=True)
    e = np.exp(z - _channel_max(z))
    e /= _channel_sum(e)
    return e


def entropy(logits: Any, dim: int = -1) -> Any:
    """Natural-log entropy of softmax(logits) over the channel axis, clipped to [0, ln S].

    numpy input: channels last (``dim`` must be -1), float32 result, ValueError on
    NaN/inf or a non-float array; torch input: a differentiable tensor of the same
    dtype, the channels on ``dim`` (1 for a network's (B, S, H, W) output: no
    transposed copy, half the time of moving them last).
    """
    if _is_torch(logits):
        import torch
        log_p = torch.log_softmax(logits, dim=dim)
        h = -(log_p.exp() * log_p).sum(dim=dim)
        return h.clamp(0.0, math.log(logits.shape[dim]))
    if dim != -1:
        raise ValueError("numpy logits are channels last: entropy(..., dim=-1)")
    x = np.asarray(logits)
    if x.ndim < 1 or x.shape[-1] < 1:
        raise ValueError(f"logits need a non-empty last (channel) axis, got shape {x.shape}")
    if not np.issubdtype(x.dtype, np.floating):
        raise ValueError(f"logits must be floating point, got {x.dtype}")
    # float32 throughout (float64 is only needed for float64 input): z <= 0 and the sum of
    # exp(z) is in [1, S], so nothing overflows, and the result is float32 anyway.
    x = x.astype(np.float32, copy=False) if x.dtype != np.float64 else x
    with np.errstate(invalid="ignore", over="ignore"):  # non-finite logits: refused below
        z = x - _channel_max(x)
        e = np.exp(z)
        s = _channel_sum(e)
        # H = lse - sum(p z) with p = exp(z) / s: one exp, not two.
        h = np.log(s[..., 0]) - _channel_sum(e * z)[..., 0] / s[..., 0]
    # Any NaN or inf among the logits makes its pixel's h NaN (inf - inf, 0 * -inf): one
    # test of the result instead of a pass over every logit.
    if not np.all(np.isfinite(h)):
        raise ValueError("logits contain NaN or inf")
    return np.clip(h, 0.0, np.log(x.shape[-1])).astype(np.float32)
