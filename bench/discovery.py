"""Discovery benchmark: depth segmentation, Markov clustering, tuning, end-to-end labelling.

Writes bench/results/discovery.json (flat figures) and bench/results/geoseg.png
(rgb | segments | ground-truth instances for a few synthetic frames).

    .venv/bin/python bench/discovery.py            # full
    .venv/bin/python bench/discovery.py --quick    # fewer frames, no 20k run (smoke)
    .venv/bin/python bench/discovery.py --only seg # segmentation figures only

Figures:
- geoseg_ms_320x240: median segmentation time per frame over 5 held-out synthetic
  seeds (seeds.TEST[:5], realistic depth noise), with the embedding and colour edge
  cues as the node runs it; segment_purity: pixel-weighted share of segment pixels
  in their segment's majority GT instance, with both cues;
  segment_purity_no_colour: embedding cue only; segment_purity_geometric_only:
  neither; per-seed extremes of the purity; segments_per_frame (median, p10, p90,
  with both cues) and the median segment size in pixels;
- mcl_5k_s / mcl_20k_s: markov_cluster (top-30 cosine graph + MCL, inflation 2)
  timed end to end (graph + clustering)
  on noisy 38-d vectors in 12 groups, with the clusters found and adjusted Rand
  index; mcl_20k_peak_rss_gb: peak RSS of a child process doing only that;
  mcl_5k_r12_*: the same 5k set at inflation 12;
- tune_<affinity>_r<inflation>_{ari,purity,clusters}: the grid of mcl.tune on
  segment descriptors of tuning seeds (seeds.TUNE[:4]; labels: each segment's
  majority GT class), plus the chosen row.
The end-to-end discovery scores (backbone -> Embedding-NeRF -> discovery) are
bench/ncd.py's. Embeddings come from the default backbone when its weights
exist, otherwise from modulation.simulate_embedding (see "embedding_source").
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from neurncd_ros.core.classes import colourise  # noqa: E402
from neurncd_ros.synth import seeds  # noqa: E402
from neurncd_ros.core.discovery.geoseg import GeoSegConfig, segment_depth  # noqa: E402
from neurncd_ros.core.discovery.mcl import MCLConfig, markov_cluster, tune  # noqa: E402
from neurncd_ros.core.discovery.metrics import adjusted_rand_index  # noqa: E402
from neurncd_ros.core.discovery.modulation import ModulationConfig, segment_descriptors, \
    simulate_embedding  # noqa: E402
from neurncd_ros.core.uncertainty import entropy  # noqa: E402

RESULTS = REPO / "bench" / "results"
GEOSEG_SEEDS = seeds.TEST[:5]
TUNE_SEEDS = seeds.TUNE[:4]


from _common import commit, results_dir  # noqa: E402  (bench/ is on sys.path)


def frames_of(seed: int, frames: int, step: int) -> list:
    from neurncd_ros.synth.generator import SynthConfig, generate
    return [f for i, f in enumerate(generate(seed, frames, SynthConfig())) if i % step == 0]


def purity_counts(seg: np.ndarray, instance: np.ndarray) -> tuple[float, float]:
    m = (seg >= 0) & (instance > 0)
    if not m.any():
        return 0.0, 0.0
    _, inst = np.unique(instance[m], return_inverse=True)
    table = np.zeros((seg.max() + 1, inst.max() + 1))
    np.add.at(table, (seg[m], inst), 1)
    return float(table.max(axis=1).sum()), float(table.sum())


def bench_geoseg(frames: int, step: int, embed) -> dict:
    """Segmentation time, purity and segment count over the GEOSEG_SEEDS; saves the PNG.

    As the node runs it: the embedding, entropy and colour are passed to
    segment_depth (appearance and colour edges, timed with the rest); the other
    purities are the same frames with fewer cues.
    """
    cfg = GeoSegConfig()
    times, counts, rows, sizes, per_seed = [], [], [], [], []
    good, total, ggood, gtotal, cgood, ctotal = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for seed in tqdm(GEOSEG_SEEDS, desc="geoseg seeds"):
        seed_good, seed_total = good, total
        for k, f in enumerate(frames_of(seed, frames, step)):
            emb, ent = embed(f, k)
            if not times:  # warm-up
                segment_depth(f.depth, f.intrinsics, cfg, emb, ent, f.rgb)
            t = time.perf_counter()
            seg = segment_depth(f.depth, f.intrinsics, cfg, emb, ent, f.rgb)
            times.append(time.perf_counter() - t)
            counts.append(int(seg.max()) + 1)
            sizes.extend(np.bincount(seg[seg >= 0]).tolist())
            g, n = purity_counts(seg, f.instance)
            good, total = good + g, total + n
            g, n = purity_counts(segment_depth(f.depth, f.intrinsics, cfg, emb, ent),
                                 f.instance)
            cgood, ctotal = cgood + g, ctotal + n
            g, n = purity_counts(segment_depth(f.depth, f.intrinsics, cfg), f.instance)
            ggood, gtotal = ggood + g, gtotal + n
            if k == 1 and len(rows) < 3:
                segs = colourise(np.where(seg >= 0, seg + 100, 0).astype(np.uint16))
                inst = colourise(np.where(f.instance > 0, f.instance % 900 + 100, 0)
                                 .astype(np.uint16))
                rows.append(np.concatenate([f.rgb, segs, inst], axis=1))
        per_seed.append((good - seed_good) / max(total - seed_total, 1.0))
    if rows:
        cv2.imwrite(str(RESULTS / "geoseg.png"), cv2.cvtColor(np.concatenate(rows, 0),
                                                              cv2.COLOR_RGB2BGR))
    return {"geoseg_ms_320x240": 1000 * statistics.median(times),
            "geoseg_frames": len(times),
            "segment_purity": good / max(total, 1.0),
            "segment_purity_no_colour": cgood / max(ctotal, 1.0),
            "segment_purity_geometric_only": ggood / max(gtotal, 1.0),
            "segment_purity_min_seed": float(min(per_seed)),
            "segment_purity_max_seed": float(max(per_seed)),
            "segments_per_frame": float(statistics.median(counts)),
            "segments_per_frame_p10": float(np.percentile(counts, 10)),
            "segments_per_frame_p90": float(np.percentile(counts, 90)),
            "segment_pixels_median": float(statistics.median(sizes))}


def groups(n: int, dim: int = 38, k: int = 12, noise: float = 0.6, seed: int = 0):
    """Noisy vectors around k random centres (the MCL scaling workload)."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(k, dim))
    y = rng.integers(0, k, n)
    return (centres[y] + noise * rng.normal(size=(n, dim))).astype(np.float32), y


