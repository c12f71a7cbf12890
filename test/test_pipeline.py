"""The offline tool (`neurncd run`, `neurncd synth`) end to end on small synthetic bags."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from neurncd_ros.core.params import build

from rosutil import REPO


def neurncd(*args: object, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run the offline tool (``python -m neurncd_ros.cli ARGS``) from the repository root."""
    return subprocess.run([sys.executable, "-m", "neurncd_ros.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=REPO)


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
    r = neurncd("run", "--bag", small_bag, "--out", out, "--set", "run.overlays=2")
    assert r.returncode == 0, r.stdout + r.stderr
    result = json.loads((out / "metrics.json").read_text())
    assert f"ran 24 frames ({result['labelled']} labelled, " in r.stdout
    # Every keyframe is labelled, as the live graph labels it.
    assert result["labelled"] >= 2 and result["keyframes_labelled"] == result["keyframes"]
    m = result["metrics"]
    for key in ("miou_all", "miou_known", "miou_novel", "total_acc", "avg_acc",
                "assigned_miou"):
        assert 0.0 <= m[key] <= 100.0, key
    # A real, trained backbone and field: far above chance on the known classes.
    assert m["miou_known"] > 20.0 and m["total_acc"] > 40.0
    assert len(list((out / "overlays").glob("*.png"))) == 2
    assert result["classes"]


def test_run_rejects_bad_input_clearly(tmp_path):
    bogus = tmp_path / "bogus.mcap"
    bogus.write_bytes(b"not a bag at all")
    r = neurncd("run", "--bag", bogus, timeout=120)
    assert r.returncode == 1 and "bogus.mcap" in r.stderr and "Traceback" not in r.stderr
    r = neurncd("run", "--bag", "x.mcap", "--set", "mapper.backend=gpu", timeout=120)
    assert r.returncode == 2 and "mapper.backend" in r.stderr


@pytest.mark.parametrize("fmt", ["mcap", "replica"])
def test_synth_cli_writes_readable_scene(tmp_path, fmt):
    from neurncd_ros.core.data.bag import FrameReader
    from neurncd_ros.core.data.formats import read_folder

    out = tmp_path / ("scene.mcap" if fmt == "mcap" else "replica")
    r = neurncd("synth", "--seed", 4, "--frames", 3, "--width", 96, "--height", 72,
                "--format", fmt, "--out", out, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "wrote 3 frames of seed 4 (96x72" in r.stdout
    frames = list(FrameReader(out) if fmt == "mcap" else read_folder(out))
    assert len(frames) == 3 and frames[0].semantic is not None
    assert frames[0].rgb.shape == (72, 96, 3)


def test_run_estimates_the_poses_of_a_bag_without_them(tmp_path):
    """As the mapper node's pose_source auto: no pose topic in the bag -> RGB-D odometry."""
    from neurncd_ros import synth
    from neurncd_ros.core.data.bag import write_bag

    bag = tmp_path / "noposes"
    write_bag(bag, synth.generate(1002, 24, synth.SynthConfig(width=160, height=120)),
              pose_mode="none")
    out = tmp_path / "out"
    r = neurncd("run", "--bag", bag, "--out", out, "--set", "run.overlays=0")
    assert r.returncode == 0, r.stdout + r.stderr
    result = json.loads((out / "metrics.json").read_text())
    assert result["poses"] == "odometry" and result["labelled"] >= 2
    assert result["metrics"]["miou_known"] > 20.0
    lost = result["odometry_lost"]
    assert (f"poses estimated by RGB-D odometry (the bag has none): {lost} of "
            f"{result['frames'] + lost} frames lost track") in r.stdout, r.stdout
