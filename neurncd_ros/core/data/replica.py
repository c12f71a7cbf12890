"""Semantic-NeRF's Replica layout: reader (class ids -> NYU-13) and exact writer.
Part of :mod:`.formats` (layout described there)."""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path
from typing import Any, Iterable, Iterator

import cv2
import numpy as np

from .. import classes
from ..camera import Intrinsics
from ..frame import Frame

from .folder_common import (FormatError, FolderConfig, _resolve, read_rgb, read_depth,
                            _make_frame, _subsample, read_matrix_rows, _indexed,
                            replacing_output)


def _id_map_entries(id_map: Any) -> dict[int, int]:
    """A class-id map (dict, JSON file of a dict, or 1-D array: source id -> NYU-13 id) as
    a dict, every target checked to be a NYU-13 id (0 = void .. 13)."""
    where = "id_map"
    if isinstance(id_map, (str, Path)):
        where = f"id_map {id_map}"
        try:
            id_map = json.loads(Path(id_map).read_text())
        except (OSError, ValueError) as err:
            raise FormatError(f"{id_map}: id map must be a JSON object of source id -> "
                              f"NYU-13 id ({err})") from None
        if not isinstance(id_map, dict):
            raise FormatError(f"{where}: must hold a JSON object of source id -> NYU-13 id")
    if isinstance(id_map, dict):
        try:
            entries = {int(k): int(v) for k, v in id_map.items()}
        except (TypeError, ValueError) as err:
            raise FormatError(f"{where}: keys and values must be integer ids ({err})") from None
    else:
        arr = np.asarray(id_map)
        if arr.ndim != 1 or arr.size == 0 or not np.issubdtype(arr.dtype, np.integer):
            raise FormatError(f"{where}: must be a dict or a 1-D array of integer ids")
        entries = {i: int(v) for i, v in enumerate(arr.tolist())}
    bad_src = sorted(k for k in entries if not 0 <= k < 65535)
    if bad_src:
        raise FormatError(f"{where}: source id(s) {bad_src[:10]} out of 0..65534")
    bad = sorted({v for v in entries.values() if not 0 <= v <= classes.NUM_CLASSES})
    if bad:
        raise FormatError(f"{where}: target id(s) {bad[:10]} are not NYU-13 ids (0 = void, "
                          f"1..{classes.NUM_CLASSES}: "
                          + ", ".join(f"{i} {n}" for i, n in enumerate(classes.NYU13_NAMES, 1))
                          + ")")
    return entries


NYU13_MARKER = "semantic_nyu13.txt"
"""Written by :func:`write_replica`: its ``semantic_class/`` images already hold NYU-13 ids."""


def _replica_lookup(folder: Path, id_map: Any, semantic_ids: str,
                    class_info: str | Path | None) -> tuple[np.ndarray | None, str]:
    """How a Replica folder's ``semantic_class`` ids become NYU-13 (None: they already are),
    and what to name when an image holds an id the mapping lacks.

    ``id_map`` entries override the scene's ``info_semantic.json`` where one is found (a
    class name the shipped table does not know is then fine if id_map maps its ids), or
    the ids of a folder that holds NYU-13 already; with neither, id_map alone maps, and an
    id it does not list is an error (never silently void): 0 is void unless id_map says
    otherwise."""
    from . import replica_classes as rc

    if semantic_ids not in ("auto", "nyu13", "replica"):
        raise FormatError(f"semantic_ids must be auto, nyu13 or replica, got {semantic_ids!r}")
    entries = None if id_map is None else _id_map_entries(id_map)
    if semantic_ids == "nyu13" or (semantic_ids == "auto" and (folder / NYU13_MARKER).is_file()):
        if entries is None:
            return None, ""
        lut = np.full(65536, 65535, dtype=np.uint16)  # NYU-13 already: id_map remaps some
        lut[: classes.NUM_CLASSES + 1] = np.arange(classes.NUM_CLASSES + 1)
        for k, v in entries.items():
            lut[k] = v
        return lut, "NYU-13 or id_map"
    info = Path(class_info) if class_info else rc.find_class_info(folder)
    if info is None and entries is None:
        raise FormatError(f"{folder}: semantic_class/ holds Replica class ids, but no "
                          "info_semantic.json was found beside it or in semantic_info/<scene>/ "
                          "above it; pass class_info=<path to the scene's info_semantic.json>, "
                          "or id_map=<JSON file of Replica id -> NYU-13 id>, or "
                          "semantic_ids=nyu13 if the images already hold NYU-13 ids")
    if info is None:
        lut = np.full(65536, 65535, dtype=np.uint16)
        lut[0] = classes.VOID
        source = "id_map (every id the images hold must be listed)"
    else:
        try:
            lut = rc.lookup_table(info, mapped=set(entries or ()))
        except rc.ReplicaClassError as err:
            raise FormatError(str(err)) from None
        source = f"{info}" + (" or id_map" if entries else "")
    for k, v in (entries or {}).items():
        lut[k] = v
    return lut, source


