"""The rows of the paper's Tables 1-2 (and, with the ablation, 3) from one engine pass per
bag (see the package doc)."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

import numpy as np

from .. import classes
from ..discovery.metrics import Evaluator
from ..engine.views import resize_to
from ..engine.offline import json_default
from ..frame import Frame
from . import progress as progress_mod
from . import semnerf, targets
from .rows import discover, explicit_baseline, geometry_only

if TYPE_CHECKING:
    from tqdm import tqdm

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
ABLATION_ONLY = ("gs_pssn_ep_mcl", "gs")
"""The ablation's rows only ``--ablation`` evaluates: Table 3 is written when one is."""
BASELINE_ROWS = ("explicit",)
PANELS = {"rgb": "colour", "gt": "ground truth", "backbone": "backbone",
          "baseline": "explicit baseline", "ours": "ours"}
"""The report grid's panels, left to right: key in a picture (and pictures.npz) -> title.
A picture holds the baseline's panel only with ``--baselines``; eval.json
``picture_panels`` records the panels the written pictures hold."""
FIGURES = ("miou_known", "miou_novel", "miou_all", "total_acc", "avg_acc", "assigned_miou")


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


def with_ground_truth(keep: dict) -> list[int]:
    """Indices of the kept (labelled) frames that carry a ground-truth image: the frames
    every row is scored on (a bag may lack it at some frames, as ``neurncd run`` allows)."""
    return [i for i, g in enumerate(keep["semantic"]) if g is not None]


def collect(frames: Iterable[Frame], cfg, total: int | None = None, progress: bool = True,
            name: str = "") -> tuple[dict[str, list], dict]:
    """One engine pass: per labelled frame what every row needs, plus run facts.

    Labelled frames without ground truth are kept (the discovery re-runs, the explicit
    map and the Semantic-NeRF fields see the stream the engine saw) and left out of
    the scores; ``facts["frames_evaluated"]`` counts those with it. A stream none of
    whose labelled frames has ground truth is a ValueError naming ``name``."""
    from ..engine.offline import OfflineEngine

    engine = OfflineEngine(cfg)
    keep: dict[str, list] = {k: [] for k in (
        "rgb", "depth", "view_depth", "intr", "pose", "semantic", "embedding", "entropy", "logits",
        "full", "keyframe", "stamp", "iterations")}
    ids = None
    where = name or "the stream"
    for o in engine.run(frames, total, progress, desc=progress_mod.label("run", name)):
        f, v = o.frame, o.view
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
        raise ValueError(f"{where}: no frames to evaluate (empty bag or no synchronised "
                         "frames)")
    if not keep["stamp"]:
        raise ValueError(f"{where}: {engine.frames_in} frames read but none labelled")
    scored = with_ground_truth(keep)
    if not scored:
        raise ValueError(f"{where}: none of its {len(keep['stamp'])} labelled frames has a "
                         f"ground-truth image ({cfg.topics.semantic}, NYU-13 ids), so there "
                         f"is nothing to score (`neurncd info` counts the frames with ground "
                         f"truth)")
    facts = {"frames": engine.frames_in, "labelled": len(keep["stamp"]),
             "frames_evaluated": len(scored),
             "keyframes": len(engine.mapping.keyframe_stamps),
             "iterations": engine.mapper.iterations if engine.mapper is not None else 0,
             "seconds": {k: round(v, 2) for k, v in engine.seconds.items()},
             "channel_to_id": ids.tolist()}
    return keep, facts


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


def _score(preds: list[np.ndarray], gts: list[np.ndarray | None]) -> tuple[dict, Evaluator]:
    """One row's metrics over the frames that have ground truth (``None``: none)."""
    ev = Evaluator()
    for p, g in zip(preds, gts):
        if g is not None:
            ev.update(p, g)
    return ev.result(), ev


def _stage(stage: str, total: int, name: str, progress: bool, unit: str = "frame"
           ) -> tqdm:
    """The progress bar of one ablation row or baseline of bag ``name``."""
    return progress_mod.bar(total, stage, name, progress, unit=unit)


