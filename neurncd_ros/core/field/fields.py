"""Embedding-NeRF fields F(x, d) = (c, e, sigma).

Density ``sigma`` and the embedding logits ``e`` depend on position only; the
colour ``c`` also sees the view direction, which enters after the embedding
head (Semantic-NeRF's layout), so the embedding is view-independent.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .encoding import PositionalEncoding, TriPlane, spherical_harmonics


def linear(n_in: int, n_out: int, generator: torch.Generator) -> nn.Linear:
    """``nn.Linear(n_in, n_out)`` with torch's default init drawn from ``generator``.

    The layer is built without touching the global generator (``skip_init``), then
    initialised as ``nn.Linear.reset_parameters`` does: Kaiming-uniform weights
    (a = sqrt 5) and biases uniform in +-1/sqrt(n_in).
    """
    layer = nn.utils.skip_init(nn.Linear, n_in, n_out)
    with torch.no_grad():
        nn.init.kaiming_uniform_(layer.weight, a=math.sqrt(5), generator=generator)
        bound = 1.0 / math.sqrt(n_in) if n_in > 0 else 0.0
        layer.bias.uniform_(-bound, bound, generator=generator)
    return layer


class EmbeddingField(nn.Module):
    """Interface of both fields: points (N, 3) world, directions (N, 3) unit."""

    channels: int

    def geometry(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Density (N,), embedding logits (N, S) and a feature for the colour head."""
        raise NotImplementedError

    def colour(self, feature: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def density(self, x: torch.Tensor) -> torch.Tensor:
        return self.geometry(x)[0]

    def forward(self, x: torch.Tensor, d: torch.Tensor) -> dict[str, torch.Tensor]:
        sigma, emb, feat = self.geometry(x)
        return {"sigma": sigma, "embedding": emb, "rgb": self.colour(feat, d)}


class NerfField(EmbeddingField):
    """Semantic-NeRF's MLP: 8 x 256 ReLU layers, input re-injected after layer 4.

    Positional encoding with 10 position / 4 direction octaves plus the raw input;
    the embedding head (256 -> 128 -> S) and the density read the trunk before
    the view direction joins the colour branch (256 + 27 -> 128 -> 3).
    World coordinates are used as they are (as Semantic-NeRF does). Initial
    weights are drawn from ``generator``.
    """

    def __init__(self, channels: int, generator: torch.Generator, depth: int = 8,
                 width: int = 256, skip: int = 4, pos_freq: int = 10,
                 dir_freq: int = 4) -> None:
        super().__init__()
        self.channels = channels
        self.pos_enc, self.dir_enc = PositionalEncoding(pos_freq), PositionalEncoding(dir_freq)
        pin, din = self.pos_enc.out_dim(), self.dir_enc.out_dim()
        self.skip = skip
        g = generator
        layers = []
        for i in range(depth):
            fan_in = pin if i == 0 else width + (pin if i == skip + 1 else 0)
            layers.append(linear(fan_in, width, g))
        self.trunk = nn.ModuleList(layers)
        self.sigma_head = linear(width, 1, g)
        self.embedding_head = nn.Sequential(linear(width, width // 2, g), nn.ReLU(),
                                            linear(width // 2, channels, g))
        self.feature = linear(width, width, g)
        self.colour_head = nn.Sequential(linear(width + din, width // 2, g), nn.ReLU(),
                                         linear(width // 2, 3, g))

    def geometry(self, x):
        px = self.pos_enc(x)
        h = px
        for i, layer in enumerate(self.trunk):
            if i == self.skip + 1:
                h = torch.cat([px, h], dim=-1)
            h = torch.relu(layer(h))
        sigma = torch.relu(self.sigma_head(h)[..., 0])
        return sigma, self.embedding_head(h), self.feature(h)

    def colour(self, feature, d):
        return torch.sigmoid(self.colour_head(torch.cat([feature, self.dir_enc(d)], dim=-1)))


class TriPlaneField(EmbeddingField):
    """CPU-friendly field: multi-resolution tri-plane features and two tiny MLP heads.

    Points are normalised into [-1, 1] by the scene AABB (buffers ``lo``/``hi``,
    grown by :meth:`set_bounds`). Density uses an exponential activation (sharp
    surfaces need a large dynamic range); colour sees SH of the direction.
    Initial weights and planes are drawn from ``generator``.
    """

    def __init__(self, channels: int, cell_sizes: list[float], generator: torch.Generator,
                 plane_channels: int = 8, hidden: int = 64, geo_features: int = 15,
                 sh_degree: int = 3) -> None:
        super().__init__()
        self.channels = channels
        self.sh_degree = sh_degree
        self.register_buffer("lo", -torch.ones(3))
        self.register_buffer("hi", torch.ones(3))
        g = generator
        self.planes = TriPlane(cell_sizes, plane_channels, g)
        self.trunk = nn.Sequential(linear(self.planes.out_dim, hidden, g), nn.ReLU(),
                                   linear(hidden, hidden, g), nn.ReLU())
        self.sigma_head = linear(hidden, 1, g)
        self.embedding_head = linear(hidden, channels, g)
        self.geo_head = linear(hidden, geo_features, g)
        self.colour_head = nn.Sequential(linear(geo_features + sh_degree ** 2, hidden, g),
                                         nn.ReLU(), linear(hidden, 3, g))

    def normalise(self, x: torch.Tensor) -> torch.Tensor:
        return 2 * (x - self.lo) / (self.hi - self.lo) - 1

    def geometry(self, x):
        h = self.trunk(self.planes(self.normalise(x)))
        sigma = torch.exp(torch.clamp(self.sigma_head(h)[..., 0], max=12.0))
        return sigma, self.embedding_head(h), self.geo_head(h)

    def colour(self, feature, d):
        sh = spherical_harmonics(d, self.sh_degree)
        return torch.sigmoid(self.colour_head(torch.cat([feature, sh], dim=-1)))

    @property
    def cell(self) -> float:
        """Coarse cell size: the box grows in whole cells so texels are kept exactly."""
        return self.planes.coarse_cell

    @torch.no_grad()
    def set_bounds(self, lo: torch.Tensor, hi: torch.Tensor, generator: torch.Generator,
                   keep: bool = True) -> None:
        """Move the AABB (corners on the coarse lattice); ``keep`` pads the learnt planes,
        otherwise fresh planes are allocated (new texels drawn from ``generator``).
        Creates new plane tensors either way."""
        lo, hi = lo.to(self.lo), hi.to(self.hi)
        cells = torch.round((hi - lo) / self.cell).long()
        if keep:
            pad_lo = torch.round((self.lo - lo) / self.cell).long()
            pad_hi = cells - self.planes.cells - pad_lo
            self.planes.grow(pad_lo.tolist(), pad_hi.tolist(), generator)
        else:
            self.planes.allocate(cells.tolist(), generator)
        self.lo.copy_(lo)
        self.hi.copy_(lo + cells.to(lo) * self.cell)
