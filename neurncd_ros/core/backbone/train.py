"""Train the default small backbone on synthetic scenes (the paper's protocol).

Protocol, following NeurNCD's use of ESANet: cross-entropy over the 9 known
NYU-13 classes only; pixels of the novel classes (ceiling, picture, tv,
window) and void pixels are ignored in the loss, so the net never learns the
novel classes and its pre-softmax logits stay an honest "known-class"
embedding. Validation uses held-out synthetic seeds (disjoint scenes).

Known-class mIoU (percent), as reported here: over all validation pixels whose
ground truth is one of the 9 known classes, the prediction is the argmax
among the 9 channels; IoU_k = |pred=k and gt=k| / |pred=k or gt=k| counted
on those pixels only; the mean runs over the known classes present in the
validation ground truth.

Synthetic frames are generated once per (seed, frames, config, generator
source) and cached as npz under a temporary folder (never inside the
repository). The key includes a hash of the generator's source files, so a
changed generator never serves stale frames.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from .. import classes
from ...synth import seeds
from . import small

IGNORE = 255
"""Target value of pixels left out of the loss (void and novel classes)."""

DEFAULT_CACHE = Path(os.environ.get("NEURNCD_SYNTH_CACHE", "/tmp/neurncd_synth_cache"))

# NYU-13 id -> training target (channel index for known classes, IGNORE otherwise).
_ID_TO_TARGET = np.full(65536, IGNORE, dtype=np.uint8)
for _cid, _k in classes.ID_TO_CHANNEL.items():
    _ID_TO_TARGET[_cid] = _k


def semantic_to_target(semantic: np.ndarray) -> np.ndarray:
    """NYU-13 label image (uint16) -> uint8 targets: channel index, or IGNORE."""
    if semantic.dtype != np.uint16:
        raise ValueError(f"semantic must be uint16 NYU-13 ids, got {semantic.dtype}")
    return _ID_TO_TARGET[semantic]


# ----------------------------------------------------------------------------- data
def _synth_cfg_dict(cfg) -> dict:
    from ..params import to_dict
    return to_dict(cfg)


def generator_hash() -> str:
    """Short hash of the synthetic generator's source (part of the cache key)."""
    from ... import synth

    h = hashlib.sha1()
    for path in sorted(Path(synth.__file__).parent.glob("*.py")):
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:10]


def synth_frames(seed: int, frames: int, cache_dir: Path | None = DEFAULT_CACHE,
                 synth_cfg=None) -> dict[str, np.ndarray]:
    """rgb (N,H,W,3) uint8, depth (N,H,W) float32, semantic (N,H,W) uint16 of one scene.

    Generated with ``synth.generate(seed, frames, cfg)`` and cached as npz
    keyed by seed, frame count, a hash of the synthetic config and a hash of
    the generator's source (:func:`generator_hash`).
    """
    from ... import synth

    cfg = synth_cfg if synth_cfg is not None else synth.SynthConfig()
    key = hashlib.sha1(json.dumps(_synth_cfg_dict(cfg), sort_keys=True, default=str)
                       .encode()).hexdigest()[:10]
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / f"synth_s{seed}_n{frames}_{key}_{generator_hash()}.npz"
        if path.is_file():
            with np.load(path) as z:
                return {k: z[k] for k in ("rgb", "depth", "semantic")}
    rgb, depth, sem = [], [], []
    for fr in synth.generate(seed, frames, cfg):
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


def training_synth_config(fps: float = 1.0):
    """Synthetic config of backbone training/validation: defaults, frames ``1/fps`` s apart.

    At the default 30 fps a 30-frame run covers one second of walking, i.e.
    nearly the same view 30 times; 1 fps spreads the frames over the room.
    """
    from ... import synth
    return synth.SynthConfig(fps=fps)


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


