"""CPU ray caster for the synthetic rooms: depth, labels, procedural texture, sensor noise.

(One module, over 500 lines: intersection, z-buffer, textures and the
sensor-noise model share the per-frame ray arrays and are tuned together.)

All rays of a frame share the camera centre, so each part is intersected only
with the rays inside its projected screen rectangle (a rasteriser-like z-buffer
of exact ray/box and ray/cylinder hits). Textures are functions of the hit
point in the part's own frame, so every view sees the same surface colours.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..core.camera import Intrinsics, camera_directions, check_pose, pixel_grid
from .materials import (CHECKER, FABRIC, OUTSIDE, PAINTING, PLAIN, PLANKS, SCREEN, SPINE,
                              STRIPES, WOOD)
from .scene import BOX, CEILING_INSTANCE, FLOOR_INSTANCE, WALL_INSTANCES, Scene

_NEAR = 1e-3
_HASH = np.random.default_rng(20240607).random(1 << 16).astype(np.float32)


# ------------------------------------------------------------------ noise

def _lattice(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray) -> np.ndarray:
    return _HASH[((ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791)) & 0xFFFF]


def value_noise(p: np.ndarray) -> np.ndarray:
    """Smooth 3D value noise in [0, 1] at points (N, 3): a fixed function of position."""
    fl = np.floor(p)
    f = p - fl
    i = fl.astype(np.int64)
    u = f * f * (3.0 - 2.0 * f)
    x0, y0, z0 = i[:, 0], i[:, 1], i[:, 2]
    x1, y1, z1 = x0 + 1, y0 + 1, z0 + 1
    ux, uy, uz = u[:, 0], u[:, 1], u[:, 2]
    c00 = _lattice(x0, y0, z0) * (1 - ux) + _lattice(x1, y0, z0) * ux
    c10 = _lattice(x0, y1, z0) * (1 - ux) + _lattice(x1, y1, z0) * ux
    c01 = _lattice(x0, y0, z1) * (1 - ux) + _lattice(x1, y0, z1) * ux
    c11 = _lattice(x0, y1, z1) * (1 - ux) + _lattice(x1, y1, z1) * ux
    return (c00 * (1 - uy) + c10 * uy) * (1 - uz) + (c01 * (1 - uy) + c11 * uy) * uz


def fbm(p: np.ndarray, octaves: int = 2) -> np.ndarray:
    """Fractal sum of value noise, normalised to about [0, 1]."""
    out, amp, tot = np.zeros(len(p), np.float32), 1.0, 0.0
    for k in range(octaves):
        out += amp * value_noise(p * (2.0 ** k) + 13.7 * k)
        tot += amp
        amp *= 0.5
    return out / tot


def _hash1(k: np.ndarray) -> np.ndarray:
    return _HASH[(k.astype(np.int64) * 2654435761) & 0xFFFF]


# ------------------------------------------------------------------ scene arrays

@dataclasses.dataclass
class SceneArrays:
    """Flat arrays of a Scene: parts first, then 6 room faces (walls 0..3, floor, ceiling)."""

    kind: np.ndarray      # (P,) BOX / CYL
    centre: np.ndarray    # (P, 3)
    half: np.ndarray      # (P, 3)
    cos: np.ndarray       # (P,)
    sin: np.ndarray
    corners: np.ndarray   # (P, 8, 3) world
    cls: np.ndarray       # (P + 6,) uint16
    inst: np.ndarray      # (P + 6,) uint16
    mat: np.ndarray       # (P + 6,) material index
    offset: np.ndarray    # (P + 6, 3) texture offset per part
    axis: np.ndarray      # (P + 6,) long axis (wood grain, stripes)
    pattern: np.ndarray   # (M,)
    col: np.ndarray       # (M, 3, 3) colours a, b, c
    scale: np.ndarray     # (M,)
    emissive: np.ndarray  # (M,)
    size: np.ndarray      # (3,) room W, D, H
    lights: np.ndarray
    power: np.ndarray
    ambient: float

    @property
    def n_parts(self) -> int:
        return len(self.kind)

    @classmethod
    def from_scene(cls, scene: Scene) -> "SceneArrays":
        """The flat arrays of ``scene`` (its parts, then the room's six faces)."""
        P = len(scene.parts)
        kind = np.array([p.kind for p in scene.parts], dtype=np.int8).reshape(P)
        centre = np.array([p.centre for p in scene.parts], dtype=np.float64).reshape(P, 3)
        half = np.array([p.half for p in scene.parts], dtype=np.float64).reshape(P, 3)
        yaw = np.array([p.yaw for p in scene.parts], dtype=np.float64).reshape(P)
        # Quarter-turn parts become axis-aligned boxes (cheaper to intersect).
        quarter = np.round(yaw / (np.pi / 2))
        aligned = np.abs(yaw - quarter * np.pi / 2) < 1e-9
        swap = aligned & (quarter.astype(np.int64) % 2 == 1)
        half[swap] = half[swap][:, [1, 0, 2]]
        yaw[aligned] = 0.0
        c, s = np.cos(yaw), np.sin(yaw)
        sg = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        loc = sg[None] * half[:, None]                     # (P, 8, 3)
        wx = c[:, None] * loc[..., 0] - s[:, None] * loc[..., 1]
        wy = s[:, None] * loc[..., 0] + c[:, None] * loc[..., 1]
        corners = np.stack([wx, wy, loc[..., 2]], -1) + centre[:, None]
        room_inst = list(WALL_INSTANCES) + [FLOOR_INSTANCE, CEILING_INSTANCE]
        insts = [p.inst for p in scene.parts] + room_inst
        clss = [p.cls for p in scene.parts] + [scene.instances[i] for i in room_inst]
        mats = [p.mat for p in scene.parts] + list(scene.room_mats)
        rng = np.random.default_rng([scene.seed, 0x7E47])
        offset = rng.uniform(-50, 50, (P + 6, 3)).astype(np.float32)
        offset[P:] = 0.0
        axis = np.concatenate([np.argmax(half, axis=1), [0, 1, 0, 1, 0, 0]])
        m = scene.materials
        return cls(kind, centre, half, c, s, corners, np.array(clss, np.uint16),
                   np.array(insts, np.uint16), np.array(mats, np.int64), offset,
                   axis.astype(np.int64),
                   np.array([x.pattern for x in m], np.int64),
                   np.array([[x.a, x.b, x.c] for x in m], np.float32).reshape(len(m), 3, 3),
                   np.array([x.scale for x in m], np.float32),
                   np.array([x.emissive for x in m], bool),
                   np.array(scene.size, np.float64), np.asarray(scene.lights, np.float64),
                   np.asarray(scene.light_power, np.float64), float(scene.ambient))


# ------------------------------------------------------------------ ray casting

@dataclasses.dataclass
class Hits:
    """Per-pixel result of casting the rays of one view."""

    depth: np.ndarray     # (H, W) z-depth of the first hit
    prim: np.ndarray      # (H, W) int64 index into SceneArrays (parts then room faces)
    normal: np.ndarray    # (H, W, 3) world unit normal facing the camera
    point: np.ndarray     # (H, W, 3) world hit point
    local: np.ndarray     # (H, W, 3) hit point in the part's frame (room: world)
    dirs: np.ndarray      # (H, W, 3) world ray directions (camera z = 1)


def _screen_rects(sa: SceneArrays, pose: np.ndarray, intr: Intrinsics
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(P, 4) pixel rectangles u0, u1, v0, v1 of each part (empty when not visible)
    and (P,) the nearest z-depth any point of the part can have."""
    R, o = pose[:3, :3], pose[:3, 3]
    pc = (sa.corners - o) @ R                              # camera-frame corners
    z = pc[..., 2]
    front = z > _NEAR
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * pc[..., 0] / z + intr.cx
        v = intr.fy * pc[..., 1] / z + intr.cy
    big = 1e9
    u0 = np.where(front, u, big).min(1)
    u1 = np.where(front, u, -big).max(1)
    v0 = np.where(front, v, big).min(1)
    v1 = np.where(front, v, -big).max(1)
    partial = front.any(1) & ~front.all(1)                 # straddles the camera plane
    rect = np.stack([np.floor(u0), np.ceil(u1) + 1, np.floor(v0), np.ceil(v1) + 1], 1)
    rect[partial] = [0, intr.width, 0, intr.height]
    rect[~front.any(1)] = 0
    rect[:, 0:2] = np.clip(rect[:, 0:2], 0, intr.width)
    rect[:, 2:4] = np.clip(rect[:, 2:4], 0, intr.height)
    return rect.astype(np.int64), z.min(1)


def cast(sa: SceneArrays, pose: np.ndarray, intr: Intrinsics) -> Hits:
    """First hit of every pixel's ray: room shell, then each visible part in its rectangle
    (near parts first, skipping parts wholly behind what is already drawn)."""
    pose = check_pose(pose)
    H, W = intr.height, intr.width
    u, v = pixel_grid(H, W)
    d64 = camera_directions(intr, u, v) @ pose[:3, :3].T   # (H, W, 3), camera z = 1
    dxyz = [np.ascontiguousarray(d64[..., k], dtype=np.float32) for k in range(3)]
    with np.errstate(divide="ignore"):
        inv_xyz = [np.float32(1.0) / a for a in dxyz]
    o = pose[:3, 3]
    # Room shell seen from inside: exit distance of the box.
    t_axes = []
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            dk = dxyz[k]
            t_axes.append(np.where(dk > 0, (sa.size[k] - o[k]) / dk,
                                   np.where(dk < 0, -o[k] / dk, np.inf)).astype(np.float32))
    t_axes = np.stack(t_axes)
    face_axis = np.argmin(t_axes, axis=0)
    depth = np.min(t_axes, axis=0)
    pos = np.choose(face_axis, dxyz) > 0
    # walls: y=0 -> 0, x=W -> 1, y=D -> 2, x=0 -> 3; floor 4; ceiling 5
    room_face = np.select([(face_axis == 1) & ~pos, (face_axis == 0) & pos,
                           (face_axis == 1) & pos, (face_axis == 0) & ~pos,
                           (face_axis == 2) & ~pos], [0, 1, 2, 3, 4], 5)
    P = sa.n_parts
    prim = (P + room_face).astype(np.int64)
    rects, zmin = _screen_rects(sa, pose, intr)
    visible = np.nonzero((rects[:, 1] > rects[:, 0]) & (rects[:, 3] > rects[:, 2]))[0]
    visible = visible[np.argsort(zmin[visible], kind="stable")]
    for i in visible:
        u0, u1, v0, v1 = rects[i]
        zb = depth[v0:v1, u0:u1]
        if zmin[i] >= zb.max():
            continue
        ex, ey, ez = (a[v0:v1, u0:u1] for a in dxyz)
        c, s = float(sa.cos[i]), float(sa.sin[i])
        rx, ry, rz = (float(x) for x in (o - sa.centre[i]))
        inv = None
        if s != 0.0:
            ex, ey = c * ex + s * ey, c * ey - s * ex
            rx, ry = c * rx + s * ry, c * ry - s * rx
        else:
            inv = tuple(a[v0:v1, u0:u1] for a in inv_xyz)
        h = sa.half[i].tolist()
        if sa.kind[i] == BOX:
            t = _hit_box((rx, ry, rz), (ex, ey, ez), inv, h)
        else:
            t = _hit_cyl((rx, ry, rz), (ex, ey, ez), h)
        closer = t < zb
        zb[closer] = t[closer]
        prim[v0:v1, u0:u1][closer] = i
    d = d64
    point = o + depth[..., None].astype(np.float64) * d
    local = _local(sa, prim, point)
    normal = _normals(sa, prim, local)
    return Hits(depth.astype(np.float64), prim, normal, point, local, d)


def _hit_box(o: tuple, d: tuple, inv: tuple | None, h: list[float]) -> np.ndarray:
    """Entry distance (inf if missed) of rays from outside into a box: each face that
    looks at the camera is hit where the ray crosses its plane inside its rectangle.
    ``inv`` optionally holds 1 / d per axis (shared by all unrotated boxes)."""
    t = np.full(d[0].shape, np.inf, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for a in range(3):
            if abs(o[a]) <= h[a]:
                continue
            b, c = (a + 1) % 3, (a + 2) % 3
            plane = h[a] if o[a] > 0 else -h[a]
            ta = (plane - o[a]) * inv[a] if inv is not None else (plane - o[a]) / d[a]
            pb = d[b] * ta
            pb += o[b]
            ok = np.abs(pb, out=pb) <= h[b]
            pc = d[c] * ta
            pc += o[c]
            ok &= np.abs(pc, out=pc) <= h[c]
            ok &= ta > _NEAR
            np.copyto(t, ta, where=ok)
    return t


def _hit_cyl(o: tuple, d: tuple, h: list[float]) -> np.ndarray:
    """Entry distance of rays from outside into a vertical capped cylinder."""
    r, hz = float(h[0]), float(h[2])
    dx, dy, dz = d
    a = dx * dx + dy * dy
    b = 2 * (o[0] * dx + o[1] * dy)
    c = o[0] ** 2 + o[1] ** 2 - r * r
    disc = b * b - 4 * a * c
    with np.errstate(divide="ignore", invalid="ignore"):
        ts = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
        side = (disc >= 0) & (ts > _NEAR) & (np.abs(o[2] + ts * dz) <= hz)
        t = np.where(side, ts, np.inf).astype(np.float32)
        if abs(o[2]) > hz:
            cap_z = hz if o[2] > 0 else -hz
            tc = (cap_z - o[2]) / dz
            xc, yc = o[0] + tc * dx, o[1] + tc * dy
            cap = (tc > _NEAR) & (xc * xc + yc * yc <= r * r)
            t = np.where(cap & (tc < t), tc, t)
    return t


def _normals(sa: SceneArrays, prim: np.ndarray, local: np.ndarray) -> np.ndarray:
    """World unit normals from the local hit points: the box face the point lies on,
    the cylinder side or cap; room faces point into the room."""
    H, W = prim.shape
    P = sa.n_parts
    normal = np.zeros((H, W, 3))
    is_part = prim < P
    pi = prim[is_part]
    q = local[is_part]
    h = sa.half[pi]
    rel = np.abs(q) / np.maximum(h, 1e-9)                  # 1 on the face's own axis
    nl = np.zeros_like(q)
    box = sa.kind[pi] == BOX
    ax = np.argmax(np.where(box[:, None], rel, 0.0), axis=1)
    nl[np.arange(len(q)), ax] = np.sign(q[np.arange(len(q)), ax])
    cyl = ~box
    if cyl.any():
        qc, hc = q[cyl], h[cyl]
        on_cap = np.abs(np.abs(qc[:, 2]) - hc[:, 2]) < 1e-4 * np.maximum(hc[:, 2], 1.0) + 1e-6
        radial = np.hypot(qc[:, 0], qc[:, 1])
        side_n = np.stack([qc[:, 0], qc[:, 1], np.zeros(len(qc))], -1) / \
            np.maximum(radial, 1e-9)[:, None]
        cap_n = np.stack([np.zeros(len(qc)), np.zeros(len(qc)), np.sign(qc[:, 2])], -1)
        on_cap &= radial < hc[:, 0] * (1 - 1e-4)
        nl[cyl] = np.where(on_cap[:, None], cap_n, side_n)
    c, s = sa.cos[pi], sa.sin[pi]
    normal[is_part] = np.stack([c * nl[:, 0] - s * nl[:, 1], s * nl[:, 0] + c * nl[:, 1],
                                nl[:, 2]], -1)
    room_n = np.array([[0, 1, 0], [-1, 0, 0], [0, -1, 0], [1, 0, 0], [0, 0, 1], [0, 0, -1]],
                      float)
    normal[~is_part] = room_n[prim[~is_part] - P]
    return normal


# ------------------------------------------------------------------ appearance

def _local(sa: SceneArrays, prim: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Hit points in each part's own frame (room faces: world frame)."""
    P = sa.n_parts
    out = point.copy()
    part = prim < P
    pi = prim[part]
    rel = point[part] - sa.centre[pi]
    c, s = sa.cos[pi], sa.sin[pi]
    out[part] = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1],
                          rel[:, 2]], -1)
    return out


