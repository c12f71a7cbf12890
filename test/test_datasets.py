"""NYUv2's labelled set (v7.3 .mat) and Replica's classes, on small files in the real layouts."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from neurncd_ros.core import classes
from neurncd_ros.core.data import bag, formats, nyu, replica_classes

REAL = Path(__file__).parent / "data" / "real"
H, W = 24, 32  # non-square, so a missed MATLAB transpose shows


def _matlab_strings(f, name: str, values: list[str]) -> None:
    """A MATLAB cell array of strings as v7.3 stores it: references into #refs#."""
    import h5py

    refs = f.require_group("#refs#")
    out = []
    for k, text in enumerate(values):
        d = refs.create_dataset(f"{name}_{k}", data=np.array([[ord(c)] for c in text],
                                                             dtype=np.uint16))
        out.append(d.ref)
    f.create_dataset(name, data=np.array([out], dtype=h5py.ref_dtype))


def write_labelled_mat(path: Path, n: int = 3, h: int = H, w: int = W,
                       raw_names: list[str] | None = None) -> dict:
    """A tiny nyu_depth_v2_labeled.mat: MATLAB 7.3 header, column-major HDF5 arrays."""
    import h5py
    import scipy.io

    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (n, h, w, 3), dtype=np.uint8)
    depth = (1 + rng.random((n, h, w))).astype(np.float32)
    labels = np.zeros((n, h, w), np.uint16)
    labels[:, : h // 2] = 21       # 894-class id 21 -> NYU-40 1 (wall)
    labels[:, h // 2:, : w // 2] = 11   # -> NYU-40 2 (floor)
    labels[:, h // 2:, w // 2:] = 4     # -> NYU-40 22 (ceiling, novel)
    labels[:, 0, 0] = 0                 # unlabelled
    with h5py.File(path, "w", userblock_size=512) as f:
        f.create_dataset("images", data=rgb.transpose(0, 3, 2, 1))
        f.create_dataset("depths", data=depth.transpose(0, 2, 1))
        f.create_dataset("rawDepths", data=depth.transpose(0, 2, 1))
        f.create_dataset("labels", data=labels.transpose(0, 2, 1))
        f.create_dataset("instances", data=np.ones((n, w, h), np.uint8))
        _matlab_strings(f, "scenes", [f"kitchen_{k // 2:04d}" for k in range(n)])
        _matlab_strings(f, "rawRgbFilenames", raw_names or
                        [f"kitchen_{k // 2:04d}/r-12948510{k}.5-1.ppm" for k in range(n)])
    with open(path, "r+b") as f:
        f.write(nyu.MATLAB_73 + b", Platform: GLNXA64, Created on: test".ljust(109))
    mapping = np.zeros(894, np.uint8)
    mapping[21 - 1], mapping[11 - 1], mapping[4 - 1] = 1, 2, 22
    scipy.io.savemat(path.with_name("classMapping40.mat"), {"mapClass": mapping[None]})
    return {"rgb": rgb, "depth": depth, "labels": labels}


def test_labelled_mat_reads_with_nyu13_ground_truth(tmp_path):
    mat = tmp_path / "nyu_depth_v2_labeled.mat"
    truth = write_labelled_mat(mat)
    frames = list(formats.read_folder(mat))
    assert len(frames) == 3
    f = frames[1]
    assert f.rgb.shape == (H, W, 3) and np.array_equal(f.rgb, truth["rgb"][1])
    assert np.allclose(f.depth, truth["depth"][1])
    assert f.semantic[0, 5] == classes.CLASS_ID["wall"]
    assert f.semantic[H - 1, 0] == classes.CLASS_ID["floor"]
    assert f.semantic[H - 1, W - 1] == classes.CLASS_ID["ceiling"]
    assert f.semantic[0, 0] == classes.VOID
    assert f.intrinsics.width == W and np.allclose(f.pose, np.eye(4))
    with nyu.NyuLabelled(mat) as ds:
        assert ds.scenes == ["kitchen_0000", "kitchen_0000", "kitchen_0001"]
        assert ds.raw_names[2] == "r-129485102.5-1.ppm"
    only = list(nyu.read_labelled(mat, scenes=["kitchen_0001"]))
    assert len(only) == 1 and np.array_equal(only[0].rgb, truth["rgb"][2])


def test_labelled_mat_converts_to_a_bag_and_a_replica_folder(tmp_path):
    mat = tmp_path / "nyu_depth_v2_labeled.mat"
    write_labelled_mat(mat)
    assert formats.convert(mat, tmp_path / "nyu.mcap") == 3
    back = list(bag.FrameReader(tmp_path / "nyu.mcap"))
    assert len(back) == 3 and back[0].semantic[0, 5] == classes.CLASS_ID["wall"]
    assert formats.convert(mat, tmp_path / "rep", to="replica") == 3
    again = list(formats.read_folder(tmp_path / "rep"))  # NYU-13 already: kept as is
    assert np.array_equal(again[2].semantic, back[2].semantic)
    with pytest.raises(formats.FormatError, match="single views"):
        formats.convert(mat, tmp_path / "x.mcap", poses="odometry")


def test_bad_nyu_files_are_named(tmp_path):
    import scipy.io

    v5 = tmp_path / "old.mat"
    scipy.io.savemat(v5, {"images": np.zeros((2, 2))})
    with pytest.raises(formats.FormatError, match=r"old\.mat: not a MATLAB v7\.3"):
        list(formats.read_folder(v5))
    mat = tmp_path / "sub" / "nyu_depth_v2_labeled.mat"
    mat.parent.mkdir()
    write_labelled_mat(mat)
    (mat.parent / "classMapping40.mat").unlink()
    with pytest.raises(formats.FormatError, match="classMapping40.mat"):
        list(formats.read_folder(mat))
    with pytest.raises(formats.FormatError, match=r"none\.mat: no such file"):
        list(formats.read_folder(tmp_path / "none.mat", kind="nyu_labelled"))


def test_nyu_raw_sequence_gets_poses_from_odometry_and_its_labelled_frame(tmp_path):
    """A raw scene folder (r-*.ppm, d-*.pgm, no poses) converts with odometry; the
    labelled frame taken from one of its files brings its ground truth."""
    scene = tmp_path / "kitchen_0000"
    scene.mkdir()
    stamps = ["1294851097.500000", "1294851097.533333", "1294851097.566667"]
    for t in stamps:
        shutil.copy(REAL / "single_frames" / "NYU_color.ppm", scene / f"r-{t}-1.ppm")
        shutil.copy(REAL / "single_frames" / "NYU_depth.pgm", scene / f"d-{t}-1.pgm")
    assert formats.detect_kind(scene) == "nyu"
    with pytest.raises(formats.FormatError, match="no camera poses"):
        formats.read_folder(scene)
    mat = tmp_path / "nyu_depth_v2_labeled.mat"
    write_labelled_mat(mat, n=1, h=480, w=640, raw_names=[f"kitchen_0000/r-{stamps[1]}-1.ppm"])
    report: dict = {}
    n = formats.convert(scene, tmp_path / "k.mcap", poses="odometry", labelled=mat,
                        report=report)
    assert n == 3 and report["lost"] == 0
    frames = list(bag.FrameReader(tmp_path / "k.mcap"))
    assert [f.semantic is not None for f in frames] == [False, True, False]
    assert frames[1].semantic[0, 5] == classes.CLASS_ID["wall"]
    # The same image three times: the odometry sees no motion.
    assert all(np.abs(f.pose - np.eye(4)).max() < 1e-3 for f in frames)


def _replica_folder(tmp_path: Path, info: dict | None) -> Path:
    """Semantic-NeRF layout: room_0/Sequence_1 with Replica class ids, semantic_info/room_0."""
    seq = tmp_path / "room_0" / "Sequence_1"
    for sub in ("rgb", "depth", "semantic_class"):
        (seq / sub).mkdir(parents=True)
    sem = np.zeros((H, W), np.uint16)
    sem[: H // 2] = 93     # wall
    sem[H // 2:] = 40      # floor
    sem[2:6, 2:8] = 31     # blinds -> window
    sem[8:10, 20:30] = 0   # void
    for i in range(2):
        cv2.imwrite(str(seq / "rgb" / f"rgb_{i}.png"), np.full((H, W, 3), 100, np.uint8))
        cv2.imwrite(str(seq / "depth" / f"depth_{i}.png"), np.full((H, W), 2000, np.uint16))
        cv2.imwrite(str(seq / "semantic_class" / f"semantic_class_{i}.png"), sem)
    (seq / "traj_w_c.txt").write_text("\n".join(" ".join(map(str, np.eye(4).ravel()))
                                                for _ in range(2)) + "\n")
    if info is not None:
        d = tmp_path / "semantic_info" / "room_0"
        d.mkdir(parents=True)
        (d / "info_semantic.json").write_text(json.dumps(info))
    return seq


INFO = {"classes": [{"id": 93, "name": "wall"}, {"id": 40, "name": "floor"},
                    {"id": 31, "name": "blinds"}, {"id": 7, "name": "undefined"}]}


def test_replica_semantic_classes_become_nyu13_without_an_id_map(tmp_path):
    seq = _replica_folder(tmp_path, INFO)
    frames = list(formats.read_folder(seq))
    s = frames[0].semantic
    assert s[0, W - 1] == classes.CLASS_ID["wall"]
    assert s[H - 1, 0] == classes.CLASS_ID["floor"]
    assert s[3, 3] == classes.CLASS_ID["window"]
    assert s[9, 25] == classes.VOID
    # Through convert into a bag: the ground truth topic holds NYU-13.
    formats.convert(seq, tmp_path / "r.mcap")
    assert np.array_equal(list(bag.FrameReader(tmp_path / "r.mcap"))[1].semantic, s)


def test_replica_mapping_covers_every_name_and_names_the_unmapped():
    assert set(replica_classes.NO_COUNTERPART) == {"undefined"}
    assert all(0 <= v <= classes.NUM_CLASSES for v in replica_classes.REPLICA_TO_NYU13.values())
    for name, nyu13 in (("door", "wall"), ("curtain", "window"), ("tv-screen", "tv"),
                        ("book", "books"), ("desk", "table"), ("rug", "floor"),
                        ("cushion", "objects"), ("nightstand", "furniture")):
        assert replica_classes.REPLICA_TO_NYU13[name] == classes.CLASS_ID[nyu13]


def test_replica_errors_name_the_file(tmp_path):
    seq = _replica_folder(tmp_path, None)
    with pytest.raises(formats.FormatError, match="info_semantic.json"):
        list(formats.read_folder(seq))
    assert len(list(formats.read_folder(seq, semantic_ids="nyu13"))) == 2
    info = tmp_path / "info.json"
    info.write_text(json.dumps({"classes": [{"id": 93, "name": "wall"},
                                            {"id": 40, "name": "floor"}]}))
    with pytest.raises(formats.FormatError, match=r"semantic_class_0\.png.*\[31\]"):
        list(formats.read_folder(seq, class_info=info))
    info.write_text(json.dumps({"classes": [{"id": 31, "name": "space-heater"}]}))
    with pytest.raises(formats.FormatError, match=r"info\.json.*space-heater"):
        list(formats.read_folder(seq, class_info=info))
    info.write_text("{not json")
    with pytest.raises(formats.FormatError, match=r"info\.json: not a Replica"):
        list(formats.read_folder(seq, class_info=info))


def test_replica_id_map_must_cover_the_images_and_name_nyu13_ids(tmp_path):
    """A user's id_map never turns ground truth into void by leaving an id out (a partial
    map once voided 87 % of a scene's pixels without a word), and its targets are NYU-13."""
    seq = _replica_folder(tmp_path, None)
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps({"93": 12, "40": 5}))
    with pytest.raises(formats.FormatError, match=r"semantic_class_0\.png.*\[31\].*id_map"):
        list(formats.read_folder(seq, id_map=partial))
    full = tmp_path / "full.json"
    full.write_text(json.dumps({"93": 12, "40": 5, "31": 13}))
    s = next(formats.read_folder(seq, id_map=full)).semantic
    assert s[0, W - 1] == 12 and s[H - 1, 0] == 5 and s[3, 3] == 13 and s[9, 25] == 0
    wrong = tmp_path / "wrong.json"
    wrong.write_text(json.dumps({"93": 200, "40": 5, "31": 13}))
    with pytest.raises(formats.FormatError, match=r"wrong\.json.*\[200\].*not NYU-13"):
        list(formats.read_folder(seq, id_map=wrong))
    # Beside the scene's class file, id_map maps what the shipped table cannot name and
    # the class file maps the rest.
    info = tmp_path / "info.json"
    info.write_text(json.dumps({"classes": [{"id": 93, "name": "wall"},
                                            {"id": 40, "name": "floor"},
                                            {"id": 31, "name": "space-heater"}]}))
    with pytest.raises(formats.FormatError, match=r"space-heater.*\[31\].*id_map"):
        list(formats.read_folder(seq, class_info=info))
    heater = tmp_path / "heater.json"
    heater.write_text(json.dumps({"31": 7}))
    s = next(formats.read_folder(seq, class_info=info, id_map=heater)).semantic
    assert s[0, W - 1] == classes.CLASS_ID["wall"] and s[3, 3] == classes.CLASS_ID["objects"]


def test_replica_missing_files_are_named(tmp_path):
    """A frame whose colour image is missing is skipped and one whose label image is
    missing carries no ground truth: each said, not silently (conversion said "converted
    44 frames" with one gone)."""
    seq = _replica_folder(tmp_path, INFO)
    (seq / "rgb" / "rgb_1.png").unlink()
    with pytest.warns(UserWarning, match=r"1 frame\(s\) with depth but no rgb.*: 1$"):
        assert len(list(formats.read_folder(seq))) == 1
    seq = _replica_folder(tmp_path / "b", INFO)
    (seq / "semantic_class" / "semantic_class_0.png").unlink()
    with pytest.warns(UserWarning, match=r"1 frame\(s\) without semantic_class.*: 0$"):
        frames = list(formats.read_folder(seq))
    assert frames[0].semantic is None and frames[1].semantic is not None
