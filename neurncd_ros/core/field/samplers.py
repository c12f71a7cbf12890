"""Where along a ray the field is evaluated.

Ray parameters ``t`` are z-depths: directions are z-normalised in the camera
(``camera.camera_directions``), so ``origin + t * direction`` lies at depth t.
``perturb`` is the generator that jitters the samples in training (drawn from
it only, never from torch's global generator), or None for the deterministic
layout of rendering.
"""

from __future__ import annotations

import torch


def aabb_near_far(origins: torch.Tensor, dirs: torch.Tensor, lo: torch.Tensor,
                  hi: torch.Tensor, min_near: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-ray entry/exit of the scene AABB (slab test); near >= ``min_near``.

    Rays missing the box get near = far = min_near (zero-length, renders empty).
    """
    inv = 1.0 / torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
    t0, t1 = (lo - origins) * inv, (hi - origins) * inv
    near = torch.minimum(t0, t1).amax(dim=-1).clamp(min=min_near)
    far = torch.maximum(t0, t1).amin(dim=-1)
    far = torch.maximum(far, near)
    return near, far


def stratified(near: torch.Tensor, far: torch.Tensor, n: int,
               perturb: torch.Generator | None) -> torch.Tensor:
    """n samples per ray, one in each of n equal bins of [near, far] (centres unless perturb)."""
    u = torch.arange(n, dtype=near.dtype, device=near.device)
    if perturb is not None:
        u = u + torch.rand(near.shape[0], n, device=near.device, generator=perturb)
    else:
        u = u + 0.5
    return near[:, None] + (far - near)[:, None] * (u / n)


def importance(t: torch.Tensor, weights: torch.Tensor, n: int,
               perturb: torch.Generator | None) -> torch.Tensor:
    """n samples from the piecewise-constant pdf of ``weights`` over bins between ``t``.

    Hierarchical sampling of NeRF: bins are centred on the coarse samples.
    """
    mids = 0.5 * (t[:, 1:] + t[:, :-1])
    edges = torch.cat([t[:, :1], mids, t[:, -1:]], dim=-1)  # (R, n_coarse + 1)
    w = weights.detach() + 1e-5
    pdf = w / w.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1)], dim=-1)
    if perturb is not None:
        u = torch.rand(t.shape[0], n, device=t.device, generator=perturb)
    else:
        u = ((torch.arange(n, dtype=t.dtype, device=t.device) + 0.5) / n).expand(t.shape[0], n)
    u = u.contiguous()
    idx = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    c0, c1 = torch.gather(cdf, 1, idx - 1), torch.gather(cdf, 1, idx)
    e0, e1 = torch.gather(edges, 1, idx - 1), torch.gather(edges, 1, idx)
    frac = (u - c0) / torch.clamp(c1 - c0, min=1e-8)
    return e0 + frac * (e1 - e0)


def depth_guided(near: torch.Tensor, far: torch.Tensor, depth: torch.Tensor, n_surface: int,
                 n_free: int, band: float, perturb: torch.Generator | None) -> torch.Tensor:
    """Samples concentrated in [depth - band, depth + band], a few stratified over [near, far].

    Rays without a measured depth (depth <= 0) get all their samples stratified.
    Returned sorted along the ray.
    """
    valid = depth > 0
    d = torch.where(valid, depth, far)
    lo = torch.maximum(d - band, near)
    hi = torch.minimum(d + band, torch.maximum(far, lo))
    t_band = stratified(lo, hi, n_surface, perturb)
    t_free = stratified(near, far, n_free, perturb)
    t_all = stratified(near, far, n_surface + n_free, perturb)
    t = torch.where(valid[:, None], torch.cat([t_band, t_free], dim=-1), t_all)
    return torch.sort(t, dim=-1).values
