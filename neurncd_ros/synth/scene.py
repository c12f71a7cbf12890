"""Procedural room layouts for the synthetic generator: parts, instances, lights.

A room is an axis-aligned box [0, W] x [0, D] x [0, H] (world z up, floor at
z = 0). Everything inside is built from parts (yaw-rotated boxes and vertical
cylinders); each part belongs to one instance of one NYU-13 class, so the
ground-truth semantic and instance images come straight from the hit part.
Large pieces are placed by rejection on their floor footprints; wall-mounted
pieces by rejection on 3D bounding boxes; small things on support surfaces.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..core.classes import CLASS_ID
from .materials import PLAIN, Material, MaterialBook, jitter

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


# ------------------------------------------------------------------ furniture

def build_bed(b: RoomBuilder) -> bool:
    wide = b.rng.random() < 0.6 and min(b.W, b.D) > 3.2
    w = b.u(1.4, 1.8) if wide else b.u(0.9, 1.1)
    d = b.u(1.95, 2.15)
    frame, _ = b.against_wall(w + 0.08, d + 0.05)
    if frame is None:
        return False
    inst = b.instance("bed")
    wood = b.mats.furniture_surface()
    hf = b.u(0.22, 0.35)
    b.box(frame, 0, 0.02, 0.0, hf, w / 2 + 0.04, d / 2, inst, wood)
    head_h = b.u(0.8, 1.15)
    b.box(frame, 0, -d / 2 - 0.0, 0.0, head_h, w / 2 + 0.04, 0.025, inst, wood)
    mt = b.u(0.16, 0.24)
    b.box(frame, 0, 0.03, hf, hf + mt, w / 2 - 0.01, d / 2 - 0.04, inst, b.mats.fabric(light=True))
    blanket = b.mats.fabric()
    bl = d * b.u(0.55, 0.7)
    b.box(frame, 0, d / 2 - bl / 2 + 0.02, hf + mt - 0.05, hf + mt + 0.03, w / 2 + 0.015,
          bl / 2, inst, blanket)
    pillow = b.mats.fabric(light=b.rng.random() < 0.6)
    n = 2 if wide else 1
    pw = (w - 0.15) / n
    for i in range(n):
        px = -w / 2 + 0.075 + pw * (i + 0.5)
        b.box(frame, px, -d / 2 + 0.28, hf + mt, hf + mt + b.u(0.1, 0.15), pw / 2 - 0.04,
              0.2, inst, pillow)
    b.targets.append(inst)
    # nightstand beside the bed sometimes
    if b.rng.random() < 0.6:
        side = 1 if b.rng.random() < 0.5 else -1
        ns = b.u(0.4, 0.5)
        fx, fy, _, fyaw = frame
        ox, oy = _rot(fyaw, side * (w / 2 + 0.1 + ns / 2), -d / 2 + ns / 2 + 0.02)
        fp = b.footprint(fx + ox, fy + oy, fyaw, ns, ns)
        if b.free(fp, 0.0):
            b.footprints.append(fp)
            nframe = (fx + ox, fy + oy, 0.0, fyaw)
            build_cabinet(b, nframe, ns, ns, b.u(0.45, 0.6), drawers=2)
    return True


def build_sofa(b: RoomBuilder, small: bool = False) -> bool:
    """Sofa against a wall (``small``: a one-seat armchair for crowded rooms)."""
    if small:
        w = b.u(0.75, 1.0)
    else:
        w = b.u(1.4, 2.3) if min(b.W, b.D) > 3.5 else b.u(1.2, 1.6)
    d = b.u(0.8, 0.95)
    frame, _ = b.against_wall(w, d, gap=b.u(0.02, 0.15))
    if frame is None:
        return False
    inst = b.instance("sofa")
    fab = b.mats.fabric()
    arm = b.u(0.12, 0.22)
    base_h = b.u(0.22, 0.3)
    back_t = b.u(0.15, 0.22)
    b.box(frame, 0, 0, 0.04, base_h, w / 2, d / 2, inst, fab)
    legs = b.mats.wood()
    for sx in (-1, 1):
        for sy in (-1, 1):
            b.box(frame, sx * (w / 2 - 0.06), sy * (d / 2 - 0.06), 0.0, 0.04, 0.025, 0.025,
                  inst, legs)
    b.box(frame, 0, -d / 2 + back_t / 2, base_h, b.u(0.78, 0.92), w / 2, back_t / 2, inst, fab)
    arm_h = b.u(0.55, 0.68)
    for sx in (-1, 1):
        b.box(frame, sx * (w / 2 - arm / 2), 0.0, base_h, arm_h, arm / 2, d / 2, inst, fab)
    n = 1 if w < 1.1 else 2 if w < 1.8 else 3
    cw = (w - 2 * arm) / n
    cush = b.mats.fabric() if b.rng.random() < 0.3 else fab
    ct = b.u(0.1, 0.16)
    for i in range(n):
        cx = -w / 2 + arm + cw * (i + 0.5)
        b.box(frame, cx, back_t / 2, base_h, base_h + ct, cw / 2 - 0.008,
              (d - back_t) / 2 - 0.01, inst, cush)
    b.targets.append(inst)
    # coffee table in front of it
    if b.rng.random() < 0.7:
        tw, td = min(w * 0.6, 1.2), b.u(0.45, 0.65)
        fx, fy, _, fyaw = frame
        ox, oy = _rot(fyaw, 0.0, d / 2 + 0.4 + td / 2)
        fp = b.footprint(fx + ox, fy + oy, fyaw, tw, td)
        if b.free(fp):
            b.footprints.append(fp)
            build_table(b, (fx + ox, fy + oy, 0.0, fyaw), tw, td, b.u(0.38, 0.46))
    return True


def build_chair(b: RoomBuilder, frame) -> None:
    inst = b.instance("chair")
    s = b.u(0.4, 0.48)
    sh = b.u(0.42, 0.48)
    seat_mat = b.mats.wood() if b.rng.random() < 0.5 else b.mats.fabric()
    leg_mat = b.mats.metal() if b.rng.random() < 0.4 else b.mats.wood()
    st = b.u(0.03, 0.06)
    b.box(frame, 0, 0, sh - st, sh, s / 2, s / 2, inst, seat_mat)
    lr = b.u(0.014, 0.022)
    round_legs = b.rng.random() < 0.5
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (s / 2 - 0.03), sy * (s / 2 - 0.03)
            if round_legs:
                b.cyl(frame, x, y, 0.0, sh - st, lr, inst, leg_mat)
            else:
                b.box(frame, x, y, 0.0, sh - st, lr, lr, inst, leg_mat)
    bh = b.u(0.35, 0.5)
    for sx in (-1, 1):
        b.box(frame, sx * (s / 2 - 0.03), -s / 2 + 0.02, sh, sh + bh, 0.018, 0.018, inst,
              leg_mat)
    b.box(frame, 0, -s / 2 + 0.02, sh + bh * 0.45, sh + bh, s / 2 - 0.01, 0.015, inst, seat_mat)
    b.targets.append(inst)


def build_table(b: RoomBuilder, frame, w: float, d: float, h: float, round_top: bool = False):
    inst = b.instance("table")
    top = b.mats.furniture_surface()
    legs = b.mats.metal() if b.rng.random() < 0.35 else top
    tt = b.u(0.025, 0.05)
    if round_top:
        r = min(w, d) / 2
        b.cyl(frame, 0, 0, h - tt, h, r, inst, top)
        b.cyl(frame, 0, 0, 0.03, h - tt, b.u(0.03, 0.05), inst, legs)
        b.cyl(frame, 0, 0, 0.0, 0.03, r * 0.55, inst, legs)
        b.surface(frame, 0, 0, h, r * 0.68, r * 0.68, 0.6)
    else:
        b.box(frame, 0, 0, h - tt, h, w / 2, d / 2, inst, top)
        lw = b.u(0.02, 0.035)
        for sx in (-1, 1):
            for sy in (-1, 1):
                b.box(frame, sx * (w / 2 - lw - 0.03), sy * (d / 2 - lw - 0.03), 0.0, h - tt,
                      lw, lw, inst, legs)
        b.surface(frame, 0, 0, h, w / 2 - 0.03, d / 2 - 0.03, 0.6)
    b.targets.append(inst)
    return inst


def build_cabinet(b: RoomBuilder, frame, w: float, d: float, h: float, drawers: int = 0,
                  doors: int = 0) -> int:
    inst = b.instance("furniture")
    body = b.mats.furniture_surface()
    front = b.mats.lacquer() if b.rng.random() < 0.3 else body
    handle = b.mats.metal()
    b.box(frame, 0, 0, 0.0, h, w / 2, d / 2, inst, body)
    if drawers:
        dh = (h - 0.08) / drawers
        for i in range(drawers):
            z0 = 0.05 + i * dh
            b.box(frame, 0, d / 2 + 0.008, z0 + 0.01, z0 + dh - 0.01, w / 2 - 0.02, 0.008, inst,
                  front)
            b.box(frame, 0, d / 2 + 0.025, z0 + dh / 2 - 0.01, z0 + dh / 2 + 0.01, 0.05, 0.01,
                  inst, handle)
    elif doors:
        dw = (w - 0.04) / doors
        for i in range(doors):
            x = -w / 2 + 0.02 + dw * (i + 0.5)
            b.box(frame, x, d / 2 + 0.008, 0.05, h - 0.03, dw / 2 - 0.006, 0.008, inst, front)
            hx = x + (dw / 2 - 0.06) * (1 if i % 2 == 0 else -1)
            b.box(frame, hx, d / 2 + 0.025, h * 0.5 - 0.08, h * 0.5 + 0.08, 0.01, 0.01, inst,
                  handle)
    b.surface(frame, 0, 0, h, w / 2 - 0.03, d / 2 - 0.03, max(0.3, b.H - h - 0.1))
    b.targets.append(inst)
    return inst


def build_shelf(b: RoomBuilder, frame, w: float, d: float, h: float) -> int:
    inst = b.instance("furniture")
    b.shelves += 1
    mat = b.mats.furniture_surface()
    back = b.mats.lacquer() if b.rng.random() < 0.4 else mat
    t = 0.02
    for sx in (-1, 1):
        b.box(frame, sx * (w / 2 - t / 2), 0, 0.0, h - t / 2, t / 2, d / 2, inst, mat)
    b.box(frame, 0, -d / 2 + 0.005, 0.0, h - t / 2, w / 2 - t, 0.005, inst, back)
    n = int(b.rng.integers(3, 6)) if h > 1.3 else int(b.rng.integers(2, 4))
    zs = np.linspace(0.05, h - t, n + 1)
    for k, z in enumerate(zs):
        b.box(frame, 0, 0.005, z - t / 2 if k else 0.0, z + t / 2, w / 2 - t, d / 2 - 0.005, inst,
              mat)
        if k < n:
            b.surface(frame, 0, 0.005, z + t / 2, w / 2 - t - 0.01, d / 2 - 0.015,
                      zs[k + 1] - z - t, shelf=True)
    b.surface(frame, 0, 0, h - t / 2, w / 2 - t - 0.01, d / 2 - 0.02, max(0.3, b.H - h - 0.1))
    b.targets.append(inst)
    return inst


def build_desk(b: RoomBuilder, frame, w: float, d: float) -> int:
    inst = b.instance("furniture")
    mat = b.mats.furniture_surface()
    h = b.u(0.72, 0.76)
    b.box(frame, 0, 0, h - 0.03, h, w / 2, d / 2, inst, mat)
    pw = b.u(0.35, 0.45)
    side = 1 if b.rng.random() < 0.5 else -1
    b.box(frame, side * (w / 2 - pw / 2), 0, 0.0, h - 0.03, pw / 2, d / 2 - 0.01, inst, mat)
    b.box(frame, -side * (w / 2 - 0.015), 0, 0.0, h - 0.03, 0.015, d / 2 - 0.01, inst, mat)
    handle = b.mats.metal()
    for i in range(3):
        z = 0.12 + i * (h - 0.15) / 3
        b.box(frame, side * (w / 2 - pw / 2), d / 2 + 0.01, z + 0.08, z + 0.1, 0.05, 0.01, inst,
              handle)
    b.surface(frame, 0, 0, h, w / 2 - 0.03, d / 2 - 0.03, 0.6)
    b.targets.append(inst)
    return inst


def build_tv(b: RoomBuilder, frame, width: float, z_bottom: float, on_stand: bool) -> int:
    """TV facing local +y: its back on the plane y = 0 (wall), or centred on y = 0 and
    standing on a foot at z_bottom - 0.075 (stand)."""
    inst = b.instance("tv")
    h = width * 9 / 16
    body = b.mats.add(Material(PLAIN, jitter(b.rng, (0.05, 0.05, 0.06), 0.015),
                               (0.1, 0.1, 0.11), (0.05, 0.05, 0.05), 3.0))
    screen = b.mats.screen(on=b.rng.random() < 0.3)
    th = b.u(0.03, 0.06)
    y0 = -th / 2 if on_stand else 0.0
    b.box(frame, 0, y0 + th / 2, z_bottom, z_bottom + h, width / 2, th / 2, inst, body)
    b.box(frame, 0, y0 + th + 0.003, z_bottom + 0.02, z_bottom + h - 0.02, width / 2 - 0.02,
          0.003, inst, screen)
    if on_stand:
        b.box(frame, 0, y0 + th / 2, z_bottom - 0.06, z_bottom, 0.04, 0.03, inst, body)
        b.box(frame, 0, y0 + th / 2, z_bottom - 0.075, z_bottom - 0.06, width * 0.15, 0.09, inst,
              body)
    b.targets.append(inst)
    return inst


def wall_frame(b: RoomBuilder, k: int, s: float, off: float = 0.0):
    """Frame on wall k at distance s along it, local y pointing into the room."""
    x, y, yaw = [(s, off, 0.0), (b.W - off, s, math.pi / 2), (b.W - s, b.D - off, math.pi),
                 (off, b.D - s, -math.pi / 2)][k]
    return (x, y, 0.0, yaw)


def _wall_free(b: RoomBuilder, new_parts_start: int, margin: float = 0.03) -> bool:
    """Do the parts added since ``new_parts_start`` stay clear of all earlier parts?"""
    new = np.array([part_aabb(p) for p in b.parts[new_parts_start:]])
    old = np.array([part_aabb(p) for p in b.parts[:new_parts_start]])
    if len(old) == 0:
        return True
    lo, hi = new[:, None, 0], new[:, None, 1]
    hit = np.all(lo < old[None, :, 1] + margin, -1) & np.all(old[None, :, 0] < hi + margin, -1)
    return not bool(hit.any())


def _try_wall_item(b: RoomBuilder, builder, w: float, z0: float, z1: float, tries: int = 30,
                   cls_name: str = "") -> int | None:
    """Place an item of width w spanning z0..z1 on some wall, rejecting overlaps."""
    for _ in range(tries):
        k = int(b.rng.integers(4))
        L = b.W if k % 2 == 0 else b.D
        if w + 0.3 > L:
            continue
        s = b.u(w / 2 + 0.15, L - w / 2 - 0.15)
        start, n_inst, n_next = len(b.parts), dict(b.instances), b.next_inst
        n_targets = len(b.targets)
        builder(wall_frame(b, k, s))
        if _wall_free(b, start):
            return k
        del b.parts[start:]
        b.instances, b.next_inst = n_inst, n_next
        del b.targets[n_targets:]
    return None


def build_window(b: RoomBuilder) -> bool:
    w = b.u(0.7, 1.6)
    sill = b.u(0.75, 1.0)
    top = min(b.H - 0.25, sill + b.u(0.9, 1.5))
    curtains = b.rng.random() < 0.5

    def make(frame):
        inst = b.instance("window")
        glass = b.mats.outside()
        fr = b.mats.lacquer() if b.rng.random() < 0.6 else b.mats.wood()
        b.box(frame, 0, 0.004, sill, top, w / 2, 0.004, inst, glass)
        ft, fd = 0.05, b.u(0.03, 0.06)
        for sx in (-1, 1):
            b.box(frame, sx * (w / 2 - ft / 2), fd / 2, sill, top, ft / 2, fd / 2, inst, fr)
        b.box(frame, 0, fd / 2, top - ft, top, w / 2 - ft, fd / 2, inst, fr)
        b.box(frame, 0, 0.08, sill - 0.03, sill + 0.0, w / 2 + 0.05, 0.08, inst, fr)
        b.box(frame, 0, fd / 2, sill, sill + ft, w / 2 - ft, fd / 2, inst, fr)
        if w > 1.0:
            b.box(frame, 0, fd / 2, sill + ft, top - ft, 0.02, fd / 2, inst, fr)
        if curtains:
            cm = b.mats.fabric()
            cw = b.u(0.2, 0.35)
            for sx in (-1, 1):
                b.box(frame, sx * (w / 2 + cw / 2 + 0.02), 0.09, max(0.05, sill - 0.6),
                      min(b.H - 0.05, top + 0.15), cw / 2, 0.03, inst, cm)
        b.targets.append(inst)
    k = _try_wall_item(b, make, w + (0.8 if curtains else 0.1), sill - 0.03, top)
    if k is None:
        return False
    # Keep the floor in front of the window free so no furniture enters the sill/curtains.
    box = np.array([part_aabb(p) for p in b.parts if p.inst == b.next_inst - 1])
    b.footprints.append((box[:, 0, 0].min(), box[:, 0, 1].min(), box[:, 1, 0].max(),
                         box[:, 1, 1].max()))
    return True


def build_door(b: RoomBuilder) -> bool:
    """A closed door in a wall (NYU-40 'door' is part of NYU-13 'wall')."""
    w, h = b.u(0.78, 0.95), b.u(1.98, min(2.15, b.H - 0.15))

    def make(frame):
        inst = b.instance("wall")
        panel = b.mats.wood() if b.rng.random() < 0.5 else b.mats.lacquer()
        trim = b.mats.lacquer()
        b.box(frame, 0, 0.02, 0.0, h, w / 2, 0.02, inst, panel)
        for sx in (-1, 1):
            b.box(frame, sx * (w / 2 + 0.035), 0.012, 0.0, h + 0.07, 0.035, 0.012, inst, trim)
        b.box(frame, 0, 0.012, h, h + 0.07, w / 2, 0.012, inst, trim)
        hx = (w / 2 - 0.08) * (1 if b.rng.random() < 0.5 else -1)
        b.box(frame, hx, 0.055, 0.98, 1.0, 0.06, 0.015, inst, b.mats.metal())
    k = _try_wall_item(b, make, w + 0.2, 0.0, h + 0.07)
    if k is None:
        return False
    box = np.array([part_aabb(p) for p in b.parts if p.inst == b.next_inst - 1])
    lo, hi = box[:, 0].min(0), box[:, 1].max(0)
    # keep the swing of the door free of furniture
    fp = [lo[0], lo[1], hi[0], hi[1]]
    if k == 0:
        fp[3] += w
    elif k == 1:
        fp[0] -= w
    elif k == 2:
        fp[1] -= w
    else:
        fp[2] += w
    b.footprints.append(tuple(fp))
    return True


def build_picture(b: RoomBuilder) -> bool:
    w, h = b.u(0.3, 1.1), b.u(0.3, 0.8)
    zc = b.u(1.2, min(1.75, b.H - h / 2 - 0.2))

    def make(frame):
        inst = b.instance("picture")
        fr = b.mats.wood() if b.rng.random() < 0.5 else b.mats.lacquer()
        fd = b.u(0.015, 0.04)
        b.box(frame, 0, fd / 2, zc - h / 2, zc + h / 2, w / 2, fd / 2, inst, fr)
        bw = b.u(0.02, 0.06)
        b.box(frame, 0, fd + 0.002, zc - h / 2 + bw, zc + h / 2 - bw, w / 2 - bw, 0.002, inst,
              b.mats.painting())
        b.targets.append(inst)
    return _try_wall_item(b, make, w, zc - h / 2, zc + h / 2) is not None


def build_wall_tv(b: RoomBuilder) -> bool:
    w = b.u(0.8, 1.3)
    zb = b.u(0.9, 1.3)

    def make(frame):
        build_tv(b, frame, w, zb, on_stand=False)
    return _try_wall_item(b, make, w, zb, zb + w * 9 / 16) is not None


# ------------------------------------------------------------------ small things

def _surface_slot(b: RoomBuilder, s: Surface, w: float, d: float, tries: int = 12):
    """Local (x, y) centre of a free w x d spot on a surface, or None."""
    hx, hy = s.half
    if w / 2 > hx or d / 2 > hy:
        return None
    for _ in range(tries):
        x, y = b.u(-hx + w / 2, hx - w / 2), b.u(-hy + d / 2, hy - d / 2)
        r = (x - w / 2, y - d / 2, x + w / 2, y + d / 2)
        if not any(_overlap(r, o, 0.01) for o in s.used):
            s.used.append(r)
            return x, y
    return None


def _sframe(s: Surface):
    return (float(s.centre[0]), float(s.centre[1]), float(s.centre[2]), s.yaw)


def place_object(b: RoomBuilder, s: Surface) -> bool:
    """A small object (box, cup, vase, lamp) on a surface."""
    kind = b.rng.random()
    maxh = s.clearance - 0.03
    if maxh < 0.06:
        return False
    if kind < 0.35:
        w, d, h = b.u(0.06, 0.3), b.u(0.06, 0.25), b.u(0.04, min(0.25, maxh))
        yaw = b.u(-0.3, 0.3)
        c, sn = math.cos(yaw), abs(math.sin(yaw))
        xy = _surface_slot(b, s, c * w + sn * d, sn * w + c * d)
        if xy is None:
            return False
        inst = b.instance("objects")
        b.box(_sframe(s), xy[0], xy[1], 0.0, h, w / 2, d / 2, inst, b.mats.vivid(), lyaw=yaw)
    elif kind < 0.75:
        r, h = b.u(0.03, 0.09), b.u(0.06, min(0.35, maxh))
        xy = _surface_slot(b, s, 2 * r, 2 * r)
        if xy is None:
            return False
        inst = b.instance("objects")
        b.cyl(_sframe(s), xy[0], xy[1], 0.0, h, r, inst, b.mats.vivid())
    else:
        if maxh < 0.35:
            return False
        r = b.u(0.08, 0.15)
        xy = _surface_slot(b, s, 2 * r, 2 * r)
        if xy is None:
            return False
        inst = b.instance("objects")
        h = b.u(0.3, min(0.55, maxh))
        f = _sframe(s)
        base = b.mats.metal() if b.rng.random() < 0.5 else b.mats.vivid()
        b.cyl(f, xy[0], xy[1], 0.0, 0.03, r * 0.7, inst, base)
        b.cyl(f, xy[0], xy[1], 0.03, h - 0.15, 0.012, inst, base)
        b.cyl(f, xy[0], xy[1], h - 0.18, h, r, inst, b.mats.fabric(light=True))
    b.targets.append(inst)
    return True


def place_books(b: RoomBuilder, s: Surface, standing: bool) -> int:
    """A row of standing books along a shelf, or a flat stack on a table."""
    f = _sframe(s)
    hx, hy = s.half
    n = 0
    if standing:
        fill = b.u(0.45, 0.95)
        x = -hx + b.u(0.0, 0.1)
        end = -hx + 2 * hx * fill
        maxh = min(0.32, s.clearance - 0.02)
        if maxh < 0.12:
            return 0
        while x < end:
            t = b.u(0.015, 0.05)
            if x + t > hx:
                break
            h = b.u(0.12, maxh)
            dd = b.u(0.12, min(0.26, 2 * hy))
            inst = b.instance("books")
            b.box(f, x + t / 2, -hy + dd / 2, 0.0, h, t / 2, dd / 2, inst, b.mats.book())
            n += 1
            x += t + (b.u(0.04, 0.15) if b.rng.random() < 0.08 else 0.001)
        s.used.append((-hx, -hy, x, hy))
        return n
    w, d = b.u(0.15, 0.25), b.u(0.2, 0.3)
    # the stack is jittered by up to 1 cm and 0.15 rad: reserve the rotated extent
    xy = _surface_slot(b, s, w + 0.15 * d + 0.03, d + 0.15 * w + 0.03)
    if xy is None:
        return 0
    z = 0.0
    for _ in range(int(b.rng.integers(2, 6))):
        t = b.u(0.015, 0.05)
        if z + t > s.clearance - 0.02:
            break
        inst = b.instance("books")
        b.box(f, xy[0] + b.u(-0.01, 0.01), xy[1] + b.u(-0.01, 0.01), z, z + t,
              w / 2 * b.u(0.85, 1.0), d / 2 * b.u(0.85, 1.0), inst, b.mats.book(),
              lyaw=b.u(-0.15, 0.15))
        z += t
        n += 1
    return n


def place_floor_object(b: RoomBuilder) -> bool:
    r = b.u(0.1, 0.2)
    plant = b.rng.random() >= 0.5
    leaf_r = r * b.u(1.1, 1.6) if plant else r
    frame = b.in_room(2 * leaf_r, 2 * leaf_r, border=leaf_r + 0.05)
    if frame is None:
        return False
    inst = b.instance("objects")
    if not plant:
        b.cyl(frame, 0, 0, 0.0, b.u(0.25, 0.4), r, inst, b.mats.vivid())
    else:
        pot = b.mats.vivid()
        ph = b.u(0.2, 0.35)
        b.cyl(frame, 0, 0, 0.0, ph, r, inst, pot)
        leaf = b.mats.add(Material(PLAIN, jitter(b.rng, (0.2, 0.45, 0.18), 0.05),
                                   (0.12, 0.3, 0.1), (0.2, 0.4, 0.2), 25.0))
        b.cyl(frame, 0, 0, ph, ph + b.u(0.3, 0.7), leaf_r, inst, leaf)
    b.targets.append(inst)
    return True


# ------------------------------------------------------------------ room

def _ensure_classes(b: RoomBuilder, names: tuple[str, ...], tries: int = 4) -> None:
    """Retry (smaller) pieces of any large class that found no room the first time."""
    def have(name: str) -> bool:
        return CLASS_ID[name] in b.instances.values()

    def small_table() -> bool:
        w, d = b.u(0.6, 0.9), b.u(0.5, 0.7)
        fr = b.in_room(w, d, border=0.5)
        if fr is None:                      # a side table against a wall
            w = d = b.u(0.4, 0.55)
            fr, _ = b.against_wall(w, d)
        return fr is not None and build_table(b, fr, w, d, b.u(0.5, 0.76)) > 0

    def small_cabinet() -> bool:
        w, d, h = b.u(0.5, 0.8), b.u(0.35, 0.45), b.u(0.5, 0.9)
        fr, _ = b.against_wall(w, d)
        return fr is not None and build_cabinet(b, fr, w, d, h, drawers=2) > 0

    def lone_chair() -> bool:
        fr = b.in_room(0.55, 0.55)
        if fr is not None:
            build_chair(b, fr)
        return fr is not None

    def floor_obj() -> bool:
        return place_floor_object(b)
    fixes = {"bed": lambda: build_bed(b), "sofa": lambda: build_sofa(b, small=True),
             "table": small_table,
             "furniture": small_cabinet, "chair": lone_chair, "tv": lambda: build_wall_tv(b),
             "picture": lambda: build_picture(b), "window": lambda: build_window(b),
             "objects": floor_obj}
    for name in names:
        for _ in range(tries):
            if have(name) or fixes[name]():
                break
    for _ in range(tries if "furniture" in names else 0):   # books need a bookshelf
        if b.shelves:
            break
        w, d, h = b.u(0.5, 0.8), b.u(0.26, 0.32), b.u(0.8, 1.3)
        fr, _ = b.against_wall(w, d)
        if fr is not None:
            build_shelf(b, fr, w, d, h)


def _clutter(b: RoomBuilder, n: int, max_cov: float = 0.36) -> None:
    """Extra storage, armchairs and side tables so large rooms are not bare."""
    for _ in range(n):
        if b.coverage() > max_cov:
            return
        kind = int(b.rng.integers(5))
        if kind == 0:
            w, d, h = b.u(0.6, 1.4), b.u(0.4, 0.55), b.u(0.5, 1.1)
            fr, _ = b.against_wall(w, d)
            if fr is not None:
                build_cabinet(b, fr, w, d, h, drawers=int(b.rng.integers(2, 5)))
        elif kind == 1:
            w, d, h = b.u(0.6, 1.1), b.u(0.28, 0.36), b.u(1.0, min(2.0, b.H - 0.3))
            fr, _ = b.against_wall(w, d)
            if fr is not None:
                build_shelf(b, fr, w, d, h)
        elif kind == 2:
            build_sofa(b, small=True)
        elif kind == 3:
            w = d = b.u(0.4, 0.6)
            fr = b.in_room(w, d, border=0.5)
            if fr is not None:
                build_table(b, fr, w, d, b.u(0.45, 0.7), round_top=b.rng.random() < 0.5)
        else:
            fr = b.in_room(0.6, 0.6, border=0.5)
            if fr is not None:
                build_chair(b, fr)


def build_room(seed: int, size_range: tuple[float, float] = (3.0, 8.0),
               height_range: tuple[float, float] = (2.4, 3.2)) -> Scene:
    """The furnished room of ``seed``: every NYU-13 class, random counts and placements."""
    rng = np.random.default_rng([int(seed), 0x5EED])
    W, D = (float(x) for x in rng.uniform(*size_range, 2))
    H = float(rng.uniform(*height_range))
    b = RoomBuilder(rng, (W, D, H))
    room_mats = []
    wall = b.mats.wall()
    for _ in range(4):
        room_mats.append(wall if rng.random() < 0.8 else b.mats.wall())
    room_mats += [b.mats.floor(), b.mats.ceiling()]
    for i, name in zip(WALL_INSTANCES, ["wall"] * 4):
        b.instances[i] = CLASS_ID[name]
    b.instances[FLOOR_INSTANCE] = CLASS_ID["floor"]
    b.instances[CEILING_INSTANCE] = CLASS_ID["ceiling"]

    # Door and windows first: they need free wall.
    if rng.random() < 0.8:
        build_door(b)
    for _ in range(int(rng.integers(1, 3))):
        build_window(b)
    build_bed(b)
    build_sofa(b)
    area = W * D
    max_cov = 0.42
    # Storage: at least one bookshelf, some cabinets / desk / wardrobe.
    others = [(k, 0.5) for k in ("cabinet", "desk", "wardrobe", "shelf")]
    big = [("shelf", 1.0)] + [others[i] for i in rng.permutation(len(others))]
    tv_stand_done = False
    for kind, p in big:
        if rng.random() > p or b.coverage() > max_cov:
            continue
        if kind == "shelf":
            w, d, h = b.u(0.6, 1.2), b.u(0.28, 0.36), b.u(1.0, min(2.0, H - 0.3))
            fr, _ = b.against_wall(w, d)
            if fr is not None:
                build_shelf(b, fr, w, d, h)
        elif kind == "cabinet":
            w, d, h = b.u(0.7, 1.6), b.u(0.4, 0.55), b.u(0.5, 1.0)
            fr, _ = b.against_wall(w, d)
            if fr is not None:
                build_cabinet(b, fr, w, d, h, drawers=int(rng.integers(2, 5)) if h > 0.6 else 0,
                              doors=0 if h > 0.6 else 2)
                if not tv_stand_done and h < 0.8 and w > 0.9 and rng.random() < 0.6:
                    tv_stand_done = True
                    tw = min(w - 0.1, b.u(0.8, 1.2))
                    build_tv(b, (fr[0], fr[1], h, fr[3]), tw, 0.075, on_stand=True)
                    b.surfaces[-1].used.append((-tw / 2 - 0.02, -d / 2, tw / 2 + 0.02, 0.12))
        elif kind == "desk":
            w, d = b.u(1.0, 1.5), b.u(0.55, 0.7)
            fr, _ = b.against_wall(w, d)
            if fr is not None:
                build_desk(b, fr, w, d)
                fx, fy, _, fyaw = fr
                ox, oy = _rot(fyaw, b.u(-0.2, 0.2), d / 2 + 0.38)
                cfp = b.footprint(fx + ox, fy + oy, fyaw, 0.62, 0.62)
                if b.free(cfp, 0.0):
                    b.footprints.append(cfp)
                    build_chair(b, (fx + ox, fy + oy, 0.0, fyaw + math.pi + b.u(-0.4, 0.4)))
        elif kind == "wardrobe" and area > 12:
            w, d, h = b.u(0.8, 1.5), b.u(0.55, 0.62), b.u(1.8, min(2.2, H - 0.2))
            fr, _ = b.against_wall(w, d)
            if fr is not None:
                build_cabinet(b, fr, w, d, h, doors=2)
    # Tables with chairs around.
    n_tables = 1 if area < 20 else int(rng.integers(1, 3))
    for _ in range(n_tables):
        if b.coverage() > max_cov + 0.05:
            break
        round_top = rng.random() < 0.3
        w = b.u(0.8, 1.6) if not round_top else b.u(0.8, 1.1)
        d = b.u(0.7, 0.95) if not round_top else w
        fr = b.in_room(w + 1.1, d + 1.1, border=(max(w, d) + 1.1) / 2 + 0.05,
                       yaw=float(rng.uniform(-math.pi, math.pi)) if rng.random() < 0.4 else
                       float(rng.integers(4)) * math.pi / 2)
        if fr is None:
            continue
        build_table(b, fr, w, d, b.u(0.72, 0.77), round_top)
        sides = [(0, d / 2 + 0.22, math.pi), (0, -d / 2 - 0.22, 0.0),
                 (w / 2 + 0.22, 0, math.pi / 2), (-w / 2 - 0.22, 0, -math.pi / 2)]
        nc = int(rng.integers(1, 5))
        for k in rng.permutation(4)[:nc]:
            sx, sy, a = sides[k]
            ox, oy = _rot(fr[3], sx, sy)
            build_chair(b, (fr[0] + ox, fr[1] + oy, 0.0, fr[3] + a + b.u(-0.25, 0.25)))
    # A lone chair if none yet.
    if CLASS_ID["chair"] not in b.instances.values():
        fr = b.in_room(0.55, 0.55)
        if fr is not None:
            build_chair(b, fr)
    _clutter(b, int(area // 10))
    for _ in range(int(rng.integers(1, 4)) + int(area // 15)):
        place_floor_object(b)
    # Floor-standing classes that found no room yet get smaller retries (before the
    # wall items, whose 3D checks then see them).
    _ensure_classes(b, ("bed", "sofa", "table", "furniture", "chair", "objects"))
    # Wall items: pictures and a TV if none on a stand.
    if not tv_stand_done:
        build_wall_tv(b)
    for _ in range(int(rng.integers(1, 4))):
        build_picture(b)
    _ensure_classes(b, ("tv", "picture", "window"))
    # Small things on every support surface.
    for s in b.surfaces:
        if s.shelf and s.half[0] > 0.15 and rng.random() < 0.85:
            place_books(b, s, standing=True)
        else:
            if rng.random() < 0.5:
                place_books(b, s, standing=False)
        for _ in range(int(rng.integers(0, 3))):
            place_object(b, s)
    order = rng.permutation(len(b.surfaces)) if b.surfaces else []
    for k in order:                         # several books in every room
        if sum(1 for c in b.instances.values() if c == CLASS_ID["books"]) >= 4:
            break
        place_books(b, b.surfaces[k], standing=False)
    lights = np.column_stack([rng.uniform(0.2, 0.8, 3) * W, rng.uniform(0.2, 0.8, 3) * D,
                              np.full(3, H - 0.25)])
    power = rng.uniform(0.3, 0.6, 3)
    # Ceiling fixtures (objects) where the lights hang: something to look up at.
    shade_mat = b.mats.add(Material(PLAIN, jitter(rng, (0.95, 0.94, 0.88), 0.02),
                                    (0.9, 0.9, 0.85), (0.9, 0.9, 0.9), 6.0))
    placed: list[tuple[float, float, float]] = []
    for lx, ly, _ in lights[: int(rng.integers(1, 4))]:
        r = b.u(0.12, 0.25)
        if any(max(abs(lx - x), abs(ly - y)) < r + q + 0.1 for x, y, q in placed):
            continue
        placed.append((float(lx), float(ly), r))
        inst = b.instance("objects")
        b.cyl((float(lx), float(ly), 0.0, 0.0), 0, 0, H - b.u(0.06, 0.12), H, r, inst, shade_mat)
        b.targets.append(inst)
    return Scene((W, D, H), b.parts, b.mats.materials, tuple(room_mats), b.instances, lights,
                 power, float(rng.uniform(0.3, 0.42)), int(seed), list(b.targets))
