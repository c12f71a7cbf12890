"""Input encodings of the fields: NeRF positional encoding, spherical harmonics, tri-planes."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class PositionalEncoding(nn.Module):
    """NeRF's sin/cos encoding with ``frequencies`` octaves (2^0 .. 2^(L-1)), input included."""

    def __init__(self, frequencies: int, include_input: bool = True) -> None:
        super().__init__()
        self.include_input = include_input
        self.register_buffer("bands", 2.0 ** torch.arange(frequencies, dtype=torch.float32),
                             persistent=False)

    def out_dim(self, in_dim: int = 3) -> int:
        return in_dim * (2 * len(self.bands) + int(self.include_input))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        xb = (x[..., None, :] * self.bands[:, None]).flatten(-2)
        parts = [torch.sin(xb), torch.cos(xb)]
        if self.include_input:
            parts.insert(0, x)
        return torch.cat(parts, dim=-1)


def spherical_harmonics(d: torch.Tensor, degree: int = 3) -> torch.Tensor:
    """Real SH basis of unit directions, ``degree`` bands (1..4): cheap view encoding."""
    if not 1 <= degree <= 4:
        raise ValueError(f"spherical harmonics degree must be in 1..4, got {degree}")
    x, y, z = d.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree > 1:
        out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
    if degree > 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [1.0925484305920792 * x * y, -1.0925484305920792 * y * z,
                0.94617469575755997 * zz - 0.31539156525251999,
                -1.0925484305920792 * x * z, 0.54627421529603959 * (xx - yy)]
    if degree > 3:
        out += [0.59004358992664352 * y * (-3.0 * xx + yy), 2.8906114426405538 * x * y * z,
                0.45704579946446572 * y * (1.0 - 5.0 * zz),
                0.3731763325901154 * z * (5.0 * zz - 3.0),
                0.45704579946446572 * x * (1.0 - 5.0 * zz),
                1.4453057213202769 * z * (xx - yy), 0.59004358992664352 * x * (-xx + 3.0 * yy)]
    return torch.stack(out, dim=-1)


class TriPlane(nn.Module):
    """Multi-resolution tri-plane: features of a point from its xy, xz, yz projections.

    Each level has a fixed metric cell size (the finer ones divide the coarsest
    by an integer, so all levels share the coarse lattice); the planes' texel
    counts follow the scene box. Growing the box by whole coarse cells
    (:meth:`grow`) pads the planes: learnt texels are kept exactly, new ones
    start fresh. The three plane features of a level are multiplied (K-planes
    style), levels are concatenated. Coordinates are normalised to [-1, 1]
    over the box (texel centres at the corners: ``align_corners=True``).
    Fresh texels are drawn from the generator given to each method.
    """

    AXES = ((0, 1), (0, 2), (1, 2))

    def __init__(self, cell_sizes: list[float], channels: int, generator: torch.Generator,
                 init_scale: float = 0.1) -> None:
        super().__init__()
        if not cell_sizes or min(cell_sizes) <= 0:
            raise ValueError(f"tri-plane cell sizes must be positive, got {cell_sizes}")
        self.coarse_cell = float(cell_sizes[0])
        self.ratios = [max(1, int(round(self.coarse_cell / c))) for c in cell_sizes]
        self.channels = channels
        self.init_scale = init_scale
        self.register_buffer("cells", torch.ones(3, dtype=torch.long))  # coarse cells per axis
        self.planes = nn.ParameterList([nn.Parameter(self._fresh(2, 2, generator))
                                        for _ in range(3 * len(self.ratios))])

    @property
    def out_dim(self) -> int:
        return self.channels * len(self.ratios)

    def texels(self, level: int) -> list[int]:
        """Texel count per axis (x, y, z) of a level."""
        return [int(c) * self.ratios[level] + 1 for c in self.cells]

    def _fresh(self, h: int, w: int, generator: torch.Generator) -> torch.Tensor:
        # Mean 1 so that the product of three planes starts as a small perturbation.
        u = torch.rand(1, self.channels, h, w, generator=generator)
        return 1.0 + self.init_scale * (2 * u - 1)

    @torch.no_grad()
    def allocate(self, coarse_cells: list[int], generator: torch.Generator) -> None:
        """Fresh planes for a box of ``coarse_cells`` coarse cells per axis."""
        self.cells.copy_(torch.as_tensor(coarse_cells, dtype=torch.long))
        for lvl in range(len(self.ratios)):
            n = self.texels(lvl)
            for k, (a, b) in enumerate(self.AXES):
                self.planes[3 * lvl + k] = nn.Parameter(self._fresh(n[b], n[a], generator))

    @torch.no_grad()
    def grow(self, pad_lo: list[int], pad_hi: list[int], generator: torch.Generator) -> None:
        """Extend the box by whole coarse cells below/above on each axis, keeping all texels."""
        pad_lo, pad_hi = [int(p) for p in pad_lo], [int(p) for p in pad_hi]
        if min(pad_lo + pad_hi) < 0:
            raise ValueError(f"tri-plane can only grow, got pads {pad_lo}, {pad_hi}")
        for lvl, q in enumerate(self.ratios):
            for k, (a, b) in enumerate(self.AXES):
                old = self.planes[3 * lvl + k].detach()
                h, w = old.shape[-2:]
                new = self._fresh(h + q * (pad_lo[b] + pad_hi[b]),
                                  w + q * (pad_lo[a] + pad_hi[a]), generator)
                new[..., q * pad_lo[b]:q * pad_lo[b] + h, q * pad_lo[a]:q * pad_lo[a] + w] = old
                self.planes[3 * lvl + k] = nn.Parameter(new)
        self.cells += torch.as_tensor(pad_lo) + torch.as_tensor(pad_hi)

    def forward(self, xyz: torch.Tensor) -> torch.Tensor:
        n = xyz.shape[0]
        feats = []
        for lvl in range(len(self.ratios)):
            f = None
            for k, (a, b) in enumerate(self.AXES):
                grid = xyz[:, [a, b]].reshape(1, 1, n, 2)
                s = F.grid_sample(self.planes[3 * lvl + k], grid, mode="bilinear",
                                  padding_mode="border", align_corners=True)[0, :, 0]  # (C, N)
                f = s if f is None else f * s
            feats.append(f)
        return torch.cat(feats, dim=0).T
