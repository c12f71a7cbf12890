"""Issue 12's evaluation on held-out synthetic scenes: the paper's Tables 1-3 with
ablations, the explicit-map and Semantic-NeRF baselines, mean and standard deviation
over scenes.

Scenes are ``seeds.TEST`` (never used for training or tuning), default
configuration, each streamed through the online engine once
(``core.eval.evaluate_frames``, the same code as ``neurncd eval``). Writes
bench/results/eval.json (the issue's keys, each {"mean", "std"} in percent),
bench/results/eval/ (eval.json, tables.md) and bench/results/eval.html. The issue's
targets and the shortfalls are checked by ``core.eval.targets`` (the same code as
``neurncd eval`` and ``neurncd report``).

    .venv/bin/python bench/eval.py --workers 1   # 8 test scenes
    .venv/bin/python bench/eval.py --quick       # 2 short scenes (smoke)
    .venv/bin/python bench/eval.py --workers 1 --cache /tmp/eval_cache  # resumable
    .venv/bin/python bench/eval.py --scenes 2 --set run.training_rate_hz=60 --name eval_rate60

``--set`` changes a parameter for every row (both the engine and the baselines'
fields see it; e.g. a longer training schedule); such a run should get its own
``--name``, which names the JSON, its folder and its HTML page in bench/results.

With ``--cache DIR`` each scene's result is kept in DIR (keyed by seed, frames and
commit) and reused by the next run at the same commit: a run stopped part way
resumes where it was.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import sys
import time
from pathlib import Path

import cv2
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from neurncd_ros import config, synth  # noqa: E402
from neurncd_ros.core.backbone.backbone import load_backbone  # noqa: E402
from neurncd_ros.core.eval import evaluate, report, targets  # noqa: E402
from neurncd_ros.synth import seeds  # noqa: E402

from _common import commit, results_dir  # noqa: E402

RESULTS = REPO / "bench" / "results"

KEYS = {  # issue key -> (row, figure)
    "full_known_miou": ("full", "miou_known"),
    "full_novel_miou": ("full", "miou_novel"),
    "full_miou": ("full", "miou_all"),
    "pssn_known_miou": ("pssn", "miou_known"),
    "gs_miou": ("gs", "assigned_miou"),
    "gs_pssn_ep_mcl_miou": ("gs_pssn_ep_mcl", "miou_all"),
    "explicit_baseline_miou": ("explicit", "miou_all"),
    "semnerf_1pct_known_miou": ("semnerf_1pct", "miou_known"),
    "semnerf_5pct_known_miou": ("semnerf_5pct", "miou_known"),
    "semnerf_10pct_known_miou": ("semnerf_10pct", "miou_known"),
}


def _config(overrides: tuple[str, ...]) -> config.Config:
    """The default configuration with ``SECTION.KEY=VALUE`` overrides (YAML values)."""
    try:
        return (config.load(None, config.parse_overrides(list(overrides))) if overrides
                else config.default())
    except config.ConfigError as err:
        raise SystemExit(f"bench/eval.py: {err}") from None


def _scene(job: tuple) -> dict:
    seed, frames, cache, overrides = job
    tag = "-".join(o.replace("=", "_").replace("/", "_") for o in overrides)
    name = f"{seed}-{frames}-{commit()}" + (f"-{tag}" if tag else "")
    path = Path(cache) / f"{name}.pkl" if cache else None
    if path is not None and path.is_file():
        return pickle.loads(path.read_bytes())
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    cfg = _config(overrides)
    out = evaluate.evaluate_frames(synth.generate(seed, frames, cfg.synth), cfg, frames,
                                   progress=False, keep_pictures=1,
                                   name=f"synthetic seed {seed}")
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(pickle.dumps(out))
    return out


def main() -> None:
    global RESULTS
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="2 short scenes (smoke); results in bench/results/quick/")
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--frames", type=int, default=300,
                    help="frames per scene (300 = 10 s, the demo's length)")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--cache", default="", help="keep and reuse each scene's result here")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override a parameter for every row (repeatable)")
    ap.add_argument("--name", default="eval",
                    help="results name: bench/results/NAME.json, NAME/ and NAME.html")
    args = ap.parse_args()
    RESULTS = results_dir(args.quick)
    RESULTS.mkdir(parents=True, exist_ok=True)
    if args.set and args.name == "eval":
        raise SystemExit("--set changes the configuration: give the run its own --name "
                         "(eval.json holds the default configuration)")
    cfg = _config(tuple(args.set))  # a bad override fails here, before any scene runs
    n, frames = (2, 40) if args.quick else (args.scenes, args.frames)
    test = list(seeds.TEST[:n])
    t0 = time.perf_counter()
    from tqdm import tqdm
    jobs = [(s, frames, args.cache, tuple(args.set)) for s in test]
    if args.workers > 1:
        import multiprocessing as mp
        with mp.get_context("fork").Pool(args.workers) as pool:
            per = list(tqdm(pool.imap(_scene, jobs), total=len(jobs), desc="scenes"))
    else:
        per = [_scene(j) for j in tqdm(jobs, desc="scenes")]
    out_dir = RESULTS / args.name
    result = evaluate.write_eval(out_dir, per)
    agg = result["aggregate"]
    res: dict = {k: {"mean": agg[r][f]["mean"], "std": agg[r][f]["std"]}
                 for k, (r, f) in KEYS.items()}
    semnerf_facts = {}
    for row in (r for r in agg if r.startswith("semnerf_")):
        runs = [b["semnerf"][row] for b in per if row in b.get("semnerf", {})]
        semnerf_facts[row] = {k: evaluate.mean_std([r[k] for r in runs]) for k in (
            "labels_per_keyframe", "label_fit", "iterations", "seconds")}
    res.update({"test_seeds": test, "frames_per_scene": frames, "quick": bool(args.quick),
                "labelled_frames": int(sum(b["labelled"] for b in per)),
                "seconds": round(time.perf_counter() - t0, 1), "cores": os.cpu_count(),
                "backbone_precision": load_backbone(cfg.backbone).precision,
                "commit": commit(), "rows": {r: {f: agg[r][f] for f in evaluate.FIGURES}
                                              for r in agg}})
    res["semnerf"] = semnerf_facts
    res["set"] = list(args.set)
    res["targets"] = result["targets"]
    res["shortfalls"] = [x for t, x in zip(result["targets"], targets.lines(result["targets"]))
                         if t["met"] is not True or t.get("caveat")]
    (RESULTS / f"{args.name}.json").write_text(json.dumps(res, indent=1, sort_keys=True))
    report.render(out_dir, RESULTS / f"{args.name}.html")
    (out_dir / "pictures.npz").unlink()  # inlined in eval.html; not kept in the repository
    print((out_dir / "tables.md").read_text())
    for k, v in res.items():
        if isinstance(v, dict) and "mean" in v:
            print(f"{k:28s} {v['mean'] if v['mean'] is None else round(v['mean'], 1)} "
                  f"± {v['std'] if v['std'] is None else round(v['std'], 1)}")
    print("\n".join(targets.lines(result["targets"])))
    print(f"wrote {RESULTS / args.name}.json, {args.name}.html, {args.name}/ in "
          f"{res['seconds']} s")


if __name__ == "__main__":
    from neurncd_ros.core.text import progress_as_lines

    with progress_as_lines():  # a log file gets the bars as lines
        main()
