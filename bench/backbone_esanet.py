"""ESANet R34-NBt1D forward time on CPU (batch 1, eval, no_grad), per input size.

Used by bench/backbone.py (``measure_esanet``) and runnable on its own:

    .venv/bin/python bench/backbone_esanet.py [--repeats N] [--quick]

writes bench/results/backbone_esanet.json. The weights are random: time does
not depend on their values. For reference, the public ESANet code measured on
this kind of 2-core machine takes about 840 ms per 480x640 frame.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from neurncd_ros.core.backbone.esanet import ESANet  # noqa: E402

SIZES = ((480, 640), (256, 320))
"""(height, width) measured: the authors' resolution and the cheaper half size."""


def _commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                             capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return "uncommitted"
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else "uncommitted"


def measure_esanet(sizes=SIZES, repeats: int = 5, num_classes: int = 40) -> dict:
    """Median ms per frame for each (H, W): keys ``esanet_ms_{H}x{W}``.

    One warm-up pass per size, then ``repeats`` timed passes; all CPU cores.
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    torch.set_num_threads(os.cpu_count() or 1)
    torch.manual_seed(0)
    model = ESANet(num_classes).eval()
    out = {}
    with torch.no_grad():
        for h, w in sizes:
            rgb, depth = torch.randn(1, 3, h, w), torch.randn(1, 1, h, w)
            model(rgb, depth)  # warm-up: allocator and kernel selection
            times = []
            for _ in tqdm(range(repeats), desc=f"esanet {h}x{w}", leave=False):
                t0 = time.perf_counter()
                model(rgb, depth)
                times.append((time.perf_counter() - t0) * 1000.0)
            out[f"esanet_ms_{h}x{w}"] = round(statistics.median(times), 1)
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="timed passes per size")
    ap.add_argument("--quick", action="store_true", help="reduced run: 2 timed passes")
    args = ap.parse_args(argv)
    repeats = 2 if args.quick else args.repeats
    res = measure_esanet(SIZES, repeats)
    res.update({"esanet_repeats": repeats, "cores": os.cpu_count(), "commit": _commit()})
    # A --quick smoke run never replaces the full results (as bench/_common.results_dir).
    dest = REPO / "bench" / "results" / ("quick" if args.quick else "") / "backbone_esanet.json"
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(json.dumps(res, indent=2) + "\n")
    print(f"{'figure':<24}{'value':>12}")
    for k, v in res.items():
        print(f"{k:<24}{v!s:>12}")
    print(f"(public ESANet code on this kind of machine: ~840 ms at 480x640) -> {dest}")
    return res


if __name__ == "__main__":
    from neurncd_ros.core.text import progress_as_lines

    with progress_as_lines():  # a log file gets the bars as lines
        main()
