"""Procedural synthetic RGB-D rooms with exact ground truth.

Each seed is a different furnished room holding instances of all 13 NYU-13
classes (``scene``); a hand-held camera walks a smooth path through it
and every frame is ray cast on the CPU (``render``) into colour, metric
z-depth (exact or Kinect-like), semantic and instance images. The semantic
accuracy of the project is measured on these scenes, so the geometry is exact,
textures are tied to 3D surface positions (multi-view consistent) and the
same seed and config always give the same arrays.

    for frame in generate(seed=3, frames=300, cfg=SynthConfig()):
        ...
"""

from __future__ import annotations

import dataclasses
import math
from typing import Iterator

import numpy as np

from ..core.camera import Intrinsics, look_at
from ..core.frame import Frame
from ..core.params import ConfigError, check_value, param, specs
from .render import SceneArrays, cast, cos_incidence, kinect_depth, point_clearance, \
    render_rgb
from .scene import Scene, build_room

__all__ = ["SynthConfig", "generate", "frames_at", "room_of", "trajectory", "intrinsics_of"]


@dataclasses.dataclass(frozen=True)
class SynthConfig:
    """Settings of the synthetic RGB-D scene generator."""

    width: int = param(320, "image width in pixels", lo=16, hi=4096, unit="px")
    height: int = param(240, "image height in pixels", lo=16, hi=4096, unit="px")
    camera: str = param("replica", "camera model: replica (square pixels, hfov_deg) or kinect "
                        "(640x480 Kinect v1, 58 deg hfov, scaled to width x height)",
                        choices=("replica", "kinect"))
    hfov_deg: float = param(90.0, "horizontal field of view of the replica camera",
                            lo=20.0, hi=150.0, unit="deg")
    depth_noise: str = param("realistic", "depth sensor model: realistic (Kinect-like noise, "
                             "quantisation, holes) or none (exact z-depth)",
                             choices=("realistic", "none"))
    rgb_noise_std: float = param(2.0, "std of Gaussian colour noise", lo=0.0, hi=50.0,
                                 unit="8-bit levels")
    dropout: float = param(0.004, "share of depth pixels dropped at random (realistic noise)",
                           lo=0.0, hi=0.5)
    grazing_cos: float = param(0.12, "|cos| of incidence below which depth starts to drop out "
                               "(realistic noise)", lo=0.0, hi=0.9)
    max_depth: float = param(10.0, "sensor range: farther depth reads 0 (both noise models)",
                             lo=0.5, hi=100.0, unit="m")
    fps: float = param(30.0, "frame rate; stamp_ns = start_ns + round(i * 1e9 / fps)",
                       lo=0.5, hi=240.0, unit="Hz")
    start_ns: int = param(1_000_000_000, "stamp of the first frame", lo=0, unit="ns")
    speed: float = param(0.35, "mean camera speed along its path", lo=0.01, hi=3.0, unit="m/s")
    speed_variation: float = param(0.3, "relative smooth variation of the speed", lo=0.0,
                                   hi=0.9)
    waypoint_spacing: float = param(1.4, "mean distance between path waypoints (larger is "
                                    "smoother)", lo=0.3, hi=5.0, unit="m")
    look_period: float = param(2.5, "time spent turning to each look-at target (larger is "
                               "calmer)", lo=0.3, hi=60.0, unit="s")
    shake_deg: float = param(0.3, "amplitude of hand-held rotational shake", lo=0.0, hi=5.0,
                             unit="deg")
    roll_deg: float = param(2.0, "amplitude of slow camera roll", lo=0.0, hi=30.0, unit="deg")
    cam_height_min: float = param(1.2, "lowest camera height above the floor", lo=0.3, hi=3.0,
                                  unit="m")
    cam_height_max: float = param(1.8, "highest camera height above the floor", lo=0.3, hi=3.0,
                                  unit="m")
    clearance: float = param(0.5, "minimum distance from the camera centre to any geometry",
                             lo=0.25, hi=2.0, unit="m")
    room_size_min: float = param(3.0, "smallest room side", lo=2.5, hi=20.0, unit="m")
    room_size_max: float = param(8.0, "largest room side", lo=2.5, hi=20.0, unit="m")
    room_height_min: float = param(2.4, "lowest room height", lo=2.2, hi=5.0, unit="m")
    room_height_max: float = param(3.2, "highest room height", lo=2.2, hi=5.0, unit="m")

    def __post_init__(self) -> None:
        for spec in specs(type(self)):
            check_value(spec, getattr(self, spec.name), spec.name)
        for lo, hi in (("cam_height_min", "cam_height_max"), ("room_size_min", "room_size_max"),
                       ("room_height_min", "room_height_max")):
            if getattr(self, lo) > getattr(self, hi):
                raise ConfigError(f"{lo} ({getattr(self, lo)}) is larger than {hi} "
                                  f"({getattr(self, hi)})")
        if self.cam_height_max + self.clearance > self.room_height_min:
            raise ConfigError(f"cam_height_max + clearance ({self.cam_height_max} + "
                              f"{self.clearance} m) does not fit under room_height_min "
                              f"({self.room_height_min} m)")
        if self.cam_height_min < self.clearance:
            raise ConfigError(f"cam_height_min ({self.cam_height_min} m) is below the "
                              f"clearance ({self.clearance} m) from the floor")


