"""`neurncd train-backbone`: choose the training data, then train with the core.

By default the data are the synthetic seeds of ``neurncd_ros.synth.seeds``
(what the shipped weights were trained on). ``--data`` trains on any bags,
dataset folders or NYUv2 labelled ``.mat`` files with semantic ground truth
(NYU-13 ids; novel classes masked out of the loss as always), resized to
``--size``; validation is ``--val-data``, or split off ``--data`` by frames
(the last ``--val-fraction`` of each file, a contiguous block, so validation
views are not neighbours of training views) or by whole files. The record
written next to the weights holds the command that reproduces the run, every
option spelt out, and what it was trained and validated on.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from ..core.backbone import data as train_data
from ..core.backbone import small, train
from ..synth import seeds
from ..synth.training import DEFAULT_CACHE, synthetic_data


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


def seed_text(values: Sequence[int]) -> str:
    """[0, 1, 2, 5] -> '0-2,5' (the inverse of the --*-seeds parser)."""
    out, run = [], []
    for s in list(values) + [None]:
        if s is not None and run and s == run[-1] + 1:
            run.append(s)
            continue
        if run:
            out.append(f"{run[0]}-{run[-1]}" if len(run) > 2 else ",".join(map(str, run)))
        run = [s] if s is not None else []
    return ",".join(out)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``neurncd train-backbone``."""
    parser.add_argument("--out", required=True,
                        help="weight file to write (its record, .json, goes next to it); "
                        "the shipped weights (neurncd_ros/models/default_backbone.pt) are "
                        "replaced only when named here and with --overwrite")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing weight file")
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
                        help="continue training from this weight file (fine-tuning); with "
                        "--arch esanet the ESANet checkpoint to fine-tune")
    parser.add_argument("--arch", choices=("default", "esanet"), default="default",
                        help="default: the small RGB-D net; esanet: fine-tune ESANet "
                        "R34-NBt1D from --init on the known classes (sizes multiples of 32, "
                        "e.g. --size 320 256 --crop 192 256; slow on a CPU)")
    parser.add_argument("--esanet-dataset", choices=("nyuv2", "sunrgbd"), default="nyuv2",
                        help="with --arch esanet: the checkpoint's classes and depth statistics")
    parser.add_argument("--outlier-weight", type=float, default=0.0,
                        help="outlier exposure: weight of the loss that pushes pasted "
                        "known-class colour on foreign geometry towards a uniform prediction "
                        "(0 = off), so unseen objects raise the entropy")
    parser.add_argument("--outlier-prob", type=float, default=0.5,
                        help="with --outlier-weight: share of training samples given a paste")
    parser.add_argument("--novelty-branch", action="store_true",
                        help="with --init and --outlier-weight: train only a novelty branch "
                        "added to the --init net (frozen, so known-class labels do not "
                        "change); its entropy raises the output's where it sees no known "
                        "class")
    parser.add_argument("--cache", default=str(DEFAULT_CACHE),
                        help="folder for cached synthetic frames (npz)")
    parser.add_argument("--data", nargs="+", default=None, metavar="BAG_OR_FOLDER",
                        help="train on these bags / dataset folders / NYUv2 .mat files with "
                        "semantic ground truth instead of the synthetic seeds")
    parser.add_argument("--val-data", nargs="+", default=None, metavar="BAG_OR_FOLDER",
                        help="validate on these (default: split off --data)")
    parser.add_argument("--val-split", choices=("frames", "files"), default="frames",
                        help="without --val-data: hold out the last --val-fraction of each "
                        "file's frames, or that share of the files")
    parser.add_argument("--val-fraction", type=float, default=0.15,
                        help="share held out for validation (at least one frame or file)")
    parser.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"),
                        help="with --data: frames are resized to this (the backbone's input)")


_SYNTH_ONLY = ("train_seeds", "val_seeds", "frames", "val_frames", "fps", "workers", "cache")
_DATA_ONLY = ("val_data", "val_split", "val_fraction", "size")
_ESANET_ONLY = ("esanet_dataset",)


def command_line(args: argparse.Namespace) -> str:
    """The ``neurncd train-backbone`` command that reproduces a run (every option spelt out)."""
    parts = ["neurncd", "train-backbone"]
    unused = _SYNTH_ONLY if getattr(args, "data", None) else _DATA_ONLY
    if getattr(args, "arch", "default") != "esanet":
        unused = unused + _ESANET_ONLY + ("arch",)
    else:
        unused = unused + ("widths",)   # ESANet's widths are fixed
    for key, value in sorted(vars(args).items()):
        if (key in ("func", "command", "command_parser", "config", "set", "overwrite")
                or key in unused or value is None):
            continue
        flag = "--" + key.replace("_", "-")
        if isinstance(value, bool):  # a switch: present or not
            if value:
                parts.append(flag)
            continue
        if isinstance(value, (list, tuple)):
            if key.endswith("seeds"):
                parts += [flag, seed_text(value)]
            else:
                parts += [flag, *map(str, value)]
        else:
            parts += [flag, str(value)]
    return " ".join(parts)


