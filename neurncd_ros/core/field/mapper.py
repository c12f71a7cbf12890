"""Incremental Embedding-NeRF mapper: keyframes in, rendered embedding and entropy out.

(One module, over 500 lines: threading, pausing, snapshots, rendering and
persistence all guard the same model state, and read best side by side.)

The mapper owns the keyframe buffer, the scene box, the optimiser, the
training thread and the random generators; everything that differs between
fields (sampling, losses, rays per iteration, what the box means to the
parameters) is asked of the backend's ``FieldModel`` (``backends``), built
from its own config section ``mapper.<backend>``.

Threading: ``start()`` trains in a background thread, independent of the
callbacks that call ``add_keyframe``. The model and optimiser are guarded by
one lock held for each optimiser step and for parameter reallocation (so an
``add_keyframe`` that grows a box-shaped backend's box waits for at most one
step; other backends' boxes grow without waiting); ``render`` and ``query``
work on a snapshot copied under that lock once per training iteration, so they
never wait for more than one step and never see a half-updated model.
``paused()`` holds the training thread between iterations, and ``render``
does so itself (``yield_to_render``): on two cores a render then gets the CPU
instead of sharing it with training.

Scene bounds: an AABB from the back-projected keyframe depth (plus a margin)
gives each ray's near/far; it only grows, by whole cells of the backend's
lattice, so the fast backend's planes are padded and keep every learnt texel
exactly (their Adam state restarts, the MLPs' is kept). Past the backend's
cell cap the box stops growing (then ``bounds_clipped`` is set).

Randomness: the initial weights, new texels and sample jitter come from one
``torch.Generator``, the training rays from one ``np.random.Generator``, both
the mapper's own and seeded from ``mapper.seed`` (``reset`` reseeds them), so
mappers in one process never affect each other. The mapper sets no thread
count: the executable that owns the process applies ``mapper.num_threads``.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from ..camera import Intrinsics, camera_directions, check_pose, pixel_grid
from ..frame import Frame
from ..params import ConfigError, build, param, specs, to_dict
from ..torchfile import read_torch_file
from . import backends, scenebox
from . import losses as L
from .backends import FieldModel, RayBatch
from .keyframes import KeyframeBuffer, KeyframeConfig, KeyframeInfo, check_embedding
from .samplers import aabb_near_far

SAVE_VERSION = 2
"""Map file layout; 2 records the keyframe and backend sections beside the mapper's."""


# Settings of how the mapper runs on this machine (threads, priority, chunk sizes), not of
# the map it builds: a loaded map takes them from the configuration in force.
RUNTIME_SETTINGS = ("render_chunk", "train_chunk", "yield_to_render", "train_nice",
                    "num_threads")


def kept_settings_text(kept: dict[str, Any]) -> str:
    """``mapper.near 0.05 (configured 0.1), ...``: :meth:`Mapper.kept_settings` for a log
    line (values as pairs or two-item lists, as in metrics.json)."""
    return ", ".join(f"{k} {v[0]!r} (configured {v[1]!r})" for k, v in kept.items())


class RenderCancelled(Exception):
    """A render stopped early because its ``cancel`` event was set."""


