"""Training losses of the Embedding-NeRF and the per-pixel entropy."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from neurncd_ros.core.uncertainty import entropy  # noqa: F401 (re-exported)


def photometric(rgb: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L_p: mean squared colour error per ray."""
    return ((rgb - target) ** 2).sum(dim=-1).mean()


def embedding_kl(target_logits: torch.Tensor, rendered_logits: torch.Tensor,
                 confidence_power: float = 0.0) -> torch.Tensor:
    """L_e = KL(softmax(E) || softmax(E_hat)) averaged over rays (E from the backbone).

    ``confidence_power`` p > 0 weights each ray by (1 - H(E) / log S)^p, normalised
    to mean 1 over the batch: where views disagree, the field follows the views in
    which the backbone was sure (0 = the paper's plain mean).
    """
    log_p = F.log_softmax(target_logits, dim=-1)
    log_q = F.log_softmax(rendered_logits, dim=-1)
    p = log_p.exp()
    kl = (p * (log_p - log_q)).sum(dim=-1)
    if confidence_power <= 0:
        return kl.mean()
    h = -(p * log_p).sum(dim=-1) / math.log(target_logits.shape[-1])
    w = (1.0 - h).clamp(min=0.0) ** confidence_power
    return (w * kl).sum() / w.sum().clamp(min=1e-8)


def label_cross_entropy(target: torch.Tensor, rendered_logits: torch.Tensor) -> torch.Tensor:
    """Semantic-NeRF's L_s: cross-entropy of the rendered logits against labelled rays.

    ``target`` (R, S) is each ray's class distribution (one-hot for a ground-truth
    label); a ray whose target is all zero carries no label and is left out, so
    sparse labels need no separate mask. Mean over the labelled rays (0 if none).
    """
    labelled = target.sum(dim=-1) > 0
    if not bool(labelled.any()):
        return rendered_logits.sum() * 0.0
    log_q = F.log_softmax(rendered_logits[labelled], dim=-1)
    return -(target[labelled] * log_q).sum(dim=-1).mean()


EMBEDDING_LOSSES = ("kl", "cross_entropy")
"""What the embedding head is trained with (``mapper.<backend>.embedding_loss``)."""


def embedding_term(kind: str, target: torch.Tensor, rendered_logits: torch.Tensor,
                   confidence_power: float = 0.0) -> torch.Tensor:
    """The embedding head's loss: ``kl`` (L_e against the backbone's logits, NeurNCD) or
    ``cross_entropy`` (L_s against sparse labels, Semantic-NeRF label propagation)."""
    if kind == "kl":
        return embedding_kl(target, rendered_logits, confidence_power)
    if kind == "cross_entropy":
        return label_cross_entropy(target, rendered_logits)
    raise ValueError(f"embedding_loss must be one of {EMBEDDING_LOSSES}, got {kind!r}")


def feature_error(target: torch.Tensor, rendered: torch.Tensor) -> torch.Tensor:
    """L_f: squared error of the rendered backbone features (R, F) relative to the
    batch's mean squared feature norm, sum ||f_hat - f||^2 / sum ||f||^2.

    The penultimate features have no fixed scale (they are whatever the backbone's last
    decoder stage outputs), so the error is relative: 1 for a field that renders zeros,
    0 for a perfect fit, independent of the backbone. 0 (kept in the graph) when there
    are no feature channels.
    """
    if target.shape[-1] == 0:
        return rendered.sum() * 0.0
    return ((rendered - target) ** 2).sum() / (target ** 2).sum().clamp(min=1e-8)


def depth_l1(depth: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean |rendered - measured| z-depth over rays with a measurement (target > 0)."""
    valid = target > 0
    if not bool(valid.any()):
        return depth.sum() * 0.0
    return (depth[valid] - target[valid]).abs().mean()


def free_space(weights: torch.Tensor, t: torch.Tensor, target: torch.Tensor,
               band: float) -> torch.Tensor:
    """Weight mass in front of the measured surface (t < depth - band): should be empty."""
    front = (t < (target[:, None] - band)) & (target[:, None] > 0)
    return (weights * front).sum(dim=-1).pow(2).mean()


# The per-pixel entropy lives in core/uncertainty.py; these names stay for callers.
entropy_torch = entropy