def read_replica(folder: str | Path, cfg: FolderConfig = FolderConfig(),
                 id_map: Any = None, semantic_ids: str = "auto",
                 class_info: str | Path | None = None) -> Iterator[Frame]:
    """Semantic-NeRF Replica layout -> Frames with NYU-13 ground truth.

    ``semantic_class/`` ids become NYU-13 by ``id_map`` if given, else by the
    shipped Replica -> NYU-13 mapping (:mod:`.replica_classes`) with the scene's
    ``info_semantic.json`` (found, or ``class_info``); folders written by
    :func:`write_replica` hold NYU-13 already (``semantic_ids="nyu13"`` says so
    for other folders).
    """
    from . import replica_classes as rc

    folder = Path(folder)
    fmt, scale, intr_vals = _resolve(cfg, "replica")
    poses = read_matrix_rows(folder / "traj_w_c.txt")
    rgbs = _indexed(folder / "rgb", "rgb_")
    depths = _indexed(folder / "depth", "depth_")
    sems = _indexed(folder / "semantic_class", "semantic_class_")
    insts = _indexed(folder / "semantic_instance", "semantic_instance_")
    if not rgbs:
        raise FormatError(f"{folder}: no rgb/rgb_<i>.png files")
    if len(poses) < len(rgbs):
        raise FormatError(f"{folder}/traj_w_c.txt has {len(poses)} poses for {len(rgbs)} "
                          "rgb images")
    stamps = _replica_stamps(folder, len(poses), cfg)
    cam_file = folder / "intrinsics.json"
    lut, lut_source = (_replica_lookup(folder, id_map, semantic_ids, class_info) if sems
                       else (None, ""))
    no_rgb = sorted(set(depths) - set(rgbs))
    if no_rgb:
        warnings.warn(f"{folder}: {len(no_rgb)} frame(s) with depth but no rgb/rgb_<i>.png "
                      f"skipped: {_id_list(no_rgb)}", stacklevel=2)
    chosen = _subsample(sorted(rgbs), cfg)
    no_gt = [i for i in chosen if i not in sems] if sems else []
    if no_gt:
        warnings.warn(f"{folder}: {len(no_gt)} frame(s) without semantic_class/"
                      f"semantic_class_<i>.png carry no ground truth: {_id_list(no_gt)}",
                      stacklevel=2)
    for i in chosen:
        if i not in depths:
            raise FormatError(f"{folder}: depth/depth_{i}.png missing")
        if i >= len(poses):
            raise FormatError(f"{folder}/traj_w_c.txt has no pose for frame {i}")
        rgb = read_rgb(rgbs[i])
        depth = read_depth(depths[i], fmt, scale, cfg.max_depth_m)
        h, w = depth.shape
        if intr_vals is not None:
            intr = Intrinsics(*intr_vals, w, h)
        elif cam_file.is_file():
            intr = _read_intrinsics_json(cam_file)
        else:
            intr = Intrinsics.from_hfov(w, h, cfg.hfov_deg)
        sem = read_labels(sems[i]) if i in sems else None
        if sem is not None and lut is not None:
            try:
                sem = rc.to_nyu13(sem, lut, str(sems[i]), lut_source)
            except rc.ReplicaClassError as err:
                raise FormatError(str(err)) from None
        inst = read_labels(insts[i]) if i in insts else None
        yield _make_frame(stamps[i], rgb, depth, poses[i], intr, f"{folder} frame {i}",
                          sem, inst)


