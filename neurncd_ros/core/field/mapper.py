"""Incremental Embedding-NeRF mapper: keyframes in, rendered embedding and entropy out.

Threading: ``start()`` trains in a background thread, independent of the
callbacks that call ``add_keyframe``. The model and optimiser are guarded by
one lock held for each optimiser step and for tri-plane reallocation (so an
``add_keyframe`` that grows the fast field's box waits for at most one step;
the reference backend's box grows without waiting); ``render`` and
``query`` work on a snapshot copied under that lock once per training
iteration, so they never wait for more than one step and never see a
half-updated model.

Scene bounds: an AABB from the back-projected keyframe depth (plus a margin)
gives each ray's near/far; it only grows, by whole coarse tri-plane cells, so
the fast backend's planes are padded and keep every learnt texel exactly
(their Adam state restarts, the MLPs' is kept). Texel size is fixed; the box
stops growing at ``max_plane_texels`` (then ``bounds_clipped`` is set).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from ..camera import Intrinsics, backproject, camera_directions, check_pose, pixel_grid
from ..frame import Frame
from ..params import build, param, to_dict
from . import losses as L
from .keyframes import KeyframeBuffer, KeyframeConfig, KeyframeInfo, check_embedding
from .fields import TriPlaneField
from .models import FastModel, FieldModel, RayBatch, ReferenceModel
from .samplers import aabb_near_far

SAVE_VERSION = 1


@dataclasses.dataclass(frozen=True)
class MapperConfig(KeyframeConfig):
    """Embedding-NeRF mapper: backend, losses, optimisation, rendering (+ keyframe buffer)."""

    backend: str = param("fast", "field backend: tri-plane 'fast' or the paper's MLP "
                         "'reference'", choices=("fast", "reference"))
    lambda_embedding: float = param(0.5, "weight of the embedding KL loss L_e against the "
                                    "photometric loss", lo=0.0, hi=100.0)
    embedding_confidence_power: float = param(
        2.0, "weight each ray's embedding loss by (1 - backbone entropy / log S)^power "
        "(fast): where views disagree the field follows the confident ones (0 = plain mean)",
        lo=0.0, hi=16.0)
    rays_per_iteration: int = param(2048, "training rays per iteration (fast backend)",
                                    lo=16, hi=65536)
    reference_rays_per_iteration: int = param(1024, "training rays per iteration "
                                              "(reference backend)", lo=16, hi=65536)
    lr_grid: float = param(2e-2, "Adam learning rate of the tri-planes (fast)", lo=0.0, hi=1.0)
    lr_mlp: float = param(5e-3, "Adam learning rate of the MLP heads (fast)", lo=0.0, hi=1.0)
    lr_reference: float = param(5e-4, "Adam learning rate of the reference MLPs",
                                lo=0.0, hi=1.0)
    plane_cell_sizes: list[float] = param([0.16, 0.04, 0.02], "texel spacing of each tri-plane "
                                          "level, coarsest first; finer ones are rounded to "
                                          "the coarsest / an integer (fast)", lo=0.001,
                                          hi=10.0, unit="m")
    max_plane_texels: int = param(1024, "most texels per axis of the finest tri-plane level; "
                                  "the scene box stops growing there (memory bound, fast)",
                                  lo=8, hi=8192)
    plane_channels: int = param(8, "feature channels per tri-plane level (fast)", lo=1, hi=128)
    hidden: int = param(32, "hidden width of the fast field's MLP heads", lo=8, hi=512)
    surface_samples: int = param(16, "training samples per ray in the band around the "
                                 "measured depth (fast)", lo=1, hi=512)
    free_samples: int = param(8, "training samples per ray stratified over [near, far] "
                              "(fast)", lo=1, hi=512)
    surface_band: float = param(0.1, "half-width of the depth-guided sampling band (fast)",
                                lo=0.001, hi=2.0, unit="m")
    lambda_depth: float = param(0.5, "weight of the L1 depth loss (fast)", lo=0.0, hi=100.0)
    lambda_free: float = param(1.0, "weight of the free-space loss (fast)", lo=0.0, hi=100.0)
    render_coarse_samples: int = param(48, "density-only stratified samples per rendered "
                                       "ray (fast)", lo=2, hi=1024)
    render_fine_samples: int = param(24, "importance samples per rendered ray (fast)",
                                     lo=1, hi=1024)
    coarse_samples: int = param(64, "stratified coarse samples per ray (reference)",
                                lo=2, hi=1024)
    fine_samples: int = param(128, "importance fine samples per ray (reference)",
                              lo=0, hi=1024)
    near: float = param(0.05, "closest distance rendered from a camera", lo=0.0, hi=10.0,
                        unit="m")
    max_depth: float = param(10.0, "measured depth beyond this is ignored", lo=0.1,
                             hi=1000.0, unit="m")
    bounds_margin: float = param(0.3, "margin added around the keyframes' points for the "
                                 "scene AABB", lo=0.0, hi=10.0, unit="m")
    bounds_growth: float = param(0.25, "extra share of the extent added when the AABB grows "
                                 "(fewer re-allocations)", lo=0.0, hi=2.0)
    min_iterations_before_publish: int = param(100, "training iterations a keyframe gets "
                                               "before it is ready to publish", lo=0, hi=10 ** 7)
    render_with_depth: bool = param(True, "render a frame that has measured depth with "
                                    "samples around it, as in training (fast backend; "
                                    "otherwise, and for the reference, from the field alone)")
    render_chunk: int = param(1 << 17, "field samples (rays x samples per ray) evaluated per "
                              "render chunk: bounds render memory", lo=1024, hi=1 << 26)
    train_chunk: int = param(1 << 16, "field samples per backward pass; larger batches are "
                             "split and their gradients summed (bounds training memory)",
                             lo=1024, hi=1 << 26)
    num_threads: int = param(1, "torch intra-op threads (0 = leave as is); 1 because the "
                             "nodes share the cores and OpenMP threads spinning against "
                             "another busy process made an iteration 8x slower (1.2 vs 0.16 s)",
                             lo=0, hi=256)
    seed: int = param(0, "seed of the field initialisation and ray sampling", lo=0,
                      hi=2 ** 31 - 1)


def build_model(cfg: MapperConfig, channels: int) -> FieldModel:
    """The backend named by ``cfg.backend``."""
    if cfg.backend == "reference":
        return ReferenceModel(channels, cfg.coarse_samples, cfg.fine_samples,
                              cfg.lambda_embedding, cfg.lr_reference)
    return FastModel(channels, list(cfg.plane_cell_sizes), cfg.plane_channels, cfg.hidden,
                     cfg.surface_samples, cfg.free_samples, cfg.surface_band,
                     cfg.render_coarse_samples, cfg.render_fine_samples, cfg.lambda_embedding,
                     cfg.lambda_depth, cfg.lambda_free, cfg.lr_grid, cfg.lr_mlp,
                     cfg.embedding_confidence_power)


def _keyframe_extent(frame: Frame, max_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Robust box of what a frame sees (1st..99th percentile of its depth points)."""
    depth = np.where(frame.depth <= max_depth, frame.depth, 0.0).astype(np.float32)
    pts, _ = backproject(depth, frame.intrinsics, frame.pose)
    if len(pts) < 16:
        # No usable depth: assume the frustum up to 3 m.
        intr = frame.intrinsics
        u = np.array([0, intr.width - 1, 0, intr.width - 1])
        v = np.array([0, 0, intr.height - 1, intr.height - 1])
        d = camera_directions(intr, u, v) * 3.0
        pts = d @ frame.pose[:3, :3].T + frame.pose[:3, 3]
    pts = np.concatenate([pts, frame.pose[None, :3, 3]])
    return np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)


