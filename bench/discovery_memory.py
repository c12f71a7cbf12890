"""Discovery over a long stream: time per labelled frame as the segment memory fills.

Discovery re-clusters its whole segment memory (Markov clustering) for every labelled
frame, so its time per frame grows with the memory until ``discovery.memory_size``
caps it. The other benches' scenes (150-300 frames, 23-47 labelled) stay below about
1000 segments and never show this; a user's long bag does.

A walk of tuning seed 500 (seeds.TUNE[0]) with one frame per second of stream, every
frame labelled (about the keyframe rate of the live graph), the default backbone's
embeddings and entropy (no field: this times discovery alone), one torch thread, the
default configuration. Per frame: ``Discoverer.process`` wall time, the memory's size
and the time inside Markov clustering.

Figures (bench/results/discovery_memory.json; times in ms, medians over windows of
25 frames): ``windows`` (first frame, memory segments, process ms, clustering ms),
``process_ms_at_cap`` / ``mcl_ms_at_cap`` (median over the frames at the cap),
``frames_to_cap``, ``memory_size``; discovery_memory.png plots them.

    .venv/bin/python bench/discovery_memory.py              # 300 frames (~8 min)
    .venv/bin/python bench/discovery_memory.py --frames 60  # smoke
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from neurncd_ros import config, synth  # noqa: E402
from neurncd_ros.core import classes  # noqa: E402
from neurncd_ros.core.backbone.backbone import load_backbone  # noqa: E402
from neurncd_ros.core.discovery import labeller, mcl  # noqa: E402
from neurncd_ros.core.uncertainty import entropy  # noqa: E402
from neurncd_ros.synth import seeds  # noqa: E402

from _common import commit  # noqa: E402  (bench/ is on sys.path)

RESULTS = REPO / "bench" / "results"
WINDOW = 25


class ClusteringTimer:
    """Wraps :func:`mcl.mcl` (what the labeller calls) to add up its time per frame."""

    def __init__(self) -> None:
        self.ms = 0.0
        self._mcl = mcl.mcl

    def __enter__(self) -> "ClusteringTimer":
        def timed(*args, **kwargs):
            t = time.perf_counter()
            try:
                return self._mcl(*args, **kwargs)
            finally:
                self.ms += (time.perf_counter() - t) * 1000
        mcl.mcl = timed
        return self

    def __exit__(self, *exc) -> None:
        mcl.mcl = self._mcl


def run(cfg: config.Config, frames: int, seed: int) -> list[dict]:
    """One labelled frame per second of a walk of ``seed``: per-frame timings."""
    backbone = load_backbone(cfg.backbone)
    disc = labeller.Discoverer(cfg.discovery, classes.CHANNEL_TO_ID, mcl_cfg=cfg.mcl,
                               seg_cfg=cfg.segmentation, mod_cfg=cfg.modulation,
                               fusion_cfg=cfg.label_fusion)
    rows = []
    with ClusteringTimer() as clock:
        walk = synth.generate(seed, frames, synth.SynthConfig(fps=1.0))
        for i, fr in enumerate(tqdm(walk, total=frames, desc="labelled frames", unit="frame")):
            emb = backbone.embed(fr.rgb, fr.depth)
            ent = entropy(emb)
            clock.ms = 0.0
            t = time.perf_counter()
            disc.process(fr.depth, fr.intrinsics, emb, ent, fr.stamp_ns, fr.rgb, None, fr.pose)
            rows.append({"frame": i, "process_ms": (time.perf_counter() - t) * 1000,
                         "mcl_ms": clock.ms, "memory": disc.memory_len})
    return rows


def summarise(rows: list[dict], memory_size: int) -> dict:
    windows = []
    for s in range(0, len(rows), WINDOW):
        w = rows[s: s + WINDOW]
        windows.append({"first_frame": s, "memory": int(w[-1]["memory"]),
                        "process_ms": statistics.median(r["process_ms"] for r in w),
                        "mcl_ms": statistics.median(r["mcl_ms"] for r in w)})
    at_cap = [r for r in rows if r["memory"] >= memory_size]
    out = {"windows": windows, "memory_size": memory_size, "frames": len(rows),
           "frames_to_cap": at_cap[0]["frame"] if at_cap else None,
           "process_ms_at_cap": statistics.median(r["process_ms"] for r in at_cap)
           if at_cap else None,
           "mcl_ms_at_cap": statistics.median(r["mcl_ms"] for r in at_cap) if at_cap else None}
    return out


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mem = [r["memory"] for r in rows]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(mem, [r["process_ms"] for r in rows], ".", ms=3, label="Discoverer.process")
    ax.plot(mem, [r["mcl_ms"] for r in rows], ".", ms=3, label="of it, Markov clustering")
    ax.set_xlabel("segments in the memory")
    ax.set_ylabel("ms per labelled frame (1 thread)")
    ax.set_title("discovery time as the segment memory fills")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="labelled frames (1 per second)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    seed = seeds.TUNE[0]
    cfg = config.load(None, {})
    rows = run(cfg, args.frames, seed)
    res = summarise(rows, cfg.discovery.memory_size)
    res.update({"seed": seed, "threads": 1, "commit": commit()})
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "discovery_memory.json").write_text(json.dumps(res, indent=1) + "\n")
    plot(rows, RESULTS / "discovery_memory.png")
    print(f"{'frames':>8} {'memory':>8} {'process ms':>11} {'mcl ms':>8}")
    for w in res["windows"]:
        print(f"{w['first_frame']:>8} {w['memory']:>8} {w['process_ms']:>11.0f} "
              f"{w['mcl_ms']:>8.0f}")
    print(f"at the cap ({res['memory_size']} segments, from frame {res['frames_to_cap']}): "
          f"process {res['process_ms_at_cap']} ms, Markov clustering {res['mcl_ms_at_cap']} ms")
    print(f"wrote {RESULTS / 'discovery_memory.json'} and discovery_memory.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