# ----------------------------------------------------------------------------- augmentation
def augment(rgb: torch.Tensor, depth: torch.Tensor, target: torch.Tensor,
            gen: torch.Generator, scale: tuple[float, float] = (0.8, 1.35),
            jitter: float = 0.25, crop: tuple[int, int] | None = None
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random flip, scale-crop (zoom in/out with translation) and colour jitter, batched.

    ``crop`` = (h, w) cuts windows of that size (at the sampled zoom) instead of
    keeping the full frame: cheaper steps, same apparent object sizes.

    rgb (B,3,H,W) float 0..255, depth (B,1,H,W) m, target (B,H,W) long with
    IGNORE. One affine warp per sample (grid_sample): bilinear for rgb,
    nearest for depth and labels; area outside the source is a depth hole
    and ignored in the loss. Zooming changes apparent size but not metric
    depth, which is what happens when the same object is seen at another
    focal length.
    """
    b, _, h, w = rgb.shape
    oh, ow = crop if crop is not None else (h, w)
    s = torch.empty(b).uniform_(*scale, generator=gen)  # >1 zooms in
    flip = (torch.rand(b, generator=gen) < 0.5).float() * 2 - 1
    sx, sy = (ow / w) / s, (oh / h) / s  # window half-size in normalised source coords
    tx = (torch.rand(b, generator=gen) * 2 - 1) * ((1 - sx).clamp(min=0) + 0.05)
    ty = (torch.rand(b, generator=gen) * 2 - 1) * ((1 - sy).clamp(min=0) + 0.05)
    theta = torch.zeros(b, 2, 3)
    theta[:, 0, 0] = flip * sx
    theta[:, 1, 1] = sy
    theta[:, 0, 2] = tx
    theta[:, 1, 2] = ty
    grid = F.affine_grid(theta, [b, 1, oh, ow], align_corners=False)
    rgb = F.grid_sample(rgb, grid, mode="bilinear", padding_mode="border", align_corners=False)
    depth = F.grid_sample(depth, grid, mode="nearest", padding_mode="zeros", align_corners=False)
    lab = F.grid_sample((target + 1).float()[:, None], grid, mode="nearest",
                        padding_mode="zeros", align_corners=False)[:, 0].long() - 1
    target = torch.where(lab < 0, torch.full_like(lab, IGNORE), lab)
    # Colour jitter: brightness, contrast, saturation, per-channel gain.
    bright = 1 + (torch.rand(b, 1, 1, 1, generator=gen) * 2 - 1) * jitter
    contrast = 1 + (torch.rand(b, 1, 1, 1, generator=gen) * 2 - 1) * jitter
    sat = 1 + (torch.rand(b, 1, 1, 1, generator=gen) * 2 - 1) * jitter
    gain = 1 + (torch.rand(b, 3, 1, 1, generator=gen) * 2 - 1) * jitter * 0.3
    grey = rgb.mean(dim=1, keepdim=True)
    rgb = grey + (rgb - grey) * sat
    mean = rgb.mean(dim=(1, 2, 3), keepdim=True)
    rgb = (mean + (rgb - mean) * contrast) * bright * gain
    rgb = rgb + torch.randn(rgb.shape, generator=gen) * 3.0  # sensor noise
    return rgb.clamp(0, 255), depth, target


# ----------------------------------------------------------------------------- metrics
def confusion(pred: np.ndarray, target: np.ndarray, n: int = classes.NUM_KNOWN) -> np.ndarray:
    """(n, n) counts [gt, pred] over pixels whose target is a known class (< n)."""
    keep = target < n
    idx = target[keep].astype(np.int64) * n + pred[keep].astype(np.int64)
    return np.bincount(idx, minlength=n * n).reshape(n, n)


def scores_from_confusion(conf: np.ndarray) -> dict:
    """Known-class mIoU (percent, over classes present in the GT), per-class IoU, accuracy."""
    tp = np.diag(conf).astype(np.float64)
    gt = conf.sum(1).astype(np.float64)
    pr = conf.sum(0).astype(np.float64)
    union = gt + pr - tp
    present = gt > 0
    iou = np.where(union > 0, tp / np.maximum(union, 1), np.nan)
    miou = float(np.nanmean(np.where(present, iou, np.nan)) * 100) if present.any() else math.nan
    acc = float(tp.sum() / max(conf.sum(), 1))
    return {"known_miou": miou, "pixel_accuracy": acc,
            "iou": {name: (None if not present[k] else round(float(iou[k]) * 100, 2))
                    for k, name in enumerate(classes.KNOWN_NAMES)}}


def evaluate(model: torch.nn.Module, data: dict[str, np.ndarray], batch: int = 8,
             progress: bool = False) -> dict:
    """Known-class mIoU etc. of ``model`` on frames ``data`` (see module doc)."""
    from tqdm import tqdm

    model.eval()
    conf = np.zeros((classes.NUM_KNOWN, classes.NUM_KNOWN), dtype=np.int64)
    n = len(data["rgb"])
    with torch.inference_mode():
        for i in tqdm(range(0, n, batch), desc="validate", disable=not progress, leave=False):
            rgb = torch.from_numpy(data["rgb"][i: i + batch]).permute(0, 3, 1, 2).float()
            depth = torch.from_numpy(np.nan_to_num(data["depth"][i: i + batch], nan=0.0,
                                                   posinf=0.0, neginf=0.0))[:, None]
            pred = model.predict_raw(rgb, depth).argmax(1).numpy()
            conf += confusion(pred, semantic_to_target(data["semantic"][i: i + batch]))
    return scores_from_confusion(conf)


# ----------------------------------------------------------------------------- training
def class_weights(targets: np.ndarray, power: float = 0.5, cap: float = 5.0) -> np.ndarray:
    """Per-class loss weights ~ frequency^-power, normalised to mean 1, capped.

    Softened inverse frequency keeps rare known classes (books, objects) from
    being swamped by wall and floor without over-predicting them.
    """
    counts = np.bincount(targets[targets != IGNORE].ravel(),
                         minlength=classes.NUM_KNOWN).astype(np.float64)
    freq = counts / max(counts.sum(), 1)
    w = np.where(freq > 0, np.maximum(freq, 1e-6) ** -power, 0.0)
    w = w / w[w > 0].mean()
    return np.minimum(w, cap).astype(np.float32)


def train_backbone(out_path: str | Path, train_seeds: Sequence[int], val_seeds: Sequence[int],
                   frames_per_seed: int = 20, epochs: int = 12, batch_size: int = 8,
                   lr: float = 4e-3, weight_decay: float = 1e-4, seed: int = 0,
                   num_threads: int = 2, cache_dir: Path | None = DEFAULT_CACHE,
                   max_minutes: float = 0.0, progress: bool = True, synth_cfg=None,
                   fps: float = 1.0, val_frames_per_seed: int = 30, workers: int = 1,
                   crop: tuple[int, int] | None = (192, 256), init: str | None = None,
                   data: tuple[dict, dict] | None = None, command: str | None = None,
                   widths: tuple[int, int, int, int] = small.DEFAULT_WIDTHS,
                   val_every: int = 0) -> dict:
    """Train the default net, save weights to ``out_path`` and the record next to it.

    Returns the training record (also written as ``<out_path stem>.json``):
    command, seeds, hyper-parameters, validation scores, time, versions.
    ``max_minutes`` > 0 sets the schedule length by time instead of epochs
    (the learning-rate schedule is stretched to the estimated step count).
    ``synth_cfg`` defaults to :func:`training_synth_config` (``fps``); ``data`` =
    (train, val) dicts bypasses the synthetic generator (tests). ``init`` continues
    from an earlier weight file (its record, if beside it, is kept under "init").
    ``val_every`` > 0 validates every that many steps and logs the score in the
    record's history (for the record only: the final weights are always those
    of the last step, no checkpoint is selected on the validation seeds).
    The reported validation scores are those of the saved fp16 weights.
    """
    from tqdm import tqdm

    if not train_seeds or not val_seeds:
        raise ValueError("need at least one training seed and one validation seed")
    overlap = set(train_seeds) & set(val_seeds)
    if overlap:
        raise ValueError(f"validation seeds overlap training seeds: {sorted(overlap)}")
    if epochs < 1 or batch_size < 1 or frames_per_seed < 1:
        raise ValueError("epochs, batch_size and frames_per_seed must be >= 1")
    t_start = time.time()
    if num_threads > 0:
        torch.set_num_threads(num_threads)
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)

    if data is None:
        if synth_cfg is None:
            synth_cfg = training_synth_config(fps)
        train = load_scenes(train_seeds, frames_per_seed, cache_dir, synth_cfg, progress,
                            "train", workers)
        val = load_scenes(val_seeds, val_frames_per_seed, cache_dir, synth_cfg, progress,
                          "val", workers)
    else:
        train, val = data
    t_data = time.time() - t_start
    targets = semantic_to_target(train["semantic"])
    weights = torch.from_numpy(class_weights(targets))
    depth_all = np.nan_to_num(train["depth"], nan=0.0, posinf=0.0, neginf=0.0)
    n = len(targets)
    steps_per_epoch = max(n // batch_size, 1)
    total_steps = steps_per_epoch * epochs

    model = small.SmallRGBDNet(widths=tuple(widths))
    init_record = None
    if init:
        prev_model = small.load_weights(init)
        if prev_model.widths != model.widths:
            raise ValueError(f"--init {init} has widths {prev_model.widths}, "
                             f"training widths {model.widths}")
        model.load_state_dict(prev_model.state_dict())
        rec_path = Path(init).with_suffix(".json")
        init_record = {"weights": str(init)}
        if rec_path.is_file():
            prev = json.loads(rec_path.read_text())
            init_record.update({k: prev.get(k) for k in (
                "command", "steps", "epochs_run", "lr", "train_seconds", "val_known_miou",
                "init")})
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=weight_decay)
    warmup = max(min(100, total_steps // 20), 1)

    def lr_at(step: int, total: int) -> float:
        if step < warmup:
            return lr * (step + 1) / warmup
        frac = min((step - warmup) / max(total - warmup, 1), 1.0)
        return lr * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * frac)))

    history = []
    val_curve: list[dict] = []
    step = 0
    t_train = time.time()
    bar = tqdm(total=total_steps, desc="train backbone", disable=not progress, unit="step")
    stop = False
    for epoch in range(epochs):
        model.train()
        order = rng.permutation(n)
        losses = []
        for i in range(steps_per_epoch):
            idx = np.sort(order[i * batch_size: (i + 1) * batch_size])
            rgb = torch.from_numpy(train["rgb"][idx]).permute(0, 3, 1, 2).float()
            depth = torch.from_numpy(depth_all[idx])[:, None]
            tgt = torch.from_numpy(targets[idx]).long()
            rgb, depth, tgt = augment(rgb, depth, tgt, gen, crop=crop)
            for g in opt.param_groups:
                g["lr"] = lr_at(step, total_steps)
            logits = model.predict_raw(rgb, depth)
            loss = F.cross_entropy(logits, tgt, weight=weights, ignore_index=IGNORE)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
            step += 1
            bar.update(1)
            bar.set_postfix(epoch=epoch, loss=f"{np.mean(losses[-20:]):.3f}")
            if max_minutes > 0 and step == 20:
                # Re-plan the schedule to fit the time budget.
                per_step = (time.time() - t_train) / step
                budget = max_minutes * 60 - (time.time() - t_start)
                total_steps = max(step + 1, min(total_steps, int(budget / per_step)))
                bar.total = total_steps
            if val_every > 0 and step % val_every == 0 and step < total_steps:
                score = evaluate(model, val)["known_miou"]
                val_curve.append({"step": step, "val_known_miou": round(score, 2)})
                tqdm.write(f"step {step}: validation known-class mIoU {score:.2f} %")
                model.train()
            if step >= total_steps:
                stop = True
                break
        entry = {"epoch": epoch, "loss": round(float(np.mean(losses)), 4), "steps": step}
        history.append(entry)
        if stop:
            break
    bar.close()
    train_time = time.time() - t_train
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    small.save_weights(model, str(out_path))
    shipped = small.load_weights(str(out_path))  # what users get: fp16 weights
    val_scores = evaluate(shipped, val, progress=progress)
    record = {
        "command": command if command is not None else " ".join(sys.argv),
        "arch": "SmallRGBDNet", "arch_version": small.ARCH_VERSION,
        "widths": list(model.widths),
        "parameters": small.count_parameters(model),
        "gflops_320x240": round(small.count_flops(model) / 1e9, 3),
        "train_seeds": list(map(int, train_seeds)), "val_seeds": list(map(int, val_seeds)),
        "frames_per_seed": frames_per_seed, "train_frames": int(n),
        "val_frames": int(len(val["rgb"])),
        "epochs_planned": epochs, "epochs_run": len(history), "steps": step,
        "batch_size": batch_size, "lr": lr, "weight_decay": weight_decay, "seed": seed,
        "class_weights": [round(float(x), 3) for x in weights],
        "loss": "cross-entropy over 9 known classes; void and novel "
                "(ceiling, picture, tv, window) ignored",
        "augmentation": f"flip, zoom 0.8-1.35, crop {crop}, colour jitter 0.25, rgb noise",
        "synth_fps": fps if data is None else None,
        "synth_generator_hash": generator_hash() if data is None else None,
        "val_known_miou": round(val_scores["known_miou"], 2),
        "val_pixel_accuracy": round(val_scores["pixel_accuracy"], 4),
        "val_iou": val_scores["iou"],
        "history": history, "val_curve": val_curve, "init": init_record,
        "data_seconds": round(t_data, 1), "train_seconds": round(train_time, 1),
        "total_seconds": round(time.time() - t_start, 1),
        "num_threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
        "torch": torch.__version__, "numpy": np.__version__, "python": platform.python_version(),
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    if synth_cfg is not None:
        record["synth_config"] = _synth_cfg_dict(synth_cfg)
    small.save_weights(model, str(out_path), extra={"val_known_miou": record["val_known_miou"]})
    record["weights_bytes"] = out_path.stat().st_size
    out_path.with_suffix(".json").write_text(json.dumps(record, indent=1) + "\n")
    if progress:
        print(summary(record))
    return record


def summary(record: dict) -> str:
    """A few readable lines about a finished training run."""
    ious = ", ".join(f"{k} {v:.1f}" for k, v in record["val_iou"].items() if v is not None)
    return (f"trained {record['steps']} steps ({record['epochs_run']} epochs, "
            f"{record['train_frames']} frames) in {record['train_seconds'] / 60:.1f} min\n"
            f"validation seeds {record['val_seeds']}: known-class mIoU "
            f"{record['val_known_miou']:.2f} %, pixel accuracy "
            f"{record['val_pixel_accuracy'] * 100:.1f} %\nper-class IoU: {ious}")


# ----------------------------------------------------------------------------- CLI
def _seed_list(text: str) -> list[int]:
    """'0-39' or '1000,1001' or '0-9,20' -> list of ints."""
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "-" in part[1:]:
            a, b = part.split("-", 1)
            out.extend(range(int(a), int(b) + 1))
        else:
            out.append(int(part))
    if not out:
        raise argparse.ArgumentTypeError(f"no seeds in {text!r}")
    return out


def seed_text(seeds: Sequence[int]) -> str:
    """[0, 1, 2, 5] -> '0-2,5' (the inverse of the --*-seeds parser)."""
    out, run = [], []
    for s in list(seeds) + [None]:
        if s is not None and run and s == run[-1] + 1:
            run.append(s)
            continue
        if run:
            out.append(f"{run[0]}-{run[-1]}" if len(run) > 2 else ",".join(map(str, run)))
        run = [s] if s is not None else []
    return ",".join(out)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``neurncd train-backbone``."""
    from .backbone import DEFAULT_WEIGHTS

    parser.add_argument("--out", default=str(DEFAULT_WEIGHTS),
                        help="weight file to write (record json goes next to it)")
    parser.add_argument("--train-seeds", type=_seed_list,
                        default=list(seeds.BACKBONE_TRAIN),
                        help="synthetic scene seeds to train on (default "
                        f"{seed_text(seeds.BACKBONE_TRAIN)}, see neurncd_ros/synth/seeds.py)")
    parser.add_argument("--val-seeds", type=_seed_list, default=list(seeds.BACKBONE_VAL),
                        help="held-out synthetic seeds for validation (default "
                        f"{seed_text(seeds.BACKBONE_VAL)})")
    parser.add_argument("--frames", type=int, default=20,
                        help="frames per training scene")
    parser.add_argument("--val-frames", type=int, default=30,
                        help="frames per validation scene")
    parser.add_argument("--fps", type=float, default=1.0,
                        help="synthetic frame rate: 1 spreads a scene's frames over its room")
    parser.add_argument("--workers", type=int, default=2,
                        help="processes rendering synthetic scenes")
    parser.add_argument("--epochs", type=int, default=32, help="passes over the training frames")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--lr", type=float, default=4e-3, help="peak AdamW learning rate")
    parser.add_argument("--seed", type=int, default=0, help="seed of init, order, augmentation")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (1 is fastest on a busy machine)")
    parser.add_argument("--crop", type=int, nargs=2, default=(192, 256), metavar=("H", "W"),
                        help="training window size after zoom")
    parser.add_argument("--max-minutes", type=float, default=0.0,
                        help="fit the schedule into this wall time (0 = run all epochs)")
    parser.add_argument("--widths", type=int, nargs=4, default=small.DEFAULT_WIDTHS,
                        metavar=("C0", "C1", "C2", "C3"),
                        help="channels of the stem and the three encoder stages")
    parser.add_argument("--val-every", type=int, default=1000,
                        help="validate every this many steps, for the record (0 = end only)")
    parser.add_argument("--init", default=None,
                        help="continue training from this weight file")
    parser.add_argument("--cache", default=str(DEFAULT_CACHE),
                        help="folder for cached synthetic frames (npz)")