class Mapper:
    """Online Embedding-NeRF: keyframe buffer, background training, rendering."""

    def __init__(self, cfg: MapperConfig | None = None, channels: int = 9) -> None:
        self.cfg = cfg or MapperConfig()
        if channels < 1:
            raise ValueError(f"channels must be >= 1, got {channels}")
        self.channels = int(channels)
        if self.cfg.num_threads > 0:
            torch.set_num_threads(self.cfg.num_threads)
        self._lock = threading.RLock()  # model + optimiser
        self._bounds_lock = threading.Lock()  # taken before _lock when both are needed
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.last_error: BaseException | None = None
        self.buffer = KeyframeBuffer(self.cfg)
        self._init_model()

    # ------------------------------------------------------------ model state
    def _init_model(self) -> None:
        torch.manual_seed(self.cfg.seed)
        self._rng = np.random.default_rng(self.cfg.seed)
        self.model = build_model(self.cfg, self.channels)
        self._opt = torch.optim.Adam(self.model.param_groups())
        self._lo: np.ndarray | None = None
        self._hi: np.ndarray | None = None
        self.bounds_clipped = False
        self._iterations = 0
        self._snap: FieldModel | None = None
        self._snap_key: tuple | None = None

    @property
    def iterations(self) -> int:
        return self._iterations

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Current scene AABB (lo, hi) in world metres, None before the first keyframe."""
        with self._lock:
            return None if self._lo is None else (self._lo.copy(), self._hi.copy())

    def _rebuild_optimizer(self) -> None:
        """New Adam over the current parameters, keeping the state of unchanged ones."""
        old = self._opt
        self._opt = torch.optim.Adam(self.model.param_groups())
        for p in self.model.parameters():
            if p in old.state:
                self._opt.state[p] = old.state[p]

    def _cell_and_cap(self) -> tuple[float, int]:
        """Lattice the box snaps to and the most coarse cells per axis."""
        field = self.model.field
        if isinstance(field, TriPlaneField):
            q = max(field.planes.ratios)
            return field.cell, max(1, (self.cfg.max_plane_texels - 1) // q)
        return float(self.cfg.plane_cell_sizes[0]), 1 << 30

    def _grow_bounds(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Grow the AABB (whole coarse cells, with margin and slack) to hold [lo, hi]."""
        lo, hi = lo - self.cfg.bounds_margin, hi + self.cfg.bounds_margin
        with self._bounds_lock:
            if self._lo is not None and np.all(lo >= self._lo) and np.all(hi <= self._hi):
                return
            cell, cap = self._cell_and_cap()
            slack = self.cfg.bounds_growth * (np.maximum(hi, self._hi if self._lo is not None
                                                         else hi)
                                              - np.minimum(lo, self._lo if self._lo is not None
                                                           else lo)) / 2
            if self._lo is None:
                n_lo = np.zeros(3)
                base_lo = lo - slack
                cells = np.ceil((hi + slack - base_lo) / cell)
                n_hi = np.minimum(cells, cap)
                self.bounds_clipped = bool(np.any(cells > cap))
            else:
                base_lo = self._lo
                old = np.round((self._hi - self._lo) / cell)
                n_lo = np.where(lo < self._lo, np.ceil((self._lo - lo + slack) / cell), 0)
                n_hi = np.where(hi > self._hi, np.ceil((hi + slack - self._hi) / cell), 0)
                room = np.maximum(cap - old, 0)
                want = n_lo + n_hi
                scale = np.where(want > room, room / np.maximum(want, 1), 1.0)
                self.bounds_clipped = self.bounds_clipped or bool(np.any(want > room))
                n_lo, n_hi = np.floor(n_lo * scale), np.floor(n_hi * scale)
                n_hi = n_hi + old
                if not np.any(n_lo + n_hi > old):
                    return
            new_lo = base_lo - n_lo * cell
            new_hi = new_lo + (n_lo + n_hi) * cell
            field = self.model.field
            if isinstance(field, TriPlaneField):  # new plane tensors: not during a step
                with self._lock:
                    field.set_bounds(torch.tensor(new_lo, dtype=torch.float32),
                                     torch.tensor(new_hi, dtype=torch.float32),
                                     keep=self._lo is not None)
                    self._rebuild_optimizer()
                    self._lo, self._hi = new_lo, new_hi
                    self._snap = None
            else:
                # Only near/far change; a reader mixing old and new corners still gets a
                # valid box (the box only grows), so no need to wait for a slow step.
                self._lo, self._hi = new_lo, new_hi

    # ------------------------------------------------------------ keyframes
    def add_keyframe(self, frame: Frame, embedding: np.ndarray, force: bool = False) -> bool:
        """Offer a frame; True if admitted as a keyframe.

        ``embedding`` (h, w, S) float logits may be coarser than the frame (same
        aspect): it is kept at its resolution and each training ray reads the
        embedding pixel covering its frame pixel (see ``keyframes``).
        """
        frame.validate()
        emb = check_embedding(frame, embedding)
        if emb.shape[-1] != self.channels:
            raise ValueError(f"embedding has {emb.shape[-1]} channels, the mapper was built "
                             f"for {self.channels}")
        if not force and not self.buffer.should_admit(frame.pose, frame.stamp_ns):
            return False
        # Bounds first: once the keyframe is in the buffer its rays may be drawn.
        self._grow_bounds(*_keyframe_extent(frame, self.cfg.max_depth))
        return self.buffer.add(frame, emb, force=True)

    def ready_keyframes(self, min_iterations: int | None = None) -> list[KeyframeInfo]:
        """Keyframes trained on >= min_iterations since admission, each returned once."""
        if min_iterations is None:
            min_iterations = self.cfg.min_iterations_before_publish
        return self.buffer.ready(min_iterations)

    # ------------------------------------------------------------ training
    def _batch(self) -> RayBatch:
        n = (self.cfg.reference_rays_per_iteration if self.cfg.backend == "reference"
             else self.cfg.rays_per_iteration)
        r = self.buffer.sample_rays(n, self._rng)
        depth = np.where(r["depth"] <= self.cfg.max_depth, r["depth"], 0.0)
        return RayBatch(torch.from_numpy(r["origins"]).float(),
                        torch.from_numpy(r["dirs"]).float(), torch.from_numpy(r["rgb"]),
                        torch.from_numpy(depth.astype(np.float32)),
                        torch.from_numpy(r["embedding"]))

    def _near_far(self, origins: torch.Tensor, dirs: torch.Tensor):
        lo = torch.tensor(self._lo, dtype=torch.float32)
        hi = torch.tensor(self._hi, dtype=torch.float32)
        return aabb_near_far(origins, dirs, lo, hi, self.cfg.near)

    def _accumulate(self, batch: RayBatch) -> dict[str, torch.Tensor]:
        """Forward/backward in micro-batches of ``train_chunk`` samples; mean losses."""
        n = batch.origins.shape[0]
        chunk = max(1, self.cfg.train_chunk // self.model.train_samples_per_ray)
        sums: dict[str, torch.Tensor] = {}
        for s in range(0, n, chunk):
            part = RayBatch(*(getattr(batch, f.name)[s:s + chunk]
                              for f in dataclasses.fields(RayBatch)))
            share = part.origins.shape[0] / n
            near, far = self._near_far(part.origins, part.dirs)
            out = self.model.losses(part, near, far)
            (out["total"] * share).backward()
            for k, v in out.items():
                sums[k] = sums.get(k, 0.0) + v.detach() * share
        return sums

    def step(self, n: int = 1) -> dict[str, float]:
        """n training iterations; mean losses. Nothing happens (empty dict) before a keyframe."""
        if n < 1:
            raise ValueError(f"step count must be >= 1, got {n}")
        totals: dict[str, float] = {}
        done = 0
        for _ in range(n):
            if len(self.buffer) == 0:
                break
            batch = self._batch()
            with self._lock:
                if self._lo is None:  # reset() raced with this step
                    break
                self.model.train()
                self._opt.zero_grad(set_to_none=True)
                out = self._accumulate(batch)
                self._opt.step()
                self._iterations += 1
            self.buffer.tick(1)
            for k, v in out.items():
                totals[k] = totals.get(k, 0.0) + float(v.detach())
            done += 1
        if done == 0:
            return {}
        res = {k: v / done for k, v in totals.items()}
        res["psnr"] = -10.0 * math.log10(max(res.pop("fine_rgb_mse"), 1e-10))
        res["iterations"] = float(self._iterations)
        return res

    def _loop(self) -> None:
        try:
            while not self._stop.is_set():
                if len(self.buffer) == 0:
                    time.sleep(0.01)
                    continue
                self.step(1)
        except BaseException as exc:  # surfaced through last_error, thread ends
            self.last_error = exc

    def start(self) -> None:
        """Train in a background thread until :meth:`stop`."""
        if self._thread is not None and self._thread.is_alive():
            return
        self._stop.clear()
        self.last_error = None
        self._thread = threading.Thread(target=self._loop, name="neurncd-mapper", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the background training (waits for the current iteration)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def reset(self) -> None:
        """Forget everything: keyframes, bounds, weights, optimiser (training thread kept)."""
        with self._bounds_lock, self._lock:
            self.buffer.clear()
            self._init_model()

    # ------------------------------------------------------------ rendering
    def _snapshot(self) -> tuple[FieldModel, np.ndarray, np.ndarray]:
        with self._lock:
            if self._lo is None:
                raise ValueError("nothing is mapped yet: add a keyframe before rendering")
            key = (self._iterations, id(self.model))
            if self._snap is None or self._snap_key != key:
                self._snap = copy.deepcopy(self.model).eval()
                self._snap_key = key
            return self._snap, self._lo.copy(), self._hi.copy()

    @torch.no_grad()
    def render_rays(self, origins: np.ndarray, dirs: np.ndarray,
                    depth: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Render world rays (directions z-normalised in their camera) in chunks.

        ``depth`` (N,) measured z-depth per ray (0 or non-finite = none; beyond
        ``max_depth`` ignored) lets the fast backend sample around the surface
        (``render_with_depth``); None renders from the field alone.
        """
        model, lo, hi = self._snapshot()
        lo_t, hi_t = torch.tensor(lo, dtype=torch.float32), torch.tensor(hi, dtype=torch.float32)
        o_all = torch.from_numpy(np.asarray(origins, np.float32).reshape(-1, 3))
        d_all = torch.from_numpy(np.asarray(dirs, np.float32).reshape(-1, 3))
        z_all = None
        if depth is not None and self.cfg.render_with_depth:
            z = np.asarray(depth, np.float32).reshape(-1)
            if z.shape[0] != o_all.shape[0]:
                raise ValueError(f"depth has {z.shape[0]} values for {o_all.shape[0]} rays")
            z = np.where(np.isfinite(z) & (z > 0) & (z <= self.cfg.max_depth), z, 0.0)
            z_all = torch.from_numpy(z.astype(np.float32))
        parts: dict[str, list[torch.Tensor]] = {"rgb": [], "depth": [], "embedding": []}
        per_ray = model.render_samples_per_ray if z_all is None else max(
            model.render_samples_per_ray, model.train_samples_per_ray)
        chunk = max(1, self.cfg.render_chunk // per_ray)
        for s in range(0, o_all.shape[0], chunk):
            o, d = o_all[s:s + chunk], d_all[s:s + chunk]
            near, far = aabb_near_far(o, d, lo_t, hi_t, self.cfg.near)
            out = model.render_rays(o, d, near, far,
                                    None if z_all is None else z_all[s:s + chunk])
            for k in parts:
                parts[k].append(out[k])
        rgb = torch.cat(parts["rgb"]).clamp(0.0, 1.0)
        emb = torch.cat(parts["embedding"])
        return {"rgb": rgb.numpy(), "depth": torch.cat(parts["depth"]).numpy(),
                "embedding": emb.numpy(), "entropy": L.entropy_torch(emb).numpy()}

    def render(self, pose: np.ndarray, intrinsics: Intrinsics, height: int | None = None,
               width: int | None = None, depth: np.ndarray | None = None
               ) -> dict[str, np.ndarray]:
        """Render a view: rgb (H, W, 3) in [0, 1], depth (H, W), embedding (H, W, S), entropy.

        With ``height``/``width`` the camera is rendered at that resolution
        (intrinsics scaled accordingly). ``depth``: the view's measured depth
        image at ``intrinsics``' size (resampled, nearest, to the rendered size),
        used to place the samples (see :meth:`render_rays`).
        """
        pose = check_pose(pose)
        intr = intrinsics
        if height is not None or width is not None:
            if height is None or width is None or height < 1 or width < 1:
                raise ValueError(f"give both height and width >= 1, got {height}x{width}")
            intr = intrinsics.scaled(int(width), int(height))
        z = None
        if depth is not None:
            z = np.asarray(depth, np.float32)
            if z.shape != intrinsics.shape:
                raise ValueError(f"depth has shape {z.shape} but the intrinsics are "
                                 f"{intrinsics.width}x{intrinsics.height}")
            if z.shape != intr.shape:
                z = cv2.resize(z, (intr.width, intr.height), interpolation=cv2.INTER_NEAREST)
        u, v = pixel_grid(intr.height, intr.width)
        d = camera_directions(intr, u, v) @ pose[:3, :3].T
        o = np.broadcast_to(pose[:3, 3], d.shape)
        out = self.render_rays(o, d, None if z is None else z[v, u])
        h, w = intr.height, intr.width
        return {"rgb": out["rgb"].reshape(h, w, 3).astype(np.float32),
                "depth": out["depth"].reshape(h, w).astype(np.float32),
                "embedding": out["embedding"].reshape(h, w, -1).astype(np.float32),
                "entropy": out["entropy"].reshape(h, w).astype(np.float32)}

    @torch.no_grad()
    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Embedding logits (N, S) and entropy (N,) of the field at world points (N, 3)."""
        pts = np.asarray(points, dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must be (N, 3), got shape {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise ValueError("points have non-finite coordinates")
        model, _, _ = self._snapshot()
        embs = [model.query(torch.from_numpy(pts[s:s + 65536]))
                for s in range(0, len(pts), 65536)]
        emb = torch.cat(embs) if embs else torch.zeros(0, self.channels)
        return emb.numpy(), L.entropy_torch(emb).numpy()

    # ------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> None:
        """Weights, optimiser, bounds and the keyframe buffer, so training can resume."""
        with self._lock:
            state = {
                "version": SAVE_VERSION, "config": to_dict(self.cfg), "channels": self.channels,
                "iterations": self._iterations,
                "bounds": None if self._lo is None else torch.tensor(np.stack([self._lo,
                                                                              self._hi])),
                "model": self.model.state_dict(), "optimizer": self._opt.state_dict(),
                "buffer": self.buffer.state(),
            }
            torch.save(state, str(path))

    @classmethod
    def load(cls, path: str | Path, **overrides) -> "Mapper":
        """A mapper restored by :meth:`save` (``overrides``: config values to change)."""
        state = torch.load(str(path), map_location="cpu", weights_only=True)
        if not isinstance(state, dict) or state.get("version") != SAVE_VERSION:
            raise ValueError(f"{path} is not a neurncd mapper file (version {SAVE_VERSION})")
        cfg = build(MapperConfig, {**state["config"], **overrides})
        m = cls(cfg, int(state["channels"]))
        with m._lock:
            if state["bounds"] is not None:
                b = state["bounds"].numpy()
                m._lo, m._hi = b[0].astype(np.float64), b[1].astype(np.float64)
                if isinstance(m.model.field, TriPlaneField):  # planes sized by the box
                    m.model.field.set_bounds(torch.tensor(m._lo, dtype=torch.float32),
                                             torch.tensor(m._hi, dtype=torch.float32),
                                             keep=False)
            m.model.load_state_dict(state["model"])
            m._opt = torch.optim.Adam(m.model.param_groups())
            m._opt.load_state_dict(state["optimizer"])
            m._iterations = int(state["iterations"])
            m.buffer.load_state(state["buffer"])
            m._rng = np.random.default_rng(cfg.seed + m._iterations)
        return m
