"""Semantic-NeRF label propagation (Zhi et al. 2021) as a baseline on the engine's stream.

One separate field per label fraction, built from the same configuration as the
engine's field (backend, sampling, scene box, seed), with an embedding head of one
channel per known class trained by cross-entropy (``embedding_loss: cross_entropy``
in the backend's section) plus the backend's photometric (and, for the fast
backend, depth and free-space) losses; no backbone embedding reaches it.

Same keyframes, same training: the keyframes the engine admitted are added in the
engine's order, and the field trains up to the iteration count the engine's field
had reached at each labelled frame and at the end of the stream (every keyframe is
a labelled frame, so the replay sees the same buffer at every iteration).

Labels: at each keyframe, ``fraction`` of its pixels are drawn once, uniformly among
the pixels whose ground truth is a known class (all of them if there are fewer),
from one ``numpy.random.Generator`` seeded by ``semnerf.label_seed``; novel-class
and void pixels are never labels. A keyframe without ground truth is added with no
label: the supervision comes only from frames with ground truth (``keyframes`` and
``keyframes_with_ground_truth`` in the facts count both). A labelled pixel's target
is its class one-hot, an unlabelled one is all zero (``losses.label_cross_entropy``
leaves it out).

Scoring: each evaluation frame (a labelled frame with ground truth) is rendered at
its pose and measured depth at ``mapper_node.render_scale`` from the field alone
(no backbone fallback), its argmax over the known classes resized (nearest) to the
frame and scored by the one ``discovery.metrics.Evaluator`` (its known-class mIoU
is the row's figure; it has no novel class). ``label_fit`` is the share of the
labelled pixels whose rendered class is their label: how well the field holds its
own supervision.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .. import classes
from ..camera import rays
from ..frame import Frame
from ..params import param
from .progress import tick

if TYPE_CHECKING:
    from tqdm import tqdm

ROW_PREFIX = "semnerf_"


@dataclasses.dataclass(frozen=True)
class SemanticNerfConfig:
    """The Semantic-NeRF label-propagation baseline of ``neurncd eval --baselines``."""

    label_fractions: list[float] = param(
        [0.01, 0.05, 0.10], "share of each keyframe's pixels that get their ground-truth "
        "label (known classes only); one separate field and one row per fraction",
        lo=0.0001, hi=1.0)
    label_seed: int = param(0, "seed of the generator that draws the labelled pixels",
                            lo=0, hi=2 ** 31 - 1)
    training_factor: float = param(
        25.0, "iterations of each Semantic-NeRF field relative to the engine field's, at every "
        "point of the stream. 25 (about 600 per 300-frame scene) lets them hold 97-99 % of "
        "their own labels (label_fit in eval.json), the baseline a comparison should be made "
        "against; 1 = the engine's schedule (run.training_rate_hz, the live graph's), which "
        "starves them (about 24 iterations: they held 27-60 % of their labels and scored "
        "known 4.5-5.8)", lo=0.01, hi=1000.0)


def check_fraction(fraction) -> float:
    """The label fraction as a float in (0, 1], or a ValueError naming it."""
    try:
        f = float(fraction)
    except (TypeError, ValueError):
        raise ValueError(f"label fraction {fraction!r} is not a number (a share of each "
                         "keyframe's pixels in (0, 1])") from None
    if not (math.isfinite(f) and 0.0 < f <= 1.0):
        raise ValueError(f"label fraction {fraction!r} must be in (0, 1] (a share of each "
                         "keyframe's pixels, e.g. 0.01 for 1 %)")
    return f


def row_key(fraction) -> str:
    """Row name of a fraction: 0.01 -> ``semnerf_1pct``, 0.005 -> ``semnerf_0p5pct``."""
    pct = format(100.0 * check_fraction(fraction), ".6g").replace(".", "p")
    return f"{ROW_PREFIX}{pct}pct"


def row_title(key: str) -> str:
    """``semnerf_1pct`` -> ``Semantic-NeRF 1%`` (Table 2's wording)."""
    return f"Semantic-NeRF {key[len(ROW_PREFIX):-3].replace('p', '.')}%"


def draw_labels(semantic: np.ndarray, fraction, rng: np.random.Generator) -> np.ndarray:
    """(H, W) int16: the known-class channel (``classes.KNOWN_CHANNEL``) at the drawn
    pixels, -1 elsewhere; round(fraction * H * W) pixels among the known-class ones."""
    f = check_fraction(fraction)
    sem = np.asarray(semantic)
    if sem.ndim != 2 or not np.issubdtype(sem.dtype, np.integer):
        raise ValueError(f"semantic must be an (H, W) integer image of NYU-13 ids, got "
                         f"shape {sem.shape} dtype {sem.dtype}")
    flat = sem.ravel()
    candidates = np.flatnonzero(np.isin(flat, classes.KNOWN_IDS))
    n = min(int(round(f * flat.size)), candidates.size)
    out = np.full(flat.size, -1, np.int16)
    if n:
        pick = rng.choice(candidates, size=n, replace=False)
        out[pick] = classes.KNOWN_CHANNEL[flat[pick]]
    return out.reshape(sem.shape)


def one_hot(labels: np.ndarray, channels: int = classes.NUM_KNOWN) -> np.ndarray:
    """(H, W, channels) float32 targets: one-hot where labelled (>= 0), zero elsewhere."""
    out = np.zeros(labels.shape + (channels,), np.float32)
    v, u = np.nonzero(labels >= 0)
    out[v, u, labels[v, u]] = 1.0
    return out


def _mapper(cfg):
    from ..field.mapper import Mapper

    name = cfg.mapper.backend
    backend_cfg = cfg.section(f"mapper.{name}")
    if "embedding_loss" not in {f.name for f in dataclasses.fields(backend_cfg)}:
        raise ValueError(f"the Semantic-NeRF baseline needs a field backend with a "
                         f"cross-entropy head (embedding_loss); mapper.{name} has none")
    backend_cfg = dataclasses.replace(backend_cfg, embedding_loss="cross_entropy")
    return Mapper(cfg.mapper, classes.NUM_KNOWN, keyframes=cfg.keyframes,
                  backend_cfg=backend_cfg)


def _frame(keep: dict, i: int) -> Frame:
    return Frame(keep["stamp"][i], keep["rgb"][i], keep["depth"][i], keep["pose"][i],
                 keep["intr"][i])


FIT_PIXELS = 2000
"""Labelled pixels per keyframe (an even stride through them) rendered for ``label_fit``."""


def label_fit(mapper, keep: dict, labelled: list[tuple[int, np.ndarray]]) -> float | None:
    """Share of the labelled keyframe pixels (at most ``FIT_PIXELS`` per keyframe) whose
    rendered class is their label."""
    hits = total = 0
    for i, lab in labelled:
        v, u = np.nonzero(lab >= 0)
        step = max(1, -(-v.size // FIT_PIXELS))
        v, u = v[::step], u[::step]
        if not v.size:
            continue
        o, d = rays(keep["pose"][i], keep["intr"][i], u, v)
        emb = mapper.render_rays(o, d, keep["depth"][i][v, u])["embedding"]
        hits += int((emb.argmax(axis=1) == lab[v, u]).sum())
        total += v.size
    return hits / total if total else None


def semantic_nerf(keep: dict, cfg, fraction, iterations: int, seed: int | None = None,
                  bar: tqdm | None = None) -> tuple[list[np.ndarray], dict]:
    """Train one label-propagation field on the cached stream of :func:`evaluate.collect`
    (``iterations``: the engine field's total; the field trains
    ``semnerf.training_factor`` times the engine's iterations at every point) and label
    every evaluation frame.

    A keyframe without ground truth joins the field as the engine's did, with no label
    (its photometric and depth terms only): the labels come only from keyframes with
    ground truth. ``bar`` (a progress bar) advances one per frame trained up to, then
    one per frame rendered.

    Returns the (H, W) uint16 NYU-13 label images and facts about the run."""
    f = check_fraction(fraction)
    seed = cfg.semnerf.label_seed if seed is None else seed

    def scaled(engine_iterations: int) -> int:
        return int(round(cfg.semnerf.training_factor * engine_iterations))

    t0 = time.perf_counter()
    mapper = _mapper(cfg)
    rng = np.random.default_rng(seed)
    labelled: list[tuple[int, np.ndarray]] = []
    n = len(keep["stamp"])
    added = 0
    for i in range(n):
        if keep["keyframe"][i]:
            sem = keep["semantic"][i]
            if sem is None:  # no ground truth: the same keyframe, without labels
                lab = np.full(keep["depth"][i].shape, -1, np.int16)
            else:
                lab = draw_labels(sem, f, rng)
                labelled.append((i, lab))
            mapper.add_keyframe(_frame(keep, i), one_hot(lab), force=True)
            added += 1
        todo = scaled(keep["iterations"][i]) - mapper.iterations
        if todo > 0 and len(mapper.buffer):
            mapper.step(todo)
        tick(bar, phase="train", iterations=mapper.iterations)
    if scaled(iterations) > mapper.iterations and len(mapper.buffer):
        mapper.step(scaled(iterations) - mapper.iterations)
    t_train = time.perf_counter() - t0
    ids = classes.CHANNEL_TO_ID
    preds = []
    s = cfg.mapper_node.render_scale
    for i in range(n):
        h, w = keep["depth"][i].shape
        if not len(mapper.buffer) or keep["semantic"][i] is None:  # nothing to render
            pred = np.zeros((h, w), np.uint16)  # or a frame no score reads: not rendered
        else:
            rh, rw = max(1, round(h * s)), max(1, round(w * s))
            out = mapper.render(keep["pose"][i], keep["intr"][i], rh, rw,
                                depth=keep["depth"][i])
            lab = ids[out["embedding"].argmax(axis=2)].astype(np.uint16)
            pred = cv2.resize(lab, (w, h), interpolation=cv2.INTER_NEAREST)
        preds.append(pred)
        tick(bar, phase="render", iterations=mapper.iterations)
    fit = label_fit(mapper, keep, labelled) if labelled else None
    counts = [int((lab >= 0).sum()) for _, lab in labelled]
    info = {"fraction": f, "seed": int(seed), "keyframes": added,
            "keyframes_with_ground_truth": len(labelled),
            "iterations": mapper.iterations,
            "training_factor": cfg.semnerf.training_factor,
            "labels_per_keyframe": float(np.mean(counts)) if counts else 0.0,
            "label_fit": fit, "seconds_training": round(t_train, 2),
            "seconds": round(time.perf_counter() - t0, 2)}
    return preds, info
