"""Volume rendering: one set of weights composites colour, embedding logits and depth."""

from __future__ import annotations

import torch


def render_weights(sigma: torch.Tensor, t: torch.Tensor, ray_norm: torch.Tensor) -> torch.Tensor:
    """NeRF quadrature weights w_i = T_i (1 - exp(-sigma_i delta_i)), shape (R, n).

    ``t`` are z-depths, so metric spacing is delta_t * |direction|. The last
    interval is open-ended: whatever light is left ends on the last sample.
    """
    delta = t[:, 1:] - t[:, :-1]
    delta = torch.cat([delta, torch.full_like(delta[:, :1], 1e10)], dim=-1) * ray_norm[:, None]
    alpha = 1.0 - torch.exp(-sigma * delta)
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha + 1e-10], -1),
                          dim=-1)[:, :-1]
    return alpha * trans


def composite(weights: torch.Tensor, t: torch.Tensor, values: dict[str, torch.Tensor]
              ) -> dict[str, torch.Tensor]:
    """Weighted sums along the ray of every (R, n, C) value, plus depth and opacity.

    The embedding is composited as logits (the paper renders the embedding and
    applies softmax afterwards), so the rendered logits are a convex mix.
    """
    out = {k: torch.einsum("rn,rnc->rc", weights, v) for k, v in values.items()}
    out["depth"] = (weights * t).sum(dim=-1)
    out["opacity"] = weights.sum(dim=-1)
    return out
