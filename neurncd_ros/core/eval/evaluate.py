"""The rows of the paper's Tables 1-3 from one engine pass per bag (see the package doc)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from .. import classes
from ..camera import backproject
from ..discovery.geoseg import points_image, segment_depth, surface_normals
from ..discovery.labeller import Discoverer
from ..discovery.mcl import markov_cluster
from ..discovery.metrics import Evaluator
from ..engine.views import resize_to
from ..engine.offline import json_default
from ..frame import Frame
from ..uncertainty import entropy as softmax_entropy
from . import semnerf, targets

ROWS = {
    "full": "GS+PSSN+EP+SE+MCL (ours, the engine's labels)",
    "gs_pssn_ep_mcl": "GS+PSSN+EP+MCL (no semantic embedding)",
    "gs": "GS alone (geometry only, assigned mIoU)",
    "pssn": "PSSN alone (backbone argmax)",
    "explicit": "explicit voxel map (Nakajima et al. 2019 style)",
}
"""Fixed rows; the Semantic-NeRF rows (``semnerf_<pct>pct``, one per
``semnerf.label_fractions``) follow them, titled by :func:`row_title`."""
ABLATION_ROWS = ("full", "gs_pssn_ep_mcl", "gs", "pssn")
BASELINE_ROWS = ("explicit",)
FIGURES = ("miou_known", "miou_novel", "miou_all", "total_acc", "avg_acc", "assigned_miou")
VOXEL_SIZE = 0.05  # m, the explicit map's voxel edge
GS_MAX_SEGMENTS = 1500  # segments MCL clusters for the GS row (the rest join the nearest)


def row_title(row: str) -> str:
    """A row's name in the tables."""
    if row.startswith(semnerf.ROW_PREFIX):
        return semnerf.row_title(row) + " (label propagation, known classes)"
    return ROWS[row]


def _row_order(row: str) -> tuple:
    if row in ROWS:
        return (list(ROWS).index(row), 0.0)
    pct = row[len(semnerf.ROW_PREFIX):-3].replace("p", ".")
    return (len(ROWS), float(pct))


def _check_gt(frame: Frame, n: int) -> None:
    if frame.semantic is None:
        raise ValueError(f"frame {n} (stamp {frame.stamp_ns}) has no ground truth: eval needs "
                         "the semantic topic (NYU-13 ids) in the bag")


def collect(frames: Iterable[Frame], cfg, total: int | None = None, progress: bool = True
            ) -> tuple[dict[str, list], dict]:
    """One engine pass: per labelled frame what every row needs, plus run facts."""
    from ..engine.offline import OfflineEngine

    engine = OfflineEngine(cfg)
    keep: dict[str, list] = {k: [] for k in (
        "rgb", "depth", "view_depth", "intr", "pose", "semantic", "embedding", "entropy", "logits",
        "full", "keyframe", "stamp", "iterations")}
    ids = None
    for o in engine.run(frames, total, progress):
        f, v = o.frame, o.view
        _check_gt(f, len(keep["stamp"]))
        h, w = f.depth.shape
        ids = o.embedding.spec.ids()
        S = o.view.spec.logit_channels
        keep["rgb"].append(f.rgb)
        keep["depth"].append(f.depth)  # measured: the per-frame baselines segment this
        keep["view_depth"].append(v.view_depth)  # the mapper's (fused): the system's rows
        keep["intr"].append(f.intrinsics)
        keep["pose"].append(f.pose)
        keep["semantic"].append(f.semantic)
        keep["embedding"].append(resize_to(np.ascontiguousarray(
            v.embedding[..., :S], np.float32), h, w).astype(np.float16))
        keep["entropy"].append(resize_to(v.entropy.astype(np.float32), h, w))
        keep["logits"].append(resize_to(o.embedding.logits.astype(np.float32), h, w)
                              .astype(np.float16))
        keep["full"].append(o.labels.labels)
        keep["keyframe"].append(bool(v.keyframe))
        keep["stamp"].append(f.stamp_ns)
        keep["iterations"].append(engine.mapper.iterations)
    if engine.frames_in == 0:
        raise ValueError("no frames to evaluate (empty bag or no synchronised frames)")
    if not keep["stamp"]:
        raise ValueError(f"{engine.frames_in} frames read but none labelled")
    facts = {"frames": engine.frames_in, "labelled": len(keep["stamp"]),
             "keyframes": len(engine.mapping.keyframe_stamps),
             "iterations": engine.mapper.iterations if engine.mapper is not None else 0,
             "seconds": {k: round(v, 2) for k, v in engine.seconds.items()},
             "channel_to_id": ids.tolist()}
    return keep, facts