def command_line(args: argparse.Namespace) -> str:
    """The ``neurncd train-backbone`` command that reproduces a run (every option spelt out)."""
    parts = ["neurncd", "train-backbone"]
    for key, value in sorted(vars(args).items()):
        if key in ("func", "command") or value is None:
            continue
        flag = "--" + key.replace("_", "-")
        if isinstance(value, (list, tuple)):
            if key.endswith("seeds"):
                parts += [flag, seed_text(value)]
            else:
                parts += [flag, *map(str, value)]
        else:
            parts += [flag, str(value)]
    return " ".join(parts)


def main(args: argparse.Namespace) -> int:
    """Run training from parsed arguments; print the summary."""
    train_backbone(args.out, args.train_seeds, args.val_seeds, frames_per_seed=args.frames,
                   epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, seed=args.seed,
                   num_threads=args.threads, cache_dir=Path(args.cache) if args.cache else None,
                   max_minutes=args.max_minutes, fps=args.fps,
                   val_frames_per_seed=args.val_frames, workers=args.workers,
                   crop=tuple(args.crop), init=args.init, widths=tuple(args.widths),
                   val_every=args.val_every, command=command_line(args))
    return 0


if __name__ == "__main__":
    _p = argparse.ArgumentParser(description="train the default small RGB-D backbone")
    add_arguments(_p)
    sys.exit(main(_p.parse_args()))
