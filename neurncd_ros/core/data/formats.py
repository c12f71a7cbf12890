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
``preset`` fills in the documented defaults of a dataset.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import cv2
import numpy as np

from ..camera import Intrinsics, check_pose, matrix_to_quat, pose_from_tq
from ..frame import Frame
from ..params import build, param
from ..sync import nearest, pose_at

KINDS = ("auto", "replica", "tum", "nyu", "nyu_labelled", "posetxt", "redwood")
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".ppm", ".pgm", ".bmp", ".tif", ".tiff")


class FormatError(ValueError):
    """A dataset folder or file cannot be read; the text names the path."""


# ---------------------------------------------------------------- parameters

@dataclasses.dataclass(frozen=True)
class Preset:
    """Documented depth encoding and camera of one dataset."""

    depth_format: str
    depth_scale: float
    intrinsics: tuple[float, float, float, float] | None  # None: format decides


PRESETS: dict[str, Preset] = {
    "replica": Preset("scale", 1000.0, None),                       # 90 deg HFOV
    "tum": Preset("scale", 5000.0, (517.3, 516.5, 318.6, 255.3)),   # TUM fr1
    "nyu": Preset("nyu_disparity", 1.0, (518.86, 519.47, 325.58, 253.74)),
    "kinect": Preset("scale", 1000.0, (518.0, 519.0, 325.5, 253.5)),  # slambook NYU seq
    "icl": Preset("scale", 5000.0, (481.2, -480.0, 319.5, 239.5)),  # y-up: negative fy
    "redwood": Preset("scale", 1000.0, (525.0, 525.0, 319.5, 239.5)),
    "sun": Preset("sun_rotated", 1000.0, (525.0, 525.0, 319.5, 239.5)),
}
DEFAULT_PRESET = {"replica": "replica", "tum": "tum", "nyu": "nyu", "posetxt": "kinect",
                  "redwood": "redwood"}


@dataclasses.dataclass(frozen=True)
class FolderConfig:
    """How a dataset folder is decoded (0 / empty = the preset's default)."""

    preset: str = param("", "dataset defaults for depth decoding and intrinsics; '' = the "
                        "folder kind's own default", choices=("",) + tuple(PRESETS))
    depth_format: str = param("", "depth decoding: scale = raw / depth_scale, nyu_disparity = "
                              "byte-swapped Kinect disparity, sun_rotated = SUN RGB-D 3-bit "
                              "rotation then / depth_scale; '' = preset",
                              choices=("", "scale", "nyu_disparity", "sun_rotated"))
    depth_scale: float = param(0.0, "raw depth units per metre; 0 = preset (Replica/Redwood/"
                               "NYU-mm 1000, TUM/ICL 5000)", lo=0.0)
    max_depth_m: float = param(0.0, "depths beyond this become 0 (no measurement); 0 = keep "
                               "all (NYU disparity always caps at 10 m)", lo=0.0, unit="m")
    intrinsics: list[float] = param([], "fx, fy, cx, cy in pixels; empty = preset or the "
                                    "folder's own camera file")
    hfov_deg: float = param(90.0, "horizontal field of view of Replica renders",
                            lo=1.0, hi=179.0, unit="deg")
    fps: float = param(30.0, "frame rate used to make stamps for layouts without timestamps",
                       lo=0.001, unit="Hz")
    start_stamp_ns: int = param(1_000_000_000, "stamp of the first frame for layouts without "
                                "timestamps", lo=0, unit="ns")
    max_time_diff_s: float = param(0.02, "TUM association: largest |t_rgb - t_depth| and "
                                   "|t_rgb - t_pose| accepted", lo=0.0, unit="s")
    max_pose_gap_s: float = param(0.0, "TUM: interpolate the pose between trajectory samples "
                                  "at most this far apart; 0 = nearest sample only",
                                  lo=0.0, unit="s")
    stride: int = param(1, "keep every n-th frame", lo=1)
    max_frames: int = param(0, "stop after this many frames; 0 = all", lo=0)


def _resolve(cfg: FolderConfig, kind: str) -> tuple[str, float, tuple | None]:
    """Depth format, scale and intrinsics after applying the preset."""
    preset = PRESETS[cfg.preset or DEFAULT_PRESET[kind]]
    fmt = cfg.depth_format or preset.depth_format
    scale = cfg.depth_scale or preset.depth_scale
    if cfg.intrinsics:
        if len(cfg.intrinsics) != 4:
            raise FormatError(f"intrinsics must be 4 numbers fx, fy, cx, cy, got "
                              f"{list(cfg.intrinsics)}")
        intr = tuple(float(v) for v in cfg.intrinsics)
    else:
        intr = preset.intrinsics
    return fmt, scale, intr