def _discover(keep: dict, cfg, mod_cfg, source: str = "rendered",
              embeddings: list | None = None, depth: str = "view_depth") -> list[np.ndarray]:
    """The discovery stage (a fresh Discoverer) over the cached frames, segmenting
    ``keep[depth]`` (the mapper's view depth, or ``"depth"``: the measured one)."""
    c2i = np.asarray(keep["_c2i"])
    d = Discoverer(cfg.discovery, c2i, mcl_cfg=cfg.mcl, seg_cfg=cfg.segmentation,
                   mod_cfg=mod_cfg, fusion_cfg=cfg.label_fusion)
    out = []
    for i in range(len(keep["stamp"])):
        if embeddings is not None:
            emb = embeddings[i]
            ent = softmax_entropy(emb)
        else:
            emb = keep["embedding"][i].astype(np.float32)
            ent = keep["entropy"][i]
        rgb = keep["rgb"][i] if cfg.segmentation.colour_edges else None
        out.append(d.process(keep[depth][i], keep["intr"][i], emb, ent,
                             keep["stamp"][i], rgb, pose=keep["pose"][i]))
    return out


def geometry_only(keep: dict, cfg, seed: int = 0) -> list[np.ndarray]:
    """GS alone: depth segments described by their world-frame mean normal and height,
    clustered by the same MCL over all frames (novel-style ids >= 100, no names)."""
    rng = np.random.default_rng(seed)
    segs, descs, owner = [], [], []
    for i in range(len(keep["stamp"])):
        depth, intr, pose = keep["view_depth"][i], keep["intr"][i], keep["pose"][i]
        seg = segment_depth(depth, intr, cfg.segmentation)
        segs.append(seg)
        pts = points_image(depth, intr)
        valid = np.isfinite(pts).all(axis=2) & (depth > 0)
        nrm = surface_normals(np.nan_to_num(pts), valid.astype(np.float32), 5).transpose(1, 2, 0)
        R = pose[:3, :3] if pose is not None else np.eye(3)
        t = pose[:3, 3] if pose is not None else np.zeros(3)
        sel = (seg >= 0) & valid
        n = int(seg.max()) + 1 if seg.size and seg.max() >= 0 else 0
        if n == 0:
            continue
        ids = seg[sel]
        cnt = np.maximum(np.bincount(ids, minlength=n), 1)[:, None]
        nw = np.nan_to_num(nrm[sel]) @ R.T
        pw = np.nan_to_num(pts[sel]) @ R.T + t
        mn = np.stack([np.bincount(ids, nw[:, k], n) for k in range(3)], 1) / cnt
        mn /= np.maximum(np.linalg.norm(mn, axis=1, keepdims=True), 1e-9)
        hz = np.bincount(ids, pw[:, 2], n)[:, None] / cnt
        present = np.bincount(ids, minlength=n) > 0
        d = np.concatenate([np.abs(mn), hz / 1.0], axis=1)[present]
        descs.append(d)
        owner.extend((i, s) for s in np.flatnonzero(present).tolist())
    if not descs:
        return [np.zeros_like(s, np.uint16) for s in segs]
    D = np.concatenate(descs).astype(np.float32)
    pick = rng.choice(len(D), size=min(len(D), GS_MAX_SEGMENTS), replace=False)
    cl = markov_cluster(D[pick], cfg.mcl) if pick.size > 1 else np.zeros(1, np.int64)
    _, cl = np.unique(cl, return_inverse=True)
    cent = np.stack([D[pick][cl == c].mean(0) for c in range(cl.max() + 1)])
    lab = np.argmin(((D[:, None, :] - cent[None]) ** 2).sum(-1), axis=1)
    seg_lab: dict[tuple[int, int], int] = {o: int(c) for o, c in zip(owner, lab)}
    out = []
    for i, seg in enumerate(segs):
        n = int(seg.max()) + 1 if seg.max() >= 0 else 0
        table = np.array([classes.NOVEL_ID_START + seg_lab[(i, s)] if (i, s) in seg_lab
                          else 0 for s in range(n)], np.int64)
        out.append(np.where(seg >= 0, table[np.maximum(seg, 0)] if n else 0, 0)
                   .astype(np.uint16))
    return out


