"""Real RGB-D dataset readers and writers that yield / take :class:`Frame`.

Folder layouts understood by :func:`read_folder`:

- ``replica``: Semantic-NeRF's Replica layout (``rgb/rgb_{i}.png``,
  ``depth/depth_{i}.png`` uint16 mm, ``semantic_class/semantic_class_{i}.png``,
  optional ``semantic_instance/``, ``traj_w_c.txt`` 16 numbers a row, 90 deg HFOV);
  :func:`write_replica` writes it back exactly (plus optional ``timestamps.txt``
  and ``intrinsics.json`` sidecars so stamps and non-default cameras survive);
- ``tum``: TUM RGB-D folders (``rgb.txt``/``depth.txt`` or timestamp-named
  files in ``rgb/`` and ``depth/``, ``groundtruth.txt`` with ``t tx ty tz qx qy
  qz qw``), associated by nearest timestamp; also NYUv2 raw sequences
  (``preset="nyu"``: byte-swapped Kinect disparity);
- ``posetxt``: ``color/{i}``, ``depth/{i}`` and ``pose.txt`` (``tx ty tz qx qy
  qz qw`` a line), e.g. slambook's NYU dining room and ICL-NUIM (``preset="icl"``);
- ``redwood``: ``color/``, ``depth/``, ``trajectory.log`` (Open3D log) and
  ``camera_primesense.json`` (column-major K).
- ``nyu``: a NYUv2 raw scene folder (``r-*.ppm``, ``d-*.pgm``, no poses: read
  with ``with_poses=False`` for the odometry; ``labelled=`` attaches the
  labelled frames taken from it);
- ``nyu_labelled``: NYUv2's labelled ``.mat`` (:mod:`.nyu`).

Replica ``semantic_class/`` ids become NYU-13 through :mod:`.replica_classes`.

Depth decoding, scales and intrinsics are parameters (:class:`FolderConfig`);
``preset`` fills in the documented defaults of a dataset. A folder read with its
kind's default scale whose first depth image is no indoor scene at that scale but
is one at another common scale (ICL-NUIM's 1/5000 m in the slambook layout reads
as a 15 m room in millimetres) is refused with the option to set
(:class:`DepthScaleCheck`). Frames always carry an OpenCV camera (fx, fy > 0): a
dataset's negative focal length (ICL-NUIM's fy = -480, a y-up camera) becomes a
positive one with the pose converted to match (:func:`opencv_axes`).

The readers live in one module per family (:mod:`.folder_common`, :mod:`.replica`,
:mod:`.tum`; posetxt, redwood, NYU and the dispatch here); every name stays
importable from this module.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Iterator, Sequence

import numpy as np

from ..frame import Frame
from ..params import ConfigError, build
from ..topics import Topics

if TYPE_CHECKING:  # the bag module (rosbags) is imported when a bag is converted
    from .bag import SyncConfig


# Every name of the family modules is re-exported: callers import them from formats.
from .folder_common import (KINDS, IMAGE_EXTS, FormatError, Preset, PRESETS,  # noqa: F401
                            detect_kind,  # noqa: F401
                            DEFAULT_PRESET, FolderConfig, _resolve, read_rgb,  # noqa: F401
                            read_raw16, nyu_disparity_to_metres, sun_rotated_to_raw,  # noqa: F401
                            decode_depth, read_depth, _camera, camera_preset,  # noqa: F401
                            _make_frame,  # noqa: F401
                            _subsample, _load_rows, _pose, read_tq_poses,  # noqa: F401
                            read_tum_trajectory, read_matrix_rows, read_redwood_log,  # noqa: F401
                            read_redwood_intrinsics, _NUM_RE, _indexed,  # noqa: F401
                            DepthScaleCheck, opencv_axes)  # noqa: F401
from .replica import (NYU13_MARKER, _replica_lookup, read_replica,  # noqa: F401
                      read_labels, _replica_stamps, _read_intrinsics_json,  # noqa: F401
                      _write_png, write_replica)  # noqa: F401
from .tum import (_STAMP_RE, _stamp_of, seconds_to_ns, _tum_list, read_tum,  # noqa: F401
                  write_tum)  # noqa: F401


def _numbered(folder: Path) -> list[Path]:
    """Image files sorted by the number in their name (1.png < 2.png < 10.png)."""
    files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS] \
        if folder.is_dir() else []
    keyed = []
    for p in files:
        m = re.search(r"(\d+)", p.stem)
        keyed.append((int(m.group(1)) if m else -1, p.name, p))
    return [p for _, _, p in sorted(keyed)]


def _stamp(i: int, cfg: FolderConfig) -> int:
    return cfg.start_stamp_ns + int(round(i * 1e9 / cfg.fps))


def read_posetxt(folder: str | Path, cfg: FolderConfig = FolderConfig()) -> Iterator[Frame]:
    """``color/``, ``depth/``, ``pose.txt`` (slambook layout) -> Frames in file order."""
    folder = Path(folder)
    fmt, scale, intr_vals = _resolve(cfg, "posetxt")
    colors, depths = _numbered(folder / "color"), _numbered(folder / "depth")
    poses = read_tq_poses(folder / "pose.txt")
    n = len(colors)
    if n == 0 or len(depths) != n or len(poses) < n:
        raise FormatError(f"{folder}: {n} colour, {len(depths)} depth images and "
                          f"{len(poses)} poses; need equal non-zero counts")
    check = DepthScaleCheck(cfg, "posetxt", folder)
    for i in _subsample(list(range(n)), cfg):
        rgb = read_rgb(colors[i])
        depth = read_depth(depths[i], fmt, scale, cfg.max_depth_m)
        check(depth, depths[i])
        intr = _camera(intr_vals, *depth.shape, folder, camera_preset(cfg, "posetxt"))
        yield _make_frame(_stamp(i, cfg), rgb, depth, poses[i], intr, str(colors[i]))


def read_redwood(folder: str | Path, cfg: FolderConfig = FolderConfig()) -> Iterator[Frame]:
    """Redwood/Open3D RGB-D folder with ``trajectory.log`` -> Frames."""
    folder = Path(folder)
    fmt, scale, intr_vals = _resolve(cfg, "redwood")
    cams = sorted(folder.glob("camera*.json"))
    cam = read_redwood_intrinsics(cams[0]) if cams and not cfg.intrinsics else None
    match = folder / "rgbd.match"
    if match.is_file():
        pairs = []
        for line in match.read_text().splitlines():
            parts = line.split()
            if len(parts) >= 2:
                pairs.append((folder / parts[1], folder / parts[0]))  # (colour, depth)
    else:
        colors, depths = _numbered(folder / "color"), _numbered(folder / "depth")
        if len(colors) != len(depths):
            raise FormatError(f"{folder}: {len(colors)} colour but {len(depths)} depth images")
        pairs = list(zip(colors, depths))
    if not pairs:
        raise FormatError(f"{folder}: no colour/depth pairs")
    traj = read_redwood_log(folder / "trajectory.log")
    check = DepthScaleCheck(cfg, "redwood", folder)
    for i in _subsample(list(range(len(pairs))), cfg):
        if i not in traj:
            raise FormatError(f"{folder}/trajectory.log has no pose for frame {i}")
        cp, dp = pairs[i]
        rgb = read_rgb(cp)
        depth = read_depth(dp, fmt, scale, cfg.max_depth_m)
        check(depth, dp)
        if cam is None:
            intr = _camera(intr_vals, *depth.shape, folder)
        else:
            intr = cam if cam.shape == depth.shape else cam.scaled(depth.shape[1],
                                                                   depth.shape[0])
        yield _make_frame(_stamp(i, cfg), rgb, depth, traj[i], intr, str(cp))


# ---------------------------------------------------------------- single frames

def read_single(color: str | Path, depth: str | Path, preset: str = "tum",
                intrinsics: Sequence[float] | None = None, stamp_ns: int = 0,
                pose: np.ndarray | None = None) -> Frame:
    """One colour + depth file pair decoded with a dataset preset (identity pose)."""
    if preset not in PRESETS:
        raise FormatError(f"unknown preset {preset!r}; known: {', '.join(PRESETS)}")
    p = PRESETS[preset]
    rgb = read_rgb(Path(color))
    d = read_depth(Path(depth), p.depth_format, p.depth_scale)
    vals = tuple(intrinsics) if intrinsics is not None else p.intrinsics
    intr = _camera(vals, *d.shape, Path(depth))
    return _make_frame(stamp_ns, rgb, d, np.eye(4) if pose is None else pose, intr,
                       str(color))


# ---------------------------------------------------------------- dispatch

READER_OPTIONS = ("id_map, class_info, semantic_ids (Replica), labelled, class_mapping "
                  "(NYUv2 raw sequence or labelled .mat), trajectory (TUM)")
"""The options :func:`read_folder` takes beside the :class:`FolderConfig` fields."""
READER_NAMES = frozenset({"id_map", "class_info", "semantic_ids", "labelled", "class_mapping",
                          "trajectory"})


def read_folder(path: str | Path, kind: str = "auto", id_map: Any = None,
                trajectory: str | Path | None = None, with_poses: bool = True,
                labelled: str | Path | None = None, class_mapping: str | Path | None = None,
                semantic_ids: str = "auto", class_info: str | Path | None = None,
                **opts: Any) -> Iterator[Frame]:
    """Frames of a dataset folder; ``opts`` are :class:`FolderConfig` fields.

    ``id_map`` remaps Replica semantic ids; ``trajectory`` overrides the TUM
    pose file; ``with_poses=False`` lets TUM-style folders without a trajectory
    (NYUv2 raw, kind "nyu", never has one) yield frames with pose None, for the
    odometry. ``nyu_labelled`` (a ``.mat`` file, detected by its suffix) reads
    NYUv2's labelled set (:mod:`.nyu`; ``class_mapping`` = classMapping40.mat if
    not beside it); ``labelled`` attaches to a NYUv2 raw sequence the labelled
    frames taken from it. Unknown options raise ConfigError (a ValueError) naming them.
    """
    if kind not in KINDS:
        raise FormatError(f"unknown folder kind {kind!r}; known: {', '.join(KINDS)}")
    try:
        cfg = build(FolderConfig, opts)
    except ConfigError as err:
        raise ConfigError(f"{err}; or a reader's own option: {READER_OPTIONS}") from None
    path = Path(path)
    if not path.exists():
        raise FormatError(f"{path}: no such file or folder")
    if kind == "nyu_labelled" or (kind == "auto" and path.is_file() and
                                  path.suffix.lower() == ".mat"):
        from .nyu import read_labelled
        return read_labelled(path, class_mapping, stride=cfg.stride,
                             max_frames=cfg.max_frames, fps=cfg.fps,
                             start_stamp_ns=cfg.start_stamp_ns)
    kind = detect_kind(path) if kind == "auto" else kind
    if labelled is not None:
        if kind != "nyu":
            raise FormatError(f"{path}: labelled applies to NYUv2 raw sequences, this is "
                              f"{kind!r}")
        from .nyu import raw_labels
        labels = raw_labels(labelled, class_mapping)
        frames = read_tum(path, cfg, trajectory, with_poses, kind="nyu")
        return _attach_nyu_labels(frames, labels, path)
    if id_map is not None and kind != "replica":
        raise FormatError(f"{path}: id_map applies to Replica folders, this is {kind!r}")
    if trajectory is not None and kind not in ("tum", "nyu"):
        raise FormatError(f"{path}: trajectory applies to TUM folders, this is {kind!r}")
    if kind == "nyu":
        if with_poses and trajectory is None:
            raise FormatError(f"{path}: a NYUv2 raw sequence has no camera poses; estimate "
                              "them from its images (convert --poses odometry)")
        return read_tum(path, cfg, trajectory, with_poses, kind="nyu")
    if kind == "replica":
        return read_replica(path, cfg, id_map, semantic_ids, class_info)
    if kind == "tum":
        return read_tum(path, cfg, trajectory, with_poses)
    if kind == "posetxt":
        return read_posetxt(path, cfg)
    return read_redwood(path, cfg)


def _attach_nyu_labels(frames: Iterator[Frame], labels: dict[str, np.ndarray], where: Path
                       ) -> Iterator[Frame]:
    """Give each raw frame whose colour file is in the labelled set that frame's labels.

    Raw NYUv2 files are named by their stamp (``r-<seconds>-<n>.ppm``), so the
    labelled frames are matched to raw frames by stamp."""
    import dataclasses as dc

    by_stamp = {}
    for name, sem in labels.items():
        t = _stamp_of(name[2:]) if name.startswith("r-") else None
        if t is not None:
            by_stamp[t] = sem
    have = {t for t, _ in _tum_list(where, "rgb.txt", "rgb", ("r-",))}
    if not have & set(by_stamp):
        raise FormatError(f"{where}: none of its colour files is in the labelled set")
    for fr in frames:
        sem = by_stamp.get(fr.stamp_ns)
        if sem is not None:
            if sem.shape != fr.depth.shape:
                raise FormatError(f"{where}: labelled frame at stamp {fr.stamp_ns} is "
                                  f"{sem.shape[1]}x{sem.shape[0]}, the raw frame "
                                  f"{fr.depth.shape[1]}x{fr.depth.shape[0]}")
            fr = dc.replace(fr, semantic=sem)
        yield fr


def is_bag(path: str | Path) -> bool:
    """A rosbag2 folder (metadata.yaml) or a raw .mcap / .db3 file."""
    p = Path(path)
    return (p.is_dir() and (p / "metadata.yaml").is_file()) or \
        (p.is_file() and p.suffix in (".mcap", ".db3"))


def bag_sync(sync: SyncConfig | None, tf_parent: str | None, tf_child: str | None
             ) -> SyncConfig:
    """How a bag source is read: ``sync`` (the configuration's ``sync.*``, default the
    parameters' defaults) with the /tf pose frames given here (``convert --tf-parent``,
    ``--tf-child``) in place of its own, each one that is given."""
    from .bag import SyncConfig

    frames = {k: v for k, v in (("tf_parent", tf_parent), ("tf_child", tf_child)) if v}
    return dataclasses.replace(sync if sync is not None else SyncConfig(), **frames)


def convert(src: str | Path, out: str | Path, kind: str = "auto", storage: str | None = None,
            tf_parent: str | None = None, tf_child: str | None = None,
            to: str = "bag", progress: bool = False, poses: str = "source",
            odometry: Any = None, report: dict | None = None, overwrite: bool = False,
            topics: Topics = Topics(), sync: SyncConfig | None = None,
            **opts: Any) -> int:
    """Convert a dataset folder or a bag into a bag (or a Replica / TUM folder).

    A bag source is read as ``neurncd info`` and ``run`` read one
    (:meth:`FrameReader.from_config`): its topics are ``topics`` (the configuration's
    ``topics.*``, e.g. a RealSense's /camera/camera/color/image_raw), its
    synchronisation ``sync`` (``sync.*``); it may carry its pose on /tf (give
    ``tf_parent``/``tf_child``, which replace ``sync``'s). The output bag always has
    the topic contract's default names (``Topics()``): converting is how a bag with
    other names becomes one the tools and nodes read without ``topics.*`` overrides.
    ``poses="odometry"`` ignores the source's poses (it need have none) and
    writes poses estimated from the images (``odometry``: an OdometryConfig);
    frames where tracking is lost are left out and counted in ``report``
    (a dict that receives ``frames_in``, ``lost``, ``segments``, ``relocalised``).
    ``opts`` go to :func:`read_folder` (folder sources) or the bag writer's
    encoding choices (``depth_encoding``, ``color_encoding``); ``overwrite`` replaces
    an existing output bag. Returns frames written.
    """
    from . import bag as bagio

    if poses not in ("source", "odometry"):
        raise FormatError(f"poses must be 'source' or 'odometry', got {poses!r}")
    if to not in ("bag", "replica", "tum"):
        raise FormatError(f"unknown output kind {to!r}; known: bag, replica, tum")
    estimate = poses == "odometry"
    writer_opts = {k: opts.pop(k) for k in ("depth_encoding", "color_encoding") if k in opts}
    if is_bag(src):
        if opts:
            known = {f.name for f in dataclasses.fields(FolderConfig)} | READER_NAMES
            unknown = sorted(set(opts) - known)
            if unknown:
                raise ConfigError(f"{', '.join(unknown)}: unknown option; the options are "
                                  f"the convert.* parameters or a reader's own: "
                                  f"{READER_OPTIONS}")
            raise FormatError(f"options {sorted(opts)} apply to folders, not to bag {src}")
        reader = bagio.FrameReader.from_config(
            src, topics, bag_sync(sync, tf_parent, tf_child), with_poses=not estimate)
        if not len(reader):  # no empty bag written with exit 0: say why nothing is left
            raise FormatError(f"no frames to convert: {reader.summary()}")
        frames: Iterable[Frame] = reader
    else:
        if tf_parent or tf_child:
            raise FormatError(f"{src} is a dataset folder: --tf-parent / --tf-child apply "
                              "to a bag's /tf (a folder's poses come from its trajectory "
                              "file)")
        if estimate and (kind == "nyu_labelled" or Path(src).suffix.lower() == ".mat"):
            raise FormatError(f"{src}: the labelled frames are single views of many scenes; "
                              "odometry needs a sequence (convert the raw sequence instead)")
        frames = read_folder(src, kind, with_poses=not estimate, **opts)
    results: list = []
    if estimate:
        from ..odometry import with_odometry
        frames = with_odometry(frames, odometry, results)
    if to == "bag":
        n = bagio.write_bag(out, frames, storage=storage, progress=progress,
                            topics=Topics(), overwrite=overwrite, **writer_opts)
    elif to == "replica":
        n = write_replica(out, frames, overwrite=overwrite)
    else:
        n = write_tum(out, frames, overwrite=overwrite)
    if report is not None and estimate:
        report.update({"frames_in": len(results),
                       "lost": sum(r.status == "lost" for r in results),
                       "relocalised": sum(r.status == "relocalised" for r in results),
                       "segments": 1 + sum(r.status == "new_segment" for r in results)})
    return n