def bench_mcl(n: int, inflation: float = 2.0) -> dict:
    x, y = groups(n)
    t = time.perf_counter()
    lab = markov_cluster(x, MCLConfig(affinity="cosine", inflation=inflation, k=30))
    return {"s": time.perf_counter() - t, "clusters": int(lab.max()) + 1,
            "ari": adjusted_rand_index(y, lab)}


def mcl_child(n: int) -> None:
    """Entry of the child process: time one MCL run and print its peak RSS."""
    torch.set_num_threads(1)
    out = bench_mcl(n)
    out["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    print(json.dumps(out))


def embedder():
    """(source name, function frame -> (embedding, entropy))."""
    try:
        from neurncd_ros.core.backbone.backbone import BackboneConfig, load_backbone
        bb = load_backbone(BackboneConfig(num_threads=1))

        def run(f, i):
            emb = bb.predict(f.rgb, f.depth)
            return emb, _entropy(emb)
        return "default_backbone", run
    except Exception:  # no trained weights yet: a stand-in from ground truth
        def run(f, i):
            emb = simulate_embedding(f.semantic, f.instance, seed=i)
            return emb, _entropy(emb)
        return "simulated", run


def _entropy(emb: np.ndarray) -> np.ndarray:
    return entropy(emb)


def bench_tuning(embed, frames: int, step: int) -> tuple[dict, list[dict]]:
    """mcl.tune on descriptors of training-seed segments; flat figures and the rows."""
    mod = ModulationConfig()
    xs, ys = [], []
    for seed in tqdm(TUNE_SEEDS, desc="tuning seeds"):
        dx, dy = [], []
        for i, f in enumerate(frames_of(seed, frames, step)):
            emb, ent = embed(f, i)
            seg = segment_depth(f.depth, f.intrinsics, GeoSegConfig(), emb, ent, f.rgb)
            dx.append(segment_descriptors(seg, emb, ent, mod))
            n = int(seg.max()) + 1
            sem = f.semantic.astype(np.int64)
            table = np.zeros((n, 14), np.int64)
            ok = seg >= 0
            np.add.at(table, (seg[ok], sem[ok]), 1)
            table[:, 0] = 0
            dy.append(table.argmax(1))
        xs.append(np.concatenate(dx))
        ys.append(np.concatenate(dy))
    rows = tune(xs, ys, inflations=(1.2, 1.4, 1.6, 2.0, 2.5, 4.0, 12.0),
                affinities=(("cosine", 0.0), ("exp", 1.0), ("exp", 3.0), ("exp", 6.0),
                            ("exp", 10.0)),
                base=MCLConfig())
    out = {"tune_segments_per_set": float(np.mean([len(x) for x in xs]))}
    for r in rows:
        name = "cosine" if r["affinity"] == "cosine" else f"exp{r['eta']:g}"
        key = f"tune_{name}_r{r['inflation']:g}"
        for m in ("ari", "purity", "clusters"):
            out[f"{key}_{m}"] = r[m]
    d = MCLConfig()
    chosen = [r for r in rows if r["affinity"] == d.affinity and r["inflation"] == d.inflation
              and (d.affinity == "cosine" or r["eta"] == d.eta)]
    if chosen:
        out.update({f"tune_default_{m}": chosen[0][m] for m in ("ari", "purity", "clusters")})
    return out, rows


def main() -> None:
    global RESULTS
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small smoke run")
    ap.add_argument("--only", choices=("seg",), default=None,
                    help="run only a part (seg: the segmentation figures; merged into the "
                    "existing discovery.json)")
    ap.add_argument("--mcl-child", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    RESULTS = results_dir(args.quick)
    RESULTS.mkdir(parents=True, exist_ok=True)
    if args.mcl_child:
        mcl_child(args.mcl_child)
        return
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    RESULTS.mkdir(parents=True, exist_ok=True)
    q = args.quick
    res: dict = {}
    source, embed = embedder()
    res["embedding_source"] = source
    res.update(bench_geoseg(frames=6 if q else 40, step=3 if q else 4, embed=embed))
    if args.only == "seg":
        path = RESULTS / "discovery.json"
        old = json.loads(path.read_text()) if path.exists() else {}
        old.update(res)
        old.update({"cores": os.cpu_count(), "commit": commit()})
        path.write_text(json.dumps(old, indent=1, sort_keys=True))
        for k in sorted(res):
            v = res[k]
            print(f"{k:34s} {v:.4g}" if isinstance(v, float) else f"{k:34s} {v}")
        return
    five = bench_mcl(5000)
    res.update({"mcl_5k_s": five["s"], "mcl_5k_clusters": five["clusters"],
                "mcl_5k_ari": five["ari"]})
    r12 = bench_mcl(5000, inflation=12.0)
    res.update({"mcl_5k_r12_clusters": r12["clusters"], "mcl_5k_r12_ari": r12["ari"]})
    if not q:
        child = subprocess.run([sys.executable, __file__, "--mcl-child", "20000"],
                               capture_output=True, text=True, cwd=REPO, timeout=1800)
        if child.returncode == 0:
            big = json.loads(child.stdout.strip().splitlines()[-1])
            res.update({"mcl_20k_s": big["s"], "mcl_20k_clusters": big["clusters"],
                        "mcl_20k_ari": big["ari"], "mcl_20k_peak_rss_gb": big["peak_rss_gb"]})
        else:
            print(child.stderr[-2000:], file=sys.stderr)
    tuned, rows = bench_tuning(embed, frames=8 if q else 24, step=4)
    res.update(tuned)
    res["cores"] = os.cpu_count()
    res["commit"] = commit()
    res["quick"] = q
    (RESULTS / "discovery.json").write_text(json.dumps(res, indent=1, sort_keys=True))

    print(f"\n{'figure':34s} value")
    for k in sorted(res):
        if k.startswith("tune_") and not k.startswith("tune_default"):
            continue
        v = res[k]
        print(f"{k:34s} {v:.4g}" if isinstance(v, float) else f"{k:34s} {v}")
    print(f"\ntuning grid (tuning seeds {TUNE_SEEDS}, ARI / purity / clusters):")
    print(f"{'affinity':10s} {'eta':>5s} {'inflation':>9s} {'ari':>7s} {'purity':>7s} "
          f"{'clusters':>8s}")
    for r in rows:
        print(f"{r['affinity']:10s} {r['eta']:5.1f} {r['inflation']:9.1f} {r['ari']:7.3f} "
              f"{r['purity']:7.3f} {r['clusters']:8.1f}")


if __name__ == "__main__":
    from neurncd_ros.core.text import progress_as_lines

    with progress_as_lines():  # a log file gets the bars as lines
        main()
