"""The interface between the mapper and a field backend, and the shared render step.

A backend owns everything that differs between fields: its sampling (where
along a ray it evaluates the field, in training and in rendering), its losses,
how many rays an iteration trains on, its parameter groups, and what the scene
box means to it (the lattice the box snaps to, and whether moving the box
reallocates parameters). The mapper owns the keyframes, the box itself, the
optimiser, threading and the random generators; it passes a backend the
``torch.Generator`` to draw from, so no backend touches torch's global one.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import nn

from .. import losses, renderer
from ..fields import EmbeddingField


@dataclasses.dataclass
class RayBatch:
    """Training rays: world origins/directions (z-normalised) and their targets."""

    origins: torch.Tensor  # (R, 3)
    dirs: torch.Tensor  # (R, 3)
    rgb: torch.Tensor  # (R, 3) in [0, 1]
    depth: torch.Tensor  # (R,) metres, 0 = none
    embedding: torch.Tensor  # (R, S) backbone logits
    features: torch.Tensor  # (R, F) backbone features the field learns (F may be 0)

    def split(self, size: int) -> list["RayBatch"]:
        """Consecutive micro-batches of at most ``size`` rays."""
        n = self.origins.shape[0]
        return [RayBatch(*(getattr(self, f.name)[s:s + size]
                           for f in dataclasses.fields(RayBatch))) for s in range(0, n, size)]


def distillation(kind: str, batch: RayBatch, rendered: torch.Tensor,
                 confidence_power: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The embedding losses of rendered (R, S + F) channels: L_e of the first S against
    the batch's logits (``losses.embedding_term``) and L_f of the other F against its
    features (``losses.feature_error``; 0 when the field learns no features)."""
    S = batch.embedding.shape[1]
    le = losses.embedding_term(kind, batch.embedding, rendered[:, :S], confidence_power)
    return le, losses.feature_error(batch.features, rendered[:, S:])


def evaluate(field: EmbeddingField, origins: torch.Tensor, dirs: torch.Tensor,
             t: torch.Tensor, geometry_only: bool = False) -> dict[str, torch.Tensor]:
    """The field at the samples t (R, n) of the rays; values shaped (R, n, ...)."""
    r, n = t.shape
    pts = (origins[:, None, :] + dirs[:, None, :] * t[..., None]).reshape(-1, 3)
    if geometry_only:
        return {"sigma": field.density(pts).reshape(r, n)}
    unit = dirs / dirs.norm(dim=-1, keepdim=True)
    out = field(pts, unit[:, None, :].expand(r, n, 3).reshape(-1, 3))
    return {"sigma": out["sigma"].reshape(r, n), "rgb": out["rgb"].reshape(r, n, 3),
            "embedding": out["embedding"].reshape(r, n, -1)}


def render_samples(field: EmbeddingField, origins: torch.Tensor, dirs: torch.Tensor,
                   t: torch.Tensor) -> dict[str, torch.Tensor]:
    """Volume-render the field at samples t: rgb, embedding, depth, opacity and weights."""
    vals = evaluate(field, origins, dirs, t)
    w = renderer.render_weights(vals["sigma"], t, dirs.norm(dim=-1))
    out = renderer.composite(w, t, {"rgb": vals["rgb"], "embedding": vals["embedding"]})
    out["weights"] = w
    return out


class FieldModel(nn.Module):
    """What the mapper needs from a backend.

    Constructed as ``Model(cfg, channels, shared, generator)``: its own config
    (``mapper.<name>``), the embedding channels it learns and renders (the S logits,
    then any backbone features it distils: ``mapper.distill_features``), the shared
    ``MapperConfig`` (``lambda_embedding``, ``lambda_features``) and the generator its
    initial weights are drawn from. :func:`distillation` gives its embedding losses.
    """

    field: EmbeddingField
    """The field :meth:`query` reads (the fine one if there are several)."""
    rays_per_iteration: int
    train_samples_per_ray: int
    """Field evaluations per training ray (bounds the training micro-batch)."""
    render_samples_per_ray: int
    """Field evaluations per rendered ray without measured depth (bounds a render chunk)."""
    box_holds_parameters: bool = False
    """True if the parameters are laid out over the scene box, so that moving the box
    reallocates them (:meth:`set_bounds`, under the training lock, then a new optimiser)."""

    BOX_CELL = 0.16
    """Metres: the default lattice the scene box grows on (whole cells: fewer changes)."""

    def losses(self, batch: RayBatch, near: torch.Tensor, far: torch.Tensor,
               generator: torch.Generator) -> dict[str, torch.Tensor]:
        """Training losses of a ray batch; ``total`` is minimised, ``fine_rgb_mse`` gives
        the PSNR. ``generator`` jitters the samples."""
        raise NotImplementedError

    def render_rays(self, origins: torch.Tensor, dirs: torch.Tensor, near: torch.Tensor,
                    far: torch.Tensor, depth: torch.Tensor | None = None
                    ) -> dict[str, torch.Tensor]:
        """Rendered rgb, depth, embedding (and opacity) per ray, deterministic.

        ``depth`` (R,) measured z-depth, 0 = none: a backend may use it to place
        its samples (the fast one does); without it the view is rendered from the
        field alone.
        """
        raise NotImplementedError

    def param_groups(self) -> list[dict]:
        """Adam parameter groups with their learning rates."""
        raise NotImplementedError

    def query(self, points: torch.Tensor) -> torch.Tensor:
        """Embedding logits at world points."""
        return self.field.geometry(points)[1]

    def samples_per_rendered_ray(self, with_depth: bool) -> int:
        """Field evaluations per rendered ray (with measured depth: at most the training
        layout's)."""
        if with_depth:
            return max(self.render_samples_per_ray, self.train_samples_per_ray)
        return self.render_samples_per_ray

    def box_lattice(self) -> tuple[float, int]:
        """Cell size (m) the scene box snaps to, and the most cells per axis."""
        return self.BOX_CELL, 1 << 30

    def set_bounds(self, lo: torch.Tensor, hi: torch.Tensor, keep: bool,
                   generator: torch.Generator) -> None:
        """The scene box is now [lo, hi] (on the lattice; it only grows). ``keep``: keep
        what was learnt inside the old box; new parameters are drawn from
        ``generator``. Nothing to do unless :attr:`box_holds_parameters`."""