# ---------------------------------------------------------------- image decoding

def read_rgb(path: Path) -> np.ndarray:
    """Colour image file to (H, W, 3) uint8 RGB (OpenCV reads BGR)."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise FormatError(f"{path}: cannot read colour image (missing or not an image)")
    return np.ascontiguousarray(img[:, :, ::-1])


def read_raw16(path: Path) -> np.ndarray:
    """Single-channel 16-bit image file as stored (uint16)."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FormatError(f"{path}: cannot read image (missing or not an image)")
    if img.ndim != 2 or img.dtype != np.uint16:
        raise FormatError(f"{path}: expected a single-channel 16-bit image, got "
                          f"{img.shape} {img.dtype}")
    return img


def nyu_disparity_to_metres(raw: np.ndarray, max_depth_m: float = 10.0) -> np.ndarray:
    """NYUv2 raw Kinect disparity (as OpenCV reads the big-endian PGM) to metres.

    The PGM stores big-endian values that OpenCV returns byte-swapped; 2047 is
    "no measurement". NYU toolbox: depth = 351.3 / (1092.5 - disparity), capped.
    """
    d = raw.astype(np.uint16).byteswap().astype(np.float64)
    with np.errstate(divide="ignore"):
        z = 351.3 / (1092.5 - d)
    bad = (d >= 2047) | ~np.isfinite(z) | (z <= 0) | (z > max_depth_m)
    z[bad] = 0.0
    return z.astype(np.float32)


def sun_rotated_to_raw(raw: np.ndarray) -> np.ndarray:
    """Undo SUN RGB-D's 16-bit storage rotation: d = (d >> 3) | (d << 13)."""
    d = raw.astype(np.uint16)
    return (d >> np.uint16(3)) | (d << np.uint16(13))


def decode_depth(raw: np.ndarray, depth_format: str, depth_scale: float,
                 max_depth_m: float = 0.0) -> np.ndarray:
    """Raw uint16 depth image to float32 metres (0 = no measurement)."""
    if depth_format == "nyu_disparity":
        z = nyu_disparity_to_metres(raw, max_depth_m or 10.0)
    else:
        if depth_format == "sun_rotated":
            raw = sun_rotated_to_raw(raw)
        elif depth_format != "scale":
            raise FormatError(f"unknown depth_format {depth_format!r}")
        if not depth_scale > 0:
            raise FormatError(f"depth_scale must be > 0, got {depth_scale}")
        z = (raw.astype(np.float64) / depth_scale).astype(np.float32)
    if max_depth_m > 0:
        z = np.where(z > max_depth_m, np.float32(0), z)
    return z


def read_depth(path: Path, depth_format: str, depth_scale: float,
               max_depth_m: float = 0.0) -> np.ndarray:
    return decode_depth(read_raw16(path), depth_format, depth_scale, max_depth_m)


def _camera(intr: tuple | None, h: int, w: int, where: Path) -> Intrinsics:
    if intr is None:
        raise FormatError(f"{where}: no intrinsics known; pass intrinsics=[fx, fy, cx, cy]")
    return Intrinsics(intr[0], intr[1], intr[2], intr[3], w, h)