class VoxelMap:
    """An explicit semantic map: voxel hash of back-projected points, running mean of the
    per-frame backbone logits in each voxel (the explicit-map baseline, no field)."""

    def __init__(self, channels: int, voxel: float = VOXEL_SIZE) -> None:
        self.voxel = voxel
        self.keys = np.zeros(0, np.int64)
        self.sums = np.zeros((0, channels), np.float64)
        self.counts = np.zeros(0, np.int64)

    @staticmethod
    def _key(pts: np.ndarray, voxel: float) -> np.ndarray:
        v = np.floor(pts / voxel).astype(np.int64) + (1 << 20)
        return (v[:, 0] << 42) | (v[:, 1] << 21) | v[:, 2]

    def fuse(self, depth, intr, pose, logits) -> None:
        """Add one frame's per-pixel logits at its back-projected points."""
        pts, mask = backproject(depth, intr, pose)
        k = self._key(pts, self.voxel)
        u, inv = np.unique(k, return_inverse=True)
        s = np.zeros((u.size, logits.shape[2]))
        np.add.at(s, inv, logits[mask].astype(np.float64))
        c = np.bincount(inv, minlength=u.size)
        keys = np.concatenate([self.keys, u])
        uk, inv2 = np.unique(keys, return_inverse=True)
        sums = np.zeros((uk.size, s.shape[1]))
        np.add.at(sums, inv2, np.concatenate([self.sums, s]))
        counts = np.bincount(inv2, weights=np.concatenate([self.counts, c]), minlength=uk.size)
        self.keys, self.sums, self.counts = uk, sums, counts.astype(np.int64)

    def lookup(self, depth, intr, pose, fallback: np.ndarray) -> np.ndarray:
        """(H, W, S) fused logits of a view (the frame's own logits where unmapped)."""
        pts, mask = backproject(depth, intr, pose)
        k = self._key(pts, self.voxel)
        pos = np.clip(np.searchsorted(self.keys, k), 0, max(self.keys.size - 1, 0))
        hit = self.keys[pos] == k if self.keys.size else np.zeros(k.size, bool)
        out = fallback.astype(np.float32).copy()
        vals = out[mask]
        vals[hit] = (self.sums[pos[hit]] / self.counts[pos[hit], None]).astype(np.float32)
        out[mask] = vals
        return out


def explicit_baseline(keep: dict, cfg) -> list[np.ndarray]:
    """Backbone logits of every labelled frame fused in a voxel map; each frame's fused
    embedding and its entropy labelled by the same discovery stage on the measured depth
    (no field, no mapper stage)."""
    S = keep["logits"][0].shape[2]
    vm = VoxelMap(S)
    fused = []
    for i in range(len(keep["stamp"])):
        lg = keep["logits"][i].astype(np.float32)
        if keep["pose"][i] is None:
            fused.append(lg)
            continue
        vm.fuse(keep["depth"][i], keep["intr"][i], keep["pose"][i], lg)
        fused.append(vm.lookup(keep["depth"][i], keep["intr"][i], keep["pose"][i], lg))
    return _discover(keep, cfg, cfg.modulation, embeddings=fused, depth="depth")


def _confusion(ev: Evaluator) -> list[list[int]]:
    """(13 GT classes) x (13 classes + 'none') pixel counts after the novel matching."""
    ids, counts = ev.table()
    match = ev.novel_matching()
    n = classes.NUM_CLASSES
    conf = np.zeros((n, n + 1), np.int64)
    for j, i in enumerate(ids.tolist()):
        m = i if 1 <= i <= n else match.get(int(i), 0)
        conf[:, m - 1 if m > 0 else n] += counts[:, j]
    return conf.tolist()


def _score(preds: list[np.ndarray], gts: list[np.ndarray]) -> tuple[dict, Evaluator]:
    ev = Evaluator()
    for p, g in zip(preds, gts):
        ev.update(p, g)
    return ev.result(), ev


