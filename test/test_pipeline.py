"""The offline path (`neurncd run` / `neurncd demo`) end to end on a small synthetic bag."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from neurncd_ros import config
from neurncd_ros.core.params import build

from rosutil import REPO


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory):
    from neurncd_ros import synth
    from neurncd_ros.core.data.bag import write_bag

    cfg = build(synth.SynthConfig, {"width": 160, "height": 120})
    path = tmp_path_factory.mktemp("run") / "scene.mcap"
    write_bag(path, synth.generate(1002, 24, cfg), storage="mcap")
    return path


def test_run_cli_on_bag_writes_metrics_and_overlays(small_bag, tmp_path):
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.cli", "run", "--bag", str(small_bag),
                        "--out", str(out), "--set", "run.warmup_iterations=60",
                        "--set", "run.label_every=6", "--set", "run.overlays=2"],
                       capture_output=True, text=True, timeout=600, cwd=REPO)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "ran 24 frames (4 labelled)" in r.stdout
    result = json.loads((out / "metrics.json").read_text())
    m = result["metrics"]
    for key in ("miou_all", "miou_known", "miou_novel", "total_acc", "avg_acc",
                "assigned_miou"):
        assert 0.0 <= m[key] <= 100.0, key
    # A real, trained backbone and field: far above chance on the known classes.
    assert m["miou_known"] > 20.0 and m["total_acc"] > 40.0
    assert len(list((out / "overlays").glob("*.png"))) == 2
    assert result["classes"]


def test_stream_renderings_labels_every_nth_frame_after_its_training():
    """The schedule the offline path shares with bench/ncd.py: one frame in label_every is
    yielded, each rendered only after min_iterations_before_publish iterations on it."""
    from neurncd_ros.core import pipeline
    from neurncd_ros.core.backbone.backbone import load_backbone
    from neurncd_ros import synth
    from neurncd_ros.core.field.mapper import Mapper

    cfg = config.load(None, {"run.warmup_iterations": 5, "run.train_iterations_per_frame": 2,
                             "run.label_every": 3, "mapper.min_iterations_before_publish": 4,
                             "mapper.fast.rays_per_iteration": 256})
    frames = list(synth.generate(1003, 8, build(synth.SynthConfig, {"width": 64,
                                                                   "height": 48})))
    backbone = load_backbone(cfg.backbone)
    mapper = Mapper.from_config(cfg, backbone.channels)
    times = pipeline.StreamTimes()
    seen = []
    for f, ids, r in pipeline.stream_renderings(frames, cfg, backbone, mapper,
                                                progress=False, times=times):
        seen.append((f.stamp_ns, mapper.iterations))
        assert r["embedding"].shape == (48, 64, backbone.channels)
        assert r["entropy"].shape == (48, 64) and ids.shape == (48, 64)
    assert [s for s, _ in seen] == [frames[i].stamp_ns for i in (0, 3, 6)]
    # Frame 0 is trained on by the warm-up + 2 (iteration 7), then rendered once 4 more
    # iterations passed (frames 1, 2: 11); frame 3 enters at 13, is rendered at 17; frame 6
    # enters at 19, the stream ends at 21 and is topped up to its 4 iterations: 23.
    assert [it for _, it in seen] == [11, 17, 23]
    assert times.frames == 8 and times.backbone > 0 and times.rendering > 0


def test_run_rejects_bad_input_clearly(tmp_path):
    bogus = tmp_path / "bogus.mcap"
    bogus.write_bytes(b"not a bag at all")
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.cli", "run", "--bag", str(bogus)],
                       capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 1 and "bogus.mcap" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.cli", "run", "--bag", "x.mcap",
                        "--set", "mapper.backend=gpu"], capture_output=True, text=True,
                       timeout=120, cwd=REPO)
    assert r.returncode == 2 and "mapper.backend" in r.stderr


@pytest.mark.parametrize("fmt", ["mcap", "replica"])
def test_synth_cli_writes_readable_scene(tmp_path, fmt):
    from neurncd_ros.core.data.bag import FrameReader
    from neurncd_ros.core.data.formats import read_folder

    out = tmp_path / ("scene.mcap" if fmt == "mcap" else "replica")
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.cli", "synth", "--seed", "4",
                        "--frames", "3", "--width", "96", "--height", "72", "--format", fmt,
                        "--out", str(out)], capture_output=True, text=True, timeout=300,
                       cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert "wrote 3 frames of seed 4 (96x72" in r.stdout
    frames = list(FrameReader(out) if fmt == "mcap" else read_folder(out))
    assert len(frames) == 3 and frames[0].semantic is not None
    assert frames[0].rgb.shape == (72, 96, 3)
