"""Embedding-NeRF benchmark: fast vs reference backend on one streamed synthetic scene.

The scene (seed 7, 300 frames at 320x240, 30 Hz) is fed to a Mapper as the
online system would: frames arrive at 30 Hz on the training clock while the
mapper trains in its background thread. Every 10th frame is held out (never
offered); ``--eval-frames`` of them (all 30 by default) are rendered at each
wall-time checkpoint (training paused, evaluation excluded from the clock) on a
4-pixel grid of exact full-resolution pixels (80x60 rays per frame; 8-pixel
grid in --quick).

Each held-out view is rendered twice: from the field alone (``free``: a novel
view, what the reference backend always does) and with the view's measured
depth placing the samples (``depth``: how the mapper renders the RGB-D frames it
publishes for labelling; only the fast backend uses it). Headline fast figures
(``fast_*_120s``; ``_30s`` in --quick, whose run ends there) are the depth-guided ones,
the way the system labels; ``fast_*_free_120s`` are the field-only ones. The speed-up
compares like with like: the fast backend's field-only renders against the reference's.

Figures per checkpoint: held-out colour PSNR, median depth error, argmax
agreement with the backbone's embedding of the held-out frame, and known-class
accuracy against ground truth (pixels whose GT is a known class).
``mapper_peak_rss_gb`` is the process's high-water mark after the fast run (the
fast mapper plus this script's frames and embeddings: an upper bound for the
mapper), ``reference_peak_rss_gb`` after the reference run. Writes
bench/results/field.json and bench/results/field.png.

    .venv/bin/python bench/field.py                 # full: fast 120 s, reference 600 s
    .venv/bin/python bench/field.py --quick         # smoke: fast 30 s, reference 40 s,
                                                    # 4 eval frames at 40x30 rays
    .venv/bin/python bench/field.py --embedding gt  # noisy one-hot GT logits, no backbone
    .venv/bin/python bench/field.py --skip-reference  # fast backend only: field_fast.json
    .venv/bin/python bench/field.py --skip-reference \\
        --set mapper.fast.embedding_confidence_power=2 --name field_fast_power2
    .venv/bin/python bench/field.py --skip-reference \\
        --set backbone.features=true --name field_fast_features

``--set`` changes a parameter of the mapper's configuration (``mapper``,
``mapper.<backend>`` and ``keyframes`` sections; the backend, its threads and the
seed stay the benchmark's own) or ``backbone.features``: the embedding then carries
the backbone's penultimate features after its logits, the field distils them
(``mapper.distill_features``), and each checkpoint adds ``feature_error``: the
rendered features' squared error relative to the held-out frame's own features'
squared norm (0 = exact, 1 = a field that renders zeros).

"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from neurncd_ros import config  # noqa: E402
from neurncd_ros.core import classes  # noqa: E402
from neurncd_ros.core.camera import camera_directions  # noqa: E402
from neurncd_ros.synth.generator import SynthConfig, generate  # noqa: E402
from neurncd_ros.core.field.mapper import Mapper  # noqa: E402

RESULTS = REPO / "bench" / "results"
FAST_CHECKPOINTS = [2, 4, 6, 8, 10, 15, 20, 30, 40, 60, 90, 120]
REFERENCE_CHECKPOINTS = [60, 120, 300, 600]


from _common import commit, results_dir  # noqa: E402  (bench/ is on sys.path)


def gt_embedding(semantic: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Stand-in backbone: 5 x one-hot of the known class + N(0, 1); novel/void pixels noise."""
    emb = rng.normal(0.0, 1.0, semantic.shape + (classes.NUM_KNOWN,)).astype(np.float32)
    for cid, k in classes.ID_TO_CHANNEL.items():
        emb[..., k] += 5.0 * (semantic == cid)
    return emb


def embeddings(frames, mode: str, features: bool = False
               ) -> tuple[list[np.ndarray], np.ndarray, str]:
    """Per-frame logits (float16 to save memory), channel_to_id, and what produced them;
    ``features``: the backbone's penultimate features after the logits."""
    if mode in ("auto", "backbone") or features:
        try:
            from neurncd_ros.core.backbone.backbone import BackboneConfig, load_backbone
            bb = load_backbone(BackboneConfig(features=features))
            out = [bb.embed(f.rgb, f.depth).astype(np.float16)
                   for f in tqdm(frames, desc="backbone", leave=False)]
            return (out, np.asarray(bb.channel_to_id),
                    "backbone(default" + (", features)" if features else ")"))
        except (ImportError, ValueError, OSError) as exc:
            if mode == "backbone" or features:
                raise
            print(f"backbone unavailable ({exc}); using noisy ground-truth logits")
    rng = np.random.default_rng(0)
    return ([gt_embedding(f.semantic, rng).astype(np.float16) for f in frames],
            classes.CHANNEL_TO_ID.copy(), "gt(5*onehot+N(0,1))")


