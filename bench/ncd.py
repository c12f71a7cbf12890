"""End-to-end novel class discovery: backbone -> Embedding-NeRF -> discovery, scored.

Each synthetic scene (``--frames`` frames at 320x240, 30 Hz, Kinect-like depth)
goes through the online engine offline exactly as ``neurncd run`` does
(``core.engine.offline.OfflineEngine``: the embedding stage's rate gate, the
field's keyframes, every keyframe and other frames up to ``run.view_rate_hz``
labels per second of stream, keyframes included, rendered at their pose and
depth with the coverage blend, the ``run.*`` training schedule), i.e. what the
live graph publishes. The views (rendered
embedding + entropy) and the backbone's own logits of the labelled frames are
cached (npz under /tmp, keyed by seed, frame count, the engine's configuration,
backbone weights, the source of the backbone, engine and field, and the
generator's source), so the discovery stage can be scored and tuned many times.

Scenes: tuning on ``seeds.TUNE`` (rooms the backbone never saw), report on
``seeds.TEST`` (held out from everything). Each scene is scored on its own
(novel ids are per scene, so its novel clusters are matched to its classes) and
the report gives the mean over scenes. Rows of the report (percent):

- ``neurncd``: the shipped defaults on the rendered embedding and entropy;
- ``backbone_logits``: the same discovery on the backbone's per-frame logits
  and their entropy, segmented on the measured depth (no mapper stage: what the
  multi-view mapper buys);
- ``measured_depth``: the mapper stage's embedding and entropy segmented on the
  measured depth instead of the view depth the mapper fuses from the keyframes'
  (``mapper_node.depth_fusion`` off);
- ``paper_mcl``: the paper's clustering (cosine affinity, inflation 12);
- ``embedding_only`` / ``entropy_only``: the paper's modulation ablations;
- ``no_colour_edges``: segmentation without the colour cue (geometry + embedding);
- ``no_colour_descriptor``: descriptors without the mean Lab colour part
  (``modulation.colour_weight`` 0);
- ``mode_split`` (``no_mode_split`` when the default is on): small, distant
  clusters of a known class split off as novel (``discovery.mode_split``, off by
  default);
- ``no_novel_merge``: novel clusters never share an id (``discovery.novel_merge_distance``
  0), each Markov cluster its own novel class;
- ``no_colour_no_split``: both off (the descriptor and decision before issue 11);
- ``backbone``: the backbone's argmax alone (knows no novel class);
- ``fallback_backbone``: the mapper stage blending in the frame's own backbone
  embedding where the field has not learnt the scene (``mapper_node.fallback``
  backbone, before issue 11) instead of the keyframe fusion; ``fusion_logits``:
  the keyframe fusion averaging logits instead of class probabilities;
  ``disagreement_2``: the views' disagreement added twice to the view's entropy
  (``mapper_node.disagreement_weight`` 2, off by default); ``fusion_unweighted``: the
  frame's own view counted once in the fusion, as every other view
  (``mapper_node.own_view_weight`` 1), with the looser visibility test and the fewer
  recent frames of before (``coverage_depth_tolerance`` 0.05, ``fusion_recent`` 8);
  ``no_novelty_branch``: the backbone's known-class logits without its outlier-exposed
  novelty branch (``backbone.novelty_branch`` false: the same argmax, the head's own
  entropy, with the entropy threshold tuned for it, 0.15) (these rows render the scenes
  again);
- ``no_uncertain_regions``: no large uncertain regions as segments of their own
  (``discovery.uncertain_region_px`` 0), on the rendered views and
  (``backbone_logits_no_uncertain_regions``) on the backbone's logits; ``no_carve``:
  such regions only where the segmentation left pixels without a segment, not carved
  out of confident segments (``discovery.uncertain_region_carve`` off);
  ``no_uncertain_clusters``: every novel cluster needs ``min_cluster_pixels``, also
  one whose mean entropy is above ``uncertain_region_entropy``
  (``discovery.uncertain_cluster_pixels`` 0);
- ``no_label_fusion``: every frame labelled on its own, without the voxel map of
  labels that keeps a surface's novel id (``label_fusion.enabled`` off);
- ``no_pixel_known``: every pixel of a known segment takes the segment's class
  (``discovery.pixel_known`` off);
- ``tuned`` (with ``--tune``): the values the search chose, on the test scenes;
- ``oracle_embedding``: discovery fed the ground truth as its embedding (5 x one-hot
  logits on known-class pixels, uniform, i.e. maximal entropy, on novel and void ones) on
  the mapper's view depth: what the same discovery scores when the known classes are
  perfect and the novel ones carry no class information, the known-class ceiling of any
  mapper stage (field or fusion) in front of it.

``--tune`` first runs a coordinate search over the labelling and clustering
parameters on the tuning scenes (mIoU over all classes) and prints the grid;
the chosen values are what the shipped config should hold (they are not
applied automatically). Writes bench/results/ncd.json and ncd.png (rgb | GT |
backbone | NeurNCD | entropy for a few test frames); with ``--frames N`` other than 150,
ncd_framesN.json and ncd_framesN.png (longer streams give the map more views).

    .venv/bin/python bench/ncd.py                # report on 8 test scenes
    .venv/bin/python bench/ncd.py --tune         # coordinate search first
    .venv/bin/python bench/ncd.py --quick        # 2 + 2 short scenes (smoke)
    .venv/bin/python bench/ncd.py --frames 300   # 10 s streams: ncd_frames300.json
    .venv/bin/python bench/ncd.py --sweep discovery.novel_merge_distance=0,0.2,0.4
                                                 # one parameter on the tuning scenes
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from neurncd_ros import config  # noqa: E402
from neurncd_ros.core import classes  # noqa: E402
from neurncd_ros.core.engine.views import resize_to  # noqa: E402
from neurncd_ros.core.engine.offline import OfflineEngine  # noqa: E402
from neurncd_ros.synth.training import generator_hash  # noqa: E402
from neurncd_ros.core.backbone.backbone import DEFAULT_WEIGHTS, load_backbone  # noqa: E402
from neurncd_ros.core.uncertainty import entropy  # noqa: E402
from neurncd_ros.core.camera import Intrinsics  # noqa: E402
from neurncd_ros import synth  # noqa: E402
from neurncd_ros.synth import seeds  # noqa: E402
from neurncd_ros.core.discovery.labeller import Discoverer  # noqa: E402
from neurncd_ros.core.discovery.metrics import Evaluator, IdStability  # noqa: E402
from neurncd_ros.core.params import to_dict  # noqa: E402

from _common import commit, results_dir  # noqa: E402  (bench/ is on sys.path)

RESULTS = REPO / "bench" / "results"
CACHE = Path(os.environ.get("NEURNCD_NCD_CACHE", "/tmp/neurncd_ncd_cache"))


def _key(cfg: config.Config, seed: int, frames: int) -> str:
    h = hashlib.sha1()
    h.update(json.dumps({**{k: to_dict(getattr(cfg, k)) for k in (
        "run", "synth", "keyframes", "embedding_node", "mapper_node")},
        "mapper": cfg.to_nested()["mapper"], "seed": seed, "frames": frames},
        sort_keys=True, default=str).encode())
    h.update(json.dumps(to_dict(cfg.backbone), sort_keys=True).encode())
    h.update(Path(cfg.backbone.checkpoint or DEFAULT_WEIGHTS).read_bytes())
    h.update(generator_hash().encode())
    h.update(_render_source_hash().encode())
    return h.hexdigest()[:12]


def _render_source_hash() -> str:
    """The source of everything that makes a view (backbone, engine, field, camera,
    entropy): a change there renders the scenes again instead of reusing stale views."""
    core = REPO / "neurncd_ros" / "core"
    files = sorted([*(core / "backbone").glob("*.py"), *(core / "engine").rglob("*.py"),
                    *(core / "field").rglob("*.py"), core / "camera.py",
                    core / "uncertainty.py", core / "frame.py"])
    h = hashlib.sha1()
    for f in files:
        h.update(f.relative_to(REPO).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()


ROWS = ("rgb", "depth", "view_depth", "K", "embedding", "entropy", "logits", "semantic", "instance",
        "stamp", "keyframe", "field_share", "iterations", "pose")


def scene(cfg: config.Config, seed: int, frames: int) -> dict[str, np.ndarray]:
    """Labelled frames of one scene: depth, K, rendered embedding/entropy, backbone logits,
    semantic, instance, rgb, the view's field share and the field's iterations (arrays
    stacked over frames; embeddings float16). A cache file without one of these arrays
    (written before it was kept) is rendered again."""
    path = CACHE / f"ncd_s{seed}_n{frames}_{_key(cfg, seed, frames)}.npz"
    if path.is_file():
        with np.load(path) as z:
            if set(ROWS) <= set(z.files):
                return {k: z[k] for k in z.files}
    engine = OfflineEngine(cfg, load_backbone(cfg.backbone))
    rows: dict[str, list] = {k: [] for k in ROWS + ("render_ms",)}
    stream = synth.generate(seed, frames, cfg.synth)
    rendered = 0.0
    for o in engine.run(stream, total=frames, progress=False):
        f, v = o.frame, o.view
        rows["render_ms"].append(1000 * (engine.seconds["rendering"] - rendered))
        rendered = engine.seconds["rendering"]
        h, w = f.depth.shape
        rows["rgb"].append(f.rgb)
        rows["depth"].append(f.depth)  # measured
        rows["view_depth"].append(v.view_depth)  # the mapper's, as discovery gets it
        rows["K"].append(f.intrinsics.K)
        rows["pose"].append(f.pose)
        rows["embedding"].append(resize_to(v.embedding, h, w).astype(np.float16))
        rows["entropy"].append(resize_to(v.entropy, h, w))
        rows["logits"].append(resize_to(o.embedding.logits, h, w).astype(np.float16))
        rows["semantic"].append(f.semantic)
        rows["instance"].append(f.instance)
        rows["field_share"].append(v.field_share)
        rows["iterations"].append(v.iterations)
        rows["stamp"].append(f.stamp_ns)
        rows["keyframe"].append(v.keyframe)
    data = {k: np.stack(v) for k, v in rows.items()}
    CACHE.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **data)
    tmp.replace(path)
    return data


def _scene_job(job: tuple) -> int:
    cfg, seed, frames = job
    torch.set_num_threads(1)
    scene(cfg, seed, frames)
    return seed


def prepare(cfg: config.Config, scene_seeds, frames: int, workers: int) -> list[dict]:
    """:func:`scene` for several seeds; missing ones rendered in ``workers`` processes."""
    def cached(seed: int) -> bool:
        path = CACHE / f"ncd_s{seed}_n{frames}_{_key(cfg, seed, frames)}.npz"
        if not path.is_file():
            return False
        with np.load(path) as z:
            return set(ROWS) <= set(z.files)

    todo = [s for s in scene_seeds if not cached(s)]
    if workers > 1 and len(todo) > 1:
        import multiprocessing as mp
        with mp.get_context("fork").Pool(min(workers, len(todo))) as pool:
            for _ in tqdm(pool.imap_unordered(_scene_job, [(cfg, s, frames) for s in todo]),
                          total=len(todo), desc="render scenes", unit="scene"):
                pass
    return [scene(cfg, s, frames) for s in tqdm(scene_seeds, desc="scenes", unit="scene")]


NOTES = ('The colour descriptor (modulation.colour_weight) and the mode split '
         '(discovery.mode_split) use per-frame inputs only (the camera colour and the clusters), '
         'so the backbone_logits row gets them too; compare neurncd with backbone_logits for what '
         'the mapper stage adds (on the live schedule the field renders no pixel of these 150-'
         'frame scenes, field_share 0 in bench/results/ncd_diagnosis_fallback-backbone.json, '
         'so what it adds is the multi-view map: the depth fusion, mapper_node.depth_fusion: '
         'compare measured_depth; and the keyframe fusion of the embedding, '
         'mapper_node.fallback keyframes: compare fallback_backbone; backbone_logits segments '
         'the measured depth), and '
         'no_colour_no_split / backbone_logits_no_colour_no_split for the discovery before them. '
         'Discovery defaults chosen on tuning seeds 500-501, the keyframe fusion on 500-503, the '
         'depth fusion and label_fusion.touch_share on 500-509 (not the full --tune search). '
         'novel_id_stability: per novel object (GT instance of a novel '
         'class), the share of its pixels over the scene\'s labelled frames carrying its most '
         'common predicted id (known ids included, so an object always called wall scores 1), '
         'mean over objects then over scenes (a fraction); _found: over its novel-labelled '
         'pixels only. view_ms: the mapper stage per view (keyframe fusion and any field '
         'render), median. oracle_embedding: the same discovery fed the ground truth as its '
         'embedding (known classes one-hot, novel ones uniform) on the view depth: the '
         'known-class ceiling of any mapper stage in front of this discovery.')

METRICS = ("miou_all", "miou_known", "miou_novel", "total_acc", "avg_acc", "assigned_miou")


def discover_scene(sc: dict, cfg: config.Config, source: str = "rendered",
                   keep: list | None = None) -> tuple[dict, list[float]]:
    """Run a fresh Discoverer over one scene's labelled frames: (metrics, seconds per frame).

    ``source``: "rendered" (the mapper stage's view: the Embedding-NeRF's embedding and
    entropy, segmented on the view's depth), "rendered_measured" (the same on the
    measured depth), "logits" (the backbone's per-frame logits and their entropy, on
    the measured depth: no mapper stage), "oracle" (the ground truth as embedding,
    :func:`oracle_embedding`, on the view's depth) or "argmax" (the backbone's argmax, no
    discovery). ``keep`` collects (rgb, gt, backbone ids, labels, entropy) of a few
    frames for the picture.
    """
    ev, ev_known, stable = Evaluator(), Evaluator(), IdStability()
    c2i = classes.CHANNEL_TO_ID
    times = []
    d = Discoverer(cfg.discovery, c2i, mcl_cfg=cfg.mcl, seg_cfg=cfg.segmentation,
                   mod_cfg=cfg.modulation, fusion_cfg=cfg.label_fusion)
    h, w = sc["depth"].shape[1:]
    for i in range(len(sc["depth"])):
        intr = Intrinsics.from_matrix(sc["K"][i], w, h)
        logits = sc["logits"][i].astype(np.float32)
        feats = None
        depth = sc["view_depth"][i] if source in ("rendered", "oracle") else sc["depth"][i]
        if source == "oracle":
            emb = oracle_embedding(sc["semantic"][i], len(c2i))
            ent = entropy(emb)
        elif source.startswith("rendered"):
            emb, ent = sc["embedding"][i].astype(np.float32), sc["entropy"][i]
            if emb.shape[-1] > len(c2i):  # backbone.features: the features follow
                emb, feats = emb[..., : len(c2i)], emb[..., len(c2i):]
        else:
            emb, ent = logits, entropy(logits)
        t = time.perf_counter()
        if source == "argmax":
            lab = c2i[logits.argmax(-1)].astype(np.uint16)
        else:
            lab = d.process(depth, intr, emb, ent, int(sc["stamp"][i]),
                            sc["rgb"][i], feats, sc["pose"][i])
        times.append(time.perf_counter() - t)
        ev.update(lab, sc["semantic"][i])
        # The known-class pixels alone (novel ones void): what is lost on known objects,
        # apart from the novel pixels called known.
        ev_known.update(lab, np.where(np.isin(sc["semantic"][i], classes.KNOWN_IDS),
                                      sc["semantic"][i], 0))
        stable.update(lab, sc["semantic"][i], sc["instance"][i])
        if keep is not None and i in (2, len(sc["depth"]) // 2) and len(keep) < 4:
            keep.append((sc["rgb"][i], sc["semantic"][i],
                         c2i[logits.argmax(-1)].astype(np.uint16), lab, ent))
    r = ev.result()
    out = {k: r[k] for k in METRICS}
    out["novel_classes_matched"] = len(r["novel_matching"])
    out["known_only_miou"] = ev_known.result()["miou_known"]
    out.update(stable.result())
    out["iou"] = {classes.class_name(c): v for c, v in r["iou"].items() if v is not None}
    return out, times


def oracle_embedding(semantic: np.ndarray, channels: int) -> np.ndarray:
    """The ground truth as an embedding: logits 5 on the known class's channel (0 elsewhere)
    at known-class pixels, all 0 (uniform, the maximal entropy) at novel and void ones."""
    emb = np.zeros(semantic.shape + (channels,), np.float32)
    for cid, k in classes.ID_TO_CHANNEL.items():
        emb[..., k] += 5.0 * (semantic == cid)
    return emb


_SCENES: list[dict] = []  # inherited by forked workers of discover()


def _discover_job(job: tuple) -> tuple[dict, list[float]]:
    i, cfg, source = job
    torch.set_num_threads(1)
    return discover_scene(_SCENES[i], cfg, source)


def discover(scenes: list[dict], cfg: config.Config, source: str = "rendered",
             keep: list | None = None, workers: int = 1) -> dict:
    """Per-scene metrics (novel ids are per scene, so each scene is matched on its own)
    and their mean over scenes, as the paper reports per scene and on average."""
    if workers > 1 and keep is None and len(scenes) > 1:
        import multiprocessing as mp
        global _SCENES
        _SCENES = scenes
        with mp.get_context("fork").Pool(min(workers, len(scenes))) as pool:
            per = pool.map(_discover_job, [(i, cfg, source) for i in range(len(scenes))])
        _SCENES = []
    else:
        per = [discover_scene(sc, cfg, source, keep) for sc in scenes]
    out: dict = {k: float(np.mean([r[k] for r, _ in per])) for k in METRICS + ("known_only_miou",)}
    out["per_scene_miou_all"] = [r["miou_all"] for r, _ in per]
    out["per_scene_miou_novel"] = [r["miou_novel"] for r, _ in per]
    for k in ("miou_all", "miou_known", "miou_novel"):
        out[f"std_{k}"] = float(np.std([r[k] for r, _ in per]))
    out["novel_classes_matched"] = int(sum(r["novel_classes_matched"] for r, _ in per))
    for k in ("novel_id_stability", "novel_id_stability_found"):  # mean over scenes
        v = [r[k] for r, _ in per if not np.isnan(r[k])]
        out[k] = float(np.mean(v)) if v else float("nan")
    out["novel_objects"] = int(sum(r["novel_objects"] for r, _ in per))
    out["ms_per_frame"] = 1000 * statistics.median([t for _, ts in per for t in ts])
    names = sorted({c for r, _ in per for c in r["iou"]})
    out["iou"] = {c: float(np.mean([r["iou"][c] for r, _ in per if c in r["iou"]]))
                  for c in names}
    return out


def with_overrides(base: config.Config, overrides: dict) -> config.Config:
    nested = base.to_nested()
    for key, value in overrides.items():
        sec, name = key.split(".", 1)
        nested[sec][name] = value
    return config.from_nested(nested)


def engine_rows(base: config.Config) -> dict[str, dict]:
    """Rows that change the engine before discovery (the mapper stage), for which the
    scenes are rendered again: ``fallback_<x>`` for each fallback other than the shipped
    one (what the view is where the field has not learnt the scene)."""
    rows = {f"fallback_{v}": {"mapper_node.fallback": v} for v in ("backbone", "keyframes")
            if v != base.mapper_node.fallback}
    if base.backbone.kind == "default" and load_backbone(base.backbone).novelty_branch:
        # The threshold tuned for the net without its branch (labeller docstring).
        rows["no_novelty_branch"] = {"backbone.novelty_branch": False,
                                     "discovery.entropy_threshold": 0.15}
    if base.backbone.kind == "default" and not base.backbone.features:
        # Direction 1: the backbone's penultimate features in the segment descriptor.
        rows["features"] = {"backbone.features": True}
    other = {"logits": "probabilities", "probabilities": "logits"}[base.mapper_node.fusion]
    if base.mapper_node.fallback == "keyframes":
        rows[f"fusion_{other}"] = {"mapper_node.fusion": other}
        if base.mapper_node.fusion == "probabilities" and base.mapper_node.disagreement_weight == 0:
            rows["disagreement_2"] = {"mapper_node.disagreement_weight": 2.0}
        if base.mapper_node.own_view_weight != 1.0:
            # The fusion before the frame's own view was weighted (its visibility test
            # was 0.05 m + 3 %, and it fused the 8 most recent frames).
            rows["fusion_unweighted"] = {"mapper_node.own_view_weight": 1.0,
                                         "mapper_node.coverage_depth_tolerance": 0.05,
                                         "mapper_node.fusion_recent": 8}
    return rows


GRID = {
    "discovery.entropy_threshold": [0.15, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8],
    "discovery.majority_share": [0.4, 0.5, 0.6, 0.7, 0.8],
    "mcl.inflation": [1.2, 1.4, 1.6, 2.0, 2.5],
    "mcl.eta": [3.0, 6.0, 10.0],
    "modulation.entropy_weight": [0.3, 1.0, 3.0],
    "discovery.min_cluster_segments": [1, 2, 4],
    "modulation.entropy_interior": [0, 2, 4],
    "segmentation.embedding_edge_threshold": [0.2, 0.3, 0.4],
    "segmentation.colour_edge_threshold": [12.0, 18.0, 25.0],
    "discovery.segment_novelty": [False, True],
    "discovery.novel_merge_distance": [0.0, 0.2, 0.4, 0.6],
}


def tune(scenes: list[dict], base: config.Config, rounds: int = 2, workers: int = 1
         ) -> tuple[dict, list]:
    """Coordinate search: each parameter in turn over its grid, keep the best mIoU(all)."""
    best = {k: getattr(getattr(base, k.split(".")[0]), k.split(".")[1]) for k in GRID}
    rows = []
    score = discover(scenes, with_overrides(base, best), workers=workers)["miou_all"]
    for rnd in range(rounds):
        changed = False
        for key, values in GRID.items():
            for v in tqdm(values, desc=f"round {rnd} {key}", leave=False):
                if v == best[key]:
                    continue
                trial = {**best, key: v}
                r = discover(scenes, with_overrides(base, trial), workers=workers)
                rows.append({"round": rnd, "param": key, "value": v, **{
                    k: r[k] for k in ("miou_all", "miou_known", "miou_novel")}})
                tqdm.write(f"  {key}={v}: all {r['miou_all']:.2f} known {r['miou_known']:.2f}"
                           f" novel {r['miou_novel']:.2f}")
                if r["miou_all"] > score + 1e-6:
                    score, best, changed = r["miou_all"], trial, True
        if not changed:
            break
    return {"best": best, "miou_all": score}, rows


def diagnose(scenes: list[dict], cfg: config.Config, workers: int = 1) -> dict:
    """Where the full pipeline differs from per-frame logits, in numbers (tuning scenes only).

    Per scene and split by keyframe / other view: the share of pixels the field
    rendered (``field_share``), the field's iterations at the last view, how often
    the rendered embedding's argmax agrees with the backbone's, the argmax accuracy
    of each on known-class pixels, and the mean normalised entropy of each on
    known and on novel pixels; then both discovery rows with per-class IoU.
    """
    c2i = classes.CHANNEL_TO_ID
    known, novel = np.array(classes.KNOWN_IDS), np.array(classes.NOVEL_IDS)
    per = []
    for sc in scenes:
        lg = sc["logits"].astype(np.float32)
        S = lg.shape[-1]
        rend = sc["embedding"][..., :S].astype(np.float32)  # any features follow the logits
        gt = sc["semantic"]
        r_ids, b_ids = c2i[rend.argmax(-1)], c2i[lg.argmax(-1)]
        ent_r = sc["entropy"] / np.log(S)
        ent_b = np.stack([entropy(x) for x in lg]) / np.log(S)
        row = {"frames": int(len(gt)), "keyframes": int(sc["keyframe"].sum()),
               "iterations_last_view": int(sc["iterations"][-1])}
        for part, sel in (("keyframe", sc["keyframe"]), ("other", ~sc["keyframe"])):
            if not sel.any():
                continue
            g = gt[sel]
            kn, nv = np.isin(g, known), np.isin(g, novel)
            row[part] = {
                "views": int(sel.sum()),
                "field_share": float(sc["field_share"][sel].mean()),
                "agreement": float((r_ids[sel] == b_ids[sel])[g > 0].mean()),
                "known_acc_rendered": float((r_ids[sel] == g)[kn].mean()),
                "known_acc_backbone": float((b_ids[sel] == g)[kn].mean()),
                "entropy_known_rendered": float(ent_r[sel][kn].mean()),
                "entropy_known_backbone": float(ent_b[sel][kn].mean()),
                "entropy_novel_rendered": float(ent_r[sel][nv].mean()) if nv.any() else None,
                "entropy_novel_backbone": float(ent_b[sel][nv].mean()) if nv.any() else None,
            }
        per.append(row)
    out = {"per_scene": per}
    for name, source in (("rendered", "rendered"), ("logits", "logits")):
        r = discover(scenes, cfg, source, workers=workers)
        out[name] = {k: r[k] for k in ("miou_all", "miou_known", "miou_novel",
                                       "known_only_miou", "novel_id_stability", "iou")}
    # Known mIoU over the known-class pixels alone: each embedding's argmax, then discovery.
    for name, key in (("logits", "logits"), ("rendered", "embedding")):
        per_scene = []
        for sc in scenes:  # each scene on its own, then the mean, as discover() does
            ev, gt = Evaluator(), sc["semantic"]
            ev.update(c2i[sc[key][..., :len(c2i)].astype(np.float32).argmax(-1)].astype(np.uint16),
                      np.where(np.isin(gt, known), gt, 0))
            per_scene.append(ev.result()["miou_known"])
        out[f"known_only_miou_{name}_argmax"] = float(np.mean(per_scene))
    return out


def _slug(pairs: list[str]) -> str:
    """File name part for ``--set`` pairs, e.g. ``_fallback-keyframes``."""
    return "".join("_" + v.split("=", 1)[0].split(".")[-1] + "-" + v.split("=", 1)[1]
                   for v in pairs)


def sweep(args: argparse.Namespace, base: config.Config, frames: int, n_tune: int) -> None:
    """``--sweep key=v1,v2,...``: the scores of each value on the tuning scenes (the
    scenes rendered again for each value of an engine parameter), a table on stdout and
    bench/results/ncd_sweep_<section>_<key>.json (how a default was chosen)."""
    if "=" not in args.sweep or "." not in args.sweep.split("=", 1)[0]:
        raise SystemExit(f"--sweep {args.sweep!r}: expected SECTION.KEY=V1,V2,...")
    key, raw = args.sweep.split("=", 1)
    values = [config.parse_overrides([f"{key}={v}"])[key] for v in raw.split(",")]
    try:  # every value is checked against the schema before any scene is scored
        for v in values:
            with_overrides(base, {key: v})
    except KeyError:
        raise SystemExit(f"--sweep {args.sweep!r}: unknown section "
                         f"{key.split('.')[0]!r}") from None
    except config.ConfigError as err:
        raise SystemExit(f"--sweep {args.sweep!r}: {err}") from None
    rows, scenes, views = [], [], None
    for v in tqdm(values, desc=f"sweep {key}"):
        cfg = with_overrides(base, {key: v})
        # Each value's own views: an engine parameter (mapper_node, keyframes, mapper,
        # backbone, run) changes the cache key and renders the scenes again; a discovery
        # parameter keeps the key, and the views already loaded are scored again.
        key_v = [_key(cfg, s, frames) for s in seeds.TUNE[:n_tune]]
        if key_v != views:
            scenes = prepare(cfg, seeds.TUNE[:n_tune], frames, args.workers)
            views = key_v
        r = discover(scenes, cfg, workers=args.workers)
        rows.append({"value": v, **{k: r[k] for k in (
            "miou_all", "miou_known", "miou_novel", "std_miou_all", "novel_id_stability",
            "novel_id_stability_found", "novel_classes_matched")}})
    out = {"param": key, "tune_seeds": list(seeds.TUNE[:n_tune]), "frames_per_scene": frames,
           "set": args.set, "rows": rows, "commit": commit()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / (f"ncd_sweep_{key.replace('.', '_')}{_slug(args.set)}"
                      + (f"_frames{frames}" if frames != 150 else "") + ".json")
    path.write_text(json.dumps(out, indent=1))
    print(f"{key} on tuning seeds {out['tune_seeds']} ({frames} frames each), percent")
    print(f"{'value':>10s} {'all':>7s} {'known':>7s} {'novel':>7s} {'id stab':>8s} {'found':>7s}")
    for r in rows:
        print(f"{str(r['value']):>10s} {r['miou_all']:7.2f} {r['miou_known']:7.2f} "
              f"{r['miou_novel']:7.2f} {r['novel_id_stability']:8.3f} "
              f"{r['novel_id_stability_found']:7.3f}")
    print(f"wrote {path}")


def picture(rows: list, path: Path) -> None:
    tiles = []
    for rgb, gt, bb_ids, lab, ent in rows:
        e = ent / max(float(ent.max()), 1e-6)
        e = cv2.applyColorMap(np.clip(e * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_MAGMA)
        tiles.append(np.concatenate([rgb, classes.colourise(gt), classes.colourise(bb_ids),
                                     classes.colourise(lab), e[:, :, ::-1]], axis=1))
    if tiles:
        cv2.imwrite(str(path), cv2.cvtColor(np.concatenate(tiles, 0), cv2.COLOR_RGB2BGR))


def main() -> None:
    global RESULTS
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 + 2 short scenes (smoke)")
    ap.add_argument("--tune", action="store_true", help="coordinate search on seeds.TUNE first")
    ap.add_argument("--diagnose", action="store_true",
                    help="only the diagnosis on the tuning scenes (bench/results/"
                         "ncd_diagnosis.json, with --set ncd_diagnosis_<key-value>.json): field "
                         "share, agreement, entropy, per-class IoU")
    ap.add_argument("--frames", type=int, default=150,
                    help="frames per scene, 30 Hz (other than 150 the report is written to "
                         "ncd_frames<N>.json and .png, beside the 150-frame ncd.json)")
    ap.add_argument("--test-scenes", type=int, default=8)
    ap.add_argument("--tune-scenes", type=int, default=4)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                    help="processes rendering uncached scenes (one torch thread each)")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override a parameter (YAML value) for every row")
    ap.add_argument("--sweep", metavar="SECTION.KEY=V1,V2,...",
                    help="only score one parameter over these values on the tuning scenes "
                         "(a discovery one on the cached views; one of the engine, e.g. "
                         "keyframes.* or mapper_node.*, renders the scenes again per value; "
                         "bench/results/ncd_sweep_<section>_<key>[_<set>][_frames<N>].json), "
                         "then stop")
    args = ap.parse_args()
    RESULTS = results_dir(args.quick)
    RESULTS.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    frames = 45 if args.quick else args.frames
    n_test = 2 if args.quick else args.test_scenes
    n_tune = 2 if args.quick else args.tune_scenes
    base = config.load(None, config.parse_overrides(args.set))
    res: dict = {"frames_per_scene": frames, "quick": bool(args.quick),
                 "test_seeds": list(seeds.TEST[:n_test])}

    if args.diagnose:
        tune_scenes = prepare(base, seeds.TUNE[:n_tune], frames, args.workers)
        diag = {"tune_seeds": list(seeds.TUNE[:n_tune]), "frames_per_scene": frames,
                "set": args.set, **diagnose(tune_scenes, base, args.workers),
                "commit": commit()}
        RESULTS.mkdir(parents=True, exist_ok=True)
        (RESULTS / f"ncd_diagnosis{_slug(args.set)}.json").write_text(json.dumps(diag, indent=1))
        print(json.dumps({k: v for k, v in diag.items() if k != "per_scene"}, indent=1))
        for i, row in enumerate(diag["per_scene"]):
            print(diag["tune_seeds"][i], json.dumps(row))
        return

    if args.sweep:
        sweep(args, base, frames, n_tune)
        return

    t0 = time.perf_counter()
    wanted = list(seeds.TEST[:n_test]) + (list(seeds.TUNE[:n_tune]) if args.tune else [])
    prepare(base, wanted, frames, args.workers)
    test = prepare(base, seeds.TEST[:n_test], frames, 1)
    engine = {}  # rows whose engine (mapper stage) differs: their own renderings
    for name, overrides in engine_rows(base).items():
        cfg = with_overrides(base, overrides)
        prepare(cfg, seeds.TEST[:n_test], frames, args.workers)
        engine[name] = (cfg, prepare(cfg, seeds.TEST[:n_test], frames, 1))
    res["scene_seconds"] = round(time.perf_counter() - t0, 1)
    res["labelled_frames"] = int(sum(len(s["depth"]) for s in test))
    if args.tune:
        tune_scenes = prepare(base, seeds.TUNE[:n_tune], frames, 1)
        chosen, rows = tune(tune_scenes, base, workers=args.workers)
        res["tune_seeds"] = list(seeds.TUNE[:n_tune])
        res["tune_best"] = chosen["best"]
        res["tune_best_miou_all"] = chosen["miou_all"]
        (RESULTS / "ncd_tuning.json").write_text(json.dumps(rows, indent=1))
        print("tuned on", res["tune_seeds"], "->", chosen)

    keep: list = []
    variants = {
        "neurncd": (base, "rendered"),
        **({"tuned": (with_overrides(base, res["tune_best"]), "rendered")} if args.tune else {}),
        "backbone_logits": (base, "logits"),
        **({"measured_depth": (base, "rendered_measured")} if base.mapper_node.depth_fusion
           else {}),
        "paper_mcl": (with_overrides(base, {"mcl.affinity": "cosine", "mcl.inflation": 12.0}),
                      "rendered"),
        "embedding_only": (with_overrides(base, {"modulation.mode": "embedding"}), "rendered"),
        "no_colour_edges": (with_overrides(base, {"segmentation.colour_edges": False}),
                            "rendered"),
        "entropy_only": (with_overrides(base, {"modulation.mode": "entropy"}), "rendered"),
        "no_colour_descriptor": (with_overrides(base, {"modulation.colour_weight": 0.0}),
                                 "rendered"),
        **({"no_mode_split": (with_overrides(base, {"discovery.mode_split": False}),
                              "rendered")} if base.discovery.mode_split else
           {"mode_split": (with_overrides(base, {"discovery.mode_split": True}), "rendered")}),
        "no_novel_merge": (with_overrides(base, {"discovery.novel_merge_distance": 0.0}),
                           "rendered"),
        "no_colour_no_split": (with_overrides(base, {"modulation.colour_weight": 0.0,
                                                     "discovery.mode_split": False}),
                               "rendered"),
        "backbone_logits_no_colour_no_split": (
            with_overrides(base, {"modulation.colour_weight": 0.0,
                                  "discovery.mode_split": False}), "logits"),
        "backbone": (base, "argmax"),
        "oracle_embedding": (base, "oracle"),
        **({"no_label_fusion": (with_overrides(base, {"label_fusion.enabled": False}),
                                "rendered")} if base.label_fusion.enabled else {}),
        **({"no_pixel_known": (with_overrides(base, {"discovery.pixel_known": False}),
                               "rendered")} if base.discovery.pixel_known else {}),
        **({"no_uncertain_regions": (
            with_overrides(base, {"discovery.uncertain_region_px": 0}), "rendered"),
            "backbone_logits_no_uncertain_regions": (
            with_overrides(base, {"discovery.uncertain_region_px": 0}), "logits")}
           if base.discovery.uncertain_region_px else {}),
        **({"no_carve": (with_overrides(base, {"discovery.uncertain_region_carve": False}),
                         "rendered")}
           if base.discovery.uncertain_region_px and base.discovery.uncertain_region_carve
           else {}),
        **({"no_uncertain_clusters": (
            with_overrides(base, {"discovery.uncertain_cluster_pixels": 0}), "rendered")}
           if base.discovery.uncertain_cluster_pixels else {}),
    }
    variants.update({name: (cfg, "rendered") for name, (cfg, _) in engine.items()})
    for name, (cfg, source) in tqdm(variants.items(), desc="report rows"):
        r = discover(engine[name][1] if name in engine else test, cfg, source,
                     keep if name == "neurncd" else None,
                     workers=1 if name == "neurncd" else args.workers)
        for k, v in r.items():
            if k == "iou":
                for c, x in v.items():
                    res[f"{name}_iou_{c}"] = x
            else:
                res[f"{name}_{k}"] = v
    for name, scs in [("neurncd", test)] + [(n, e[1]) for n, e in engine.items()]:
        if all("render_ms" in sc for sc in scs):  # the mapper stage's time per view
            res[f"{name}_view_ms"] = float(np.median(np.concatenate([sc["render_ms"]
                                                                      for sc in scs])))
    res["notes"] = NOTES
    res["cores"] = os.cpu_count()
    # What backbone.precision resolved to here (auto: bfloat16 only on a CPU that has it).
    res["backbone_precision"] = load_backbone(base.backbone).precision
    res["commit"] = commit()
    RESULTS.mkdir(parents=True, exist_ok=True)
    # Another stream length is another record: ncd.json stays the 150-frame one.
    stem = "ncd" if args.quick or args.frames == 150 else f"ncd_frames{args.frames}"
    (RESULTS / f"{stem}.json").write_text(json.dumps(res, indent=1, sort_keys=True))
    picture(keep, RESULTS / f"{stem}.png")

    cols = METRICS + ("novel_classes_matched", "novel_id_stability")
    print(f"\n{res['labelled_frames']} labelled frames of test seeds {res['test_seeds']} "
          f"({frames} frames each), percent")
    print(f"{'row':34s} " + " ".join(f"{c[:13]:>13s}" for c in cols))
    for name in variants:
        print(f"{name:34s} " + " ".join(
            f"{res[f'{name}_{c}']:13.3f}" if c == "novel_id_stability"
            else f"{res[f'{name}_{c}']:13.1f}" if isinstance(res[f"{name}_{c}"], float)
            else f"{res[f'{name}_{c}']:13d}" for c in cols))
    print(f"wrote {RESULTS / stem}.json and {stem}.png")


if __name__ == "__main__":
    from neurncd_ros.core.text import progress_as_lines

    with progress_as_lines():  # a log file gets the bars as lines
        main()
