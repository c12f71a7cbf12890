"""RGB-D odometry benchmark: trajectory error, speed, and what estimated poses cost the system.

Figures (bench/results/odometry.json; trajectory errors measured with evo):

- ``ate_rmse_cm_synth``: absolute trajectory error (RMSE, after evo's SE(3)
  Umeyama alignment) of 300-frame synthetic sequences (320x240, 30 Hz,
  realistic Kinect-like depth noise), mean over 3 held-out seeds
  (``seeds.TEST``, never used to choose a parameter; the defaults were chosen on
  tuning seeds 500-501); ``rpe_trans_cm_synth`` / ``rpe_rot_deg_synth``: mean
  frame-to-frame relative pose error; per seed under ``synth_seeds``;
  ``ate_rmse_cm_synth_every3``: the same sequences tracked one frame in three
  (10 Hz of the 30 Hz camera, a third of the CPU);
- ``ate_rmse_cm_redwood``, ``ate_rmse_cm_icl``: the real fixtures in test/data/real.
  The ICL-NUIM fixture is 5 frames 15 cm to 1.1 m and 20-91 degrees apart (two
  consecutive pairs do not overlap at all): it is tracked with the default step
  limits and ``new_segment_after`` 1 (a view that overlaps nothing starts a new
  segment; read with OpenCV axes, fy > 0, the 79 degree pair is matched about 90
  degrees wrong, a step the limits refuse), and its ATE is over the frames of the largest
  segment with the segment's first pose anchored to the true one (too few
  frames to align; ``icl_frames_tracked`` says how many); null when no segment
  has 2 frames;
- ``odometry_ms_per_frame_320x240``: median ``track()`` time on one core
  (OpenCV and torch at 1 thread), over the synthetic runs;
- ``miou_all_true_poses`` / ``miou_all_odometry``: the whole pipeline
  (``engine.offline.run_frames``, as ``neurncd run``: backbone, Embedding-NeRF,
  discovery) on the same
  synthetic bags (the 3 test seeds, 300 frames as above), once with their true
  poses and once with the pose topic ignored and poses estimated
  (``FrameReader(with_poses=False)`` -> ``with_odometry``), mean over seeds;
  ``miou_drop_points`` is the difference. The engine's live schedule trains the
  field about 6 iterations per second of stream, so on these 10 s the labels are
  mostly the backbone's; ``*_trained_field`` repeats the comparison with
  ``run.training_rate_hz`` 60, where the field (and so the poses) decides more;

Writes bench/results/odometry.png (top view of estimated vs true paths).

    .venv/bin/python bench/odometry.py            # everything (about 30 min on 2 cores)
    .venv/bin/python bench/odometry.py --no-ncd   # trajectories and speed only (2 min)
    .venv/bin/python bench/odometry.py --no-trained-field   # the live schedule only
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from neurncd_ros import config, synth  # noqa: E402
from neurncd_ros.core.data import bag, formats  # noqa: E402
from neurncd_ros.core.engine import offline  # noqa: E402
from neurncd_ros.core.odometry import OdometryConfig, RGBDOdometry, with_odometry  # noqa: E402
from neurncd_ros.synth import seeds  # noqa: E402

from _common import commit  # noqa: E402  (bench/ is on sys.path)

RESULTS = REPO / "bench" / "results"
REAL = REPO / "test" / "data" / "real"
SEEDS = seeds.TEST[:3]
FIELD_RATE_HZ = 60.0


def evo_errors(stamps_ns, est: list[np.ndarray], gt: list[np.ndarray], align: str = "se3"
               ) -> dict:
    """ATE RMSE (cm) and mean frame-to-frame RPE (cm, deg) by evo.

    ``align``: "se3" = Umeyama rigid alignment of the whole path; "origin" = the
    first poses made equal (for paths too short to align)."""
    import copy

    from evo.core import metrics
    from evo.core.trajectory import PoseTrajectory3D

    t = np.asarray(stamps_ns, dtype=np.float64) / 1e9
    traj_est = PoseTrajectory3D(poses_se3=[np.asarray(p) for p in est], timestamps=t)
    traj_gt = PoseTrajectory3D(poses_se3=[np.asarray(p) for p in gt], timestamps=t)
    aligned = copy.deepcopy(traj_est)
    if align == "se3":
        aligned.align(traj_gt, correct_scale=False)
    else:
        aligned.align_origin(traj_gt)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((traj_gt, aligned))
    out = {"ate_rmse_cm": ape.get_statistic(metrics.StatisticsType.rmse) * 100}
    for rel, key, scale in ((metrics.PoseRelation.translation_part, "rpe_trans_cm", 100),
                            (metrics.PoseRelation.rotation_angle_deg, "rpe_rot_deg", 1)):
        rpe = metrics.RPE(rel, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
        rpe.process_data((traj_gt, traj_est))
        out[key] = rpe.get_statistic(metrics.StatisticsType.mean) * scale
    return out


def track(frames, cfg: OdometryConfig, times: list[float] | None = None):
    """(results, frames) of one run from the identity pose."""
    odo = RGBDOdometry(cfg)
    res = []
    for f in frames:
        t0 = time.perf_counter()
        res.append(odo.track(f.stamp_ns, f.rgb, f.depth, f.intrinsics))
        if times is not None:
            times.append(time.perf_counter() - t0)
    return res


def synthetic(n_frames: int) -> tuple[dict, list]:
    from tqdm import tqdm

    out, times, paths = {}, [], []
    for seed in tqdm(SEEDS, desc="synthetic trajectories", unit="seed"):
        frames = list(synth.generate(seed, n_frames, synth.SynthConfig()))
        res = track(frames, OdometryConfig(), times)
        ok = [i for i, r in enumerate(res) if r.pose is not None]
        e = evo_errors([frames[i].stamp_ns for i in ok], [res[i].pose for i in ok],
                       [frames[i].pose for i in ok])
        e.update(frames=len(frames), tracked=len(ok),
                 lost=sum(r.status == "lost" for r in res),
                 segments=1 + sum(r.status == "new_segment" for r in res),
                 keyframes=sum(r.keyframe for r in res),
                 path_m=float(sum(np.linalg.norm(b.pose[:3, 3] - a.pose[:3, 3])
                                  for a, b in zip(frames, frames[1:]))))
        # Tracking one frame in three (10 Hz of a 30 Hz camera) costs a third of the CPU.
        sub = frames[::3]
        r3 = track(sub, OdometryConfig())
        ok3 = [i for i, r in enumerate(r3) if r.pose is not None]
        e["ate_rmse_cm_every3"] = evo_errors([sub[i].stamp_ns for i in ok3],
                                             [r3[i].pose for i in ok3],
                                             [sub[i].pose for i in ok3])["ate_rmse_cm"]
        e["tracked_every3"] = len(ok3)
        out[str(seed)] = {k: round(v, 3) if isinstance(v, float) else v for k, v in e.items()}
        paths.append((seed, [frames[i].pose for i in ok], [res[i].pose for i in ok]))
    res = {"synth_seeds": out, "synth_frames": n_frames,
           "odometry_ms_per_frame_320x240": statistics.median(times) * 1000,
           "odometry_ms_p90_320x240": float(np.percentile(times, 90)) * 1000}
    for key in ("ate_rmse_cm", "rpe_trans_cm", "rpe_rot_deg"):
        res[f"{key}_synth"] = float(np.mean([v[key] for v in out.values()]))
    res["ate_rmse_cm_synth_every3"] = float(np.mean([v["ate_rmse_cm_every3"]
                                                     for v in out.values()]))
    res["ate_rmse_cm_synth_max"] = float(max(v["ate_rmse_cm"] for v in out.values()))
    return res, paths


def real_fixtures() -> dict:
    res = {}
    frames = list(formats.read_folder(REAL / "redwood_livingroom"))
    r = track(frames, OdometryConfig())
    ok = [i for i, x in enumerate(r) if x.pose is not None]
    e = evo_errors([frames[i].stamp_ns for i in ok], [r[i].pose for i in ok],
                   [frames[i].pose for i in ok])
    res.update(ate_rmse_cm_redwood=e["ate_rmse_cm"], rpe_trans_cm_redwood=e["rpe_trans_cm"],
               redwood_frames_tracked=len(ok), redwood_frames=len(frames))
    frames = list(formats.read_folder(REAL / "icl_livingroom", "posetxt", preset="icl"))
    cfg = OdometryConfig(new_segment_after=1)
    r = track(frames, cfg)
    by_seg: dict[int, list[int]] = {}
    for i, x in enumerate(r):
        if x.pose is not None:
            by_seg.setdefault(x.segment, []).append(i)
    best = max(by_seg.values(), key=len) if by_seg else []
    res["icl_frames"] = len(frames)
    res["icl_frames_tracked"] = len(best)
    res["icl_segments"] = len(by_seg)
    res["icl_statuses"] = [x.status for x in r]
    if len(best) >= 2:
        e = evo_errors([frames[i].stamp_ns for i in best], [r[i].pose for i in best],
                       [frames[i].pose for i in best], align="origin")
        res["ate_rmse_cm_icl"] = e["ate_rmse_cm"]
        res["rpe_trans_cm_icl"] = e["rpe_trans_cm"]
        res["rpe_rot_deg_icl"] = e["rpe_rot_deg"]
    else:
        res["ate_rmse_cm_icl"] = None
    return res


def whole_system(n_frames: int, overrides: dict | None = None, suffix: str = "") -> dict:
    """Pipeline mIoU on the same bags with true and with estimated poses."""
    cfg = config.default() if not overrides else config.from_flat(
        {**config.default().to_flat(), **overrides})
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in SEEDS:
            path = Path(tmp) / f"s{seed}.mcap"
            bag.write_bag(path, synth.generate(seed, n_frames, cfg.synth), topics=cfg.topics)
            row = {}
            for mode in ("true_poses", "odometry"):
                torch.manual_seed(0)
                if mode == "true_poses":
                    frames = bag.FrameReader(path, cfg.topics)
                else:
                    results: list = []
                    frames = with_odometry(bag.FrameReader(path, cfg.topics, with_poses=False),
                                           cfg.odometry, results)
                t0 = time.perf_counter()
                out = offline.run_frames(frames, cfg, Path(tmp) / f"run_{seed}_{mode}",
                                          total=n_frames, progress=False)
                row[f"miou_all_{mode}"] = out["metrics"]["miou_all"]
                row[f"miou_known_{mode}"] = out["metrics"]["miou_known"]
                row[f"miou_novel_{mode}"] = out["metrics"]["miou_novel"]
                row[f"seconds_{mode}"] = round(time.perf_counter() - t0, 1)
                if mode == "odometry":
                    row["odometry_lost"] = sum(r.status == "lost" for r in results)
                row[f"iterations_{mode}"] = out["iterations"]
            rows[str(seed)] = {k: round(v, 2) if isinstance(v, float) else v
                               for k, v in row.items()}
            print(f"seed {seed}{suffix}: {rows[str(seed)]}", flush=True)
    res = {f"ncd_seeds{suffix}": rows, "ncd_frames": n_frames}
    for key in ("miou_all", "miou_known", "miou_novel"):
        for mode in ("true_poses", "odometry"):
            res[f"{key}_{mode}{suffix}"] = float(np.mean([r[f"{key}_{mode}"]
                                                          for r in rows.values()]))
    res[f"miou_drop_points{suffix}"] = (res[f"miou_all_true_poses{suffix}"] -
                                        res[f"miou_all_odometry{suffix}"])
    return res


def save_png(paths: list, path: Path) -> None:
    """Top view (x, z of the world) of each seed's true and estimated camera path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(paths), figsize=(4.5 * len(paths), 4.5))
    for ax, (seed, gt, est) in zip(np.atleast_1d(axes), paths):
        g = np.array([p[:3, 3] for p in gt])
        # Express the estimate in the true world frame through the first pose.
        e = np.array([(gt[0] @ p)[:3, 3] for p in est])
        ax.plot(g[:, 0], g[:, 1], "k-", label="true")
        ax.plot(e[:, 0], e[:, 1], "r--", label="odometry")
        ax.set_title(f"seed {seed}")
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=300, help="frames per synthetic trajectory")
    ap.add_argument("--ncd-frames", type=int, default=300,
                    help="frames per scene for the whole-system comparison")
    ap.add_argument("--no-ncd", action="store_true", help="skip the whole-system comparison")
    ap.add_argument("--no-trained-field", action="store_true",
                    help="skip its repetition with the field trained at "
                    f"{FIELD_RATE_HZ:g} iterations/s (two thirds of the run time)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    torch.set_num_threads(1)
    measured = commit()  # the code that runs is the code at start
    t0 = time.time()
    res, paths = synthetic(args.frames)
    res.update(real_fixtures())
    if not args.no_ncd:
        res.update(whole_system(args.ncd_frames))
        # The live schedule trains the field ~6 iterations per second of stream, so on
        # 10 s the labels are mostly the backbone's and poses barely matter; with the
        # field trained 10x harder the poses decide what it renders.
        if not args.no_trained_field:
            res.update(whole_system(args.ncd_frames, {"run.training_rate_hz": FIELD_RATE_HZ},
                                    "_trained_field"))
            res["trained_field_rate_hz"] = FIELD_RATE_HZ
    res.update(cores=os.cpu_count(), commit=measured, seconds=round(time.time() - t0, 1))
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / "odometry.json"
    out.write_text(json.dumps(res, indent=1, sort_keys=True) + "\n")
    save_png(paths, RESULTS / "odometry.png")
    rows = [(k, res[k]) for k in sorted(res) if not isinstance(res[k], (dict, list))]
    for k, v in rows:
        print(f"{k:36s} {v:.3f}" if isinstance(v, float) else f"{k:36s} {v}")


if __name__ == "__main__":
    from neurncd_ros.core.text import progress_as_lines

    with progress_as_lines():  # a log file gets the bars as lines
        main()
