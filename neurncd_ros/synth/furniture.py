"""Furniture and objects for the synthetic rooms: one builder per kind of piece.

Large pieces are placed by rejection on their floor footprints; wall-mounted
pieces (windows, doors, pictures, TVs) by rejection on 3D bounding boxes; small
things on the support surfaces the large pieces leave. Each builder draws
from the room builder's own generator, so a seed gives one room. The
builders stay in one module (over 500 lines) because they share the wall,
surface and footprint placement helpers and are read together.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.classes import CLASS_ID
from .materials import PLAIN, Material, jitter
from .parts import RoomBuilder, Surface, _overlap, _rot, part_aabb



def build_bed(b: RoomBuilder) -> bool:
    """Bed against a wall (double in most rooms over 3.2 m across, else single): frame,
    headboard, mattress, blanket, pillows; False if no wall had room."""
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
    """Chair at ``frame``: seat, four legs (round or square) and a back."""
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
    """Table w x d, top at height h (round: one pedestal), with a support surface on top;
    returns its instance id."""
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
    """Cabinet w x d x h with drawer or door fronts and handles, its top a support
    surface; returns its instance id."""
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
    """Open bookshelf: sides, back and 3-6 boards; the space above each board and the top
    are support surfaces (books go there); returns its instance id."""
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
    """Desk: top, a drawer pedestal on a random side and a panel on the other; returns
    its instance id."""
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
    """Window in a free stretch of wall: glass showing the outside, frame, sill and
    maybe curtains; False if no wall had room."""
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
    """Framed painting flat on a wall at eye height (a novel class flush with the wall);
    False if no wall had room."""
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
    """Wall-mounted 16:9 TV; False if no wall had room."""
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
    """A cylindrical floor object or a potted plant (NYU-13 objects) on free floor; False
    if no floor was free."""
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