@dataclasses.dataclass(frozen=True)
class MapperConfig:
    """Embedding-NeRF mapper: backend choice, shared loss weight, scene box, rendering, threads.

    Each backend's own settings are the section ``mapper.<backend>``; the
    keyframe buffer's are the section ``keyframes``.
    """

    backend: str = param("fast", "field backend: tri-plane 'fast' or the paper's MLP "
                         "'reference' (settings in mapper.<backend>)", choices=backends.names)
    lambda_embedding: float = param(0.5, "weight of the embedding KL loss L_e against the "
                                    "photometric loss", lo=0.0, hi=100.0)
    distill_features: bool = param(True, "when the embedding carries the backbone's "
                                   "penultimate features (backbone.features), the field "
                                   "learns them beside the logits and renders both; false: "
                                   "it learns the logits alone and the features only ride "
                                   "along with the keyframes for the mapper stage's keyframe "
                                   "fusion")
    lambda_features: float = param(0.5, "weight of the feature loss L_f (squared error "
                                   "relative to the features' mean squared norm) when the "
                                   "field distils features", lo=0.0, hi=100.0)
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
                                    "samples around it, as in training (if the backend "
                                    "places samples by depth: fast; otherwise from the "
                                    "field alone)")
    render_chunk: int = param(1 << 17, "field samples (rays x samples per ray) evaluated per "
                              "render chunk: bounds render memory", lo=1024, hi=1 << 26)
    train_chunk: int = param(1 << 16, "field samples per backward pass; larger batches are "
                             "split and their gradients summed (bounds training memory)",
                             lo=1024, hi=1 << 26)
    yield_to_render: bool = param(True, "pause background training while a view renders, so "
                                  "that the render gets the CPU")
    train_nice: int = param(10, "niceness added to the background training thread (Linux, "
                            "where a thread has its own; elsewhere ignored): on a busy "
                            "machine the embedding, the views and discovery run first and "
                            "the field trains on the idle CPU (0 = as any thread). Live "
                            "graph on 2 cores, medians of 5 interleaved runs "
                            "(bench/results/graph_sweep_mapper_train_nice.json): at 0 "
                            "1.74 labels/s, latency median 5.48 s (p95 6.27), 5.7 field "
                            "iterations/s; at 10 1.86 labels/s, 4.21 s (4.96), 2.2 "
                            "iterations/s", lo=0, hi=19)
    num_threads: int = param(1, "torch intra-op threads the executable running the mapper "
                             "sets (0 = leave torch's setting); 1 because the nodes share "
                             "the cores (README, Limits)", lo=0, hi=256)
    seed: int = param(0, "seed of the mapper's generators: field initialisation, sample "
                      "jitter and ray sampling", lo=0, hi=2 ** 31 - 1)

    @staticmethod
    def subsections() -> dict[str, type]:
        """``mapper.<name>``: one config section per registered backend."""
        return backends.config_classes()


def lower_thread_priority(nice: int) -> bool:
    """Add ``nice`` to the calling thread's niceness (``mapper.train_nice``); whether it did.

    On Linux the nice value is a thread's own (setpriority on its native id), so the
    training thread can give way to the rest of the node and to the other nodes while its
    process keeps its priority. Elsewhere setpriority would renice the whole process, so
    nothing is done. Lowering a priority needs no privilege."""
    if nice <= 0 or not sys.platform.startswith("linux"):
        return False
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))
    except OSError:
        return False
    return True