def _make_frame(stamp_ns: int, rgb: np.ndarray, depth: np.ndarray, pose: np.ndarray,
                intr: Intrinsics, where: str, semantic: np.ndarray | None = None,
                instance: np.ndarray | None = None) -> Frame:
    if rgb.shape[:2] != depth.shape:
        raise FormatError(f"{where}: colour is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                          f"{depth.shape[1]}x{depth.shape[0]}")
    try:
        return Frame(int(stamp_ns), rgb, depth, pose, intr, semantic, instance).validate()
    except ValueError as err:
        raise FormatError(f"{where}: {err}") from None


def _subsample(items: list, cfg: FolderConfig) -> list:
    items = items[:: cfg.stride]
    return items[: cfg.max_frames] if cfg.max_frames else items


# ---------------------------------------------------------------- pose files

def _load_rows(path: Path, ncols: Sequence[int]) -> np.ndarray:
    """Numeric rows of a text file, skipping blanks and '#' comments."""
    if not path.is_file():
        raise FormatError(f"{path}: file not found")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            vals = [float(v) for v in line.replace(",", " ").split()]
        except ValueError:
            raise FormatError(f"{path}:{n}: not numbers: {line!r}") from None
        if len(vals) not in ncols:
            raise FormatError(f"{path}:{n}: expected {' or '.join(map(str, ncols))} numbers, "
                              f"got {len(vals)}")
        rows.append(vals)
    if not rows:
        raise FormatError(f"{path}: no poses")
    return np.array(rows, dtype=np.float64)


def _pose(T: np.ndarray, where: str) -> np.ndarray:
    try:
        return check_pose(T, where)
    except ValueError as err:
        raise FormatError(str(err)) from None


def read_tq_poses(path: Path) -> np.ndarray:
    """``tx ty tz qx qy qz qw`` a line (slambook pose.txt) -> (N, 4, 4) T_wc."""
    rows = _load_rows(path, (7,))
    return np.stack([_pose(pose_from_tq(r[:3], r[3:]), f"{path} row {i + 1}")
                     for i, r in enumerate(rows)])


def read_tum_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """TUM ``t tx ty tz qx qy qz qw`` -> (times in s, (N, 4, 4) T_wc), sorted by time."""
    rows = _load_rows(path, (8,))
    rows = rows[np.argsort(rows[:, 0], kind="stable")]
    poses = np.stack([_pose(pose_from_tq(r[1:4], r[4:]), f"{path} t={r[0]:.6f}")
                      for r in rows])
    return rows[:, 0], poses


def read_matrix_rows(path: Path) -> np.ndarray:
    """Replica ``traj_w_c.txt``: 16 numbers (row-major 4x4) a line -> (N, 4, 4)."""
    rows = _load_rows(path, (16,))
    return np.stack([_pose(r.reshape(4, 4), f"{path} row {i + 1}")
                     for i, r in enumerate(rows)])


def read_redwood_log(path: Path) -> dict[int, np.ndarray]:
    """Open3D/Redwood ``.log``: a header ``i j n`` then 4 rows of T_wc, per frame."""
    if not path.is_file():
        raise FormatError(f"{path}: file not found")
    lines = [ln.split() for ln in path.read_text().splitlines() if ln.strip()]
    if len(lines) % 5:
        raise FormatError(f"{path}: {len(lines)} non-empty lines, expected 5 per frame "
                          "(header + 4 matrix rows)")
    out = {}
    for k in range(0, len(lines), 5):
        try:
            idx = int(lines[k][0])
            T = np.array([[float(v) for v in row] for row in lines[k + 1:k + 5]])
        except (ValueError, IndexError):
            raise FormatError(f"{path}: malformed block at line {k + 1}") from None
        if T.shape != (4, 4):
            raise FormatError(f"{path}: block at line {k + 1} is not 4x4")
        out[idx] = _pose(T, f"{path} frame {idx}")
    return out


def read_redwood_intrinsics(path: Path) -> Intrinsics:
    """Open3D camera json (``intrinsic_matrix`` column-major, width, height)."""
    try:
        d = json.loads(path.read_text())
        K = np.asarray(d["intrinsic_matrix"], dtype=np.float64).reshape(3, 3).T
        return Intrinsics.from_matrix(K, int(d["width"]), int(d["height"]))
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise FormatError(f"{path}: not an Open3D camera json ({err})") from None


# ---------------------------------------------------------------- Replica

_NUM_RE = re.compile(r"(\d+)(?=\.[^.]+$)")


def _indexed(folder: Path, prefix: str) -> dict[int, Path]:
    """Files ``{prefix}{i}.ext`` in ``folder`` keyed by i."""
    out = {}
    if folder.is_dir():
        for p in folder.iterdir():
            if p.name.startswith(prefix) and p.suffix.lower() in IMAGE_EXTS:
                m = _NUM_RE.search(p.name[len(prefix):])
                if m and p.name[len(prefix):].startswith(m.group(1)):
                    out[int(m.group(1))] = p
    return out


def _as_lookup(id_map: Any) -> np.ndarray | None:
    """Class-id map (dict, JSON file of a dict, or array: source id -> target id) as a LUT."""
    if id_map is None:
        return None
    if isinstance(id_map, (str, Path)):
        try:
            id_map = json.loads(Path(id_map).read_text())
        except (OSError, ValueError) as err:
            raise FormatError(f"{id_map}: id map must be a JSON object of source id -> "
                              f"target id ({err})") from None
        if not isinstance(id_map, dict):
            raise FormatError("id map file must hold a JSON object of source id -> target id")
    if isinstance(id_map, dict):
        lut = np.zeros(65536, dtype=np.uint16)
        for k, v in id_map.items():
            lut[int(k)] = int(v)
        return lut
    arr = np.asarray(id_map)
    if arr.ndim != 1 or arr.size == 0 or arr.min() < 0 or arr.max() > 65535:
        raise FormatError("id_map must be a dict or a 1-D array of ids in 0..65535")
    lut = np.zeros(65536, dtype=np.uint16)
    lut[: arr.size] = arr.astype(np.uint16)
    return lut


NYU13_MARKER = "semantic_nyu13.txt"
"""Written by :func:`write_replica`: its ``semantic_class/`` images already hold NYU-13 ids."""


def _replica_lookup(folder: Path, id_map: Any, semantic_ids: str,
                    class_info: str | Path | None) -> np.ndarray | None:
    """How a Replica folder's ``semantic_class`` ids become NYU-13 (None: they already are)."""
    from . import replica_classes as rc

    if semantic_ids not in ("auto", "nyu13", "replica"):
        raise FormatError(f"semantic_ids must be auto, nyu13 or replica, got {semantic_ids!r}")
    if id_map is not None:
        return _as_lookup(id_map)
    if semantic_ids == "nyu13" or (semantic_ids == "auto" and (folder / NYU13_MARKER).is_file()):
        return None
    info = Path(class_info) if class_info else rc.find_class_info(folder)
    if info is None:
        raise FormatError(f"{folder}: semantic_class/ holds Replica class ids, but no "
                          "info_semantic.json was found beside it or in semantic_info/<scene>/ "
                          "above it; pass class_info=<path to the scene's info_semantic.json>, "
                          "or semantic_ids=nyu13 if the images already hold NYU-13 ids")
    try:
        return rc.lookup_table(info)
    except rc.ReplicaClassError as err:
        raise FormatError(str(err)) from None


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
    lut = _replica_lookup(folder, id_map, semantic_ids, class_info) if sems else None
    for i in _subsample(sorted(rgbs), cfg):
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
                sem = rc.to_nyu13(sem, lut, str(sems[i]))
            except rc.ReplicaClassError as err:
                raise FormatError(str(err)) from None
        inst = read_labels(insts[i]) if i in insts else None
        yield _make_frame(stamps[i], rgb, depth, poses[i], intr, f"{folder} frame {i}",
                          sem, inst)


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


def write_replica(folder: str | Path, frames: Iterable[Frame], hfov_deg: float = 90.0) -> int:
    """Write Frames in the Replica layout so :func:`read_replica` gives them back.

    Depth is stored as uint16 millimetres (exact for mm-quantised depth), labels
    as uint16 PNG. Stamps go to ``timestamps.txt``; a camera other than the
    ``hfov_deg`` default goes to ``intrinsics.json``. Returns the frame count.
    """
    folder = Path(folder)
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

_STAMP_RE = re.compile(r"(\d+(?:\.\d+)?)")


def _stamp_of(name: str) -> int | None:
    """Timestamp (ns) in a file name: ``1305031102.175304.png`` or NYU ``d-1294439283.37-..``."""
    m = _STAMP_RE.search(name)
    return seconds_to_ns(m.group(1)) if m else None


def seconds_to_ns(text: str) -> int:
    """Decimal seconds text ('1305031102.175304') to integer ns without float rounding."""
    whole, _, frac = text.strip().partition(".")
    if not whole.isdigit() or (frac and not frac.isdigit()):
        raise ValueError(f"not a timestamp in seconds: {text!r}")
    return int(whole) * 1_000_000_000 + int((frac + "000000000")[:9])


def _tum_list(folder: Path, list_name: str, sub: str, prefixes: tuple[str, ...]
              ) -> list[tuple[int, Path]]:
    """(time s, file) from a TUM list file, or from timestamp-named files in ``sub``."""
    lst = folder / list_name
    out = []
    if lst.is_file():
        for n, line in enumerate(lst.read_text().splitlines(), 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            parts = line.split()
            try:
                out.append((seconds_to_ns(parts[0]), folder / parts[1]))
            except (ValueError, IndexError):
                raise FormatError(f"{lst}:{n}: expected 'timestamp filename'") from None
    else:
        d = folder / sub
        if d.is_dir():
            for p in d.iterdir():
                if p.suffix.lower() in IMAGE_EXTS and (not prefixes or
                                                       p.name.startswith(prefixes)):
                    t = _stamp_of(p.name)
                    if t is not None:
                        out.append((t, p))
        if not out:
            # NYU raw: r-*.ppm and d-*.pgm side by side in the scene folder.
            for p in folder.iterdir():
                if p.suffix.lower() in IMAGE_EXTS and p.name.startswith(prefixes or ("",)):
                    t = _stamp_of(p.name[2:] if prefixes else p.name)
                    if t is not None:
                        out.append((t, p))
    out.sort(key=lambda x: x[0])
    return out


def read_tum(folder: str | Path, cfg: FolderConfig = FolderConfig(),
             trajectory: str | Path | None = None, with_poses: bool = True,
             kind: str = "tum") -> Iterator[Frame]:
    """TUM RGB-D style folder -> Frames, associating depth and pose by nearest time.

    Colour frames with no depth or pose within ``max_time_diff_s`` are skipped.
    ``with_poses=False`` reads no trajectory and yields frames with pose None
    (for the odometry: NYUv2 raw sequences have no poses).
    """
    folder = Path(folder)
    fmt, scale, intr_vals = _resolve(cfg, kind)
    nyu = fmt == "nyu_disparity"
    rgbs = _tum_list(folder, "rgb.txt", "rgb", ("r-",) if nyu else ())
    depths = _tum_list(folder, "depth.txt", "depth", ("d-",) if nyu else ())
    if not rgbs or not depths:
        raise FormatError(f"{folder}: no colour/depth images found (rgb.txt + depth.txt, "
                          "timestamp-named files in rgb/ and depth/, or NYUv2 r-*.ppm and "
                          "d-*.pgm)")
    dtimes = np.array([t for t, _ in depths], dtype=np.int64)
    tol = int(round(cfg.max_time_diff_s * 1e9))
    gap = int(round(cfg.max_pose_gap_s * 1e9))
    if with_poses:
        traj = Path(trajectory) if trajectory else folder / "groundtruth.txt"
        if not traj.is_file():
            raise FormatError(f"{traj}: file not found; a sequence without poses needs "
                              "poses estimated from its images (convert --poses odometry)")
        ptimes, poses = read_tum_trajectory(traj)
        ptimes_ns = np.round(ptimes * 1e9).astype(np.int64)
    pairs = []
    for t, rp in rgbs:
        kd, ed = nearest(dtimes, t)
        pose = None
        if with_poses:
            try:
                pose = pose_at(ptimes_ns, list(poses), t, tol, gap)
            except LookupError:
                continue
        if ed <= tol:
            pairs.append((t, rp, depths[kd][1], pose))
    if not pairs:
        raise FormatError(f"{folder}: no colour frame has depth" +
                          (" and pose" if with_poses else "") +
                          f" within {cfg.max_time_diff_s} s")
    for t, rp, dp, pose in _subsample(pairs, cfg):
        rgb = read_rgb(rp)
        depth = read_depth(dp, fmt, scale, cfg.max_depth_m)
        intr = _camera(intr_vals, *depth.shape, folder)
        yield _make_frame(t, rgb, depth, pose, intr, str(rp))


def write_tum(folder: str | Path, frames: Iterable[Frame], depth_scale: float = 5000.0
              ) -> int:
    """Write Frames as a TUM RGB-D folder (rgb/, depth/, lists, groundtruth.txt)."""
    folder = Path(folder)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    rgb_l, dep_l, gt_l = [], [], []
    for fr in frames:
        fr.validate()
        if fr.pose is None:
            raise FormatError(f"frame {fr.stamp_ns} has no pose (estimate poses with "
                              "convert --poses odometry)")
        t = f"{fr.stamp_ns // 1_000_000_000}.{fr.stamp_ns % 1_000_000_000:09d}"
        _write_png(folder / "rgb" / f"{t}.png", fr.rgb[:, :, ::-1])
        d = np.where(np.isfinite(fr.depth) & (fr.depth > 0), np.round(fr.depth * depth_scale),
                     0)
        if d.max(initial=0) > 65535:
            raise FormatError(f"stamp {fr.stamp_ns}: depth does not fit uint16 at scale "
                              f"{depth_scale}")
        _write_png(folder / "depth" / f"{t}.png", d.astype(np.uint16))
        rgb_l.append(f"{t} rgb/{t}.png")
        dep_l.append(f"{t} depth/{t}.png")
        q = matrix_to_quat(fr.pose[:3, :3])
        gt_l.append(" ".join([t] + [repr(float(v)) for v in (*fr.pose[:3, 3], *q)]))
    for name, lines in (("rgb.txt", rgb_l), ("depth.txt", dep_l), ("groundtruth.txt", gt_l)):
        (folder / name).write_text("# timestamp data\n" + "\n".join(lines) + "\n")
    return len(rgb_l)


# ---------------------------------------------------------------- pose.txt, Redwood

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
    for i in _subsample(list(range(n)), cfg):
        rgb = read_rgb(colors[i])
        depth = read_depth(depths[i], fmt, scale, cfg.max_depth_m)
        intr = _camera(intr_vals, *depth.shape, folder)
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
    for i in _subsample(list(range(len(pairs))), cfg):
        if i not in traj:
            raise FormatError(f"{folder}/trajectory.log has no pose for frame {i}")
        cp, dp = pairs[i]
        rgb = read_rgb(cp)
        depth = read_depth(dp, fmt, scale, cfg.max_depth_m)
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

def detect_kind(folder: str | Path) -> str:
    """Which folder layout ``folder`` holds (replica, tum, posetxt, redwood)."""
    f = Path(folder)
    if not f.is_dir():
        raise FormatError(f"{f}: not a folder")
    if (f / "traj_w_c.txt").is_file() and (f / "rgb").is_dir():
        return "replica"
    if (f / "trajectory.log").is_file():
        return "redwood"
    if (f / "pose.txt").is_file() and (f / "color").is_dir():
        return "posetxt"
    if (f / "groundtruth.txt").is_file() or (f / "rgb.txt").is_file():
        return "tum"
    if any(f.glob("r-*.ppm")) and any(f.glob("d-*.pgm")):
        return "nyu"
    raise FormatError(f"{f}: unknown layout (expected traj_w_c.txt + rgb/ (replica), "
                      "trajectory.log (redwood), pose.txt + color/ (posetxt), "
                      "groundtruth.txt / rgb.txt (tum), or r-*.ppm + d-*.pgm (NYUv2 raw))")


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
    cfg = build(FolderConfig, opts)
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


def convert(src: str | Path, out: str | Path, kind: str = "auto", storage: str = "mcap",
            tf_parent: str | None = None, tf_child: str | None = None,
            to: str = "bag", progress: bool = False, poses: str = "source",
            odometry: Any = None, report: dict | None = None, **opts: Any) -> int:
    """Convert a dataset folder or a bag into a bag (or a Replica / TUM folder).

    A bag source may carry its pose on /tf (give ``tf_parent``/``tf_child``).
    ``poses="odometry"`` ignores the source's poses (it need have none) and
    writes poses estimated from the images (``odometry``: an OdometryConfig);
    frames where tracking is lost are left out and counted in ``report``
    (a dict that receives ``frames_in``, ``lost``, ``segments``, ``relocalised``).
    ``opts`` go to :func:`read_folder` (folder sources) or the bag writer's
    encoding choices (``depth_encoding``, ``color_encoding``). Returns frames written.
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
            raise FormatError(f"options {sorted(opts)} apply to folders, not to bag {src}")
        frames: Iterable[Frame] = bagio.FrameReader(src, tf_parent=tf_parent,
                                                    tf_child=tf_child,
                                                    with_poses=not estimate)
    else:
        if estimate and (kind == "nyu_labelled" or Path(src).suffix.lower() == ".mat"):
            raise FormatError(f"{src}: the labelled frames are single views of many scenes; "
                              "odometry needs a sequence (convert the raw sequence instead)")
        frames = read_folder(src, kind, with_poses=not estimate, **opts)
    results: list = []
    if estimate:
        from ..odometry import with_odometry
        frames = with_odometry(frames, odometry, results)
    if to == "bag":
        n = bagio.write_bag(out, frames, storage=storage, progress=progress, **writer_opts)
    elif to == "replica":
        n = write_replica(out, frames)
    else:
        n = write_tum(out, frames)
    if report is not None and estimate:
        report.update({"frames_in": len(results),
                       "lost": sum(r.status == "lost" for r in results),
                       "relocalised": sum(r.status == "relocalised" for r in results),
                       "segments": 1 + sum(r.status == "new_segment" for r in results)})
    return n
