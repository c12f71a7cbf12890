"""The online engine driven offline, in one process, on a stream of frames.

``neurncd run``, ``make demo`` and the benchmarks call this. The same stages
as the ROS nodes run in the same order with the same policies (the embedding
stage's rate gate, the field's keyframe admission, keyframes always rendered,
the coverage blend, discovery on every view); what the live graph decides by
the wall clock is decided here by the frames' stamps, so a run is
reproducible and describes what the nodes publish:

- the field trains ``run.training_rate_hz`` iterations per second of stream
  time (what the mapper node reaches beside the other nodes on 2 cores);
- every keyframe is rendered and labelled (the mapper node queues them), and
  another frame only where the last label is at least ``1 / run.view_rate_hz``
  seconds of stream time old: the live graph's label rate, keyframes included;
  the others are skipped, as the mapper node skips frames when a newer one
  waits or discovery is busy.

It stays one module with ``neurncd run``'s outputs (label images, overlays, metrics.json,
its summary): they are the engine's Output records written out, and change with them.
"""

from __future__ import annotations

import dataclasses
import json
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import cv2
import numpy as np

from .. import classes
from ..frame import Frame
from ..params import param
from ..text import plural
from .discovery import DiscoveryStage
from .embedding import EmbeddingStage
from .mapping import MapperStage
from .views import resize_to
from .records import EmbeddingRecord, LabelsRecord, ViewRecord


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """The offline engine (`neurncd run`, the benchmarks): the live graph's schedule, in
    stream time, without DDS."""

    training_rate_hz: float = param(2.5, "field training iterations per second of stream "
                                    "time, as the mapper node trains beside the other nodes "
                                    "on 2 cores (bench/graph.py measures it: 2.2 with the "
                                    "training thread at mapper.train_nice 10, the median of "
                                    "5 runs; 5.7 at 0)", lo=0.0, hi=100000.0, unit="Hz")
    view_rate_hz: float = param(3.0, "views rendered and labelled per second of stream time, "
                                "keyframes included: every keyframe is labelled, another "
                                "frame when the last label is at least 1 / this old (the "
                                "live graph's label rate on 2 cores with the backbone at its "
                                "40 ms target: 2.8-4.0, bench/results/graph.json "
                                "label_rate_hz_at_probe_40ms; 0 = keyframes only)",
                                lo=0.0, hi=1000.0, unit="Hz")
    max_frames: int = param(0, "stop after this many input frames (0 = all)", lo=0,
                            hi=10_000_000)
    overlays: int = param(6, "how many labelled frames get a PNG overlay", lo=0, hi=10_000)
    out_dir: str = param("out/run", "where metrics.json, labels/ and overlays/ are "
                         "written")


@dataclasses.dataclass
class Output:
    """One labelled frame and what led to it."""

    frame: Frame
    embedding: EmbeddingRecord
    view: ViewRecord
    labels: LabelsRecord

    def backbone_ids(self) -> np.ndarray:
        """The backbone's own argmax labels at the frame's size (the 'backbone alone' row)."""
        h, w = self.frame.depth.shape
        logits = resize_to(self.embedding.logits.astype(np.float32), h, w)
        return self.embedding.spec.ids()[np.argmax(logits, axis=2)]


def mapper_factory(cfg) -> Callable[[int, int], Any]:
    """(channels S the field learns, feature_channels kept with the keyframes) -> a new
    Mapper configured by ``cfg`` (the whole configuration)."""
    from ..field.mapper import Mapper

    return lambda channels, feature_channels: Mapper.from_config(cfg, channels,
                                                                 feature_channels)


