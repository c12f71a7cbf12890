"""Room geometry for the synthetic generator: parts, instances, support surfaces.

A room is an axis-aligned box [0, W] x [0, D] x [0, H] (world z up, floor at
z = 0). Everything inside is built from parts (yaw-rotated boxes and vertical
cylinders); each part belongs to one instance of one NYU-13 class, so the
ground-truth semantic and instance images come straight from the hit part.
:class:`RoomBuilder` holds the parts, instances, materials and free surfaces
while :mod:`.furniture` adds pieces and :func:`.scene.build_room` furnishes a room.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core.classes import CLASS_ID
from .materials import Material, MaterialBook

BOX, CYL = 0, 1

WALL_INSTANCES = (1, 2, 3, 4)  # walls at y = 0, x = W, y = D, x = 0
FLOOR_INSTANCE, CEILING_INSTANCE = 5, 6


@dataclasses.dataclass(frozen=True)
class Part:
    """One primitive: a box (half extents) or vertical cylinder (r, r, half height)."""

    kind: int
    centre: tuple[float, float, float]
    half: tuple[float, float, float]
    yaw: float
    cls: int
    inst: int
    mat: int


@dataclasses.dataclass
class Scene:
    """A furnished room: parts, materials, lights and the instance -> class table."""

    size: tuple[float, float, float]
    parts: list[Part]
    materials: list[Material]
    room_mats: tuple[int, ...]          # walls 0..3, floor, ceiling
    instances: dict[int, int]            # instance id -> NYU-13 class id
    lights: np.ndarray                   # (L, 3) point-light positions
    light_power: np.ndarray              # (L,)
    ambient: float
    seed: int = 0
    targets: list[int] = dataclasses.field(default_factory=list)  # instances worth looking at

    def instance_aabb(self, inst: int) -> np.ndarray:
        """(2, 3) world bounds of all parts of one instance."""
        box = np.array([part_aabb(p) for p in self.parts if p.inst == inst])
        if len(box) == 0:
            raise ValueError(f"instance {inst} has no parts")
        return np.stack([box[:, 0].min(0), box[:, 1].max(0)])

    def classes(self) -> set[int]:
        """NYU-13 ids present in the room (room shell included)."""
        return set(self.instances.values())

    def aabbs(self) -> np.ndarray:
        """(P, 2, 3) world axis-aligned bounds of every part."""
        return np.array([part_aabb(p) for p in self.parts]).reshape(-1, 2, 3)


def part_aabb(p: Part) -> np.ndarray:
    """World axis-aligned bounds (2, 3) of a part (yaw taken into account)."""
    c, s = abs(math.cos(p.yaw)), abs(math.sin(p.yaw))
    hx, hy, hz = p.half
    if p.kind == CYL:
        ex, ey = hx, hy
    else:
        ex, ey = c * hx + s * hy, s * hx + c * hy
    cen = np.asarray(p.centre)
    e = np.array([ex, ey, hz])
    return np.stack([cen - e, cen + e])


# ------------------------------------------------------------------ builder

@dataclasses.dataclass
class Surface:
    """A horizontal support (table top, shelf board) in its own yaw frame."""

    centre: np.ndarray   # world (x, y, z_top)
    half: tuple[float, float]
    yaw: float
    clearance: float
    shelf: bool = False                                     # a bookshelf board
    used: list = dataclasses.field(default_factory=list)   # local (x0, y0, x1, y1)


def _rot(yaw: float, x: float, y: float) -> tuple[float, float]:
    c, s = math.cos(yaw), math.sin(yaw)
    return c * x - s * y, s * x + c * y


def _overlap(a, b, margin: float = 0.0) -> bool:
    """Axis-aligned rectangles (x0, y0, x1, y1) overlap (with a margin)?"""
    return not (a[2] + margin <= b[0] or b[2] + margin <= a[0]
                or a[3] + margin <= b[1] or b[3] + margin <= a[1])


class RoomBuilder:
    """Places furniture in a room with rejection sampling; collects parts."""

    def __init__(self, rng: np.random.Generator, size: tuple[float, float, float]):
        self.rng = rng
        self.W, self.D, self.H = size
        self.mats = MaterialBook(rng)
        self.parts: list[Part] = []
        self.instances: dict[int, int] = {}
        self.footprints: list[tuple] = []
        self.surfaces: list[Surface] = []
        self.targets: list[int] = []
        self.next_inst = CEILING_INSTANCE + 1
        self.shelves = 0

    # ---- primitives
    def instance(self, cls_name: str) -> int:
        """A new instance id of NYU-13 class ``cls_name`` (parts added with it share it)."""
        i = self.next_inst
        self.next_inst += 1
        self.instances[i] = CLASS_ID[cls_name]
        return i

    def put(self, frame, kind: int, local, half, inst: int, mat: int, lyaw: float = 0.0) -> Part:
        """Add a part given in a furniture frame (x, y, z, yaw) to the room."""
        fx, fy, fz, fyaw = frame
        wx, wy = _rot(fyaw, local[0], local[1])
        p = Part(kind, (fx + wx, fy + wy, fz + local[2]), tuple(float(h) for h in half),
                 float(fyaw + lyaw), self.instances[inst], inst, mat)
        self.parts.append(p)
        return p

    def box(self, frame, x, y, z0, z1, hx, hy, inst, mat, lyaw=0.0) -> Part:
        """Box spanning heights z0..z1 (frame-relative) centred at (x, y)."""
        return self.put(frame, BOX, (x, y, 0.5 * (z0 + z1)), (hx, hy, 0.5 * (z1 - z0)),
                        inst, mat, lyaw)

    def cyl(self, frame, x, y, z0, z1, r, inst, mat) -> Part:
        return self.put(frame, CYL, (x, y, 0.5 * (z0 + z1)), (r, r, 0.5 * (z1 - z0)), inst, mat)

    def u(self, lo: float, hi: float) -> float:
        return float(self.rng.uniform(lo, hi))

    # ---- placement
    def footprint(self, x: float, y: float, yaw: float, w: float, d: float) -> tuple:
        c, s = abs(math.cos(yaw)), abs(math.sin(yaw))
        ex, ey = 0.5 * (c * w + s * d), 0.5 * (s * w + c * d)
        return (x - ex, y - ey, x + ex, y + ey)

    def free(self, fp: tuple, margin: float = 0.08) -> bool:
        if fp[0] < 0.01 or fp[1] < 0.01 or fp[2] > self.W - 0.01 or fp[3] > self.D - 0.01:
            return False
        return not any(_overlap(fp, o, margin) for o in self.footprints)

    def against_wall(self, w: float, d: float, tries: int = 40, gap: float = 0.01,
                     walls=None):
        """Frame (x, y, 0, yaw) with the piece's back (local y = -d/2) on a wall."""
        for _ in range(tries):
            k = int(self.rng.integers(4)) if walls is None else int(self.rng.choice(walls))
            L = self.W if k % 2 == 0 else self.D
            if w + 0.1 > L:
                continue
            s = self.u(w / 2 + 0.05, L - w / 2 - 0.05)
            off = d / 2 + gap
            x, y, yaw = [(s, off, 0.0), (self.W - off, s, math.pi / 2),
                         (self.W - s, self.D - off, math.pi), (off, self.D - s, -math.pi / 2)][k]
            fp = self.footprint(x, y, yaw, w, d)
            if self.free(fp):
                self.footprints.append(fp)
                return (x, y, 0.0, yaw), k
        return None, None

    def in_room(self, w: float, d: float, tries: int = 40, border: float = 0.3,
                yaw: float | None = None):
        for _ in range(tries):
            a = self.u(-math.pi, math.pi) if yaw is None else yaw
            x, y = self.u(border, self.W - border), self.u(border, self.D - border)
            fp = self.footprint(x, y, a, w, d)
            if self.free(fp):
                self.footprints.append(fp)
                return (x, y, 0.0, a)
        return None

    def coverage(self) -> float:
        return sum((f[2] - f[0]) * (f[3] - f[1]) for f in self.footprints) / (self.W * self.D)

    def surface(self, frame, x, y, z, hx, hy, clearance, shelf: bool = False) -> None:
        fx, fy, fz, fyaw = frame
        wx, wy = _rot(fyaw, x, y)
        self.surfaces.append(Surface(np.array([fx + wx, fy + wy, fz + z]), (hx, hy), fyaw,
                                     float(clearance), shelf))