def intrinsics_of(cfg: SynthConfig) -> Intrinsics:
    """Camera intrinsics the config asks for."""
    if cfg.camera == "kinect":
        return Intrinsics.from_hfov(640, 480, 58.0).scaled(cfg.width, cfg.height)
    return Intrinsics.from_hfov(cfg.width, cfg.height, cfg.hfov_deg)


def room_of(seed: int, cfg: SynthConfig | None = None) -> Scene:
    """The room (parts, instances, classes, materials, lights) of a seed."""
    cfg = cfg or SynthConfig()
    _check_seed(seed)
    return build_room(seed, (cfg.room_size_min, cfg.room_size_max),
                      (cfg.room_height_min, cfg.room_height_max))


def _check_seed(seed: int) -> None:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")


# ------------------------------------------------------------------ trajectory

def _catmull_rom(p0, p1, p2, p3, s: np.ndarray) -> np.ndarray:
    s = s[:, None]
    return 0.5 * ((2 * p1) + (-p0 + p2) * s + (2 * p0 - 5 * p1 + 4 * p2 - p3) * s ** 2
                  + (-p0 + 3 * p1 - 3 * p2 + p3) * s ** 3)


class _PathBuilder:
    """Random waypoints in free space, one after the other (so shorter runs are prefixes)."""

    def __init__(self, sa: SceneArrays, cfg: SynthConfig, rng: np.random.Generator):
        self.sa, self.cfg, self.rng = sa, cfg, rng
        self.margin = cfg.clearance + 0.12

    def free(self, pts: np.ndarray, margin: float) -> np.ndarray:
        return point_clearance(self.sa, pts) >= margin

    def start(self) -> np.ndarray:
        W, D, _ = self.sa.size
        for margin in (self.margin, self.cfg.clearance + 0.02):
            for _ in range(20):
                n = 256
                c = np.column_stack([self.rng.uniform(0, W, n), self.rng.uniform(0, D, n),
                                     self.rng.uniform(self.cfg.cam_height_min,
                                                      self.cfg.cam_height_max, n)])
                ok = np.nonzero(self.free(c, margin))[0]
                if len(ok):
                    return c[ok[0]]
        raise ValueError(f"no free space for the camera in this {W:.1f} x {D:.1f} m room with "
                         f"clearance {self.cfg.clearance} m; lower clearance")

    def segment_free(self, a: np.ndarray, b: np.ndarray, margin: float) -> bool:
        n = max(2, int(np.linalg.norm(b - a) / 0.04) + 1)
        s = np.linspace(0, 1, n)[:, None]
        return bool(self.free(a + s * (b - a), margin).all())

    def next(self, pts: list[np.ndarray], heading: float) -> tuple[np.ndarray, float]:
        """The next waypoint and heading: a random free point about ``waypoint_spacing``
        away, reachable in a straight line, within 90 degrees of the heading if one is
        (else in any direction); boxed in, the previous waypoint."""
        p = pts[-1]
        cfg = self.cfg
        n = 48
        for spread in (math.pi / 2, math.pi):
            ang = heading + self.rng.uniform(-spread, spread, n)
            step = cfg.waypoint_spacing * self.rng.uniform(0.5, 1.3, n)
            z = np.clip(p[2] + self.rng.normal(0, 0.15, n), cfg.cam_height_min,
                        cfg.cam_height_max)
            cand = np.column_stack([p[0] + step * np.cos(ang), p[1] + step * np.sin(ang), z])
            ok = self.free(cand, self.margin)
            for k in np.nonzero(ok)[0]:
                if self.segment_free(p, cand[k], self.margin):
                    return cand[k], float(ang[k])
        # Boxed in: step back to where we came from.
        back = pts[-2] if len(pts) > 1 else p
        return back.copy(), heading + math.pi


