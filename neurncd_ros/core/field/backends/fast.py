"""The default backend: a tri-plane field trained with depth-guided samples.

Training samples are depth-guided (RGB-D input): most lie in a band around the
measured depth, a few are stratified over the ray, and a depth loss plus a
free-space loss shape the density. A view with measured depth (every frame
the mapper publishes) is rendered with that same layout around its depth (no
search pass); a view without depth is rendered coarse-to-fine: a density-only
stratified pass, then importance samples evaluated by the full field.

The tri-planes are laid out over the scene box, so the box snaps to their
coarse lattice and is capped by ``max_plane_texels``; growing it pads the
planes (``box_holds_parameters``).
"""

from __future__ import annotations

import dataclasses

import torch

from ...params import param
from .. import losses, renderer, samplers
from ..fields import TriPlaneField
from .registry import register
from .base import FieldModel, RayBatch, distillation, evaluate, render_samples


@dataclasses.dataclass(frozen=True)
class FastConfig:
    """Tri-plane field: planes, MLP heads, depth-guided sampling, losses, optimiser.

    Why these defaults: the levels, channels, width and confidence power were
    chosen in an ablation on a streamed synthetic scene; the result is
    ``fast_known_acc_120s`` / ``fast_psnr_120s`` in bench/results/field.json.
    """

    rays_per_iteration: int = param(2048, "training rays per iteration", lo=16, hi=65536)
    plane_cell_sizes: list[float] = param([0.16, 0.04, 0.02], "texel spacing of each "
                                          "tri-plane level, coarsest first; finer ones are "
                                          "rounded to the coarsest / an integer", lo=0.001,
                                          hi=10.0, unit="m")
    max_plane_texels: int = param(1024, "most texels per axis of the finest tri-plane level; "
                                  "the scene box stops growing there (memory bound)",
                                  lo=8, hi=8192)
    plane_channels: int = param(8, "feature channels per tri-plane level", lo=1, hi=128)
    hidden: int = param(32, "hidden width of the MLP heads", lo=8, hi=512)
    surface_samples: int = param(16, "training samples per ray in the band around the "
                                 "measured depth", lo=1, hi=512)
    free_samples: int = param(8, "training samples per ray stratified over [near, far]",
                              lo=1, hi=512)
    surface_band: float = param(0.1, "half-width of the depth-guided sampling band",
                                lo=0.001, hi=2.0, unit="m")
    coarse_samples: int = param(48, "density-only stratified samples per ray when a view "
                                "is rendered without measured depth", lo=2, hi=1024)
    fine_samples: int = param(24, "importance samples per ray, evaluated by the full field, "
                              "when a view is rendered without measured depth", lo=1, hi=1024)
    embedding_confidence_power: float = param(
        0.0, "weight each ray's embedding loss by (1 - backbone entropy / log S)^power, so "
        "that where views disagree the field follows the confident ones; 0 (plain mean) "
        "keeps the backbone's uncertainty on novel objects, which power 2 sharpens away",
        lo=0.0, hi=16.0)
    embedding_loss: str = param(
        "kl", "what trains the embedding head: 'kl' against the backbone's logits "
        "(NeurNCD), or 'cross_entropy' against sparse one-hot labels, all-zero rays "
        "unlabelled (the Semantic-NeRF label-propagation baseline of neurncd eval)",
        choices=losses.EMBEDDING_LOSSES)
    lambda_depth: float = param(0.5, "weight of the L1 depth loss", lo=0.0, hi=100.0)
    lambda_free: float = param(1.0, "weight of the free-space loss", lo=0.0, hi=100.0)
    lr_grid: float = param(2e-2, "Adam learning rate of the tri-planes", lo=0.0, hi=1.0)
    lr_mlp: float = param(5e-3, "Adam learning rate of the MLP heads", lo=0.0, hi=1.0)