def _id_list(ids: list[int], most: int = 10) -> str:
    """Frame numbers for a message: the first ``most``, then how many more."""
    head = ", ".join(map(str, ids[:most]))
    return head + (f" and {len(ids) - most} more" if len(ids) > most else "")


def read_labels(path: Path) -> np.ndarray:
    """Label image (8- or 16-bit, single channel) as uint16."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
        raise FormatError(f"{path}: expected a single-channel 8/16-bit label image")
    return img.astype(np.uint16)


def _replica_stamps(folder: Path, n: int, cfg: FolderConfig) -> list[int]:
    f = folder / "timestamps.txt"
    if f.is_file():
        vals = [int(v) for v in f.read_text().split()]
        if len(vals) >= n:
            return vals
        raise FormatError(f"{f}: {len(vals)} stamps for {n} poses")
    period = 1e9 / cfg.fps
    return [cfg.start_stamp_ns + int(round(i * period)) for i in range(n)]


def _read_intrinsics_json(path: Path) -> Intrinsics:
    try:
        d = json.loads(path.read_text())
        return Intrinsics(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]),
                          int(d["width"]), int(d["height"]))
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise FormatError(f"{path}: bad intrinsics file ({err})") from None


def _write_png(path: Path, img: np.ndarray) -> None:
    if not cv2.imwrite(str(path), img):
        raise FormatError(f"{path}: cannot write image")


def write_replica(folder: str | Path, frames: Iterable[Frame], hfov_deg: float = 90.0,
                  overwrite: bool = False) -> int:
    """Write Frames in the Replica layout so :func:`read_replica` gives them back.

    Depth is stored as uint16 millimetres (exact for mm-quantised depth), labels
    as uint16 PNG. Stamps go to ``timestamps.txt``; a camera other than the
    ``hfov_deg`` default goes to ``intrinsics.json``. An existing folder is refused
    without ``overwrite`` and replaced only by a complete one
    (:func:`.folder_common.replacing_output`). Returns the frame count.
    """
    with replacing_output(folder, overwrite, lambda p: (p / "traj_w_c.txt").is_file(),
                          "Replica folder") as target:
        return _write_replica(target, frames, hfov_deg)


def _write_replica(folder: Path, frames: Iterable[Frame], hfov_deg: float) -> int:
    for sub in ("rgb", "depth", "semantic_class", "semantic_instance"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    rows, stamps, cam = [], [], None
    for i, fr in enumerate(frames):
        fr.validate()
        if fr.pose is None:
            raise FormatError(f"frame {fr.stamp_ns} has no pose (estimate poses with "
                              "convert --poses odometry)")
        h, w = fr.depth.shape
        _write_png(folder / "rgb" / f"rgb_{i}.png", fr.rgb[:, :, ::-1])
        d = np.where(np.isfinite(fr.depth) & (fr.depth > 0), np.round(fr.depth * 1000.0), 0)
        if d.max(initial=0) > 65535:
            raise FormatError(f"frame {i}: depth above 65.535 m does not fit uint16 mm")
        _write_png(folder / "depth" / f"depth_{i}.png", d.astype(np.uint16))
        if fr.semantic is not None:
            _write_png(folder / "semantic_class" / f"semantic_class_{i}.png", fr.semantic)
        if fr.instance is not None:
            _write_png(folder / "semantic_instance" / f"semantic_instance_{i}.png",
                       fr.instance)
        rows.append(" ".join(repr(float(v)) for v in fr.pose.reshape(-1)))
        stamps.append(str(int(fr.stamp_ns)))
        if fr.intrinsics != Intrinsics.from_hfov(w, h, hfov_deg):
            if cam is not None and cam != fr.intrinsics:
                raise FormatError(f"frame {i}: intrinsics differ from earlier frames; the "
                                  "Replica layout holds one camera")
            cam = fr.intrinsics
    (folder / "traj_w_c.txt").write_text("\n".join(rows) + "\n")
    (folder / NYU13_MARKER).write_text("semantic_class/ holds NYU-13 ids (neurncd_ros)\n")
    (folder / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    if cam is not None:
        (folder / "intrinsics.json").write_text(json.dumps(dataclasses.asdict(cam)))
    for sub in ("semantic_class", "semantic_instance"):
        if not any((folder / sub).iterdir()):
            (folder / sub).rmdir()
    return len(rows)


# ---------------------------------------------------------------- TUM / NYU raw
