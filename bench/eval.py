"""Issue 12's evaluation on held-out synthetic scenes: the paper's Tables 1-3 with
ablations and the explicit-map baseline, mean and standard deviation over scenes.

Scenes are ``seeds.TEST`` (never used for training or tuning), default
configuration, each streamed through the online engine once
(``core.eval.evaluate_frames``, the same code as ``neurncd eval``). Writes
bench/results/eval.json (the issue's keys, each {"mean", "std"} in percent),
bench/results/eval/ (eval.json, tables.md) and bench/results/eval.html.

    .venv/bin/python bench/eval.py               # 8 test scenes
    .venv/bin/python bench/eval.py --quick       # 2 short scenes (smoke)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from neurncd_ros import config, synth  # noqa: E402
from neurncd_ros.core.eval import evaluate, report  # noqa: E402
from neurncd_ros.synth import seeds  # noqa: E402

from _common import commit  # noqa: E402

RESULTS = REPO / "bench" / "results"

KEYS = {  # issue key -> (row, figure)
    "full_known_miou": ("full", "miou_known"),
    "full_novel_miou": ("full", "miou_novel"),
    "full_miou": ("full", "miou_all"),
    "pssn_known_miou": ("pssn", "miou_known"),
    "gs_miou": ("gs", "assigned_miou"),
    "gs_pssn_ep_mcl_miou": ("gs_pssn_ep_mcl", "miou_all"),
    "explicit_baseline_miou": ("explicit", "miou_all"),
}


def _scene(job: tuple) -> dict:
    seed, frames = job
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    cfg = config.default()
    return evaluate.evaluate_frames(synth.generate(seed, frames, cfg.synth), cfg, frames,
                                    progress=False, keep_pictures=1,
                                    name=f"synthetic seed {seed}")


def shortfalls(res: dict, bags: list[dict]) -> list[str]:
    """Why a target of the issue is missed, from what was measured (one line each)."""
    out = []
    m = {k: v["mean"] for k, v in res.items() if isinstance(v, dict) and "mean" in v}
    it = [b["iterations"] for b in bags]
    kf = [b["keyframes"] for b in bags]
    rows = res["rows"]
    gap = m["full_miou"] - m["explicit_baseline_miou"]
    if gap < 10.0:
        dk = rows["full"]["miou_known"]["mean"] - rows["explicit"]["miou_known"]["mean"]
        dn = rows["full"]["miou_novel"]["mean"] - rows["explicit"]["miou_novel"]["mean"]
        out.append(
            f"full vs explicit map: {gap:+.1f} mIoU points, {10.0 - gap:.1f} short of the +10 "
            f"target (known {dk:+.1f}, novel {dn:+.1f}). The explicit map averages the "
            f"backbone's logits of every labelled frame per 5 cm voxel with exact depth and "
            f"poses, so it is already a multi-view fusion; the field trains only "
            f"{min(it)}-{max(it)} iterations per scene in the stream time "
            f"(run.training_rate_hz) over {min(kf)}-{max(kf)} keyframes, and its views are "
            f"completed from the backbone where it has not learnt the scene. Both rows share "
            f"the backbone and the discovery stage, so the gap measures the field against a "
            f"direct multi-view fusion of the same logits, not a weaker pipeline.")
    if m["full_miou"] <= m["gs_pssn_ep_mcl_miou"]:
        out.append("full is not above GS+PSSN+EP+MCL")
    if m["gs_pssn_ep_mcl_miou"] <= m["gs_miou"]:
        out.append("GS+PSSN+EP+MCL is not above GS alone")
    out.append("full known vs Semantic-NeRF 1 %: not measured; the Semantic-NeRF "
               "label-propagation head is not implemented.")
    return out


def annotate() -> None:
    """Add the shortfall notes to an existing bench/results/eval.json and eval.html."""
    res = json.loads((RESULTS / "eval.json").read_text())
    bags = json.loads((RESULTS / "eval" / "eval.json").read_text())["bags"]
    res["shortfalls"] = shortfalls(res, bags)
    (RESULTS / "eval.json").write_text(json.dumps(res, indent=1, sort_keys=True))
    page = (RESULTS / "eval.html").read_text()
    if "<h3>Why</h3>" not in page:
        why = "<h3>Why</h3><ul>" + "".join(f"<li>{x}</li>" for x in res["shortfalls"]) + "</ul>"
        page = page.replace("</ul>", "</ul>" + why, 1)
        (RESULTS / "eval.html").write_text(page)
    print("\n".join(res["shortfalls"]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--frames", type=int, default=300,
                    help="frames per scene (300 = 10 s, the demo's length)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--annotate", action="store_true",
                    help="only add the shortfall notes to the existing results")
    args = ap.parse_args()
    if args.annotate:
        annotate()
        return
    n, frames = (2, 40) if args.quick else (args.scenes, args.frames)
    test = list(seeds.TEST[:n])
    t0 = time.perf_counter()
    from tqdm import tqdm
    jobs = [(s, frames) for s in test]
    if args.workers > 1:
        import multiprocessing as mp
        with mp.get_context("fork").Pool(args.workers) as pool:
            per = list(tqdm(pool.imap(_scene, jobs), total=len(jobs), desc="scenes"))
    else:
        per = [_scene(j) for j in tqdm(jobs, desc="scenes")]
    out_dir = RESULTS / "eval"
    result = evaluate.write_eval(out_dir, per)
    agg = result["aggregate"]
    res: dict = {k: {"mean": agg[r][f]["mean"], "std": agg[r][f]["std"]}
                 for k, (r, f) in KEYS.items()}
    for k in ("semnerf_1pct_known_miou", "semnerf_10pct_known_miou"):
        res[k] = {"mean": None, "std": None, "note": "not done (no Semantic-NeRF head)"}
    res.update({"test_seeds": test, "frames_per_scene": frames, "quick": bool(args.quick),
                "labelled_frames": int(sum(b["labelled"] for b in per)),
                "seconds": round(time.perf_counter() - t0, 1), "cores": os.cpu_count(),
                "commit": commit(), "rows": {r: {f: agg[r][f] for f in evaluate.FIGURES}
                                              for r in agg}})
    # The ordering and targets, measured.
    m = {k: v["mean"] for k, v in res.items() if isinstance(v, dict) and "mean" in v}
    checks = {
        "full > gs_pssn_ep_mcl": m["full_miou"] - m["gs_pssn_ep_mcl_miou"],
        "gs_pssn_ep_mcl > gs": m["gs_pssn_ep_mcl_miou"] - m["gs_miou"],
        "full >= explicit + 10": m["full_miou"] - m["explicit_baseline_miou"] - 10.0,
    }
    res["targets_margin"] = checks
    (RESULTS / "eval.json").write_text(json.dumps(res, indent=1, sort_keys=True))
    notes = "<h2>Issue 12 targets (margin in mIoU points; negative = short)</h2><ul>" + "".join(
        f"<li>{k}: {v:+.1f}</li>" for k, v in checks.items()) + \
        "<li>full known > Semantic-NeRF 1 %: not measured (Semantic-NeRF head not done)</li></ul>"
    res["shortfalls"] = shortfalls(res, result["bags"])
    (RESULTS / "eval.json").write_text(json.dumps(res, indent=1, sort_keys=True))
    notes += "<h3>Why</h3><ul>" + "".join(f"<li>{x}</li>" for x in res["shortfalls"]) + "</ul>"
    report.render(out_dir, RESULTS / "eval.html", notes=notes)
    (out_dir / "pictures.npz").unlink()  # inlined in eval.html; not kept in the repository
    print((out_dir / "tables.md").read_text())
    for k, v in res.items():
        if isinstance(v, dict) and "mean" in v:
            print(f"{k:28s} {v['mean'] if v['mean'] is None else round(v['mean'], 1)} "
                  f"± {v['std'] if v['std'] is None else round(v['std'], 1)}")
    for k, v in checks.items():
        print(f"target {k}: margin {v:+.1f}")
    print(f"wrote {RESULTS / 'eval.json'}, eval.html, eval/ in {res['seconds']} s")


if __name__ == "__main__":
    main()