def albedo(sa: SceneArrays, prim: np.ndarray, point: np.ndarray, normal: np.ndarray,
           dirs: np.ndarray, local: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Surface colour (N, 3) in [0, 1] and emissive flag (N,) of flat hit arrays."""
    q = _local(sa, prim, point) if local is None else local
    mat = sa.mat[prim]
    pat = sa.pattern[mat]
    col = sa.col[mat]                                       # (N, 3, 3)
    a, b, cc = col[:, 0], col[:, 1], col[:, 2]
    sc = sa.scale[mat]
    off = sa.offset[prim]
    ax = sa.axis[prim]
    f = np.zeros(len(prim), np.float32)
    out = np.empty((len(prim), 3), np.float32)
    qo = q + off

    def sel(p):
        return np.nonzero(pat == p)[0]

    for idx, fn in ((sel(PLAIN), lambda k: 0.5 * value_noise(qo[k] * sc[k, None])),
                    (sel(FABRIC), lambda k: _fabric(qo[k], sc[k]))):
        if len(idx):
            f[idx] = fn(idx)
    k = sel(WOOD)
    if len(k):
        f[k] = _wood(qo[k], q[k], ax[k], sc[k])
    k = sel(STRIPES)
    if len(k):
        coord = np.take_along_axis(q[k], (ax[k] % 3)[:, None], 1)[:, 0]
        coord = np.where(ax[k] == 2, q[k, 0] + q[k, 1], coord)
        f[k] = 0.5 + 0.5 * np.tanh(4 * np.sin(2 * np.pi * coord * sc[k]))
    k = sel(SPINE)
    if len(k):
        hz = sa.half[np.minimum(prim[k], sa.n_parts - 1), 2].astype(np.float32)
        rz = np.abs(q[k, 2]) / np.maximum(hz, 1e-3)
        f[k] = ((rz > 0.72) & (rz < 0.84)) | (np.abs(q[k, 2] / np.maximum(hz, 1e-3) - 0.3) < 0.08)
    out[:] = a + (b - a) * f[:, None]
    k = sel(CHECKER)
    if len(k):
        nk = normal[k]
        if sa.n_parts:
            pk = np.minimum(prim[k], sa.n_parts - 1)
            ck, sk = np.where(prim[k] < sa.n_parts, sa.cos[pk], 1.0), \
                np.where(prim[k] < sa.n_parts, sa.sin[pk], 0.0)
            nk = np.stack([ck * nk[:, 0] + sk * nk[:, 1], -sk * nk[:, 0] + ck * nk[:, 1],
                           nk[:, 2]], -1)
        out[k] = _checker(q[k], nk, sc[k], a[k], b[k], cc[k])
    k = sel(PLANKS)
    if len(k):
        out[k] = _planks(q[k], sc[k], a[k], b[k])
    k = sel(PAINTING)
    if len(k):
        n1 = fbm(qo[k] * sc[k, None], 3)
        n2 = fbm(qo[k] * sc[k, None] + 31.0, 3)
        s1 = np.clip((n1 - 0.35) * 3.3, 0, 1)[:, None]
        s2 = np.clip((n2 - 0.45) * 3.3, 0, 1)[:, None]
        out[k] = (a[k] * (1 - s1) + b[k] * s1) * (1 - s2) + cc[k] * s2
    k = sel(SCREEN)
    if len(k):
        g = np.clip(0.5 + 0.5 * (q[k, 0] + q[k, 2]), 0, 1)[:, None] * 0.4
        out[k] = a[k] + (b[k] - a[k]) * g
    k = sel(OUTSIDE)
    if len(k):
        out[k] = _outside(dirs[k], sc[k], a[k], b[k], cc[k])
    return out, sa.emissive[mat]


def _fabric(q: np.ndarray, sc: np.ndarray) -> np.ndarray:
    w = np.sin(q[:, 0] * sc) * np.sin(q[:, 1] * sc) + np.sin(q[:, 2] * sc) * np.sin(q[:, 1] * sc)
    return np.clip(0.35 + 0.15 * w + 0.5 * (value_noise(q * 6.0) - 0.5), 0, 1)


def _wood(qo: np.ndarray, q: np.ndarray, ax: np.ndarray, sc: np.ndarray) -> np.ndarray:
    """Growth rings around the part's long axis, wobbled by noise."""
    a1 = (ax + 1) % 3
    a2 = (ax + 2) % 3
    x1 = np.take_along_axis(qo, a1[:, None], 1)[:, 0]
    x2 = np.take_along_axis(qo, a2[:, None], 1)[:, 0]
    along = np.take_along_axis(q, ax[:, None], 1)[:, 0]
    r = np.sqrt((x1 % 7.0 - 3.5) ** 2 + (x2 % 7.0 - 3.5) ** 2) * sc * 3.0
    wob = value_noise(np.stack([x1 * 4, x2 * 4, along * 0.8], -1))
    ring = 0.5 + 0.5 * np.sin(2 * np.pi * (r + 1.5 * wob))
    return 0.65 * ring ** 3 + 0.35 * value_noise(qo * 30.0)


def _checker(q, nl, sc, a, b, grout) -> np.ndarray:
    """Tiles of two tones with grout lines on the face's two in-plane axes."""
    g = q * sc[:, None]
    cell = np.floor(g)
    parity = (cell.sum(1) % 2).astype(bool)
    fr = g - cell
    dist = np.minimum(fr, 1 - fr)
    dist[np.arange(len(q)), np.argmax(np.abs(nl), axis=1)] = np.inf
    out = np.where(parity[:, None], a, b) * (0.9 + 0.2 * value_noise(q * 3.0))[:, None]
    return np.where((dist.min(1) < 0.03)[:, None], grout, out)


def _planks(q, width, a, b) -> np.ndarray:
    """Floor boards along x, rows of ``width`` metres along y, staggered joints."""
    row = np.floor(q[:, 1] / width)
    fy = q[:, 1] / width - row
    length = 1.2
    shift = _hash1(row + 7.0) * length
    col = np.floor((q[:, 0] + shift) / length)
    fx = (q[:, 0] + shift) / length - col
    tone = _hash1(row * 31.0 + col * 7.0 + 3.0)
    grain = value_noise(np.stack([q[:, 0] * 2.0, q[:, 1] * 40.0, row], -1))
    f = 0.45 * tone + 0.4 * grain
    seam = (np.minimum(fy, 1 - fy) * width < 0.003) | (np.minimum(fx, 1 - fx) * length < 0.003)
    f = np.where(seam, 1.6, f)
    return np.clip(a + (b - a) * f[:, None], 0, 1)


def _outside(d: np.ndarray, sc, sky, ground, haze) -> np.ndarray:
    """Bright view through a window: sky over a noisy skyline, by ray direction."""
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    elev = dn[:, 2]
    az = np.arctan2(dn[:, 1], dn[:, 0])
    sk = value_noise(np.stack([np.cos(az) * sc, np.sin(az) * sc, np.zeros_like(az)], -1))
    horizon = -0.05 + 0.25 * sk
    t = np.clip(elev * 2.0, 0, 1)[:, None]
    sky_col = haze * (1 - t) + sky * t
    gnd = ground * (0.8 + 0.4 * value_noise(dn * 12.0))[:, None]
    return np.where((elev > horizon)[:, None], sky_col, gnd)


def shade(sa: SceneArrays, point: np.ndarray, normal: np.ndarray, alb: np.ndarray,
          emissive: np.ndarray) -> np.ndarray:
    """Lambertian light from the room's point lights plus ambient; emissive as is."""
    px, py, pz = point[:, 0], point[:, 1], point[:, 2]
    nx, ny, nz = normal[:, 0], normal[:, 1], normal[:, 2]
    inten = np.full(len(point), sa.ambient, np.float32)
    for lp, pw in zip(sa.lights.tolist(), sa.power.tolist()):
        vx, vy, vz = lp[0] - px, lp[1] - py, lp[2] - pz
        dist2 = vx * vx + vy * vy + vz * vz
        ndl = np.maximum(nx * vx + ny * vy + nz * vz, 0) / np.sqrt(dist2)
        inten += pw * ndl / (1.0 + 0.12 * dist2)
    out = alb * inten[:, None]
    out[emissive] = alb[emissive]
    return out


def render_rgb(sa: SceneArrays, hits: Hits) -> np.ndarray:
    """Noise-free colour (H, W, 3) float32 in [0, 1] of a cast view."""
    H, W = hits.depth.shape
    prim = hits.prim.reshape(-1)
    point = hits.point.reshape(-1, 3).astype(np.float32)
    normal = hits.normal.reshape(-1, 3).astype(np.float32)
    alb, emi = albedo(sa, prim, point, normal, hits.dirs.reshape(-1, 3).astype(np.float32),
                      hits.local.reshape(-1, 3).astype(np.float32))
    rgb = shade(sa, point, normal, alb, emi)
    return np.clip(rgb, 0, 1).reshape(H, W, 3)


# ------------------------------------------------------------------ sensor

KINECT_FX, KINECT_BASELINE, DISPARITY_STEP = 580.0, 0.075, 1.0 / 8.0


def kinect_depth(depth: np.ndarray, cos_incidence: np.ndarray, rng: np.random.Generator,
                 dropout: float, grazing_cos: float) -> np.ndarray:
    """Kinect-v1-like depth: axial noise, disparity quantisation, holes at grazing
    angles, edge shadows and random dropouts. Input exact z-depth (0 = none)."""
    z = depth.astype(np.float64)
    valid = z > 0
    H, W = z.shape
    holes = np.zeros((H, W), bool)
    # grazing angles: dropping out more as the surface turns away
    p_graze = np.clip((grazing_cos * 1.5 - cos_incidence) / (grazing_cos * 0.5 + 1e-9), 0, 1)
    holes |= rng.random((H, W)) < p_graze
    # depth edges: background pixels beside a closer neighbour lose their return;
    # the shadow side (projector to the right of the IR camera) gets a wider band
    zp = np.where(valid, z, np.inf)
    thr = 0.03 + 0.02 * z
    for k, p in ((1, 0.8), (2, 0.5), (3, 0.25)):
        nb = np.full_like(zp, np.inf)
        nb[:, :-k] = zp[:, k:]                              # neighbour to the right
        holes |= ((z - nb) > thr) & (rng.random((H, W)) < p)
    for dy, dx in ((0, 1), (1, 0), (-1, 0)):
        nb = np.full_like(zp, np.inf)                       # neighbour at (v - dy, u - dx)
        nb[max(dy, 0):H + min(dy, 0), max(dx, 0):W + min(dx, 0)] = \
            zp[max(-dy, 0):H + min(-dy, 0), max(-dx, 0):W + min(-dx, 0)]
        holes |= ((z - nb) > thr) & (rng.random((H, W)) < 0.4)
    holes |= rng.random((H, W)) < dropout
    sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
    zn = z + rng.normal(size=z.shape) * sigma
    with np.errstate(divide="ignore", invalid="ignore"):
        disp = KINECT_FX * KINECT_BASELINE / zn
        disp = np.round(disp / DISPARITY_STEP) * DISPARITY_STEP
        zq = KINECT_FX * KINECT_BASELINE / disp
    zq = np.round(zq * 1000.0) / 1000.0
    out = np.where(valid & ~holes & np.isfinite(zq) & (zq > 0), zq, 0.0)
    return out.astype(np.float32)


def cos_incidence(hits: Hits) -> np.ndarray:
    """|cos| of the angle between each pixel's ray and the surface normal."""
    d = hits.dirs / np.linalg.norm(hits.dirs, axis=-1, keepdims=True)
    return np.abs((d * hits.normal).sum(-1))


def point_clearance(sa: SceneArrays, points: np.ndarray) -> np.ndarray:
    """Distance (N,) from points to the nearest part (boxes; cylinders as their box)
    or room face; negative inside."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    room = np.minimum(p, sa.size - p).min(1)
    if sa.n_parts == 0:
        return room
    rel = p[:, None, :] - sa.centre[None]                    # (N, P, 3)
    c, s = sa.cos[None], sa.sin[None]
    lx = c * rel[..., 0] + s * rel[..., 1]
    ly = -s * rel[..., 0] + c * rel[..., 1]
    q = np.abs(np.stack([lx, ly, rel[..., 2]], -1)) - sa.half[None]
    outside = np.linalg.norm(np.maximum(q, 0), axis=-1)
    inside = np.minimum(q.max(-1), 0)
    return np.minimum(room, (outside + inside).min(1))