class OfflineEngine:
    """Feed frames in stamp order; get the labelled frames out."""

    def __init__(self, cfg, backbone=None, make_mapper: Callable[[int, int], Any] | None = None
                 ) -> None:
        from ..backbone.backbone import load_backbone, threshold_warning

        self.cfg = cfg
        self.backbone = backbone if backbone is not None else load_backbone(cfg.backbone)
        advice = threshold_warning(self.backbone, cfg.discovery.entropy_threshold)
        if advice:
            warnings.warn(advice, stacklevel=2)
        self.embedding = EmbeddingStage(self.backbone, cfg.embedding_node)
        self.mapping = MapperStage(cfg.mapper_node, make_mapper or mapper_factory(cfg),
                                   online=False)
        self.discovery = DiscoveryStage(cfg, cfg.discovery_node)
        self.frames_in = 0
        self._t0: int | None = None
        self._last_in: int | None = None  # stamp of the last frame fed
        self.refused = 0  # frames run() skipped because feed() refused them
        self._trained = 0
        self._last_label: int | None = None  # stamp of the last labelled frame
        self.seconds = dict.fromkeys(("backbone", "training", "rendering", "discovery"), 0.0)

    @property
    def mapper(self):
        return self.mapping.mapper

    def load_map(self, path: str | Path) -> dict[str, int]:
        """Continue from a map the mapper node or ``neurncd run`` saved
        (``mapper_node.map_path``: the file and its ``.spec.json``), as the mapper node
        does at start; returns its iterations, keyframes and ``kept_settings``: the settings
        the map keeps from when it was built where the configuration differs,
        ``{"mapper.near": [the map's, the configuration's]}`` (Mapper.kept_settings)."""
        from ..field.mapper import Mapper

        self.mapping.load(path, lambda p: Mapper.load_configured(p, self.cfg))
        kept = self.mapper.kept_settings(self.cfg)
        return {"iterations": self.mapper.iterations, "keyframes": len(self.mapper.buffer),
                "kept_settings": {k: list(v) for k, v in kept.items()}}

    def save_map(self, path: str | Path) -> bool:
        """Save the map (the field and its keyframes) as the mapper node does, to ``path``
        and ``<path>.spec.json``, atomically; False if there is no map yet. What
        :meth:`load_map` (and the mapper node's ``mapper_node.map_path``) continues."""
        return self.mapping.save(path)

    def _train_until(self, stamp_ns: int) -> None:
        due = int(self.cfg.run.training_rate_hz * (stamp_ns - self._t0) * 1e-9)
        if due > self._trained and self.mapper is not None and len(self.mapper.buffer):
            t = time.perf_counter()
            self.mapper.step(due - self._trained)
            self.seconds["training"] += time.perf_counter() - t
        self._trained = max(self._trained, due)

    def feed(self, frame: Frame) -> list[Output]:
        """One input frame (with pose); the labelled outputs it produced (0 or 1).

        A frame refused with a ValueError (:meth:`Frame.validate`, no pose, a stamp before
        the previous frame's, what the backbone refuses) leaves the engine as it was: the
        frames after it are labelled as if it had never come."""
        frame.validate()
        if frame.pose is None:
            raise ValueError(f"frame {frame.stamp_ns} has no pose: the engine takes each "
                             "frame's camera-to-world pose (frames without poses get them "
                             "from neurncd_ros.core.odometry.with_odometry)")
        if self._last_in is not None and frame.stamp_ns < self._last_in:
            raise ValueError(f"frame {frame.stamp_ns} is "
                             f"{(self._last_in - frame.stamp_ns) * 1e-9:.3g} s before the "
                             f"previous frame ({self._last_in}): feed frames in stamp order "
                             "(another sequence: a new OfflineEngine)")
        rec = None
        if self.embedding.wanted(frame.stamp_ns):
            t = time.perf_counter()
            rec = self.embedding.embed(frame.stamp_ns, frame.rgb, frame.depth)
            self.seconds["backbone"] += time.perf_counter() - t
        self.frames_in += 1
        self._last_in = frame.stamp_ns
        if self._t0 is None:
            self._t0 = frame.stamp_ns
        if rec is None:
            return []
        job = self.mapping.admit(frame, rec)
        self._train_until(frame.stamp_ns)
        if job is None:
            return []
        rate = self.cfg.run.view_rate_hz
        due = rate > 0 and (self._last_label is None
                            or (frame.stamp_ns - self._last_label) * 1e-9 >= 0.999 / rate)
        if not job.keyframe and not due:
            return []
        job = self.mapping.next_view()
        if job is None:
            return []
        self._last_label = frame.stamp_ns
        t = time.perf_counter()
        view = self.mapping.render_view(job)
        self.seconds["rendering"] += time.perf_counter() - t
        t = time.perf_counter()
        labels = self.discovery.label_view(view)
        self.seconds["discovery"] += time.perf_counter() - t
        self.mapping.labelled(frame.stamp_ns)
        return [Output(frame, rec, view, labels)]

    def run(self, frames: Iterable[Frame], total: int | None = None, progress: bool = True,
            desc: str = "run") -> Iterator[Output]:
        """:meth:`feed` over a stream, with a progress bar named ``desc``. A frame that
        :meth:`feed` refuses (a stamp before the previous frame's, as in a bag of two
        recordings, where the nodes' pairing drops it too) is skipped: the first is warned
        of, and :attr:`refused` counts them (``frames_refused`` in metrics.json)."""
        from tqdm import tqdm

        bar = tqdm(frames, total=total, desc=desc, unit="frame", disable=not progress)
        for frame in bar:
            if self.cfg.run.max_frames and self.frames_in >= self.cfg.run.max_frames:
                break
            try:
                outputs = self.feed(frame)
            except ValueError as err:
                if not self.refused:
                    warnings.warn(f"frame skipped: {err}", stacklevel=2)
                self.refused += 1
                continue
            yield from outputs
            if self.mapper is not None:
                bar.set_postfix(iterations=self.mapper.iterations,
                                keyframes=len(self.mapping.keyframe_stamps))
        bar.close()