def evaluate_frames(frames: Iterable[Frame], cfg, total: int | None = None,
                    ablation: bool = True, baselines: bool = True, progress: bool = True,
                    keep_pictures: int = 4, name: str = "") -> dict[str, Any]:
    """Every row on one stream: {"rows": {row: metrics}, "curve", "confusion", ...}.

    Rows are scored on the labelled frames that have ground truth (``frames_evaluated``
    of ``labelled``); every stage after the engine pass shows a progress bar named by
    the stage and ``name``. ``keep_pictures`` frames with ground truth (evenly spaced)
    keep their images for the report grid, under the keys of :data:`PANELS`."""
    keep, facts = collect(frames, cfg, total, progress, name)
    keep["_c2i"] = facts["channel_to_id"]
    c2i = np.asarray(facts["channel_to_id"])
    gts = keep["semantic"]
    n = len(gts)
    preds: dict[str, list[np.ndarray]] = {"full": keep["full"]}
    preds["pssn"] = [c2i[lg.astype(np.float32).argmax(-1)].astype(np.uint16)
                     for lg in keep["logits"]]
    if ablation:
        with _stage("GS+PSSN+EP+MCL", n, name, progress) as bar:
            preds["gs_pssn_ep_mcl"] = discover(
                keep, cfg, dataclasses.replace(cfg.modulation, mode="entropy"), bar=bar)
        with _stage("GS alone", n, name, progress) as bar:
            preds["gs"] = geometry_only(keep, cfg, bar=bar)
    semnerf_runs: dict[str, dict] = {}
    if baselines:
        with _stage("explicit map", 2 * n, name, progress, unit="step") as bar:
            preds["explicit"] = explicit_baseline(keep, cfg, bar=bar)
        for f in cfg.semnerf.label_fractions:
            key = semnerf.row_key(f)
            with _stage(semnerf.row_title(key).replace("Semantic-NeRF", "semnerf"), 2 * n,
                        name, progress, unit="step") as bar:
                preds[key], semnerf_runs[key] = semnerf.semantic_nerf(
                    keep, cfg, f, facts["iterations"], bar=bar)
    rows, confusion = {}, None
    for row, p in preds.items():
        r, ev = _score(p, gts)
        rows[row] = r
        if row == "full":
            confusion = _confusion(ev)
    # How discovery improves online: the engine's scores over the frames up to each
    # keyframe (from the first keyframe with scored frames before it).
    curve, ev = [], Evaluator()
    kf = seen = 0
    for i in range(n):
        if gts[i] is not None:
            ev.update(keep["full"][i], gts[i])
            seen += 1
        if keep["keyframe"][i]:
            kf += 1
            if seen:
                r = ev.result()
                curve.append({"keyframes": kf, "miou_known": r["miou_known"],
                              "miou_novel": r["miou_novel"], "miou_all": r["miou_all"]})
    scored = with_ground_truth(keep)
    m = len(scored)
    pick = sorted({scored[j] for j in np.linspace(0, m - 1, min(keep_pictures, m))
                   .round().astype(int).tolist()}) if keep_pictures else []
    images = {"rgb": keep["rgb"], "gt": gts, "backbone": preds["pssn"],
              "baseline": preds.get("explicit"), "ours": keep["full"]}
    pictures = [{"stamp": keep["stamp"][i],
                 **{k: images[k][i] for k in PANELS if images[k] is not None}}
                for i in pick]
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


def _cell(ms: dict | None, n_bags: int = 1) -> str:
    """A figure over bags: "mean ± std"; a figure measured in fewer than all ``n_bags``
    bags (a class in only some bags' ground truth) says in how many, so a lone bag's
    value is not read as an average: "84.8 (1 bag)", "80.1 ± 2.0 (2 bags)"; "-" if in
    none."""
    if not ms or ms.get("mean") is None:
        return "-"
    n = ms.get("n", 1)
    s = f"{ms['mean']:.1f}" + (f" ± {ms['std']:.1f}" if n > 1 else "")
    return s + (f" ({n} bag{'s' if n > 1 else ''})" if 0 < n < n_bags else "")


