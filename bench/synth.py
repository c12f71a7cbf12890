"""Synthetic scene benchmark: generation speed (with bag writing) and class pixel shares.

Writes bench/results/synth.json (figures) and bench/results/synth.png (contact
sheet: rgb | depth | semantic of a few frames of a few seeds).

    .venv/bin/python bench/synth.py            # full: 3 x 300 frames, 20 seeds x 20 frames
    .venv/bin/python bench/synth.py --quick    # 1 x 60 frames, 5 seeds x 5 frames (smoke)
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from neurncd_ros.core import classes  # noqa: E402
from neurncd_ros.synth.generator import SynthConfig, frames_at, generate  # noqa: E402

RESULTS = REPO / "bench" / "results"


from _common import commit, results_dir  # noqa: E402  (bench/ is on sys.path)


def time_generation(frames: int, runs: int, seed: int = 0) -> dict:
    """Median seconds to generate ``frames`` 320x240 frames, alone and written to a bag."""
    cfg = SynthConfig()
    gen, with_bag = [], []
    try:
        from neurncd_ros.core.data.bag import write_bag
    except ImportError:                                   # colleague's module not there yet
        write_bag = None
    for r in range(runs):
        t = time.perf_counter()
        for _ in generate(seed + r, frames, cfg):
            pass
        gen.append(time.perf_counter() - t)
        if write_bag is not None:
            with tempfile.TemporaryDirectory() as tmp:
                t = time.perf_counter()
                write_bag(Path(tmp) / "scene", generate(seed + r, frames, cfg), storage="mcap")
                with_bag.append(time.perf_counter() - t)
    out = {f"synth_gen_{frames}f_s": round(statistics.median(gen), 2),
           "synth_ms_per_frame": round(1000 * statistics.median(gen) / frames, 1)}
    if with_bag:
        out[f"synth_{frames}f_s"] = round(statistics.median(with_bag), 2)
    return out


def class_shares(seeds: int, frames: int) -> dict:
    """Pixel share of each NYU-13 class over ``seeds`` rooms, ``frames`` views each.

    Frames are taken at 2 fps so they span the same 10 s walk a 300-frame
    30 fps run covers.
    """
    cfg = SynthConfig(width=160, height=120, fps=frames / 10.0, depth_noise="none",
                      rgb_noise_std=0.0)
    counts = np.zeros(classes.NUM_CLASSES + 1)
    for seed in tqdm_range(seeds):
        for f in generate(seed, frames, cfg):
            counts += np.bincount(f.semantic.ravel(), minlength=classes.NUM_CLASSES + 1)
    share = counts / counts.sum()
    return {classes.NYU13_NAMES[i - 1]: round(float(share[i]), 4)
            for i in range(1, classes.NUM_CLASSES + 1)}


def tqdm_range(n: int):
    try:
        from tqdm import tqdm
        return tqdm(range(n), desc="class shares", unit="seed")
    except ImportError:
        return range(n)


def contact_sheet(path: Path, seeds=(0, 3, 7, 12), frames=(0, 150)) -> None:
    """rgb | depth (jet, holes black) | semantic rows for a few seeds and frames."""
    rows = []
    cfg = SynthConfig()
    for seed in seeds:
        for f in frames_at(seed, frames, cfg):
            d = f.depth
            dv = cv2.applyColorMap((np.clip(d / 6.0, 0, 1) * 255).astype(np.uint8),
                                   cv2.COLORMAP_JET)[..., ::-1].copy()
            dv[d == 0] = 0
            rows.append(np.hstack([f.rgb, dv, classes.colourise(f.semantic)]))
    cv2.imwrite(str(path), np.vstack(rows)[..., ::-1])


def main() -> None:
    global RESULTS
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke run with fewer frames")
    args = ap.parse_args()
    RESULTS = results_dir(args.quick)
    RESULTS.mkdir(parents=True, exist_ok=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    frames, runs = (60, 1) if args.quick else (300, 3)
    seeds, per_seed = (5, 5) if args.quick else (20, 20)
    res = time_generation(frames, runs)
    res["class_pixel_share"] = class_shares(seeds, per_seed)
    res["class_share_seeds"] = seeds
    res["class_share_frames_per_seed"] = per_seed
    res["cores"] = os.cpu_count()
    res["commit"] = commit()
    with open(RESULTS / "synth.json", "w") as fh:
        json.dump(res, fh, indent=2)
    contact_sheet(RESULTS / "synth.png", frames=(0, 60) if args.quick else (0, 150))
    print(f"{'figure':32s} value")
    for k, v in res.items():
        if k != "class_pixel_share":
            print(f"{k:32s} {v}")
    print(f"\n{'class':12s} pixel share")
    for k, v in sorted(res["class_pixel_share"].items(), key=lambda kv: -kv[1]):
        print(f"{k:12s} {v:.4f}")


if __name__ == "__main__":
    from neurncd_ros.core.text import progress_as_lines

    with progress_as_lines():  # a log file gets the bars as lines
        main()