def _frames_of(path: str):
    """Frames of one bag, dataset folder or NYUv2 .mat (poses not needed for training)."""
    from ..core.data import bag, formats

    if formats.is_bag(path):
        return bag.FrameReader(path, with_poses=False)
    return formats.read_folder(path, with_poses=False)


def _arrays(path: str, size: tuple[int, int]) -> dict:
    arrays, skipped = train_data.frames_to_arrays(_frames_of(path), *size)
    n = len(arrays["rgb"])
    if n == 0:
        raise ValueError(f"{path}: no frame with semantic ground truth "
                         f"({skipped} frames without)")
    known = (train_data.semantic_to_target(arrays["semantic"]) != train_data.IGNORE).mean()
    print(f"{path}: {n} frames with ground truth ({skipped} without, skipped); "
          f"{known * 100:.0f} % of pixels are known classes")
    return {"arrays": arrays, "skipped": skipped, "path": str(path)}


def _concat(parts: list[dict]) -> dict:
    return {k: np.concatenate([p[k] for p in parts]) for k in train_data.ARRAY_KEYS}


def data_from_files(paths: Sequence[str], val_paths: Sequence[str] | None, split: str,
                    fraction: float, size: tuple[int, int]) -> tuple[dict, dict, dict]:
    """(train arrays, validation arrays, source record) from bags / folders / .mat files."""
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"--val-fraction must be in (0, 1), got {fraction}")
    loaded = [_arrays(p, size) for p in paths]
    if val_paths:
        val_loaded = [_arrays(p, size) for p in val_paths]
        train_parts = [x["arrays"] for x in loaded]
        val_parts = [x["arrays"] for x in val_loaded]
        train_files, val_files, how = [x["path"] for x in loaded], \
            [x["path"] for x in val_loaded], "given"
    elif split == "files":
        if len(loaded) < 2:
            raise ValueError("--val-split files needs at least two --data files")
        k = max(1, int(round(len(loaded) * fraction)))
        train_parts = [x["arrays"] for x in loaded[:-k]]
        val_parts = [x["arrays"] for x in loaded[-k:]]
        train_files = [x["path"] for x in loaded[:-k]]
        val_files, how = [x["path"] for x in loaded[-k:]], "files"
        val_loaded = loaded[-k:]
    else:
        train_parts, val_parts = [], []
        for x in loaded:
            a = x["arrays"]
            n = len(a["rgb"])
            if n < 2:
                raise ValueError(f"{x['path']}: {n} frame(s) with ground truth; a frame split "
                                 "needs at least 2 (or use --val-split files / --val-data)")
            k = max(1, int(round(n * fraction)))
            train_parts.append({key: v[: n - k] for key, v in a.items()})
            val_parts.append({key: v[n - k:] for key, v in a.items()})
        train_files = val_files = [x["path"] for x in loaded]
        how, val_loaded = "frames", []
    train_data, val_data = _concat(train_parts), _concat(val_parts)
    source = {"trained_on": "data", "train_files": train_files, "val_files": val_files,
              "val_split": how, "val_fraction": fraction if how != "given" else None,
              "frames_per_file": {x["path"]: int(len(x["arrays"]["rgb"]))
                                  for x in loaded + val_loaded},
              "frames_without_ground_truth": int(sum(x["skipped"]
                                                     for x in loaded + val_loaded))}
    return train_data, val_data, source


def load_data(args: argparse.Namespace) -> tuple[dict, dict, dict]:
    """(train arrays, validation arrays, source record) chosen by the options."""
    if getattr(args, "data", None):
        return data_from_files(args.data, args.val_data, args.val_split, args.val_fraction,
                               tuple(args.size))
    if getattr(args, "val_data", None):
        raise ValueError("--val-data needs --data (the synthetic seeds validate on "
                         "--val-seeds)")
    return synthetic_data(args.train_seeds, args.val_seeds, frames_per_seed=args.frames,
                          val_frames_per_seed=args.val_frames, fps=args.fps,
                          cache_dir=Path(args.cache) if args.cache else None,
                          workers=args.workers, progress=True)


def main(args: argparse.Namespace) -> int:
    """Load the data the options name, train, print the summary."""
    import torch

    out = Path(args.out)
    if out.exists() and not args.overwrite:  # before minutes of loading and training
        raise ValueError(f"{out} exists already; name another --out, or pass --overwrite "
                         "to replace it")
    if args.threads > 0:  # this process's choice, not the core's
        torch.set_num_threads(args.threads)
    t0 = time.time()
    train_data, val_data, source = load_data(args)
    train.train_backbone(args.out, train_data, val_data, source, epochs=args.epochs,
                         batch_size=args.batch_size, lr=args.lr, seed=args.seed,
                         max_minutes=args.max_minutes,
                         crop=tuple(args.crop), init=args.init, widths=tuple(args.widths),
                         val_every=args.val_every, command=command_line(args),
                         data_seconds=time.time() - t0, arch=args.arch,
                         esanet_dataset=args.esanet_dataset,
                         outlier_weight=args.outlier_weight, outlier_prob=args.outlier_prob,
                         novelty_branch=args.novelty_branch)
    print(f"wrote {out} and its record {out.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    _p = argparse.ArgumentParser(description="train the default small RGB-D backbone")
    add_arguments(_p)
    sys.exit(main(_p.parse_args()))