def _path_positions(sa: SceneArrays, cfg: SynthConfig, rng: np.random.Generator,
                    lengths: np.ndarray) -> np.ndarray:
    """Points at arc lengths ``lengths`` along a smooth spline through free waypoints."""
    pb = _PathBuilder(sa, cfg, rng)
    pts = [pb.start()]
    heading = float(rng.uniform(-math.pi, math.pi))
    need = float(lengths.max()) if len(lengths) else 0.0
    dense: list[np.ndarray] = []
    total = 0.0
    i = 0
    # A camera boxed in by furniture can make no progress: stop adding segments then
    # (positions past the end of the path stay at its end).
    max_segments = 1000 + int(need / 0.01)
    while i < max_segments:
        while len(pts) < i + 3:
            p, heading = pb.next(pts, heading)
            pts.append(p)
        p0 = pts[i - 1] if i > 0 else pts[0]
        p1, p2, p3 = pts[i], pts[i + 1], pts[i + 2]
        s = np.linspace(0, 1, 40, endpoint=False)
        lin = p1 + s[:, None] * (p2 - p1)
        spl = _catmull_rom(p0, p1, p2, p3, s)
        for alpha in (1.0, 0.5, 0.25, 0.0):
            seg = lin + alpha * (spl - lin)
            if alpha == 0.0 or pb.free(seg, cfg.clearance + 0.01).all():
                break
        dense.append(seg)
        prev = dense[-2][-1] if len(dense) > 1 else seg[0]
        total += float(np.linalg.norm(np.diff(np.vstack([prev, seg]), axis=0), axis=1).sum())
        i += 1
        if total > need + 0.05:
            break
    dense_pts = np.vstack(dense)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense_pts, axis=0), axis=1))])
    return np.column_stack([np.interp(lengths, cum, dense_pts[:, k]) for k in range(3)])


def _smooth_wave(rng: np.random.Generator, t: np.ndarray, f_lo: float, f_hi: float,
                 terms: int = 3) -> np.ndarray:
    """Sum of random sinusoids scaled to roughly [-1, 1]."""
    f = rng.uniform(f_lo, f_hi, terms)
    ph = rng.uniform(0, 2 * math.pi, terms)
    return np.sin(2 * math.pi * f[None] * t[:, None] + ph[None]).sum(1) / math.sqrt(terms * 2)