@register("fast", FastConfig)
class FastModel(FieldModel):
    """Tri-plane field trained on depth-guided samples (photometric, embedding, depth and
    free-space losses); renders depth-guided where a ray has depth, coarse-to-fine
    elsewhere."""

    box_holds_parameters = True

    def __init__(self, cfg: FastConfig, channels: int, shared, generator: torch.Generator
                 ) -> None:
        super().__init__()
        self.cfg = cfg
        self.lambda_embedding = shared.lambda_embedding
        self.lambda_features = shared.lambda_features
        self.field = TriPlaneField(channels, list(cfg.plane_cell_sizes), generator,
                                   cfg.plane_channels, cfg.hidden)
        self.rays_per_iteration = cfg.rays_per_iteration
        self.train_samples_per_ray = cfg.surface_samples + cfg.free_samples
        self.render_samples_per_ray = cfg.coarse_samples + cfg.fine_samples

    def _guided(self, near, far, depth, perturb: torch.Generator | None) -> torch.Tensor:
        c = self.cfg
        return samplers.depth_guided(near, far, depth, c.surface_samples, c.free_samples,
                                     c.surface_band, perturb)

    def losses(self, batch: RayBatch, near, far, generator):
        t = self._guided(near, far, batch.depth, generator)
        out = render_samples(self.field, batch.origins, batch.dirs, t)
        c = self.cfg
        lp = losses.photometric(out["rgb"], batch.rgb)
        le, lfeat = distillation(c.embedding_loss, batch, out["embedding"],
                                 c.embedding_confidence_power)
        ld = losses.depth_l1(out["depth"], batch.depth)
        lf = losses.free_space(out["weights"], t, batch.depth, c.surface_band)
        total = (lp + self.lambda_embedding * le + self.lambda_features * lfeat
                 + c.lambda_depth * ld + c.lambda_free * lf)
        return {"total": total, "photometric": lp, "embedding": le, "features": lfeat,
                "depth": ld, "free_space": lf,
                "fine_rgb_mse": ((out["rgb"] - batch.rgb) ** 2).mean().detach()}

    def _render_free(self, origins, dirs, near, far):
        """No depth: a density-only stratified pass, then importance samples."""
        t_c = samplers.stratified(near, far, self.cfg.coarse_samples, None)
        sigma = evaluate(self.field, origins, dirs, t_c, geometry_only=True)["sigma"]
        w = renderer.render_weights(sigma, t_c, dirs.norm(dim=-1))
        t_f = samplers.importance(t_c, w, self.cfg.fine_samples, None)
        return render_samples(self.field, origins, dirs, torch.sort(t_f, dim=-1).values)

    def _render_guided(self, origins, dirs, near, far, depth):
        """Measured depth: the training sample layout, no search pass; the surface is where
        training put it, and no mass from in front of or behind it blends into the
        embedding."""
        return render_samples(self.field, origins, dirs, self._guided(near, far, depth, None))

    def render_rays(self, origins, dirs, near, far, depth=None):
        if depth is None:
            return self._render_free(origins, dirs, near, far)
        valid = depth > 0
        if bool(valid.all()):
            return self._render_guided(origins, dirs, near, far, depth)
        if not bool(valid.any()):
            return self._render_free(origins, dirs, near, far)
        out_g = self._render_guided(origins[valid], dirs[valid], near[valid], far[valid],
                                    depth[valid])
        out_f = self._render_free(origins[~valid], dirs[~valid], near[~valid], far[~valid])
        out = {}
        for k in ("rgb", "embedding", "depth", "opacity"):
            v = out_g[k].new_empty((origins.shape[0],) + out_g[k].shape[1:])
            v[valid], v[~valid] = out_g[k], out_f[k]
            out[k] = v
        return out

    def param_groups(self):
        grid = list(self.field.planes.parameters())
        ids = {id(p) for p in grid}
        rest = [p for p in self.parameters() if id(p) not in ids]
        return [{"params": grid, "lr": self.cfg.lr_grid, "name": "grid"},
                {"params": rest, "lr": self.cfg.lr_mlp, "name": "mlp"}]

    def box_lattice(self) -> tuple[float, int]:
        q = max(self.field.planes.ratios)
        return self.field.cell, max(1, (self.cfg.max_plane_texels - 1) // q)

    def set_bounds(self, lo, hi, keep, generator):
        self.field.set_bounds(lo, hi, generator, keep=keep)
