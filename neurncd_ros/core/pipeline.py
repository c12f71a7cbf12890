"""The offline path: backbone -> Embedding-NeRF mapper -> discovery on a stream of frames.

``neurncd run`` and ``neurncd demo`` call this; the ROS nodes call the very
same core objects (``Backbone``, ``Mapper``, ``Discoverer``) from callbacks.
Offline, training runs in the caller's thread for a fixed number of
iterations per frame so that a run is reproducible, and a frame is labelled
once the field has trained on it for ``mapper.min_iterations_before_publish``
iterations, as the mapper node publishes it.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections import deque
from pathlib import Path
from typing import Any, Iterable, Iterator

import cv2
import numpy as np

from . import classes
from ..config import Config
from .frame import Frame


def _overlay(frame: Frame, labels: np.ndarray, backbone_ids: np.ndarray,
             entropy: np.ndarray) -> np.ndarray:
    """One picture per frame: rgb | ground truth | backbone | NeurNCD labels | entropy."""
    tiles = [frame.rgb]
    if frame.semantic is not None:
        tiles.append(classes.colourise(frame.semantic))
    tiles.append(classes.colourise(backbone_ids))
    tiles.append(classes.colourise(labels))
    ent = entropy / max(float(entropy.max()), 1e-6)
    ent = cv2.applyColorMap(np.clip(ent * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_MAGMA)
    tiles.append(ent[:, :, ::-1])
    return np.concatenate(tiles, axis=1)


@dataclasses.dataclass
class StreamTimes:
    """Seconds spent per stage of :func:`stream_renderings` (accumulated)."""

    backbone: float = 0.0
    training: float = 0.0
    rendering: float = 0.0
    frames: int = 0


def stream_renderings(frames: Iterable[Frame], cfg: Config, backbone, mapper,
                      total: int | None = None, progress: bool = True,
                      times: StreamTimes | None = None
                      ) -> Iterator[tuple[Frame, np.ndarray, dict[str, np.ndarray]]]:
    """Backbone and Embedding-NeRF over a stream; yields what discovery needs.

    Every frame goes through the backbone and is offered to the mapper as a
    keyframe, then ``run.train_iterations_per_frame`` iterations train (plus
    ``run.warmup_iterations`` after the first); one frame in ``run.label_every``
    is rendered (with its measured depth) once the field has trained on it for
    ``mapper.min_iterations_before_publish`` iterations, and yielded as
    (frame, backbone argmax ids, rendering with embedding and entropy).
    """
    from tqdm import tqdm

    run = cfg.run
    times = times if times is not None else StreamTimes()
    pending: deque[tuple[int, Frame, np.ndarray]] = deque()
    min_iters = cfg.mapper.min_iterations_before_publish

    def render(frame: Frame) -> dict[str, np.ndarray]:
        t0 = time.perf_counter()
        out = mapper.render(frame.pose, frame.intrinsics, depth=frame.depth)
        times.rendering += time.perf_counter() - t0
        return out

    bar = tqdm(frames, total=total, desc="run", unit="frame", disable=not progress)
    n_in = 0
    for frame in bar:
        if run.max_frames and n_in >= run.max_frames:
            break
        t0 = time.perf_counter()
        logits = backbone.predict(frame.rgb, frame.depth)
        backbone_ids = backbone.channel_to_id[np.argmax(logits, axis=2)].astype(np.uint16)
        t1 = time.perf_counter()
        mapper.add_keyframe(frame, logits)
        iters = run.train_iterations_per_frame + (run.warmup_iterations if n_in == 0 else 0)
        if iters:
            mapper.step(iters)
        t2 = time.perf_counter()
        times.backbone += t1 - t0
        times.training += t2 - t1
        if n_in % run.label_every == 0:
            pending.append((mapper.iterations, frame, backbone_ids))
        n_in += 1
        times.frames = n_in
        while pending and mapper.iterations - pending[0][0] >= min_iters:
            _, f, ids = pending.popleft()
            yield f, ids, render(f)
        bar.set_postfix(iters=mapper.iterations)
    bar.close()
    if pending:  # the stream ended: give the last frames their training, then label them
        more = max(0, min_iters - (mapper.iterations - pending[-1][0]))
        if more:
            t0 = time.perf_counter()
            mapper.step(more)
            times.training += time.perf_counter() - t0
        while pending:
            _, f, ids = pending.popleft()
            yield f, ids, render(f)


def run_frames(frames: Iterable[Frame], cfg: Config, out_dir: str | Path,
               total: int | None = None, progress: bool = True) -> dict[str, Any]:
    """Run the whole pipeline on frames; returns a result dict (metrics if GT exists)."""
    from .backbone.backbone import load_backbone
    from .discovery.labeller import Discoverer
    from .discovery.metrics import Evaluator
    from .field.mapper import Mapper

    out = Path(out_dir)
    (out / "overlays").mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    backbone = load_backbone(cfg.backbone)
    mapper = Mapper.from_config(cfg, backbone.channels)
    discoverer = Discoverer(cfg.discovery, backbone.channel_to_id, mcl_cfg=cfg.mcl,
                            seg_cfg=cfg.segmentation, mod_cfg=cfg.modulation)
    ev_ncd, ev_backbone = Evaluator(), Evaluator()
    times = StreamTimes()
    n_labelled = n_overlays = n_evaluated = 0
    t_discovery = 0.0
    for frame, backbone_ids, rendering in stream_renderings(frames, cfg, backbone, mapper,
                                                            total, progress, times):
        t0 = time.perf_counter()
        labels = discoverer.process(frame.depth, frame.intrinsics, rendering["embedding"],
                                    rendering["entropy"], frame.stamp_ns, frame.rgb)
        t_discovery += time.perf_counter() - t0
        n_labelled += 1
        if frame.semantic is not None:
            ev_ncd.update(labels, frame.semantic)
            ev_backbone.update(backbone_ids, frame.semantic)
            n_evaluated += 1
        if n_overlays < cfg.run.overlays:
            pic = _overlay(frame, labels, backbone_ids, rendering["entropy"])
            cv2.imwrite(str(out / "overlays" / f"{frame.stamp_ns}.png"), pic[:, :, ::-1])
            n_overlays += 1
    n_in = times.frames
    if n_in == 0:
        raise ValueError("no frames to run on")

    result: dict[str, Any] = {
        "frames": n_in, "labelled": n_labelled, "iterations": mapper.iterations,
        "backend": cfg.mapper.backend, "backbone": cfg.backbone.kind,
        "seconds": round(time.perf_counter() - t_start, 2),
        "seconds_backbone": round(times.backbone, 2),
        "seconds_training": round(times.training, 2),
        "seconds_rendering": round(times.rendering, 2),
        "seconds_discovery": round(t_discovery, 2),
        "classes": {str(k): v for k, v in discoverer.classes().items()},
        "out_dir": str(out),
    }
    if n_evaluated:
        result["metrics"] = ev_ncd.result()
        result["metrics_backbone_only"] = ev_backbone.result()
    (out / "metrics.json").write_text(json.dumps(result, indent=2, default=_json_default))
    return result


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(type(obj).__name__)


def run_bag(bag: str | Path, cfg: Config, out_dir: str | Path) -> dict[str, Any]:
    """``neurncd run --bag``: read synchronised frames from a bag and run on them."""
    from .data.bag import FrameReader

    reader = FrameReader.from_config(bag, cfg.topics, cfg.sync)
    result = run_frames(reader, cfg, out_dir)
    result["bag"] = str(bag)
    result["dropped"] = len(reader.dropped)
    result["reader"] = reader.summary()
    return result


def demo(cfg: Config, out_dir: str | Path, seed: int = 1001, frames: int = 90
         ) -> dict[str, Any]:
    """``make demo``: a held-out synthetic scene written as a bag, then the whole pipeline."""
    from .. import synth
    from .data.bag import write_bag

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    bag = out / "scene.mcap"
    if bag.exists():
        import shutil
        shutil.rmtree(bag) if bag.is_dir() else bag.unlink()
    t0 = time.perf_counter()
    n = write_bag(bag, synth.generate(seed, frames, cfg.synth), storage="mcap",
                  topics=cfg.topics)
    print(f"demo: wrote synthetic scene seed {seed}, {n} frames, to {bag} in "
          f"{time.perf_counter() - t0:.1f} s")
    result = run_bag(bag, cfg, out)
    result["demo_seed"] = seed
    return result


def summary(result: dict[str, Any]) -> str:
    """A few lines a person reads after a run."""
    lines = [f"ran {result['frames']} frames ({result['labelled']} labelled) in "
             f"{result['seconds']} s: backbone {result['seconds_backbone']} s, field "
             f"training {result['seconds_training']} s ({result['iterations']} iterations, "
             f"{result['backend']}), rendering {result['seconds_rendering']} s, discovery "
             f"{result['seconds_discovery']} s"]
    m = result.get("metrics")
    if m:
        b = result["metrics_backbone_only"]
        lines.append(f"NeurNCD: mIoU all {m['miou_all']:.1f}, known {m['miou_known']:.1f}, "
                     f"novel {m['miou_novel']:.1f}; Total Acc {m['total_acc']:.1f}, Avg Acc "
                     f"{m['avg_acc']:.1f}; SCIM assigned mIoU {m['assigned_miou']:.1f} (%)")
        lines.append(f"backbone alone (known classes only): mIoU known "
                     f"{b['miou_known']:.1f}, Total Acc {b['total_acc']:.1f} (%)")
    novel = [k for k, v in result.get("classes", {}).items() if v.get("kind") == "novel"]
    lines.append(f"classes: {len(result.get('classes', {}))} ({len(novel)} novel: "
                 f"{', '.join(novel[:8])}{'...' if len(novel) > 8 else ''})")
    lines.append(f"wrote {result['out_dir']}/metrics.json and overlays/*.png "
                 "(rgb | ground truth | backbone | NeurNCD labels | entropy)")
    return "\n".join(lines)