def _look_directions(scene: Scene, cfg: SynthConfig, rng: np.random.Generator,
                     times: np.ndarray, eye_at) -> np.ndarray:
    """Smoothly varying unit view directions turning towards content targets."""
    n_keys = int(math.ceil((times.max() if len(times) else 0) / cfg.look_period)) + 3
    targets = scene.targets or [1, 2, 3, 4]
    boxes = {i: scene.instance_aabb(i) for i in set(targets)}
    keys = []
    prev = None
    for k in range(n_keys):
        eye = eye_at(k * cfg.look_period)
        best = None
        for _ in range(24):
            inst = targets[int(rng.integers(len(targets)))]
            lo, hi = boxes[inst]
            pt = rng.uniform(lo, hi)
            v = pt - eye
            horiz = math.hypot(v[0], v[1])
            if horiz < 1.0:
                continue
            v = v / np.linalg.norm(v)
            if v[2] < -0.75 or v[2] > 0.5:
                continue
            if prev is not None and float(v @ prev) < math.cos(math.radians(100)):
                continue
            best = v
            break
        if best is None:
            ang = rng.uniform(-math.pi, math.pi) if prev is None else \
                math.atan2(prev[1], prev[0]) + rng.uniform(-1, 1)
            best = np.array([math.cos(ang), math.sin(ang), -0.2])
            best /= np.linalg.norm(best)
        keys.append(best)
        prev = best
    keys = np.array(keys)
    u = times / cfg.look_period
    k = np.floor(u).astype(np.int64)
    s = u - k
    p0 = keys[np.maximum(k - 1, 0)]
    out = 0.5 * ((2 * keys[k]) + (-p0 + keys[k + 1]) * s[:, None]
                 + (2 * p0 - 5 * keys[k] + 4 * keys[k + 1] - keys[k + 2]) * s[:, None] ** 2
                 + (-p0 + 3 * keys[k] - 3 * keys[k + 1] + keys[k + 2]) * s[:, None] ** 3)
    out[:, 2] = np.clip(out[:, 2], -0.8, 0.55)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _rot(axis: int, ang: np.ndarray) -> np.ndarray:
    c, s = np.cos(ang), np.sin(ang)
    R = np.zeros((len(ang), 3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[:, axis, axis] = 1
    R[:, i, i], R[:, j, j] = c, c
    R[:, i, j], R[:, j, i] = -s, s
    return R


def trajectory(seed: int, frames: int, cfg: SynthConfig, scene: Scene | None = None,
               sa: SceneArrays | None = None) -> np.ndarray:
    """(frames, 4, 4) camera-to-world poses of a smooth hand-held walk through the room.

    A shorter run is a prefix of a longer one with the same seed and config.
    """
    _check_seed(seed)
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 0:
        raise ValueError(f"frames must be a non-negative integer, got {frames!r}")
    scene = scene or room_of(seed, cfg)
    sa = sa or SceneArrays.from_scene(scene)
    if frames == 0:
        return np.zeros((0, 4, 4))
    t = np.arange(frames) / cfg.fps
    # Arc length is integrated on the frame grid extended past the last look-at key,
    # so every quantity at a given time is the same whatever the number of frames.
    n_keys = int(math.ceil(t[-1] / cfg.look_period)) + 3
    key_t = np.arange(n_keys) * cfg.look_period
    t_ext = np.arange(int(math.ceil(key_t[-1] * cfg.fps)) + 2) / cfg.fps
    rng_speed = np.random.default_rng([seed, 0x5BEED])
    speed = cfg.speed * (1 + cfg.speed_variation * np.clip(
        _smooth_wave(rng_speed, t_ext, 0.05, 0.3), -1, 1))
    lengths = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) / cfg.fps)])
    all_len = np.concatenate([lengths[:frames], np.interp(key_t, t_ext, lengths)])
    pos_all = _path_positions(sa, cfg, np.random.default_rng([seed, 0xA7]), all_len)
    pos, key_pos = pos_all[:frames], pos_all[frames:]

    def eye_at(tk: float) -> np.ndarray:
        return key_pos[int(round(tk / cfg.look_period))]
    rng_look = np.random.default_rng([seed, 0x100C])
    dirs = _look_directions(scene, cfg, rng_look, t, eye_at)
    rng_shake = np.random.default_rng([seed, 0x5A4E])
    sh = math.radians(cfg.shake_deg)
    yaw = sh * _smooth_wave(rng_shake, t, 0.8, 3.0)
    pitch = sh * _smooth_wave(rng_shake, t, 0.8, 3.0)
    roll = math.radians(cfg.roll_deg) * _smooth_wave(rng_shake, t, 0.05, 0.25)
    jitter = _rot(1, yaw) @ _rot(0, pitch) @ _rot(2, roll)
    poses = np.array([look_at(p, p + d) for p, d in zip(pos, dirs)])
    poses[:, :3, :3] = poses[:, :3, :3] @ jitter
    return poses


