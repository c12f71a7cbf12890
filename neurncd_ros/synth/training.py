"""Synthetic scenes as a training data source for the backbone.

The default backbone trains on rendered frames of the synthetic seeds
(:mod:`.seeds`). Frames are generated once per (seed, frames, config, generator
source) and cached as npz under a temporary folder (never inside the
repository). The key includes a hash of the generator's source files, so a
changed generator never serves stale frames (frames of an older generator
would score the backbone on scenes it no longer describes).

:func:`synthetic_data` returns what ``core.backbone.train.train_backbone``
takes: train and validation arrays, and the record of where they came from.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.params import to_dict

DEFAULT_CACHE = Path(os.environ.get("NEURNCD_SYNTH_CACHE", "/tmp/neurncd_synth_cache"))

# The files that decide what a seed renders (this module and the seed split do not).
_GENERATOR_FILES = ("__init__.py", "generator.py", "materials.py", "render.py", "scene.py")


def generator_hash() -> str:
    """Short hash of the synthetic generator's source (part of every cache key)."""
    h = hashlib.sha1()
    for name in _GENERATOR_FILES:
        path = Path(__file__).parent / name
        h.update(name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:10]


def training_synth_config(fps: float = 1.0):
    """Synthetic config of backbone training/validation: defaults, frames ``1/fps`` s apart.

    At the default 30 fps a 30-frame run covers one second of walking, i.e.
    nearly the same view 30 times; 1 fps spreads the frames over the room.
    """
    from .generator import SynthConfig
    return SynthConfig(fps=fps)


def synth_frames(seed: int, frames: int, cache_dir: Path | None = DEFAULT_CACHE,
                 synth_cfg=None) -> dict[str, np.ndarray]:
    """rgb (N,H,W,3) uint8, depth (N,H,W) float32, semantic (N,H,W) uint16 of one scene.

    Generated with ``synth.generate(seed, frames, cfg)`` and cached as npz
    keyed by seed, frame count, a hash of the synthetic config and a hash of
    the generator's source (:func:`generator_hash`).
    """
    from .generator import SynthConfig, generate

    cfg = synth_cfg if synth_cfg is not None else SynthConfig()
    key = hashlib.sha1(json.dumps(to_dict(cfg), sort_keys=True, default=str)
                       .encode()).hexdigest()[:10]
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"synth_s{seed}_n{frames}_{key}_{generator_hash()}.npz"
        if path.is_file():
            with np.load(path) as z:
                return {k: z[k] for k in ("rgb", "depth", "semantic")}
    rgb, depth, sem = [], [], []
    for fr in generate(seed, frames, cfg):
        if fr.semantic is None:
            raise ValueError(f"synthetic seed {seed}: frame has no semantic ground truth")
        rgb.append(fr.rgb)
        depth.append(fr.depth.astype(np.float32))
        sem.append(fr.semantic.astype(np.uint16))
    data = {"rgb": np.stack(rgb), "depth": np.stack(depth), "semantic": np.stack(sem)}
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **data)
        tmp.replace(path)
    return data


def _synth_job(args):
    seed, frames, cache_dir, synth_cfg = args
    synth_frames(seed, frames, cache_dir, synth_cfg)
    return seed


def load_scenes(seeds: Sequence[int], frames: int, cache_dir: Path | None = DEFAULT_CACHE,
                synth_cfg=None, progress: bool = True, what: str = "scenes",
                workers: int = 1) -> dict[str, np.ndarray]:
    """Concatenate :func:`synth_frames` over seeds (one progress bar).

    ``workers`` > 1 renders missing scenes in that many processes first (needs
    a cache folder to hand the arrays back).
    """
    from tqdm import tqdm

    seeds = list(seeds)
    if synth_cfg is None:
        synth_cfg = training_synth_config()
    if workers > 1 and cache_dir is not None and len(seeds) > 1:
        import multiprocessing as mp
        jobs = [(s, frames, cache_dir, synth_cfg) for s in seeds]
        with mp.get_context("fork").Pool(workers) as pool:
            for _ in tqdm(pool.imap_unordered(_synth_job, jobs), total=len(jobs),
                          desc=f"render {what}", disable=not progress, unit="seed"):
                pass
    parts = [synth_frames(s, frames, cache_dir, synth_cfg)
             for s in tqdm(seeds, desc=f"synth {what}", disable=not progress, unit="seed")]
    return {k: np.concatenate([p[k] for p in parts]) for k in ("rgb", "depth", "semantic")}


def synthetic_data(train_seeds: Sequence[int], val_seeds: Sequence[int],
                   frames_per_seed: int = 20, val_frames_per_seed: int = 30,
                   fps: float = 1.0, cache_dir: Path | None = DEFAULT_CACHE,
                   workers: int = 1, progress: bool = True
                   ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict]:
    """(train arrays, validation arrays, source record) of the synthetic seeds.

    The source record names the seeds, frame counts, frame rate, generator hash
    and synthetic config, so a training record says exactly what it saw.
    """
    if not train_seeds or not val_seeds:
        raise ValueError("need at least one training seed and one validation seed")
    overlap = set(train_seeds) & set(val_seeds)
    if overlap:
        raise ValueError(f"validation seeds overlap training seeds: {sorted(overlap)}")
    if frames_per_seed < 1 or val_frames_per_seed < 1:
        raise ValueError("frames_per_seed and val_frames_per_seed must be >= 1")
    cfg = training_synth_config(fps)
    train = load_scenes(train_seeds, frames_per_seed, cache_dir, cfg, progress, "train",
                        workers)
    val = load_scenes(val_seeds, val_frames_per_seed, cache_dir, cfg, progress, "val",
                      workers)
    source = {"trained_on": "synthetic",
              "train_seeds": list(map(int, train_seeds)),
              "val_seeds": list(map(int, val_seeds)),
              "frames_per_seed": int(frames_per_seed), "synth_fps": fps,
              "synth_generator_hash": generator_hash(), "synth_config": to_dict(cfg)}
    return train, val, source
