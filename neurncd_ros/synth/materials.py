"""Surface materials of the synthetic rooms: patterns and class-typical palettes.

A material names a procedural pattern (evaluated on 3D surface points by
``render.albedo``) and up to three colours; ``MaterialBook`` draws
per-instance variations of the colours each class typically has, so classes are
learnable from colour and geometry without any class having a single colour.
"""

from __future__ import annotations

import dataclasses

import numpy as np

# Texture patterns (see render.albedo).
PLAIN, WOOD, STRIPES, CHECKER, PLANKS, FABRIC, PAINTING, SCREEN, OUTSIDE, SPINE = range(10)


@dataclasses.dataclass(frozen=True)
class Material:
    """Procedural surface appearance: pattern mixing colours a, b, c (linear 0..1)."""

    pattern: int
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    c: tuple[float, float, float]
    scale: float = 1.0
    emissive: bool = False


# ------------------------------------------------------------------ palettes

def _hsv(h: float, s: float, v: float) -> tuple[float, float, float]:
    """HSV in [0, 1] to linear-ish RGB in [0, 1]."""
    h6 = (h % 1.0) * 6.0
    i = int(h6) % 6
    f = h6 - int(h6)
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    return [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]


def jitter(rng: np.random.Generator, rgb, amount: float = 0.06) -> tuple[float, float, float]:
    """A colour near ``rgb``: per-instance variation within a class palette."""
    out = np.clip(np.asarray(rgb, dtype=float) + rng.normal(0, amount, 3), 0.02, 0.98)
    return tuple(float(x) for x in out)


def _shade(rgb, k: float) -> tuple[float, float, float]:
    return tuple(float(min(max(x * k, 0.0), 1.0)) for x in rgb)


WOODS = [(0.55, 0.36, 0.20), (0.66, 0.48, 0.30), (0.40, 0.25, 0.14), (0.75, 0.60, 0.42),
         (0.30, 0.19, 0.11), (0.80, 0.68, 0.50)]
FABRICS = [(0.45, 0.47, 0.50), (0.22, 0.30, 0.50), (0.50, 0.35, 0.25), (0.30, 0.42, 0.30),
           (0.60, 0.20, 0.20), (0.70, 0.65, 0.55), (0.25, 0.25, 0.27), (0.55, 0.50, 0.62)]
PAINTS = [(0.88, 0.86, 0.80), (0.80, 0.84, 0.86), (0.86, 0.80, 0.70), (0.75, 0.82, 0.74),
          (0.90, 0.88, 0.86), (0.84, 0.76, 0.76), (0.70, 0.74, 0.82)]
LACQUERS = [(0.92, 0.92, 0.90), (0.30, 0.30, 0.32), (0.70, 0.72, 0.74), (0.85, 0.82, 0.74),
            (0.20, 0.28, 0.40)]