def coverage(bags: list[dict]) -> list[str]:
    """One line per bag whose labelled frames did not all have ground truth: the rows
    were scored on the others only."""
    out = []
    for b in bags:
        n, k = b.get("labelled", 0), b.get("frames_evaluated", b.get("labelled", 0))
        if k < n:
            out.append(f"{b.get('name') or b.get('bag', '?')}: evaluated on the {k} of {n} "
                       "labelled frames that have ground truth")
    return out


def tables(agg: dict) -> list[int]:
    """The paper's tables an evaluation of ``agg``'s rows writes: 1 and 2, and 3 (the
    ablation) when an ablation row was evaluated (``--ablation``)."""
    return [1, 2, 3] if any(r in agg for r in ABLATION_ONLY) else [1, 2]


def tables_label(agg: dict) -> str:
    """"Tables 1-3" or "Tables 1-2": what tables.md holds."""
    t = tables(agg)
    return f"Tables {t[0]}-{t[-1]}"


def written(out_dir: str | Path, result: dict) -> str:
    """The line after an eval: what it wrote, naming the tables tables.md holds."""
    return (f"wrote {out_dir}/eval.json, tables.md ({tables_label(result['aggregate'])}); "
            f"neurncd report {out_dir} renders the HTML page")


def _named(row: str) -> bool:
    """Whether a row's clusters carry class names (GS alone's do not: it is scored by
    assigned mIoU only, its named mIoUs given nowhere)."""
    return row != "gs"


def markdown_tables(agg: dict, n_bags: int, notes: Iterable[str] = ()) -> str:
    """Tables 1-2 of the paper, and with the ablation's rows (:data:`ABLATION_ONLY`)
    Table 3, laid out as there (percent; mean ± std over bags); ``notes`` (e.g.
    :func:`coverage`) are said under the first line. The notes under the tables
    describe only rows that are present."""
    known = [int(c) for c in classes.KNOWN_IDS]
    novel = [int(c) for c in classes.NOVEL_IDS]
    names = [classes.class_name(c) for c in known + novel]
    lines = [f"Over {n_bags} bag(s); percent; mean ± std over bags where several (the "
             "population standard deviation, ddof 0)" + (
                 "; a figure measured in only some of the bags (a class in only some "
                 "bags' ground truth) says in how many, e.g. \"84.8 (1 bag)\"; \"-\": "
                 "in none." if n_bags > 1 else "."), ""]
    lines += [f"{x}." for x in notes] + ([""] if notes else [])
    lines += ["### Table 1: per-class IoU (9 known | 4 novel)", "",
             "| method | " + " | ".join(names[:len(known)]) + " | " +
             " | ".join(f"*{n}*" for n in names[len(known):]) + " |",
             "|---" * (1 + len(names)) + "|"]
    for row in agg:
        if not _named(row):  # GS alone: Table 3's assigned mIoU only
            continue
        lines.append(f"| {row_title(row)} | " + " | ".join(
            _cell(agg[row]["iou"][str(c)], n_bags) for c in known + novel) + " |")
    lines += ["", "### Table 2: known / novel mIoU and accuracies", "",
              "| method | mIoU known | mIoU novel | mIoU all | Total Acc | Avg Acc | "
              "assigned mIoU (SCIM) |", "|---|---|---|---|---|---|---|"]
    for row in agg:
        if not _named(row):  # GS alone: Table 3's assigned mIoU only
            continue
        a = agg[row]
        lines.append(f"| {row_title(row)} | " + " | ".join(_cell(a[k], n_bags)
                                                            for k in FIGURES) + " |")
    if 3 in tables(agg):
        lines += ["", "### Table 3: ablation", "",
                  "| GS | PSSN | EP | SE | MCL | mIoU known | mIoU novel | mIoU all | "
                  "assigned mIoU |", "|---|---|---|---|---|---|---|---|---|"]
        marks = {"gs": "✓ | | | | ✓", "pssn": " | ✓ | | | ",
                 "gs_pssn_ep_mcl": "✓ | ✓ | ✓ | | ✓", "full": "✓ | ✓ | ✓ | ✓ | ✓"}
        for row in ("gs", "pssn", "gs_pssn_ep_mcl", "full"):
            if row in agg:
                a = agg[row]
                lines.append(f"| {marks[row]} | " + " | ".join(
                    _cell(a[k], n_bags) if _named(row) or k == "assigned_miou" else "n/a"
                    for k in ("miou_known", "miou_novel", "miou_all", "assigned_miou"))
                    + " |")
    said = []
    if "gs" in agg:
        said.append("GS alone has no class names: its row is scored by SCIM's assigned "
                    "mIoU only (every cluster matched one-to-one to a ground-truth class); "
                    "its named mIoUs (n/a) would only see the novel matching.")
    if any(r.startswith(semnerf.ROW_PREFIX) for r in agg):
        said.append("The Semantic-NeRF rows are fields trained on ground-truth labels of "
                    "the known classes at that share of each keyframe's pixels (no "
                    "backbone); they name no novel class, so their figure is mIoU known.")
    if said:
        lines += ["", " ".join(said)]
    return "\n".join(lines) + "\n"