# ------------------------------------------------------------------ frames

def render_frame(sa: SceneArrays, pose: np.ndarray, intr: Intrinsics, cfg: SynthConfig,
                 rng: np.random.Generator, stamp_ns: int) -> Frame:
    """Ray cast one view into a Frame with ground truth and the configured sensor noise."""
    hits = cast(sa, pose, intr)
    depth = np.where(hits.depth <= cfg.max_depth, hits.depth, 0.0)
    rgb = render_rgb(sa, hits) * np.float32(255.0)
    if cfg.rgb_noise_std > 0:
        rgb += rng.standard_normal(rgb.shape, dtype=np.float32) * np.float32(cfg.rgb_noise_std)
    rgb8 = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    if cfg.depth_noise == "realistic":
        depth32 = kinect_depth(depth, cos_incidence(hits), rng, cfg.dropout, cfg.grazing_cos)
        depth32[depth32 > cfg.max_depth] = 0.0
    else:
        depth32 = depth.astype(np.float32)
    return Frame(stamp_ns=int(stamp_ns), rgb=rgb8, depth=depth32, pose=pose, intrinsics=intr,
                 semantic=sa.cls[hits.prim], instance=sa.inst[hits.prim])


def generate(seed: int, frames: int, cfg: SynthConfig | None = None) -> Iterator[Frame]:
    """Frames of a hand-held walk through the room of ``seed`` (deterministic).

    Yields ``frames`` Frames with rgb, depth (metres; exact or Kinect-like),
    pose T_wc, intrinsics, semantic (NYU-13 ids) and instance ids; stamps are
    ``start_ns + round(i * 1e9 / fps)``.
    """
    cfg = cfg or SynthConfig()
    if not isinstance(cfg, SynthConfig):
        raise ValueError(f"cfg must be a SynthConfig, got {type(cfg).__name__}")
    _check_seed(seed)
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 0:
        raise ValueError(f"frames must be a non-negative integer, got {frames!r}")
    return _frames(int(seed), int(frames), cfg)


def frames_at(seed: int, indices, cfg: SynthConfig | None = None) -> Iterator[Frame]:
    """Only the frames ``indices`` of the walk, identical to ``generate``'s frames there
    (a walk does not depend on its length), without rendering the others."""
    cfg = cfg or SynthConfig()
    _check_seed(seed)
    idx = [int(i) for i in indices]
    if any(i < 0 for i in idx):
        raise ValueError(f"frame indices must be non-negative, got {min(idx)}")
    return _frames(int(seed), max(idx, default=-1) + 1, cfg, idx)


def _frames(seed: int, frames: int, cfg: SynthConfig, only: list[int] | None = None
            ) -> Iterator[Frame]:
    scene = room_of(seed, cfg)
    sa = SceneArrays.from_scene(scene)
    intr = intrinsics_of(cfg)
    poses = trajectory(seed, frames, cfg, scene, sa)
    for i in (range(frames) if only is None else only):
        rng = np.random.default_rng([seed, 0xF4A3E, i])
        stamp = cfg.start_ns + int(round(i * 1e9 / cfg.fps))
        yield render_frame(sa, poses[i], intr, cfg, rng, stamp)
