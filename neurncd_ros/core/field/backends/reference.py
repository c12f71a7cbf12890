"""The paper's backend: Semantic-NeRF's coarse and fine 8x256 MLPs.

Stratified coarse samples, importance fine samples drawn from the coarse
weights, L = L_p + lambda L_e on both coarse and fine renders. Faithful to the
paper: no depth loss, no depth-guided sampling, the measured depth of a view is
not used to render it.
"""

from __future__ import annotations

import dataclasses

import torch

from ...params import param
from .. import losses, samplers
from ..fields import NerfField
from .registry import register
from .base import FieldModel, RayBatch, distillation, render_samples


@dataclasses.dataclass(frozen=True)
class ReferenceConfig:
    """The paper's Semantic-NeRF MLPs: samples per ray, rays per iteration, optimiser."""

    rays_per_iteration: int = param(1024, "training rays per iteration", lo=16, hi=65536)
    coarse_samples: int = param(64, "stratified samples per ray evaluated by the coarse MLP",
                                lo=2, hi=1024)
    fine_samples: int = param(128, "importance samples per ray added for the fine MLP",
                              lo=0, hi=1024)
    lr: float = param(5e-4, "Adam learning rate of both MLPs", lo=0.0, hi=1.0)
    embedding_loss: str = param(
        "kl", "what trains the embedding heads: 'kl' against the backbone's logits (the "
        "paper), or 'cross_entropy' against sparse one-hot labels, all-zero rays unlabelled "
        "(Semantic-NeRF label propagation, neurncd eval --baselines)",
        choices=losses.EMBEDDING_LOSSES)


@register("reference", ReferenceConfig)
class ReferenceModel(FieldModel):
    """Semantic-NeRF's two MLPs: a coarse one on stratified samples, a fine one on those
    plus importance samples, photometric and embedding losses on both (the paper's
    setting); renders the fine pass and never uses depth."""
    def __init__(self, cfg: ReferenceConfig, channels: int, shared,
                 generator: torch.Generator) -> None:
        super().__init__()
        self.cfg = cfg
        self.lambda_embedding = shared.lambda_embedding
        self.lambda_features = shared.lambda_features
        self.coarse = NerfField(channels, generator)
        self.field = NerfField(channels, generator)
        self.rays_per_iteration = cfg.rays_per_iteration
        # coarse + fine evaluations per ray (the fine MLP sees the coarse samples too)
        self.train_samples_per_ray = self.render_samples_per_ray = (
            2 * cfg.coarse_samples + cfg.fine_samples)

    def _both(self, origins, dirs, near, far, perturb: torch.Generator | None):
        t_c = samplers.stratified(near, far, self.cfg.coarse_samples, perturb)
        coarse = render_samples(self.coarse, origins, dirs, t_c)
        t_f = samplers.importance(t_c, coarse["weights"], self.cfg.fine_samples, perturb)
        t = torch.sort(torch.cat([t_c, t_f.detach()], dim=-1), dim=-1).values
        return coarse, render_samples(self.field, origins, dirs, t)

    def losses(self, batch: RayBatch, near, far, generator):
        coarse, fine = self._both(batch.origins, batch.dirs, near, far, generator)
        lp = (losses.photometric(coarse["rgb"], batch.rgb)
              + losses.photometric(fine["rgb"], batch.rgb))
        kind = self.cfg.embedding_loss
        le_c, lf_c = distillation(kind, batch, coarse["embedding"])
        le_f, lf_f = distillation(kind, batch, fine["embedding"])
        le, lfeat = le_c + le_f, lf_c + lf_f
        return {"total": lp + self.lambda_embedding * le + self.lambda_features * lfeat,
                "photometric": lp, "embedding": le, "features": lfeat,
                "fine_rgb_mse": ((fine["rgb"] - batch.rgb) ** 2).mean().detach()}

    def render_rays(self, origins, dirs, near, far, depth=None):
        return self._both(origins, dirs, near, far, None)[1]

    def param_groups(self):
        return [{"params": list(self.parameters()), "lr": self.cfg.lr}]