class Mapper:
    """Online Embedding-NeRF: keyframe buffer, background training, rendering.

    ``Mapper(cfg, channels, keyframes, backend_cfg, feature_channels)``: the
    ``mapper`` section, the embedding logits S, the ``keyframes`` section, the
    backend's own section (defaults where None), and how many feature channels
    follow the S logits in a keyframe's embedding (``backbone.features``: kept with
    the keyframe for the mapper stage's keyframe fusion). The field learns and
    renders the S logits and, with ``distill_features``, the F features after them
    (:attr:`field_channels`); the entropy is always that of the S logits.
    :meth:`from_config` takes them from a whole configuration.
    """

    def __init__(self, cfg: MapperConfig | None = None, channels: int = 9,
                 keyframes: KeyframeConfig | None = None, backend_cfg: Any = None,
                 feature_channels: int = 0) -> None:
        self.cfg = cfg or MapperConfig()
        if channels < 1:
            raise ValueError(f"channels must be >= 1, got {channels}")
        if feature_channels < 0:
            raise ValueError(f"feature_channels must be >= 0, got {feature_channels}")
        self.channels = int(channels)
        self.feature_channels = int(feature_channels)
        self.field_channels = self.channels + (self.feature_channels
                                               if self.cfg.distill_features else 0)
        self._backend = backends.get(self.cfg.backend)
        self.backend_cfg = backend_cfg if backend_cfg is not None else self._backend.config()
        if not isinstance(self.backend_cfg, self._backend.config):
            raise TypeError(f"backend {self.cfg.backend!r} takes a "
                            f"{self._backend.config.__name__}, got "
                            f"{type(self.backend_cfg).__name__}")
        self.keyframe_cfg = keyframes or KeyframeConfig()
        self._lock = threading.RLock()  # model + optimiser
        self._bounds_lock = threading.Lock()  # taken before _lock when both are needed
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pause = threading.Condition()  # guards _pauses and _training
        self._pauses = 0
        self._training = False  # the background thread is inside an iteration
        self.last_error: BaseException | None = None
        self.buffer = KeyframeBuffer(self.keyframe_cfg)
        self._init_model()

    @classmethod
    def from_config(cls, cfg: Any, channels: int, feature_channels: int = 0) -> "Mapper":
        """A mapper from a whole configuration: anything with ``.mapper``, ``.keyframes``
        and ``.section("mapper.<backend>")`` (as ``neurncd_ros.config.Config``)."""
        return cls(cfg.mapper, channels, keyframes=cfg.keyframes,
                   backend_cfg=cfg.section(f"mapper.{cfg.mapper.backend}"),
                   feature_channels=feature_channels)

    @classmethod
    def load_configured(cls, path: str | Path, cfg: Any) -> "Mapper":
        """:meth:`load` with the settings of how the mapper runs on this machine
        (:data:`RUNTIME_SETTINGS`) taken from ``cfg``, the configuration in force: the map
        keeps every other setting it was built with (:meth:`kept_settings`)."""
        return cls.load(path, **{k: getattr(cfg.mapper, k) for k in RUNTIME_SETTINGS})

    def kept_settings(self, cfg: Any) -> dict[str, tuple[Any, Any]]:
        """The settings in which this mapper differs from what ``cfg`` (a whole
        configuration, as for :meth:`from_config`) would build: ``{"mapper.near": (the
        map's, the configuration's)}``. A loaded map keeps the mapper, keyframes and backend
        settings it was built with, so a changed value has no effect on it; the mapper node
        and ``neurncd run`` say which."""
        mine = {"mapper": self.cfg, "keyframes": self.keyframe_cfg,
                f"mapper.{self.cfg.backend}": self.backend_cfg}
        out: dict[str, tuple[Any, Any]] = {}
        for name, built in mine.items():
            have, want = to_dict(built), to_dict(cfg.section(name))
            out.update({f"{name}.{k}": (have[k], want[k]) for k in have
                        if k in want and have[k] != want[k]})
        return out

    # ------------------------------------------------------------ model state
    def _init_model(self) -> None:
        self._gen = torch.Generator().manual_seed(self.cfg.seed)
        self._rng = np.random.default_rng(self.cfg.seed)
        self.model: FieldModel = self._backend.model(self.backend_cfg, self.field_channels,
                                                     self.cfg, self._gen)
        self._opt = torch.optim.Adam(self.model.param_groups())
        self._lo: np.ndarray | None = None
        self._hi: np.ndarray | None = None
        # A grown box not yet applied because a training step held the model (see
        # _grow_bounds); applied before the next batch is drawn and before a render.
        self._pending_box: tuple[np.ndarray, np.ndarray] | None = None
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
        self._apply_pending_bounds()
        with self._lock:
            return None if self._lo is None else (self._lo.copy(), self._hi.copy())

    def _rebuild_optimizer(self) -> None:
        """New Adam over the current parameters, keeping the state of unchanged ones."""
        old = self._opt
        self._opt = torch.optim.Adam(self.model.param_groups())
        for p in self.model.parameters():
            if p in old.state:
                self._opt.state[p] = old.state[p]

    def _grow_bounds(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Grow the box (backend lattice, with margin and slack) to hold [lo, hi].

        A backend whose box holds parameters gets its new box between two training
        steps. If a step holds the model, the box waits in ``_pending_box`` and the
        training thread applies it before drawing its next batch (the keyframe's rays
        are in that batch at the earliest), so the caller never waits for a step: the
        training thread runs at a lower priority (``train_nice``), and on a busy
        machine a step took over a second, all of which the mapper node's intake of
        frames then waited. Without a step under way the box is applied at once, as
        always offline.
        """
        lo, hi = lo - self.cfg.bounds_margin, hi + self.cfg.bounds_margin
        with self._bounds_lock:
            cell, cap = self.model.box_lattice()
            old = self._pending_box or (None if self._lo is None else (self._lo, self._hi))
            box, clipped = scenebox.grow(old, lo, hi, cell, cap, self.cfg.bounds_growth)
            self.bounds_clipped = self.bounds_clipped or clipped
            if box is None:
                return
            if self.model.box_holds_parameters:  # new parameters: not during a step
                self._pending_box = box
                if self._lock.acquire(blocking=False):
                    try:
                        self._apply_box()
                    finally:
                        self._lock.release()
            else:
                # Only near/far change; a reader mixing old and new corners still gets a
                # valid box (the box only grows), so no need to wait for a slow step.
                self._lo, self._hi = box

    # ------------------------------------------------------------ keyframes
    def add_keyframe(self, frame: Frame, embedding: np.ndarray, force: bool = False) -> bool:
        """Offer a frame; True if admitted as a keyframe.

        ``embedding`` (h, w, S [+ feature_channels]) float logits [and features] may be
        coarser than the frame (same aspect): it is kept at its resolution and each
        training ray reads the embedding pixel covering its frame pixel (see
        ``keyframes``); the field learns the S logits (and, with ``distill_features``,
        the features).
        """
        frame.validate()
        emb = check_embedding(frame, embedding)
        if emb.shape[-1] != self.channels + self.feature_channels:
            raise ValueError(f"embedding has {emb.shape[-1]} channels, the mapper was built "
                             f"for {self.channels}"
                             + (f" + {self.feature_channels} features"
                                if self.feature_channels else ""))
        if not force and not self.buffer.should_admit(frame.pose, frame.stamp_ns):
            return False
        # Bounds first: once the keyframe is in the buffer its rays may be drawn.
        self._grow_bounds(*scenebox.keyframe_extent(frame, self.cfg.max_depth))
        return self.buffer.add(frame, emb, force=True)

    def ready_keyframes(self, min_iterations: int | None = None) -> list[KeyframeInfo]:
        """Keyframes trained on >= min_iterations since admission, each returned once."""
        if min_iterations is None:
            min_iterations = self.cfg.min_iterations_before_publish
        return self.buffer.ready(min_iterations)

    def _apply_box(self) -> None:
        """Give the model the pending box, if any; with ``_bounds_lock`` held. Takes the
        model (``_lock``: waits for a step under way) only when a box is pending."""
        if self._pending_box is None:
            return
        with self._lock:
            box, self._pending_box = self._pending_box, None
            self.model.set_bounds(torch.tensor(box[0], dtype=torch.float32),
                                  torch.tensor(box[1], dtype=torch.float32),
                                  keep=self._lo is not None, generator=self._gen)
            self._rebuild_optimizer()
            self._lo, self._hi = box
            self._snap = None

    def _apply_pending_bounds(self) -> None:
        """Apply a box :meth:`_grow_bounds` left pending (waits for a step under way)."""
        with self._bounds_lock:
            self._apply_box()

    # ------------------------------------------------------------ training
    def _batch(self) -> RayBatch:
        r = self.buffer.sample_rays(self.model.rays_per_iteration, self._rng)
        depth = np.where(r["depth"] <= self.cfg.max_depth, r["depth"], 0.0)
        S, C = self.channels, self.field_channels
        return RayBatch(torch.from_numpy(r["origins"]).float(),
                        torch.from_numpy(r["dirs"]).float(), torch.from_numpy(r["rgb"]),
                        torch.from_numpy(depth.astype(np.float32)),
                        torch.from_numpy(np.ascontiguousarray(r["embedding"][:, :S])),
                        torch.from_numpy(np.ascontiguousarray(r["embedding"][:, S:C])))

    def _near_far(self, origins: torch.Tensor, dirs: torch.Tensor):
        lo = torch.tensor(self._lo, dtype=torch.float32)
        hi = torch.tensor(self._hi, dtype=torch.float32)
        return aabb_near_far(origins, dirs, lo, hi, self.cfg.near)

    def _accumulate(self, batch: RayBatch) -> dict[str, torch.Tensor]:
        """Forward/backward in micro-batches of ``train_chunk`` samples; mean losses."""
        n = batch.origins.shape[0]
        chunk = max(1, self.cfg.train_chunk // self.model.train_samples_per_ray)
        sums: dict[str, torch.Tensor] = {}
        for part in batch.split(chunk):
            share = part.origins.shape[0] / n
            near, far = self._near_far(part.origins, part.dirs)
            out = self.model.losses(part, near, far, self._gen)
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
            with self._bounds_lock:  # the box holds every keyframe the batch may draw
                self._apply_box()
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
            lower_thread_priority(self.cfg.train_nice)
            while not self._stop.is_set():
                if len(self.buffer) == 0:
                    time.sleep(0.01)
                    continue
                with self._pause:
                    while self._pauses and not self._stop.is_set():
                        self._pause.wait()
                    if self._stop.is_set():
                        break
                    self._training = True
                try:
                    self.step(1)
                finally:
                    with self._pause:
                        self._training = False
                        self._pause.notify_all()
        except BaseException as exc:  # surfaced through last_error, thread ends
            self.last_error = exc

    @contextlib.contextmanager
    def paused(self):
        """While inside, the background thread starts no new training iteration.

        Entering waits for the iteration under way to finish; pauses nest, and
        training resumes when the last one exits. :meth:`step` called directly
        is not affected.
        """
        with self._pause:
            self._pauses += 1
            while self._training and threading.current_thread() is not self._thread:
                self._pause.wait()
        try:
            yield self
        finally:
            with self._pause:
                self._pauses -= 1
                self._pause.notify_all()

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
        with self._pause:
            self._pause.notify_all()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def reset(self) -> None:
        """Forget everything: keyframes, bounds, weights, optimiser; the generators are
        reseeded, so the mapper is as built (training thread kept)."""
        with self._bounds_lock, self._lock:
            self.buffer.clear()
            self._init_model()

    # ------------------------------------------------------------ rendering
    def _snapshot(self) -> tuple[FieldModel, np.ndarray, np.ndarray]:
        self._apply_pending_bounds()
        with self._lock:
            if self._lo is None:
                raise ValueError("nothing is mapped yet: add a keyframe before rendering")
            key = (self._iterations, id(self.model))
            if self._snap is None or self._snap_key != key:
                self._snap = copy.deepcopy(self.model).eval()
                self._snap_key = key
            return self._snap, self._lo.copy(), self._hi.copy()

    def _render_pause(self):
        return self.paused() if self.cfg.yield_to_render else contextlib.nullcontext()

    @torch.no_grad()
    def render_rays(self, origins: np.ndarray, dirs: np.ndarray,
                    depth: np.ndarray | None = None,
                    cancel: threading.Event | None = None) -> dict[str, np.ndarray]:
        """Render world rays (directions z-normalised in their camera) in chunks.

        ``depth`` (N,) measured z-depth per ray (0 or non-finite = none; beyond
        ``max_depth`` ignored) lets the fast backend sample around the surface
        (``render_with_depth``); None renders from the field alone. ``cancel`` is
        checked before each chunk: once set, :class:`RenderCancelled` is raised.
        """
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
        with self._render_pause():
            model, lo, hi = self._snapshot()
            lo_t = torch.tensor(lo, dtype=torch.float32)
            hi_t = torch.tensor(hi, dtype=torch.float32)
            per_ray = model.samples_per_rendered_ray(with_depth=z_all is not None)
            chunk = max(1, self.cfg.render_chunk // per_ray)
            for s in range(0, o_all.shape[0], chunk):
                if cancel is not None and cancel.is_set():
                    raise RenderCancelled(f"render cancelled after {s} of {o_all.shape[0]} "
                                          "rays")
                o, d = o_all[s:s + chunk], d_all[s:s + chunk]
                near, far = aabb_near_far(o, d, lo_t, hi_t, self.cfg.near)
                out = model.render_rays(o, d, near, far,
                                        None if z_all is None else z_all[s:s + chunk])
                for k in parts:
                    parts[k].append(out[k])
        rgb = torch.cat(parts["rgb"]).clamp(0.0, 1.0)
        emb = torch.cat(parts["embedding"])
        return {"rgb": rgb.numpy(), "depth": torch.cat(parts["depth"]).numpy(),
                "embedding": emb.numpy(),
                "entropy": L.entropy_torch(emb[:, : self.channels]).numpy()}

    def render(self, pose: np.ndarray, intrinsics: Intrinsics, height: int | None = None,
               width: int | None = None, depth: np.ndarray | None = None,
               cancel: threading.Event | None = None) -> dict[str, np.ndarray]:
        """Render a view: rgb (H, W, 3) in [0, 1], depth (H, W), embedding (H, W,
        :attr:`field_channels`: the S logits, then any distilled features), entropy (of
        the logits).

        With ``height``/``width`` the camera is rendered at that resolution
        (intrinsics scaled accordingly). ``depth``: the view's measured depth
        image at ``intrinsics``' size (resampled, nearest, to the rendered size),
        used to place the samples (see :meth:`render_rays`). ``cancel``: set it
        (from any thread) to stop the render between chunks with
        :class:`RenderCancelled`, e.g. on shutdown.
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
        out = self.render_rays(o, d, None if z is None else z[v, u], cancel)
        h, w = intr.height, intr.width
        return {"rgb": out["rgb"].reshape(h, w, 3).astype(np.float32),
                "depth": out["depth"].reshape(h, w).astype(np.float32),
                "embedding": out["embedding"].reshape(h, w, -1).astype(np.float32),
                "entropy": out["entropy"].reshape(h, w).astype(np.float32)}

    @torch.no_grad()
    def query(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Embedding (N, :attr:`field_channels`: logits, then any distilled features) and
        the logits' entropy (N,) of the field at world points (N, 3)."""
        pts = np.asarray(points, dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must be (N, 3), got shape {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise ValueError("points have non-finite coordinates")
        model, _, _ = self._snapshot()
        embs = [model.query(torch.from_numpy(pts[s:s + 65536]))
                for s in range(0, len(pts), 65536)]
        emb = torch.cat(embs) if embs else torch.zeros(0, self.field_channels)
        return emb.numpy(), L.entropy_torch(emb[:, : self.channels]).numpy()

    # ------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> None:
        """Weights, optimiser, bounds, the keyframe buffer and every config section the map
        was built with (mapper, keyframes, backend), so training can resume."""
        self._apply_pending_bounds()
        with self._lock:
            state = {
                "version": SAVE_VERSION, "channels": self.channels,
                "feature_channels": self.feature_channels,
                "config": {"mapper": to_dict(self.cfg), "keyframes": to_dict(self.keyframe_cfg),
                           "backend": to_dict(self.backend_cfg)},
                "iterations": self._iterations,
                "bounds": None if self._lo is None else torch.tensor(np.stack([self._lo,
                                                                              self._hi])),
                "model": self.model.state_dict(), "optimizer": self._opt.state_dict(),
                "buffer": self.buffer.state(),
            }
            torch.save(state, str(path))

    @classmethod
    def load(cls, path: str | Path, **overrides) -> "Mapper":
        """A mapper restored by :meth:`save`.

        ``overrides``: parameter values to change, by name, from the mapper, keyframes
        or the map's backend section (the backend itself cannot change).
        """
        state = read_torch_file(path, "cpu", "map")
        if not isinstance(state, dict) or "version" not in state:
            raise ValueError(f"{path} is not a neurncd mapper file")
        if state["version"] != SAVE_VERSION:
            raise ValueError(f"{path} is a version {state['version']} map; this neurncd reads "
                             f"version {SAVE_VERSION} (which records the backend's settings): "
                             "build the map again")
        sections = {k: dict(v) for k, v in state["config"].items()}
        # Maps saved before mapper.distill_features existed never distilled features.
        sections["mapper"].setdefault("distill_features", False)
        backend = sections["mapper"]["backend"]
        classes = {"mapper": MapperConfig, "keyframes": KeyframeConfig,
                   "backend": backends.get(backend).config}
        for key, value in overrides.items():
            if key == "backend":
                raise ConfigError(f"{path}: the map was built by backend {backend!r}, which "
                                  "cannot be changed on load")
            owner = [n for n, c in classes.items() if key in {s.name for s in specs(c)}]
            if not owner:
                raise ConfigError(f"{key}: unknown parameter of a {backend!r} map")
            sections[owner[0]][key] = value
        prefixes = {"mapper": "mapper.", "keyframes": "keyframes.",
                    "backend": f"mapper.{backend}."}
        built = {n: build(c, sections[n], prefix=prefixes[n]) for n, c in classes.items()}
        m = cls(built["mapper"], int(state["channels"]), built["keyframes"], built["backend"],
                int(state.get("feature_channels", 0)))
        with m._lock:
            if state["bounds"] is not None:
                b = state["bounds"].numpy()
                m._lo, m._hi = b[0].astype(np.float64), b[1].astype(np.float64)
                m.model.set_bounds(torch.tensor(m._lo, dtype=torch.float32),
                                   torch.tensor(m._hi, dtype=torch.float32), keep=False,
                                   generator=m._gen)
            m.model.load_state_dict(state["model"])
            m._opt = torch.optim.Adam(m.model.param_groups())
            m._opt.load_state_dict(state["optimizer"])
            m._iterations = int(state["iterations"])
            m.buffer.load_state(state["buffer"])
            # Resumed training draws fresh numbers, reproducibly from the seed.
            m._gen.manual_seed(m.cfg.seed + m._iterations)
            m._rng = np.random.default_rng(m.cfg.seed + m._iterations)
        return m