class MaterialBook:
    """Class-typical material choices, varied per instance."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.materials: list[Material] = []

    def add(self, m: Material) -> int:
        self.materials.append(m)
        return len(self.materials) - 1

    def pick(self, seq):
        return seq[int(self.rng.integers(len(seq)))]

    def wood(self) -> int:
        base = jitter(self.rng, self.pick(WOODS), 0.04)
        return self.add(Material(WOOD, base, _shade(base, 0.72), base,
                                 float(self.rng.uniform(6, 14))))

    def lacquer(self) -> int:
        base = jitter(self.rng, self.pick(LACQUERS), 0.03)
        return self.add(Material(PLAIN, base, _shade(base, 0.93), base, 4.0))

    def furniture_surface(self) -> int:
        return self.wood() if self.rng.random() < 0.65 else self.lacquer()

    def fabric(self, light: bool = False) -> int:
        base = jitter(self.rng, (0.85, 0.84, 0.80) if light else self.pick(FABRICS), 0.05)
        if self.rng.random() < 0.3 and not light:
            other = jitter(self.rng, self.pick(FABRICS), 0.05)
            return self.add(Material(STRIPES, base, other, base, float(self.rng.uniform(4, 10))))
        return self.add(Material(FABRIC, base, _shade(base, 0.8), base,
                                 float(self.rng.uniform(60, 120))))

    def metal(self) -> int:
        g = float(self.rng.uniform(0.15, 0.75))
        base = jitter(self.rng, (g, g, g * 1.02), 0.02)
        return self.add(Material(PLAIN, base, _shade(base, 0.9), base, 8.0))

    def vivid(self) -> int:
        """A saturated random colour for small objects (any hue: objects have no palette)."""
        base = _hsv(self.rng.random(), self.rng.uniform(0.4, 0.9), self.rng.uniform(0.35, 0.95))
        other = _hsv(self.rng.random(), self.rng.uniform(0.2, 0.8), self.rng.uniform(0.5, 1.0))
        pat = self.pick([PLAIN, PLAIN, STRIPES, CHECKER])
        return self.add(Material(pat, base, other, base, float(self.rng.uniform(8, 30))))

    def book(self) -> int:
        base = _hsv(self.rng.random(), self.rng.uniform(0.3, 0.9), self.rng.uniform(0.2, 0.85))
        band = self.pick([(0.85, 0.75, 0.35), (0.92, 0.92, 0.88), (0.1, 0.1, 0.1)])
        return self.add(Material(SPINE, base, band, base, 1.0))

    def painting(self) -> int:
        cols = [_hsv(self.rng.random(), self.rng.uniform(0.3, 0.9), self.rng.uniform(0.3, 1.0))
                for _ in range(3)]
        return self.add(Material(PAINTING, cols[0], cols[1], cols[2],
                                 float(self.rng.uniform(3, 10))))

    def screen(self, on: bool) -> int:
        if on:
            cols = [_hsv(self.rng.random(), 0.6, 0.8) for _ in range(3)]
            return self.add(Material(PAINTING, cols[0], cols[1], cols[2], 4.0, emissive=True))
        base = jitter(self.rng, (0.04, 0.045, 0.06), 0.01)
        return self.add(Material(SCREEN, base, (0.12, 0.13, 0.16), base, 1.0))

    def outside(self) -> int:
        sky = jitter(self.rng, (0.55, 0.75, 0.98), 0.05)
        ground = jitter(self.rng, self.pick([(0.35, 0.55, 0.28), (0.55, 0.55, 0.52)]), 0.05)
        return self.add(Material(OUTSIDE, sky, ground, (0.98, 0.98, 0.97),
                                 float(self.rng.uniform(2, 6)), emissive=True))

    def wall(self) -> int:
        base = jitter(self.rng, self.pick(PAINTS), 0.03)
        if self.rng.random() < 0.2:
            return self.add(Material(STRIPES, base, _shade(base, 0.9), base,
                                     float(self.rng.uniform(3, 8))))
        return self.add(Material(PLAIN, base, _shade(base, 0.94), base, 1.5))

    def floor(self) -> int:
        """Floor material: wooden planks (half the rooms), checker tiles or carpet."""
        r = self.rng.random()
        if r < 0.5:
            base = jitter(self.rng, self.pick(WOODS), 0.04)
            return self.add(Material(PLANKS, base, _shade(base, 0.75), base,
                                     float(self.rng.uniform(0.1, 0.22))))
        if r < 0.75:
            a = jitter(self.rng, self.pick([(0.8, 0.8, 0.78), (0.6, 0.55, 0.5), (0.3, 0.3, 0.32)]))
            return self.add(Material(CHECKER, a, _shade(a, 0.8), (0.35, 0.35, 0.35),
                                     float(self.rng.uniform(2.0, 4.0))))
        base = jitter(self.rng, self.pick(FABRICS), 0.05)
        return self.add(Material(FABRIC, base, _shade(base, 0.85), base, 150.0))

    def ceiling(self) -> int:
        base = jitter(self.rng, (0.93, 0.93, 0.91), 0.02)
        return self.add(Material(PLAIN, base, _shade(base, 0.96), base, 1.0))