def evaluate_frames(frames: Iterable[Frame], cfg, total: int | None = None,
                    ablation: bool = True, baselines: bool = True, progress: bool = True,
                    keep_pictures: int = 4, name: str = "") -> dict[str, Any]:
    """Every row on one stream: {"rows": {row: metrics}, "curve", "confusion", ...}.

    ``keep_pictures`` frames (evenly spaced) keep their images for the report grid."""
    keep, facts = collect(frames, cfg, total, progress)
    keep["_c2i"] = facts["channel_to_id"]
    c2i = np.asarray(facts["channel_to_id"])
    gts = keep["semantic"]
    preds: dict[str, list[np.ndarray]] = {"full": keep["full"]}
    preds["pssn"] = [c2i[lg.astype(np.float32).argmax(-1)].astype(np.uint16)
                     for lg in keep["logits"]]
    if ablation:
        preds["gs_pssn_ep_mcl"] = _discover(
            keep, cfg, dataclasses.replace(cfg.modulation, mode="entropy"))
        preds["gs"] = geometry_only(keep, cfg)
    semnerf_runs: dict[str, dict] = {}
    if baselines:
        preds["explicit"] = explicit_baseline(keep, cfg)
        for f in cfg.semnerf.label_fractions:
            key = semnerf.row_key(f)
            preds[key], semnerf_runs[key] = semnerf.semantic_nerf(keep, cfg, f,
                                                                  facts["iterations"])
    rows, confusion = {}, None
    for row, p in preds.items():
        r, ev = _score(p, gts)
        rows[row] = r
        if row == "full":
            confusion = _confusion(ev)
    # How discovery improves online: the engine's scores over the frames up to each keyframe.
    curve, ev = [], Evaluator()
    kf = 0
    for i in range(len(gts)):
        ev.update(keep["full"][i], gts[i])
        if keep["keyframe"][i]:
            kf += 1
            r = ev.result()
            curve.append({"keyframes": kf, "miou_known": r["miou_known"],
                          "miou_novel": r["miou_novel"], "miou_all": r["miou_all"]})
    n = len(gts)
    pick = sorted(set(np.linspace(0, n - 1, min(keep_pictures, n)).round().astype(int)
                      .tolist())) if keep_pictures else []
    pictures = [{"stamp": keep["stamp"][i], "rgb": keep["rgb"][i], "gt": gts[i],
                 "backbone": preds["pssn"][i], "baseline": preds.get("explicit", [None] * n)[i],
                 "ours": keep["full"][i]} for i in pick]
    return {"name": name, **facts, "rows": rows, "curve": curve, "confusion": confusion,
            "pictures": pictures, "semnerf": semnerf_runs}


def check_bag(bag: str | Path, cfg) -> None:
    """Raise ValueError (BagError) unless the bag can be read and has a ground-truth
    semantic topic: ``neurncd eval`` checks every bag before it runs the engine on any."""
    from ..data.bag import bag_topics

    topics = bag_topics(bag)
    if cfg.topics.semantic not in topics:
        raise ValueError(f"{bag}: no ground-truth topic {cfg.topics.semantic} (NYU-13 ids); "
                         f"eval needs it. Topics in the bag: {sorted(topics)}")


def evaluate_bag(bag: str | Path, cfg, ablation: bool = True, baselines: bool = True,
                 progress: bool = True, keep_pictures: int = 4) -> dict[str, Any]:
    """:func:`evaluate_frames` on a bag with a ground-truth semantic topic (poses from the
    bag, or RGB-D odometry as ``neurncd run``)."""
    from ..data.bag import FrameReader
    from ..engine.offline import bag_poses

    check_bag(bag, cfg)
    poses = bag_poses(bag, cfg)
    reader = FrameReader.from_config(bag, cfg.topics, cfg.sync, with_poses=poses == "bag")
    frames: Iterable[Frame] = reader
    if poses == "odometry":
        from ..odometry import with_odometry
        frames = with_odometry(reader, cfg.odometry)
    out = evaluate_frames(frames, cfg, len(reader), ablation, baselines, progress,
                          keep_pictures, name=str(bag))
    out.update({"bag": str(bag), "poses": poses, "dropped": len(reader.dropped)})
    return out


def mean_std(values: list[float]) -> dict[str, float | None]:
    v = [x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))]
    if not v:
        return {"mean": None, "std": None, "n": 0}
    return {"mean": float(np.mean(v)), "std": float(np.std(v)), "n": len(v)}


def aggregate(per_bag: list[dict]) -> dict[str, Any]:
    """Mean and standard deviation over bags of every figure and per-class IoU."""
    rows = sorted({r for b in per_bag for r in b["rows"]}, key=_row_order)
    out: dict[str, Any] = {}
    for row in rows:
        got = [b["rows"][row] for b in per_bag if row in b["rows"]]
        out[row] = {k: mean_std([g[k] for g in got]) for k in FIGURES}
        out[row]["iou"] = {str(c): mean_std([g["iou"].get(c) for g in got])
                           for c in range(1, classes.NUM_CLASSES + 1)}
    return out


def _cell(ms: dict | None, pct: bool = True) -> str:
    if not ms or ms.get("mean") is None:
        return "-"
    s = f"{ms['mean']:.1f}"
    return s + (f" ± {ms['std']:.1f}" if ms.get("n", 1) > 1 else "")


