"""Discovery over a long stream: time per labelled frame as the segment memory fills, and
what the labels are worth there.

Discovery re-clusters its segment memory (Markov clustering), so its time per frame
grows with the memory until ``discovery.memory_size`` caps it; beyond
``discovery.recluster_segments`` segments it re-clusters less often to stay near that
cost. The other benches' scenes (150-300 frames, 23-47 labelled) stay below about 1000
segments and never show this; a user's long bag does.

A walk of a tuning scene (``--seed``, default seed 500) with one frame per second of stream, every
frame labelled (about the keyframe rate of the live graph), the default backbone's
embeddings and entropy (no field: this measures discovery alone), one torch thread.
The walk and its embeddings are computed once; each configuration then runs a fresh
Discoverer over it. Per frame: ``Discoverer.process`` wall time, the memory's size,
the time inside Markov clustering; per run: mIoU (all / known / novel, Hungarian-matched
as in bench/ncd.py) and novel-id stability, over the whole walk and over the frames at
the memory cap.

Figures (bench/results/discovery_memory.json, or discovery_memory_s<seed>.json with
``--seed``; times in ms, medians): per run
(``runs``, the first the default configuration) ``windows`` (first frame, memory
segments, process ms, clustering ms, and the window's own all / known / novel mIoU,
its 25 frames matched on their own: whether discovery holds up as the memory fills),
``process_ms_at_cap`` / ``mcl_ms_at_cap`` / ``process_ms_mean_at_cap`` (what sets the
throughput), ``frames_to_cap``, ``quality`` and ``quality_at_cap``;
discovery_memory.png plots the time per frame and each window's novel mIoU of every
run.

    .venv/bin/python bench/discovery_memory.py              # 300 frames, default (~4 min)
    .venv/bin/python bench/discovery_memory.py --sweep discovery.recluster_segments=0,1000
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
from neurncd_ros.core.discovery.metrics import Evaluator, IdStability  # noqa: E402
from neurncd_ros.core.uncertainty import entropy  # noqa: E402
from neurncd_ros.synth import seeds  # noqa: E402

from _common import commit, parse_sweep  # noqa: E402  (bench/ is on sys.path)

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


def walk(cfg: config.Config, frames: int, seed: int) -> list[tuple]:
    """The walk's frames, each with the backbone's embedding and entropy."""
    backbone = load_backbone(cfg.backbone)
    out = []
    for fr in tqdm(synth.generate(seed, frames, synth.SynthConfig(fps=1.0)), total=frames,
                   desc="walk and embeddings", unit="frame"):
        emb = backbone.embed(fr.rgb, fr.depth)
        out.append((fr, emb, entropy(emb)))
    return out


def _quality(ev: Evaluator, stable: IdStability) -> dict:
    r = ev.result()
    out = {k: r[k] for k in ("miou_all", "miou_known", "miou_novel")}
    s = stable.result()
    out.update(novel_id_stability=s["novel_id_stability"],
               novel_id_stability_found=s["novel_id_stability_found"])
    return out


def run(cfg: config.Config, frames: list[tuple]) -> tuple[list[dict], dict, dict]:
    """A fresh Discoverer over the walk: per-frame timings, quality over the walk and
    quality over the frames at the memory cap."""
    disc = labeller.Discoverer(cfg.discovery, classes.CHANNEL_TO_ID, mcl_cfg=cfg.mcl,
                               seg_cfg=cfg.segmentation, mod_cfg=cfg.modulation,
                               fusion_cfg=cfg.label_fusion)
    rows = []
    ev, stable = Evaluator(), IdStability()
    ev_cap, stable_cap = Evaluator(), IdStability()
    ev_win = Evaluator()
    with ClusteringTimer() as clock:
        for i, (fr, emb, ent) in enumerate(tqdm(frames, desc="labelled frames",
                                                unit="frame")):
            clock.ms = 0.0
            t = time.perf_counter()
            lab = disc.process(fr.depth, fr.intrinsics, emb, ent, fr.stamp_ns, fr.rgb, None,
                               fr.pose)
            rows.append({"frame": i, "process_ms": (time.perf_counter() - t) * 1000,
                         "mcl_ms": clock.ms, "memory": disc.memory_len})
            ev.update(lab, fr.semantic)
            stable.update(lab, fr.semantic, fr.instance)
            ev_win.update(lab, fr.semantic)
            if (i + 1) % WINDOW == 0 or i + 1 == len(frames):
                q = ev_win.result()  # this window's frames alone, matched on their own
                rows[-1]["window_quality"] = {k: q[k] for k in
                                              ("miou_all", "miou_known", "miou_novel")}
                ev_win = Evaluator()
            if disc.memory_len >= cfg.discovery.memory_size:
                ev_cap.update(lab, fr.semantic)
                stable_cap.update(lab, fr.semantic, fr.instance)
    at_cap = any(r["memory"] >= cfg.discovery.memory_size for r in rows)
    return rows, _quality(ev, stable), _quality(ev_cap, stable_cap) if at_cap else {}


def summarise(rows: list[dict], memory_size: int) -> dict:
    windows = []
    for s in range(0, len(rows), WINDOW):
        w = rows[s: s + WINDOW]
        windows.append({"first_frame": s, "memory": int(w[-1]["memory"]),
                        "process_ms": statistics.median(r["process_ms"] for r in w),
                        "mcl_ms": statistics.median(r["mcl_ms"] for r in w),
                        **w[-1].get("window_quality", {})})
    at_cap = [r for r in rows if r["memory"] >= memory_size]

    def med(key):
        return statistics.median(r[key] for r in at_cap) if at_cap else None
    return {"windows": windows, "memory_size": memory_size, "frames": len(rows),
            "frames_to_cap": at_cap[0]["frame"] if at_cap else None,
            "process_ms_at_cap": med("process_ms"), "mcl_ms_at_cap": med("mcl_ms"),
            "process_ms_mean_at_cap": statistics.fmean(r["process_ms"] for r in at_cap)
            if at_cap else None}


def plot(runs: list[dict], path: Path) -> None:
    """Time per labelled frame, and each window's novel mIoU, as the memory fills."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, aq) = plt.subplots(1, 2, figsize=(12, 4))
    for r in runs:
        name = r["name"]
        ax.plot([x["frame"] for x in r["rows"]], [x["process_ms"] for x in r["rows"]], ".",
                ms=3, label=f"{name}: Discoverer.process")
        win = [w for w in r["windows"] if "miou_novel" in w]
        aq.plot([w["first_frame"] for w in win], [w["miou_novel"] for w in win], "o-",
                label=name)
    ax.set_xlabel("labelled frame (one per second of stream)")
    ax.set_ylabel("ms per labelled frame (1 thread)")
    ax.set_yscale("log")
    ax.set_title("discovery time as the segment memory fills")
    ax.legend(fontsize=8)
    aq.set_xlabel(f"first labelled frame of the window ({WINDOW} frames)")
    aq.set_ylabel("novel mIoU in the window (%)")
    aq.set_ylim(0, 100)
    aq.set_title("novel classes as the memory fills")
    aq.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="labelled frames (1 per second)")
    ap.add_argument("--seed", type=int, default=seeds.TUNE[0],
                    help="scene seed of the walk (a tuning seed to tune discovery on; a "
                    "test seed only to check a chosen default on held-out data)")
    ap.add_argument("--sweep", metavar="SECTION.KEY=V1,V2,...",
                    help="also run these values of one parameter (the default first)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    seed = args.seed
    base = config.load(None, {})
    variants = [("default", base, {})]
    if args.sweep:
        key, parsed = parse_sweep(args.sweep)
        variants += [(f"{key}={v}", cfg, over) for v, over, cfg in parsed]
    frames = walk(base, args.frames, seed)
    runs = []
    for name, cfg, over in variants:
        rows, quality, quality_cap = run(cfg, frames)
        res = summarise(rows, cfg.discovery.memory_size)
        res.update(name=name, overrides=over, quality=quality, quality_at_cap=quality_cap,
                   rows=rows)
        runs.append(res)
    RESULTS.mkdir(parents=True, exist_ok=True)
    stem = "discovery_memory" + ("" if seed == seeds.TUNE[0] else f"_s{seed}")
    plot(runs, RESULTS / f"{stem}.png")
    for r in runs:
        del r["rows"]
    out = {"runs": runs, "seed": seed, "threads": 1, "frames": args.frames,
           "commit": commit()}
    (RESULTS / f"{stem}.json").write_text(json.dumps(out, indent=1) + "\n")
    for r in runs:
        print(f"\n{r['name']}")
        print(f"{'frames':>8} {'memory':>8} {'process ms':>11} {'mcl ms':>8}   window mIoU "
              "all / known / novel")
        for w in r["windows"]:
            print(f"{w['first_frame']:>8} {w['memory']:>8} {w['process_ms']:>11.0f} "
                  f"{w['mcl_ms']:>8.0f}   {w.get('miou_all', float('nan')):5.1f} / "
                  f"{w.get('miou_known', float('nan')):5.1f} / "
                  f"{w.get('miou_novel', float('nan')):5.1f}")
        if r["frames_to_cap"] is not None:
            print(f"at the cap ({r['memory_size']} segments, from frame {r['frames_to_cap']}): "
                  f"process median {r['process_ms_at_cap']:.0f} ms, mean "
                  f"{r['process_ms_mean_at_cap']:.0f} ms; Markov clustering median "
                  f"{r['mcl_ms_at_cap']:.0f} ms")
    print(f"\n{'run':<40} {'all':>6} {'known':>6} {'novel':>6} {'stab':>6}   at the cap: "
          f"{'all':>6} {'novel':>6} {'stab':>6}")
    for r in runs:
        q, c = r["quality"], r["quality_at_cap"]
        cap = (f"{c['miou_all']:>6.1f} {c['miou_novel']:>6.1f} "
               f"{c['novel_id_stability']:>6.3f}" if c else "")
        print(f"{r['name']:<40} {q['miou_all']:>6.1f} {q['miou_known']:>6.1f} "
              f"{q['miou_novel']:>6.1f} {q['novel_id_stability']:>6.3f}   {'':>11}{cap}")
    print(f"wrote {RESULTS / stem}.json and {stem}.png")
    return 0


if __name__ == "__main__":
    from neurncd_ros.core.text import progress_as_lines

    with progress_as_lines():  # a log file gets the bars as lines
        sys.exit(main())