# ---------------------------------------------------------------- neurncd run

OUTPUT_LAYOUT = """\
The output folder (--out, default run.out_dir) holds:
  metrics.json        every figure of the run: frames, labelled frames, timings, the
                      class table, "evaluated" (true when the bag has ground truth and the
                      frames were scored, then "metrics" and "metrics_backbone_only")
  labels/<stamp>.png  the label image of every labelled frame, 16-bit PNG, exactly the
                      image the discovery node publishes on /neurncd/labels: 0
                      unlabelled, 1..13 NYU-13 (known classes), 100 and up novel classes
  overlays/<stamp>.png  the first run.overlays labelled frames side by side: rgb | ground
                      truth (only where the frame has it) | backbone | NeurNCD labels |
                      entropy
<stamp> is the frame's stamp in nanoseconds. A run replaces the label images and overlays
an earlier run left in the same folder."""


def overlay_tiles(with_ground_truth: bool) -> str:
    """The tiles of an overlay, left to right, as the summary names them."""
    return " | ".join(["rgb"] + (["ground truth"] if with_ground_truth else []) +
                      ["backbone", "NeurNCD labels", "entropy"])


def overlay(out: Output) -> np.ndarray:
    """One picture per labelled frame: rgb | ground truth | backbone | labels | entropy; the
    ground-truth tile only where the frame has ground truth (:func:`overlay_tiles`)."""
    f = out.frame
    h, w = f.depth.shape
    tiles = [f.rgb]
    if f.semantic is not None:
        tiles.append(classes.colourise(f.semantic))
    tiles.append(classes.colourise(out.backbone_ids()))
    tiles.append(classes.colourise(out.labels.labels))
    ent = resize_to(out.view.entropy, h, w) / max(np.log(out.view.spec.logit_channels), 1e-6)
    ent = cv2.applyColorMap(np.clip(ent * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_MAGMA)
    tiles.append(ent[:, :, ::-1])
    return np.concatenate(tiles, axis=1)


def write_labels_png(path: Path, labels: np.ndarray) -> None:
    """A published label image (H, W) uint16 as a 16-bit PNG, ids unchanged: what a user
    reads back with ``cv2.imread(path, cv2.IMREAD_UNCHANGED)`` is the /neurncd/labels
    image."""
    if labels.ndim != 2 or labels.dtype != np.uint16:
        raise ValueError(f"labels must be (H, W) uint16, got {labels.shape} {labels.dtype}")
    if not cv2.imwrite(str(path), labels):
        raise ValueError(f"{path}: cannot write the label image")


def _clear_stale(folder: Path) -> None:
    """Remove the ``<stamp>.png`` files an earlier run left in one of the output's own
    subfolders, so the folder shows this run's frames only (nothing else is touched)."""
    for p in folder.glob("*.png"):
        if p.stem.isdigit():
            p.unlink()


class _ClassTally:
    """Which ids the published label images show, in how many pixels and frames.

    The discoverer's own class table lists every novel id it still holds, with the
    pixels of the last labelled frame only, so a novel id that was merged into another
    or is not in the last frame reads as a class with 0 pixels. The run's class table
    is made from what was published instead."""

    def __init__(self) -> None:
        self.pixels: dict[int, int] = {}
        self.frames: dict[int, int] = {}

    def add(self, labels: np.ndarray) -> None:
        ids, counts = np.unique(labels, return_counts=True)
        for i, c in zip(ids.tolist(), counts.tolist()):
            if i:
                self.pixels[i] = self.pixels.get(i, 0) + int(c)
                self.frames[i] = self.frames.get(i, 0) + 1

    def table(self, discoverer) -> tuple[dict[str, dict], list[int]]:
        """(the classes the labels show, by id: name, kind, pixels and frames over all
        labelled frames, and for a novel id later published under another id the id it
        was merged into; the ids the discoverer holds that no label image shows)."""
        held = discoverer.classes() if discoverer is not None else {}
        fusion = getattr(discoverer, "fusion", None)
        aliases = fusion.aliases if fusion is not None else {}
        shown: dict[str, dict] = {}
        for i in sorted(self.pixels):
            row = {"name": classes.class_name(i),
                   "kind": "novel" if i >= classes.NOVEL_ID_START else "known",
                   "pixels": self.pixels[i], "frames": self.frames[i]}
            if i in aliases:
                row["merged_into"] = int(aliases[i])
            shown[str(i)] = row
        unshown = sorted(int(i) for i in held if int(i) not in self.pixels)
        return shown, unshown


def run_frames(frames: Iterable[Frame], cfg, out_dir: str | Path, total: int | None = None,
               progress: bool = True, source: Callable[[], dict] | None = None
               ) -> dict[str, Any]:
    """Run the engine on frames; write metrics.json, the label images and the overlays
    (layout: :data:`OUTPUT_LAYOUT`); return the result.

    ``source()``, called once the frames are used up, adds what the frame source
    knows about itself (the bag, its drops, where the poses came from)."""
    from ..discovery.metrics import Evaluator

    out = Path(out_dir)
    for sub in ("labels", "overlays"):
        (out / sub).mkdir(parents=True, exist_ok=True)
        _clear_stale(out / sub)
    t_start = time.perf_counter()
    map_path = cfg.mapper_node.map_path
    if map_path:  # before the run, not at its end
        from ..torchfile import check_save_path
        check_save_path(map_path, "mapper_node.map_path")
    engine = OfflineEngine(cfg)
    loaded = engine.load_map(map_path) if map_path and Path(map_path).is_file() else None
    ev, ev_backbone = Evaluator(), Evaluator()
    tally = _ClassTally()
    n_labelled = n_keyframes = n_evaluated = n_overlays = n_overlays_gt = 0
    for o in engine.run(frames, total, progress):
        n_labelled += 1
        n_keyframes += o.view.keyframe
        write_labels_png(out / "labels" / f"{o.frame.stamp_ns}.png", o.labels.labels)
        tally.add(o.labels.labels)
        if o.frame.semantic is not None:
            ev.update(o.labels.labels, o.frame.semantic)
            ev_backbone.update(o.backbone_ids(), o.frame.semantic)
            n_evaluated += 1
        if n_overlays < cfg.run.overlays:
            cv2.imwrite(str(out / "overlays" / f"{o.frame.stamp_ns}.png"),
                        overlay(o)[:, :, ::-1])
            n_overlays += 1
            n_overlays_gt += o.frame.semantic is not None
    if engine.frames_in == 0:
        raise ValueError("no frames to run on")
    mapper = engine.mapper
    shown, unshown = tally.table(engine.discovery.discoverer)
    result: dict[str, Any] = {
        "frames": engine.frames_in, "frames_refused": engine.refused,
        "labelled": n_labelled, "keyframes_labelled": n_keyframes,
        "keyframes": len(engine.mapping.keyframe_stamps),
        "iterations": mapper.iterations if mapper is not None else 0,
        "backend": cfg.mapper.backend, "backbone": cfg.backbone.kind,
        "backbone_checkpoint": cfg.backbone.checkpoint or "shipped default",
        "seconds": round(time.perf_counter() - t_start, 2),
        **{f"seconds_{k}": round(v, 2) for k, v in engine.seconds.items()},
        "evaluated": n_evaluated > 0,
        "frames_evaluated": n_evaluated,
        "classes": shown,
        "class_ids_not_in_labels": unshown,
        "label_images": n_labelled,
        "overlays": n_overlays,
        "overlays_with_ground_truth": n_overlays_gt,
        "out_dir": str(out),
    }
    if n_evaluated:
        result["metrics"] = ev.result()
        result["metrics_backbone_only"] = ev_backbone.result()
    if map_path:
        result["map"] = {"path": map_path, "loaded": loaded,
                         "saved": engine.save_map(map_path),
                         "iterations": mapper.iterations if mapper is not None else 0}
    state_path = cfg.discovery_node.state_path
    if state_path:
        result["discovery_state"] = {"path": state_path,
                                     "continued_novel_ids": engine.discovery.continued,
                                     "refused": engine.discovery.state_refused,
                                     "saved": engine.discovery.save_state(),
                                     "novel_ids": engine.discovery.discoverer.novel_ids
                                     if engine.discovery.discoverer is not None else []}
    if source is not None:
        result.update(source())
    (out / "metrics.json").write_text(json.dumps(result, indent=2, default=json_default))
    return result


def json_default(obj: Any) -> Any:
    """``json.dumps(default=...)`` for numpy scalars and arrays in result files."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(type(obj).__name__)


def bag_poses(bag: str | Path, cfg) -> str:
    """Where ``neurncd run`` takes a bag's poses from, by ``mapper_node.pose_source`` as the
    mapper node decides it: "bag" (its pose topic or the /tf pair in ``sync``) or
    "odometry" (estimated from the images)."""
    from ..data.bag import bag_topics

    source = cfg.mapper_node.pose_source
    if source == "odometry":
        return "odometry"
    if source in ("topic", "tf"):
        return "bag"
    topics = bag_topics(bag)
    has_tf = bool(cfg.sync.tf_parent and cfg.sync.tf_child) and (
        cfg.topics.tf in topics or cfg.topics.tf_static in topics)
    return "bag" if cfg.topics.pose in topics or has_tf else "odometry"


def run_bag(bag: str | Path, cfg, out_dir: str | Path) -> dict[str, Any]:
    """``neurncd run --bag``: synchronised frames from a bag through the engine; a bag
    without poses gets them from RGB-D odometry, as the mapper node's pose_source auto."""
    from ..data.bag import FrameReader

    poses = bag_poses(bag, cfg)
    reader = FrameReader.from_config(bag, cfg.topics, cfg.sync, with_poses=poses == "bag")
    frames: Iterable[Frame] = reader
    tracked: list = []
    if poses == "odometry":
        from ..odometry import with_odometry
        frames = with_odometry(reader, cfg.odometry, tracked)
    def source() -> dict:
        out = {"bag": str(bag), "poses": poses, "dropped": len(reader.dropped),
               "reader": reader.summary()}
        if poses == "odometry":
            out["odometry_lost"] = sum(r.pose is None for r in tracked)
        return out

    if not len(reader):  # every frame dropped: say why, not only that nothing is left
        raise ValueError(f"no frames to run on: {reader.summary()}")
    return run_frames(frames, cfg, out_dir, total=len(reader), source=source)


def summary(result: dict[str, Any]) -> str:
    """A few lines a person reads after a run: what ran, the scores or that nothing was
    scored, the classes the labels show, and what was written where."""
    lines = [f"ran {plural(result['frames'], 'frame')} ({result['labelled']} labelled, "
             f"{result['keyframes_labelled']} of {plural(result['keyframes'], 'keyframe')}) in "
             f"{result['seconds']} s: backbone {result['seconds_backbone']} s, field "
             f"training {result['seconds_training']} s ({result['iterations']} iterations, "
             f"{result['backend']}), rendering {result['seconds_rendering']} s, discovery "
             f"{result['seconds_discovery']} s"]
    if result.get("frames_refused"):
        lines.append(f"{plural(result['frames_refused'], 'frame')} skipped, refused by the "
                     "engine (the first is warned of above: a stamp before the previous "
                     "frame's, as in a bag of two recordings)")
    if result.get("poses") == "odometry":
        lost = int(result.get("odometry_lost", 0))
        lines.append(f"poses estimated by RGB-D odometry (the bag has none): {lost} of "
                     f"{result['frames'] + lost} frames lost track and were skipped"
                     + (" (each logged with its reason)" if lost else ""))
    m = result.get("metrics")
    if m:
        b = result["metrics_backbone_only"]
        n_eval = result.get("frames_evaluated", result["labelled"])
        if n_eval < result["labelled"]:
            lines.append(f"evaluated on the {n_eval} of {result['labelled']} labelled "
                         "frames that have ground truth")
        lines.append(f"NeurNCD: mIoU all {m['miou_all']:.1f}, known {m['miou_known']:.1f}, "
                     f"novel {m['miou_novel']:.1f}; Total Acc {m['total_acc']:.1f}, Avg Acc "
                     f"{m['avg_acc']:.1f}; SCIM assigned mIoU {m['assigned_miou']:.1f} (%)")
        lines.append(f"backbone alone (known classes only): mIoU known "
                     f"{b['miou_known']:.1f}, Total Acc {b['total_acc']:.1f} (%)")
    elif result["labelled"]:
        lines.append("no ground truth in the bag: labels written, nothing evaluated")
    shown = result.get("classes", {})
    merged = [k for k, v in shown.items() if "merged_into" in v]
    novel = [k for k, v in shown.items() if v.get("kind") == "novel" and k not in merged]
    n_known = sum(v.get("kind") == "known" for v in shown.values())
    line = (f"classes in the labels: {n_known + len(novel)} ({n_known} known, {len(novel)} "
            "novel" + (f": {', '.join(novel[:8])}{'...' if len(novel) > 8 else ''}"
                       if novel else "") + ")")
    extra = []
    if merged:
        extra.append(f"{len(merged)} novel id(s) in earlier labels later merged into "
                     "another (metrics.json: merged_into)")
    hidden = result.get("class_ids_not_in_labels", [])
    if hidden:
        extra.append(f"{len(hidden)} novel id(s) held by discovery but in no label image")
    lines.append(line + ("; " + "; ".join(extra) if extra else ""))
    m_info = result.get("map")
    if m_info:
        from ..field.mapper import kept_settings_text

        was = m_info["loaded"]
        lines.append((f"continued map {m_info['path']} ({was['iterations']} iterations, "
                      f"{was['keyframes']} keyframes"
                      + (f"; it keeps the settings it was built with: "
                         f"{kept_settings_text(was['kept_settings'])}"
                         if was.get("kept_settings") else "") + ")" if was else
                      f"no map at {m_info['path']} yet: started a new one")
                     + (f"; saved it ({m_info['iterations']} iterations)" if m_info["saved"]
                        else "; nothing to save (no frame was embedded)"))
    d_info = result.get("discovery_state")
    if d_info:
        was, refused = d_info["continued_novel_ids"], d_info.get("refused")
        lines.append((f"continued discovery state {d_info['path']} (novel ids {was})"
                      if was is not None else
                      f"discovery state {d_info['path']} not continued ({refused}): started "
                      "afresh" if refused else
                      f"no discovery state at {d_info['path']} yet: started afresh")
                     + (f"; saved it (novel ids {d_info['novel_ids']})" if d_info["saved"]
                        else "; nothing to save (no view was labelled)"))
    out = result["out_dir"]
    n_ov, n_gt = result.get("overlays", 0), result.get("overlays_with_ground_truth", 0)
    wrote = (f"wrote {out}/metrics.json, {out}/labels/<stamp>.png "
             f"({plural(result['labelled'], 'label image')}, 16-bit: 1-13 NYU-13, 100+ novel, "
             "0 unlabelled)")
    if n_ov:
        tiles = overlay_tiles(n_gt == n_ov) if n_gt in (0, n_ov) else \
            overlay_tiles(True).replace("ground truth", "ground truth (where the frame has "
                                        "it)")
        wrote += f" and {out}/overlays/<stamp>.png ({n_ov}: {tiles})"
    lines.append(wrote)
    return "\n".join(lines)
