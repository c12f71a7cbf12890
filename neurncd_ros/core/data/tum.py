"""TUM RGB-D folders (also NYUv2 raw via ``preset="nyu"``): reader and writer.
Part of :mod:`.formats` (layout described there)."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from ..camera import matrix_to_quat
from ..frame import Frame
from ..sync import nearest, pose_at
from .folder_common import (IMAGE_EXTS, FormatError, FolderConfig, _resolve, camera_preset,
                            read_rgb, read_depth, _camera, _make_frame, _subsample,
                            read_tum_trajectory, DepthScaleCheck, replacing_output)
from .replica import _read_intrinsics_json, _write_png



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
    check = DepthScaleCheck(cfg, kind, folder)
    cam_file = folder / "intrinsics.json"  # written by write_tum (TUM itself has none)
    own = None if cfg.intrinsics or not cam_file.is_file() else _read_intrinsics_json(cam_file)
    preset = camera_preset(cfg, kind)
    for t, rp, dp, pose in _subsample(pairs, cfg):
        rgb = read_rgb(rp)
        depth = read_depth(dp, fmt, scale, cfg.max_depth_m)
        check(depth, dp)
        if own is not None:
            if own.shape != depth.shape:
                raise FormatError(f"{cam_file}: the camera is {own.width}x{own.height} but "
                                  f"{dp.name} is {depth.shape[1]}x{depth.shape[0]}")
            intr = own
        else:
            intr = _camera(intr_vals, *depth.shape, folder, preset)
        yield _make_frame(t, rgb, depth, pose, intr, str(rp))


def write_tum(folder: str | Path, frames: Iterable[Frame], depth_scale: float = 5000.0,
              overwrite: bool = False) -> int:
    """Write Frames as a TUM RGB-D folder (rgb/, depth/, lists, groundtruth.txt), and the
    camera as ``intrinsics.json`` (TUM folders carry none; :func:`read_tum` reads it back
    rather than a preset's camera). An existing folder is refused without ``overwrite``
    and replaced only by a complete one (:func:`.folder_common.replacing_output`)."""
    with replacing_output(folder, overwrite, lambda p: (p / "rgb.txt").is_file(),
                          "TUM folder") as target:
        return _write_tum(target, frames, depth_scale)


def _write_tum(folder: Path, frames: Iterable[Frame], depth_scale: float) -> int:
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    rgb_l, dep_l, gt_l = [], [], []
    camera = None
    for fr in frames:
        fr.validate()
        if camera is not None and fr.intrinsics != camera:
            raise FormatError(f"frame {fr.stamp_ns}: the camera changed ({fr.intrinsics}, "
                              f"first {camera}); a TUM folder holds one")
        camera = fr.intrinsics
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
    if camera is not None:
        (folder / "intrinsics.json").write_text(json.dumps(dataclasses.asdict(camera)))
    for name, lines in (("rgb.txt", rgb_l), ("depth.txt", dep_l), ("groundtruth.txt", gt_l)):
        (folder / name).write_text("# timestamp data\n" + "\n".join(lines) + "\n")
    return len(rgb_l)


# ---------------------------------------------------------------- pose.txt, Redwood
