"""What every folder reader shares: kinds, presets, FolderConfig, image/depth
decoding, trajectory files. Split out of :mod:`.formats` (whose docstring lists
the layouts); import from there."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import shutil
import warnings
from pathlib import Path
from typing import Callable, Iterator, Sequence

import cv2
import numpy as np

from ..camera import Intrinsics, check_pose, pose_from_tq
from ..frame import Frame
from ..params import param


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
    # ICL-NUIM documents fy = -480 (its camera and world frames are y-up, left-handed):
    # the readers turn it into an OpenCV camera (:func:`opencv_axes`).
    "icl": Preset("scale", 5000.0, (481.2, -480.0, 319.5, 239.5)),
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
    """A depth image file in metres: its raw 16-bit values through :func:`decode_depth`."""
    return decode_depth(read_raw16(path), depth_format, depth_scale, max_depth_m)


# Median depth of an indoor RGB-D frame, metres: outside this a depth scale is suspect.
PLAUSIBLE_MEDIAN_DEPTH_M = (0.3, 8.0)
# Depth units per metre of the common datasets, and who uses them.
COMMON_DEPTH_SCALES = {1000.0: "millimetres: Kinect/NYU, Redwood, Replica",
                       5000.0: "1/5000 m: TUM RGB-D, ICL-NUIM"}


def measured_depth(depth: np.ndarray) -> tuple[float | None, float]:
    """(median of the measured depths, None if there is none; the share of pixels
    measured): what tells whether a depth scale makes an indoor scene
    (:data:`PLAUSIBLE_MEDIAN_DEPTH_M`)."""
    valid = depth[np.isfinite(depth) & (depth > 0)]
    return (float(np.median(valid)) if valid.size else None), valid.size / depth.size


class DepthScaleCheck:
    """Refuses a folder whose depth, decoded with the folder kind's default scale, is
    not an indoor scene while another common scale makes it one.

    A folder in a shared layout does not say its depth unit: slambook's ``color/``,
    ``depth/``, ``pose.txt`` layout holds NYU's millimetres (the default) as well as
    ICL-NUIM's 1/5000 m, which read as millimetres gives a 15 m living room and
    wrong geometry throughout. The check runs on the first frame with depth; it is
    skipped when the user chose the decoding (``preset``, ``depth_scale`` or
    ``depth_format``), so a choice is never second-guessed."""

    def __init__(self, cfg: "FolderConfig", kind: str, folder: Path) -> None:
        preset = PRESETS[DEFAULT_PRESET[kind]]
        self.scale = preset.depth_scale
        self.preset_name = DEFAULT_PRESET[kind]
        self.kind, self.folder = kind, folder
        self.active = (not cfg.preset and not cfg.depth_scale and
                       cfg.depth_format in ("", "scale") and preset.depth_format == "scale")

    def __call__(self, depth: np.ndarray, where: Path) -> None:
        """Check one decoded depth image (metres) until a frame with depth is seen."""
        if not self.active:
            return
        med, share = measured_depth(depth)
        if share < 0.05:
            return  # too little depth to judge: try the next frame
        self.active = False
        lo, hi = PLAUSIBLE_MEDIAN_DEPTH_M
        if lo <= med <= hi:
            return
        raw = read_raw16(where)
        measured = raw[raw > 0]
        if measured.size and np.mean(measured % 8 == 0) > 0.9:
            # SUN RGB-D's rotated storage (a value's low 3 bits are its top 3, 0 below
            # 8.2 m: nearly all multiples of 8, against an eighth of other data's): at
            # 1/5000 m it also looks indoor, and the ICL advice gave 4.3 m for a 2.7 m room.
            sun, _ = measured_depth(decode_depth(raw, "sun_rotated", 1000.0))
            if sun is not None and lo <= sun <= hi:
                raise FormatError(
                    f"{self.folder}: the depth of {where.name} read with the default scale "
                    f"of a {self.kind} folder has a median of {med:.1f} m, not an indoor "
                    f"scene ({lo:g}-{hi:g} m); its values are nearly all multiples of 8, as SUN "
                    f"RGB-D stores them rotated, and read so they give {sun:.1f} m. Say "
                    "which: neurncd convert --opt preset=sun (SUN RGB-D). Setting preset "
                    "or depth_scale skips this check")
        for scale, who in COMMON_DEPTH_SCALES.items():
            alt = med * self.scale / scale
            if scale == self.scale or not lo <= alt <= hi:
                continue
            if scale == 5000.0 and self.kind == "posetxt":
                fix = ("an ICL-NUIM folder needs preset icl (neurncd convert --opt "
                       "preset=icl), which also sets its camera; other data: depth_scale "
                       "5000 and its intrinsics")
            else:
                fix = (f"set depth_scale {scale:g} (neurncd convert --opt depth_scale="
                       f"{scale:g}) or the dataset's preset")
            raise FormatError(
                f"{self.folder}: the depth of {where.name} read with the default scale of a "
                f"{self.kind} folder ({self.scale:g} units per metre, preset "
                f"{self.preset_name}) has a median of {med:.1f} m, not an indoor scene "
                f"({lo:g}-{hi:g} m); at {scale:g} units per metre ({who}) it is {alt:.1f} m. "
                f"Say which: {fix}. Setting preset or depth_scale skips this check")
        warnings.warn(f"{self.folder}: the depth of {where.name} has a median of {med:.1f} m "
                      f"at {self.scale:g} units per metre (preset {self.preset_name}), "
                      f"outside {lo:g}-{hi:g} m; check depth_scale", stacklevel=2)


def opencv_axes(intr: Intrinsics, pose: np.ndarray | None
                ) -> tuple[Intrinsics, np.ndarray | None]:
    """A camera with negative focal lengths as the OpenCV camera the topic contract asks
    for (x right, y down, z forward: fx, fy > 0), the same 3D points in the same places.

    ICL-NUIM documents fy = -480: its camera frame has y up (x right, z forward), a
    left-handed frame, and its poses map it to a left-handed, y-up world (POV-Ray's).
    Backprojecting pixel v gives Y = (v - cy) z / fy; with S = diag(1, -1, 1) the
    point S p is what fy > 0 gives, in the right-handed frame S C. A rotation between
    two left-handed frames becomes one between right-handed frames by conjugation,
    so the pose becomes S T S (the world mirrored the same way: its y axis points
    down). Images are unchanged (nothing is flipped), reprojection between frames is
    exactly as before, and every rotation stays a rotation (det +1). A negative fx is
    handled alike; both negative is a 180 degree roll, T S, the world unchanged."""
    sx, sy = (-1.0 if intr.fx < 0 else 1.0), (-1.0 if intr.fy < 0 else 1.0)
    if sx > 0 and sy > 0:
        return intr, pose
    fixed = Intrinsics(abs(intr.fx), abs(intr.fy), intr.cx, intr.cy, intr.width, intr.height)
    if pose is None:
        return fixed, None
    S = np.diag([sx, sy, 1.0, 1.0])
    T = np.asarray(pose, dtype=np.float64)
    return fixed, (S @ T @ S if sx * sy < 0 else T @ S)


def camera_preset(cfg: FolderConfig, kind: str) -> str:
    """The preset a reader of ``kind`` takes its camera from, "" when the user gave one
    (``intrinsics``): :func:`_camera` checks a preset's camera against the images."""
    return "" if cfg.intrinsics else (cfg.preset or DEFAULT_PRESET[kind])


def _camera(intr: tuple | None, h: int, w: int, where: Path, preset: str = "") -> Intrinsics:
    """The camera of ``w`` x ``h`` images from (fx, fy, cx, cy). ``preset``: the preset they
    came from (not given by the user or the folder), whose camera is refused where its
    principal point is not near the images' centre: a preset made for other images (a
    TUM preset's 640x480 camera on 320x240 images) would place every point wrongly."""
    if intr is None:
        raise FormatError(f"{where}: no intrinsics known; pass intrinsics=[fx, fy, cx, cy]")
    if preset and not (0.25 * w <= intr[2] <= 0.75 * w and 0.25 * h <= intr[3] <= 0.75 * h):
        raise FormatError(f"{where}: the {preset!r} preset's camera (fx {intr[0]:g}, fy "
                          f"{intr[1]:g}, cx {intr[2]:g}, cy {intr[3]:g}) does not fit these "
                          f"{w}x{h} images (its principal point is not near their centre): "
                          "give the camera with --opt intrinsics=[fx,fy,cx,cy]")
    return Intrinsics(intr[0], intr[1], intr[2], intr[3], w, h)


def _make_frame(stamp_ns: int, rgb: np.ndarray, depth: np.ndarray, pose: np.ndarray,
                intr: Intrinsics, where: str, semantic: np.ndarray | None = None,
                instance: np.ndarray | None = None) -> Frame:
    if rgb.shape[:2] != depth.shape:
        raise FormatError(f"{where}: colour is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                          f"{depth.shape[1]}x{depth.shape[0]}")
    intr, pose = opencv_axes(intr, pose)
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
    hint = ("; rgb/ and depth/ without rgb.txt read as a TUM folder with --kind tum "
            "(files named by their timestamps)"
            if (f / "rgb").is_dir() and (f / "depth").is_dir() else "")
    raise FormatError(f"{f}: unknown layout (expected traj_w_c.txt + rgb/ (replica), "
                      "trajectory.log (redwood), pose.txt + color/ (posetxt), "
                      "groundtruth.txt / rgb.txt (tum), or r-*.ppm + d-*.pgm (NYUv2 raw))"
                      + hint)


@contextlib.contextmanager
def replacing_output(path: str | Path, overwrite: bool, is_kind: Callable[[Path], bool],
                     kind: str, error: type[Exception] = FormatError,
                     staged_name: str | None = None) -> Iterator[Path]:
    """Where to write an output folder (a bag, a Replica or TUM folder) so that nothing
    is lost: an existing ``path`` is refused without ``overwrite``, and with it replaced
    only once the new output is complete; a write that fails leaves ``path`` as it was
    and nothing beside it. (A failed ``convert --overwrite`` once deleted the old bag; a
    Replica folder was silently rewritten in place.) ``is_kind`` tells an existing folder
    of this kind (never overwritten otherwise: it may be anything of the user's).
    ``staged_name``: the name the folder is written under before it is moved to ``path``
    (a bag's storage file is named after its folder: rosbags would write
    ``scene.db3/scene.db3.db3``)."""
    path = Path(path)
    if path.exists():
        if not overwrite:
            raise error(f"{path}: exists already; remove it, or overwrite it (--overwrite)")
        if not path.is_dir() or not is_kind(path):
            raise error(f"{path}: exists and is not a {kind}; not overwriting")
    staging = path.parent / f".{path.name}.partial"
    shutil.rmtree(staging, ignore_errors=True)  # a killed earlier write's
    staging.mkdir(parents=True)
    target = staging / (staged_name or path.name)
    try:
        yield target
        if path.exists():
            shutil.rmtree(path)
        os.replace(target, path)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