def markdown_tables(agg: dict, n_bags: int) -> str:
    """Tables 1-3 of the paper, laid out as there (percent; mean ± std over bags)."""
    known = [int(c) for c in classes.KNOWN_IDS]
    novel = [int(c) for c in classes.NOVEL_IDS]
    names = [classes.class_name(c) for c in known + novel]
    lines = [f"Over {n_bags} bag(s); percent; mean ± std over bags where several (the "
             "population standard deviation, ddof 0).", "",
             "### Table 1: per-class IoU (9 known | 4 novel)", "",
             "| method | " + " | ".join(names[:len(known)]) + " | " +
             " | ".join(f"*{n}*" for n in names[len(known):]) + " |",
             "|---" * (1 + len(names)) + "|"]
    for row in agg:
        if row == "gs":
            continue
        lines.append(f"| {row_title(row)} | " + " | ".join(
            _cell(agg[row]["iou"][str(c)]) for c in known + novel) + " |")
    lines += ["", "### Table 2: known / novel mIoU and accuracies", "",
              "| method | mIoU known | mIoU novel | mIoU all | Total Acc | Avg Acc | "
              "assigned mIoU (SCIM) |", "|---|---|---|---|---|---|---|"]
    for row in agg:
        if row == "gs":
            continue
        a = agg[row]
        lines.append(f"| {row_title(row)} | " + " | ".join(_cell(a[k]) for k in FIGURES)
                     + " |")
    lines += ["", "### Table 3: ablation", "",
              "| GS | PSSN | EP | SE | MCL | mIoU known | mIoU novel | mIoU all | "
              "assigned mIoU |", "|---|---|---|---|---|---|---|---|---|"]
    marks = {"gs": "✓ | | | | ✓", "pssn": " | ✓ | | | ", "gs_pssn_ep_mcl": "✓ | ✓ | ✓ | | ✓",
             "full": "✓ | ✓ | ✓ | ✓ | ✓"}
    for row in ("gs", "pssn", "gs_pssn_ep_mcl", "full"):
        if row in agg:
            a = agg[row]
            lines.append(f"| {marks[row]} | " + " | ".join(
                _cell(a[k]) for k in ("miou_known", "miou_novel", "miou_all",
                                      "assigned_miou")) + " |")
    lines += ["", "GS alone has no class names: its row is scored by SCIM's assigned mIoU "
              "(every cluster matched one-to-one to a ground-truth class); its named "
              "mIoUs only see the novel matching. The Semantic-NeRF rows are fields "
              "trained on ground-truth labels of the known classes at that share of each "
              "keyframe's pixels (no backbone); they name no novel class, so their figure "
              "is mIoU known."]
    return "\n".join(lines) + "\n"


def write_eval(out_dir: str | Path, per_bag: list[dict]) -> dict[str, Any]:
    """DIR/eval.json, DIR/tables.md, DIR/pictures.npz (for ``neurncd report``)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    agg = aggregate(per_bag)
    bags = [{k: v for k, v in b.items() if k != "pictures"} for b in per_bag]
    checked = targets.check(agg, bags)
    result = {"bags": bags, "aggregate": agg, "rows": {r: row_title(r) for r in agg},
              "targets": checked}
    (out / "eval.json").write_text(json.dumps(result, indent=1, default=json_default))
    (out / "tables.md").write_text(markdown_tables(agg, len(per_bag)) + "\n"
                                   + targets.markdown(checked))
    pics = {}
    for bi, b in enumerate(per_bag):
        for pi, p in enumerate(b["pictures"]):
            for k, v in p.items():
                if v is not None:
                    pics[f"b{bi}_p{pi}_{k}"] = np.asarray(v)
    np.savez_compressed(out / "pictures.npz", **pics)
    return result


def summary(result: dict) -> str:
    """A few lines after an eval."""
    agg = result["aggregate"]
    lines = [f"evaluated {len(result['bags'])} bag(s), "
             f"{sum(b['labelled'] for b in result['bags'])} labelled frames"]
    for row, a in agg.items():
        lines.append(f"  {row_title(row):52s} known {_cell(a['miou_known'])}, novel "
                     f"{_cell(a['miou_novel'])}, all {_cell(a['miou_all'])}, assigned "
                     f"{_cell(a['assigned_miou'])}")
    lines.append("issue 12 targets ('10 percent' read as 10 mIoU points):")
    lines += [f"  {x}" for x in targets.lines(result.get("targets")
                                             or targets.check(agg, result["bags"]))]
    return "\n".join(lines)
