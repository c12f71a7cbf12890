"""Procedural room layouts for the synthetic generator: one furnished room per seed.

:func:`build_room` draws the room's size and materials, then furnishes it with
the builders of :mod:`.furniture` (door and windows first, as they need free
wall; then bed, sofa, storage, tables, wall items and clutter), so that every
NYU-13 class appears. The geometry (parts, instances, surfaces) lives in
:mod:`.parts`; its names are re-exported here for the renderer and the tests.
"""

from __future__ import annotations

import math

import numpy as np

from ..core.classes import CLASS_ID
from .furniture import (_clutter, _ensure_classes, build_bed, build_cabinet, build_chair,
                        build_desk, build_door, build_picture, build_shelf, build_sofa,
                        build_table, build_tv, build_wall_tv, build_window, place_books,
                        place_floor_object, place_object)
from .materials import PLAIN, Material, jitter
from .parts import (BOX, CEILING_INSTANCE, CYL, FLOOR_INSTANCE, WALL_INSTANCES, Part,
                    RoomBuilder, Scene, Surface, _rot, part_aabb)

__all__ = ["BOX", "CYL", "CEILING_INSTANCE", "FLOOR_INSTANCE", "WALL_INSTANCES", "Part",
           "RoomBuilder", "Scene", "Surface", "build_room", "part_aabb"]



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