def picture_panels(per_bag: list[dict]) -> list[dict[str, str]]:
    """The panels every kept picture holds, left to right, as ``{"key", "title"}``
    (:data:`PANELS`): what the report's grid shows and its heading names."""
    pics = [p for b in per_bag for p in b.get("pictures", [])]
    return [{"key": k, "title": t} for k, t in PANELS.items()
            if pics and all(p.get(k) is not None for p in pics)]


def write_eval(out_dir: str | Path, per_bag: list[dict]) -> dict[str, Any]:
    """DIR/eval.json, DIR/tables.md, DIR/pictures.npz (for ``neurncd report``).

    eval.json ``tables`` lists the paper's tables tables.md holds (:func:`tables`: 1-2,
    and 3 with the ablation's rows).

    eval.json ``picture_panels`` names the panels of pictures.npz's grid rows, so the
    report's heading says what the images hold (no baseline panel without
    ``--baselines``)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    agg = aggregate(per_bag)
    bags = [{k: v for k, v in b.items() if k != "pictures"} for b in per_bag]
    checked = targets.check(agg, bags)
    panels = picture_panels(per_bag)
    result = {"bags": bags, "aggregate": agg, "rows": {r: row_title(r) for r in agg},
              "tables": tables(agg), "targets": checked, "picture_panels": panels}
    (out / "eval.json").write_text(json.dumps(result, indent=1, default=json_default))
    (out / "tables.md").write_text(markdown_tables(agg, len(per_bag), coverage(bags))
                                   + "\n" + targets.markdown(checked))
    pics = {}
    for bi, b in enumerate(per_bag):
        for pi, p in enumerate(b["pictures"]):
            for k in ["stamp"] + [q["key"] for q in panels]:
                pics[f"b{bi}_p{pi}_{k}"] = np.asarray(p[k])
    np.savez_compressed(out / "pictures.npz", **pics)
    return result


def summary(result: dict) -> str:
    """A few lines after an eval."""
    agg, bags = result["aggregate"], result["bags"]
    n = len(bags)
    labelled = sum(b["labelled"] for b in bags)
    scored = sum(b.get("frames_evaluated", b["labelled"]) for b in bags)
    lines = [f"evaluated {n} bag(s), {labelled} labelled frames"
             + (f" ({scored} with ground truth, the frames scored)" if scored < labelled
                else "")]
    lines += [f"  {x}" for x in coverage(bags)]
    for row, a in agg.items():
        if not _named(row):  # GS alone: scored by assigned mIoU only
            lines.append(f"  {row_title(row):52s} assigned {_cell(a['assigned_miou'], n)}")
            continue
        lines.append(f"  {row_title(row):52s} known {_cell(a['miou_known'], n)}, novel "
                     f"{_cell(a['miou_novel'], n)}, all {_cell(a['miou_all'], n)}, assigned "
                     f"{_cell(a['assigned_miou'], n)}")
    lines.append("issue 12 targets ('10 percent' read as 10 mIoU points):")
    lines += [f"  {x}" for x in targets.lines(result.get("targets")
                                             or targets.check(agg, result["bags"]))]
    return "\n".join(lines)
