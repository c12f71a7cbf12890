"""`neurncd train-backbone`: choose the training data, then train with the core.

By default the data are the synthetic seeds of ``neurncd_ros.synth.seeds``
(what the shipped weights were trained on). The record written next to the
weights holds the command that reproduces the run, every option spelt out.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Sequence

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
    from ..core.backbone.backbone import DEFAULT_WEIGHTS

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
                        help="continue training from this weight file (fine-tuning)")
    parser.add_argument("--cache", default=str(DEFAULT_CACHE),
                        help="folder for cached synthetic frames (npz)")


def command_line(args: argparse.Namespace) -> str:
    """The ``neurncd train-backbone`` command that reproduces a run (every option spelt out)."""
    parts = ["neurncd", "train-backbone"]
    for key, value in sorted(vars(args).items()):
        if key in ("func", "command", "config", "set") or value is None:
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


def load_data(args: argparse.Namespace) -> tuple[dict, dict, dict]:
    """(train arrays, validation arrays, source record) chosen by the options."""
    return synthetic_data(args.train_seeds, args.val_seeds, frames_per_seed=args.frames,
                          val_frames_per_seed=args.val_frames, fps=args.fps,
                          cache_dir=Path(args.cache) if args.cache else None,
                          workers=args.workers, progress=True)


def main(args: argparse.Namespace) -> int:
    """Load the data the options name, train, print the summary."""
    t0 = time.time()
    train_data, val_data, source = load_data(args)
    train.train_backbone(args.out, train_data, val_data, source, epochs=args.epochs,
                         batch_size=args.batch_size, lr=args.lr, seed=args.seed,
                         num_threads=args.threads, max_minutes=args.max_minutes,
                         crop=tuple(args.crop), init=args.init, widths=tuple(args.widths),
                         val_every=args.val_every, command=command_line(args),
                         data_seconds=time.time() - t0)
    return 0


if __name__ == "__main__":
    _p = argparse.ArgumentParser(description="train the default small RGB-D backbone")
    add_arguments(_p)
    sys.exit(main(_p.parse_args()))