EVAL_STRIDE = 4


def eval_rays(f, stride: int | None = None):
    """Rays and targets of a grid of exact full-resolution pixels (centre of each block)."""
    stride = stride or EVAL_STRIDE
    h, w = f.intrinsics.height, f.intrinsics.width
    v, u = np.mgrid[stride // 2:h:stride, stride // 2:w:stride]
    u, v = u.ravel(), v.ravel()
    d = camera_directions(f.intrinsics, u, v) @ f.pose[:3, :3].T
    o = np.broadcast_to(f.pose[:3, 3], d.shape)
    return o, d, u, v


def evaluate(mapper: Mapper, frames, embs, channel_to_id, use_depth: bool = False
             ) -> dict[str, float]:
    """Held-out PSNR, depth error, agreement with the backbone, known accuracy vs GT.

    ``use_depth``: render with the held-out view's measured depth (never trained on;
    only its depth places the samples)."""
    psnr, derr, agree, known_ok, known_n = [], [], [], 0, 0
    S = len(channel_to_id)
    feat_err, feat_norm = 0.0, 0.0
    for f, e in zip(frames, embs):
        o, d, u, v = eval_rays(f)
        out = mapper.render_rays(o, d, f.depth[v, u] if use_depth else None)
        mse = float(np.mean((out["rgb"] - f.rgb[v, u] / 255.0) ** 2))
        psnr.append(-10 * math.log10(max(mse, 1e-10)))
        z = f.depth[v, u]
        ok = z > 0
        derr.append(np.abs(out["depth"][ok] - z[ok]))
        pred = out["embedding"][:, :S].argmax(-1)
        target = e[v, u].astype(np.float32)
        agree.append(float(np.mean(pred == target[:, :S].argmax(-1))))
        if out["embedding"].shape[1] > S:  # distilled features: where the view has depth
            feat_err += float(((out["embedding"][ok, S:] - target[ok, S:]) ** 2).sum())
            feat_norm += float((target[ok, S:] ** 2).sum())
        gt = f.semantic[v, u]
        known = np.isin(gt, classes.KNOWN_IDS)
        known_ok += int((channel_to_id[pred] == gt)[known].sum())
        known_n += int(known.sum())
    res = {"psnr": float(np.mean(psnr)), "depth_err_cm": 100 * float(np.median(
        np.concatenate(derr))), "agreement": float(np.mean(agree)),
        "known_acc": known_ok / max(known_n, 1)}
    if feat_norm > 0:
        res["feature_error"] = feat_err / feat_norm
    return res


def backbone_known_acc(frames, embs, channel_to_id) -> float:
    ok = n = 0
    for f, e in zip(frames, embs):
        _, _, u, v = eval_rays(f)
        gt = f.semantic[v, u]
        known = np.isin(gt, classes.KNOWN_IDS)
        logits = e[v, u, : len(channel_to_id)].astype(np.float32)
        ok += int((channel_to_id[logits.argmax(-1)] == gt)[known].sum())
        n += int(known.sum())
    return ok / max(n, 1)


def run_stream(backend: str, frames, embs, held, checkpoints, eval_set, channel_to_id,
               threads: int, fps: float, base: config.Config | None = None) -> list[dict]:
    """Feed frames at ``fps`` on the training clock while training; evaluate at checkpoints.

    ``base``: the configuration whose mapper, backend and keyframe sections are used
    (default: the shipped defaults); backend, threads and seed are set here."""
    base = base or config.default()
    nested = base.to_nested()
    nested["mapper"].update(backend=backend, num_threads=threads, seed=0)
    S = len(channel_to_id)
    mapper = Mapper.from_config(config.from_nested(nested), S, embs[0].shape[-1] - S)
    eval_frames = [frames[i] for i in eval_set]
    eval_embs = [embs[i] for i in eval_set]
    curve, nxt, clock, admitted = [], 0, 0.0, 0
    bar = tqdm(total=checkpoints[-1], desc=backend, unit="s")
    mapper.start()
    resumed = time.monotonic()
    for cp in checkpoints:
        while True:
            now = clock + time.monotonic() - resumed
            while nxt < len(frames) and nxt / fps <= now:
                if nxt not in held:
                    admitted += mapper.add_keyframe(frames[nxt], embs[nxt].astype(np.float32))
                nxt += 1
            if now >= cp:
                break
            time.sleep(0.005)
        mapper.stop()
        if mapper.last_error is not None:
            raise mapper.last_error
        clock += time.monotonic() - resumed
        bar.update(clock - bar.n)
        row = {"t": round(clock, 2), "iterations": mapper.iterations,
               "frames_fed": nxt, "keyframes": len(mapper.buffer), "admitted": admitted}
        row.update(evaluate(mapper, eval_frames, eval_embs, channel_to_id))
        if backend == "fast":
            guided = evaluate(mapper, eval_frames, eval_embs, channel_to_id, use_depth=True)
            row.update({f"{k}_depth": v for k, v in guided.items()})
        curve.append(row)
        tqdm.write(f"{backend:9s} t={row['t']:6.1f}s it={row['iterations']:5d} "
                   f"kf={row['keyframes']:3d} psnr={row['psnr']:5.2f} "
                   f"depth={row['depth_err_cm']:5.1f}cm agree={row['agreement']:.3f} "
                   f"known={row['known_acc']:.3f}"
                   + (f" features={row['feature_error']:.3f}" if "feature_error" in row else "")
                   + (f" | depth-guided psnr={row['psnr_depth']:5.2f} agree="
                      f"{row['agreement_depth']:.3f} known={row['known_acc_depth']:.3f}"
                      if "psnr_depth" in row else ""))
        mapper.start()
        resumed = time.monotonic()
    mapper.stop()
    bar.close()
    return curve


def at(curve: list[dict], t: float, key: str) -> float:
    """Value at the last checkpoint not after t (the curve is sampled at checkpoints)."""
    rows = [r for r in curve if r["t"] <= t + 1.0] or curve[:1]
    return rows[-1][key]


def plot(curves: dict[str, list[dict]], path: Path, backbone_acc: float | None = None) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker
    fig, axes = plt.subplots(1, 4, figsize=(17, 3.8))
    for name, curve in curves.items():
        t = [r["t"] for r in curve]
        for suffix, style, tag in (("", "o-", ""), ("_depth", "s--", " (depth-guided)")):
            if f"psnr{suffix}" not in curve[0]:
                continue
            for ax, key, label in zip(axes, ("psnr", "depth_err_cm", "agreement", "known_acc"),
                                      ("held-out PSNR (dB)", "median depth error (cm)",
                                       "argmax agreement with backbone",
                                       "known-class accuracy vs ground truth")):
                ax.plot(t, [r[key + suffix] for r in curve], style, label=name + tag,
                        markersize=4)
    for ax in axes:
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        ax.set_xlabel("training wall time (s)")
        ax.grid(True, alpha=0.3)
    for ax, label in zip(axes, ("held-out PSNR (dB)", "median depth error (cm)",
                                "argmax agreement with backbone",
                                "known-class accuracy vs ground truth")):
        ax.set_title(label)
    if backbone_acc is not None:
        axes[3].axhline(backbone_acc, color="k", lw=1, ls=":", label="backbone")
        axes[3].legend(fontsize=8)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    global RESULTS
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="short smoke run for a shared machine")
    ap.add_argument("--embedding", choices=("auto", "backbone", "gt"), default="auto")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--eval-frames", type=int, default=30)
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads of the fast backend (1: the shipped default)")
    ap.add_argument("--reference-threads", type=int, default=os.cpu_count() or 1,
                    help="torch threads of the reference backend (its fastest setting)")
    ap.add_argument("--skip-reference", action="store_true")
    ap.add_argument("--name", default=None,
                    help="results file stem (default: field, or field_fast with "
                    "--skip-reference, so a run without the reference never replaces the "
                    "full record)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="change a mapper parameter (repeatable; give the run its own --name)")
    args = ap.parse_args()
    RESULTS = results_dir(args.quick)
    RESULTS.mkdir(parents=True, exist_ok=True)
    if args.set and args.name is None:
        raise SystemExit("--set changes the configuration: give the run its own --name")
    run_cfg = config.load(None, config.parse_overrides(args.set))
    fast_cps, ref_cps = FAST_CHECKPOINTS, REFERENCE_CHECKPOINTS
    if args.quick:
        global EVAL_STRIDE
        fast_cps, ref_cps = [5, 10, 20, 30], [20, 30, 40]
        args.eval_frames = min(args.eval_frames, 4)
        EVAL_STRIDE = 8
    torch.set_num_threads(args.threads)

    cfg = SynthConfig()
    frames = list(tqdm(generate(args.seed, args.frames, cfg), total=args.frames,
                       desc="synth", leave=False))
    embs, channel_to_id, source = embeddings(frames, args.embedding, run_cfg.backbone.features)
    held = set(range(5, len(frames), 10))
    step = max(1, len(held) // args.eval_frames)
    eval_set = sorted(held)[::step][:args.eval_frames]
    base = backbone_known_acc([frames[i] for i in eval_set], [embs[i] for i in eval_set],
                              channel_to_id)
    print(f"{len(frames)} frames {cfg.width}x{cfg.height}, {len(held)} held out, "
          f"{len(eval_set)} evaluated; embedding {source}; backbone known acc {base:.3f}")

    curves = {"fast": run_stream("fast", frames, embs, held, fast_cps, eval_set,
                                 channel_to_id, args.threads, cfg.fps, run_cfg)}
    # High-water mark so far: the fast mapper plus this script's 300 frames and their
    # embeddings (a conservative bound for the mapper alone); the reference comes later.
    fast_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    if not args.skip_reference:
        torch.set_num_threads(args.reference_threads)
        curves["reference"] = run_stream("reference", frames, embs, held, ref_cps, eval_set,
                                         channel_to_id, args.reference_threads, cfg.fps, run_cfg)

    fast = curves["fast"]
    h = fast_cps[-1]  # the headline time: 120 s, 30 in --quick (the keys say which)
    res: dict = {
        "embedding": source, "frames": len(frames), "eval_frames": len(eval_set),
        "eval_rays_per_frame": int(eval_rays(frames[0])[0].shape[0]),
        "threads": args.threads, "reference_threads": args.reference_threads,
        "quick": bool(args.quick), "set": args.set,
        f"fast_psnr_{h}s": at(fast, h, "psnr_depth"),
        f"fast_depth_err_cm_{h}s": at(fast, h, "depth_err_cm_depth"),
        f"fast_agreement_{h}s": at(fast, h, "agreement_depth"),
        f"fast_known_acc_{h}s": at(fast, h, "known_acc_depth"),
        f"fast_psnr_free_{h}s": at(fast, h, "psnr"),
        f"fast_depth_err_cm_free_{h}s": at(fast, h, "depth_err_cm"),
        f"fast_agreement_free_{h}s": at(fast, h, "agreement"),
        f"fast_known_acc_free_{h}s": at(fast, h, "known_acc"),
        f"fast_iterations_{h}s": at(fast, h, "iterations"),
        **({f"fast_feature_error_{h}s": at(fast, h, "feature_error_depth"),
            f"fast_feature_error_free_{h}s": at(fast, h, "feature_error")}
           if "feature_error" in fast[0] else {}),
        "fast_last_t": fast[-1]["t"],
        "backbone_known_acc": base,
    }
    if "reference" in curves:
        ref = curves["reference"]
        res.update({
            f"reference_psnr_{h}s": at(ref, h, "psnr"),
            f"reference_agreement_{h}s": at(ref, h, "agreement"),
            f"reference_known_acc_{h}s": at(ref, h, "known_acc"),
            "reference_final_t": ref[-1]["t"], "reference_final_psnr": ref[-1]["psnr"],
            "reference_final_agreement": ref[-1]["agreement"],
            "reference_iterations_final": ref[-1]["iterations"],
        })
        reach = [r["t"] for r in fast if r["psnr"] >= ref[-1]["psnr"]
                 and r["agreement"] >= ref[-1]["agreement"]]
        if reach:
            res["speedup_to_reference_best"] = ref[-1]["t"] / reach[0]
            res["speedup_is_lower_bound"] = reach[0] == fast[0]["t"]
            res["fast_time_to_reference_best_s"] = reach[0]
        else:
            res["speedup_to_reference_best"] = None
            res["speedup_is_lower_bound"] = False
    res["mapper_peak_rss_gb"] = fast_rss
    res["reference_peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    for name, curve in curves.items():
        for key in ("t", "iterations", "psnr", "depth_err_cm", "agreement", "known_acc",
                    "psnr_depth", "depth_err_cm_depth", "agreement_depth", "known_acc_depth",
                    "feature_error", "feature_error_depth"):
            if key in curve[0]:
                res[f"{name}_curve_{key}"] = [r[key] for r in curve]
    res["cores"] = os.cpu_count()
    res["commit"] = commit()

    RESULTS.mkdir(parents=True, exist_ok=True)
    stem = args.name or ("field_fast" if args.skip_reference else "field")
    (RESULTS / f"{stem}.json").write_text(json.dumps(res, indent=2))
    plot(curves, RESULTS / f"{stem}.png", base)
    print()
    for k, v in res.items():
        if not isinstance(v, list):
            print(f"  {k:34s} {v:.4g}" if isinstance(v, float) else f"  {k:34s} {v}")
    print(f"wrote {RESULTS / stem}.json and {stem}.png")


if __name__ == "__main__":
    from neurncd_ros.core.text import progress_as_lines

    with progress_as_lines():  # a log file gets the bars as lines
        main()
