"""ROS 2 bag I/O: exact round trips, /tf poses, synchronisation drops, bad bags."""

from __future__ import annotations

import os
import shutil
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from neurncd_ros.core.camera import Intrinsics, look_at
from neurncd_ros.core.data import bag
from neurncd_ros.core.data.mcap_recover import recover_mcap
from neurncd_ros.core.data.sqlite_recover import recover_sqlite
from neurncd_ros.core.data.bag import BagError, FrameReader
from neurncd_ros.core.topics import Topics
from neurncd_ros.core.sync import tf_chain, tf_root
from neurncd_ros.core.frame import Frame

torch.set_num_threads(1)

STAMP0 = 1_700_000_000_123_456_789
PERIOD = 33_333_333


def make_frames(n: int = 4, w: int = 40, h: int = 30, seed: int = 0, gt: bool = True
                ) -> list[Frame]:
    """Random frames: mm-quantised depth with holes, distinct poses, NYU-13 / instance GT."""
    rng = np.random.default_rng(seed)
    intr = Intrinsics(35.5, 36.25, 19.25, 14.75, w, h)
    out = []
    for i in range(n):
        depth = (rng.integers(300, 6000, (h, w)) / 1000.0).astype(np.float32)
        depth[rng.random((h, w)) < 0.1] = 0.0
        eye = rng.uniform(-2, 2, 3) + [0, 0, 1.5]
        out.append(Frame(
            STAMP0 + i * PERIOD, rng.integers(0, 256, (h, w, 3), dtype=np.uint8), depth,
            look_at(eye, rng.uniform(-1, 1, 3)), intr,
            rng.integers(0, 14, (h, w)).astype(np.uint16) if gt else None,
            rng.integers(0, 400, (h, w)).astype(np.uint16) if gt else None))
    return out


def assert_same(a: list[Frame], b: list[Frame], gt: bool = True) -> None:
    assert len(a) == len(b)
    for fa, fb in zip(a, b):
        assert fa.stamp_ns == fb.stamp_ns
        assert fa.intrinsics == fb.intrinsics
        np.testing.assert_array_equal(fa.rgb, fb.rgb)
        np.testing.assert_array_equal(fa.depth, fb.depth)
        assert fb.depth.dtype == np.float32
        np.testing.assert_allclose(fa.pose, fb.pose, atol=1e-12)
        if gt:
            np.testing.assert_array_equal(fa.semantic, fb.semantic)
            np.testing.assert_array_equal(fa.instance, fb.instance)


def bag_file(path: Path) -> Path:
    return next(p for p in path.iterdir() if p.suffix in (".mcap", ".db3"))


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
@pytest.mark.parametrize("depth_encoding", ["16UC1", "32FC1"])
def test_round_trip_exact(tmp_path, storage, depth_encoding):
    frames = make_frames()
    if depth_encoding == "32FC1":  # any float depth survives 32FC1
        frames[0].depth = frames[0].depth + np.float32(1e-4)
    n = bag.write_bag(tmp_path / "b", frames, storage=storage, depth_encoding=depth_encoding)
    assert n == len(frames)
    reader = FrameReader(tmp_path / "b")
    assert len(reader) == n
    got = list(reader)
    assert reader.dropped == []
    assert_same(frames, got)
    # the storage file alone is a bag too
    assert_same(frames, list(FrameReader(bag_file(tmp_path / "b"))))


@pytest.mark.parametrize("storage,mode", [("mcap", "MESSAGE"), ("mcap", "FILE"),
                                          ("mcap", "STORAGE"), ("sqlite3", "MESSAGE"),
                                          ("sqlite3", "FILE")])
def test_a_zstd_compressed_recording_reads_exactly(tmp_path, storage, mode):
    """`ros2 bag record --compression-mode file|message --compression-format zstd` and
    MCAP's zstd chunks (storage presets zstd_fast, zstd_small): the same frames as the
    plain bag, for run and info (FrameReader) and for the replay (iter_raw)."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, Writer

    frames = make_frames()
    bag.write_bag(tmp_path / "plain", frames, storage=storage)
    w = Writer(tmp_path / "z", version=9, storage_plugin=bag._storage_plugin(storage))
    w.set_compression(CompressionMode[mode], CompressionFormat.ZSTD)
    w.open()
    with Reader(tmp_path / "plain") as r:
        conns = {c.id: w.add_connection(c.topic, c.msgtype, typestore=bag.typestore())
                 for c in r.connections}
        for c, t, raw in r.messages():
            w.write(conns[c.id], t, raw)
    w.close()
    assert_same(frames, list(FrameReader(tmp_path / "z")))
    assert [m[:3] for m in bag.iter_raw(tmp_path / "z")] == \
        [m[:3] for m in bag.iter_raw(tmp_path / "plain")]
    assert [m[3] for m in bag.iter_raw(tmp_path / "z")] == \
        [m[3] for m in bag.iter_raw(tmp_path / "plain")]


def test_bgr8_and_no_ground_truth(tmp_path):
    frames = make_frames(3, gt=False)
    bag.write_bag(tmp_path / "b", frames, color_encoding="bgr8")
    topics = bag.bag_topics(tmp_path / "b")
    assert Topics().semantic not in topics and topics[Topics().color] == (bag.IMAGE, 3)
    got = list(FrameReader(tmp_path / "b"))
    assert_same(frames, got, gt=False)
    assert all(f.semantic is None for f in got)
    frames_gt = make_frames(2)
    bag.write_bag(tmp_path / "c", frames_gt)
    assert all(f.semantic is None for f in FrameReader(tmp_path / "c", with_ground_truth=False))


def test_custom_topic_names(tmp_path):
    topics = Topics(color="/rgb", depth="/d", camera_info="/info", pose="/p",
                    semantic="/sem", instance="/inst", camera_frame="cam")
    frames = make_frames(2)
    bag.write_bag(tmp_path / "b", frames, topics=topics)
    assert set(bag.bag_topics(tmp_path / "b")) == {"/rgb", "/d", "/info", "/p", "/sem",
                                                   "/inst"}
    assert_same(frames, list(FrameReader(tmp_path / "b", topics=topics)))
    with pytest.raises(BagError, match="no color topic '/camera/color/image_raw'"):
        FrameReader(tmp_path / "b")


def test_tf_instead_of_pose_topic(tmp_path):
    frames = make_frames(4)
    bag.write_bag(tmp_path / "tf", frames, pose_mode="tf")
    assert Topics().pose not in bag.bag_topics(tmp_path / "tf")
    with pytest.raises(BagError, match="tf_parent"):
        FrameReader(tmp_path / "tf")
    got = list(FrameReader(tmp_path / "tf", tf_parent="world", tf_child="camera"))
    assert_same(frames, got)


def test_tf_chain_static_and_dynamic(tmp_path):
    """world -> odom on /tf_static, odom -> base and base -> camera on /tf, camera pose composed."""
    frames = make_frames(3)
    tp = Topics()
    T_wo = look_at([1.0, 2.0, 0.5], [3.0, 2.5, 0.0])
    T_bc = look_at([0.1, 0.0, 0.2], [1.0, 0.1, 0.1])
    T_ow = np.linalg.inv(T_wo)
    items = [(tp.tf_static, bag.TF_MESSAGE, STAMP0 - 10, bag.tf_msg(STAMP0 - 10,
                                                                    [("world", "odom", T_wo)]))]
    for f in frames:
        T_ob = T_ow @ f.pose @ np.linalg.inv(T_bc)
        for topic, typ, s, msg in bag.frame_messages(f, tp, pose_mode="tf"):
            if topic == tp.tf:  # replace the direct transform by the chain
                msg = bag.tf_msg(s + 2_000_000, [("odom", "base", T_ob)])
                items.append((topic, typ, s, msg))
                msg = bag.tf_msg(s, [("base", "camera", T_bc)])
            items.append((topic, typ, s, msg))
    bag.write_messages(tmp_path / "chain", items)
    reader = FrameReader(tmp_path / "chain", tf_parent="world", tf_child="camera")
    got = list(reader)
    assert len(got) == 3 and reader.dropped == []
    for f, g in zip(frames, got):
        np.testing.assert_allclose(g.pose, f.pose, atol=1e-9)
    # a tighter skew than the 2 ms offset of odom->base loses every frame, with the reason
    strict = FrameReader(tmp_path / "chain", tf_parent="world", tf_child="camera",
                         max_stamp_skew_ns=1_000_000)
    assert list(strict) == [] and len(strict.dropped) == 3
    assert all("odom->base" in r for _, r in strict.dropped)
    # a frame not in the tree is refused at once, naming the bag's frames in tree order
    # (it would drop every frame as "missing pose")
    with pytest.raises(BagError, match=r"chain: tf frame 'map' \(tf_parent\) is not in the "
                       r"bag's /tf tree \(frames: world, odom, base, camera\)$"):
        FrameReader(tmp_path / "chain", tf_parent="map", tf_child="camera")
    # tf2's names have no leading slash; one given with it is the same frame
    assert len(FrameReader(tmp_path / "chain", tf_parent="/world", tf_child="camera")) == 3


def test_tf_frames_missing_or_not_connected_are_named(tmp_path):
    """A wrong tf frame name (map for odom) or two frames in separate trees: one line
    naming the bag's frames, from the reader whatever reads the bag (info, run, convert)."""
    frames = make_frames(2)
    tp = Topics()
    items = [(tp.tf_static, bag.TF_MESSAGE, STAMP0 - 10,
              bag.tf_msg(STAMP0 - 10, [("map", "marker", np.eye(4))]))]
    items += [it for f in frames for it in bag.frame_messages(f, tp, pose_mode="tf")]
    bag.write_messages(tmp_path / "two", items)
    with pytest.raises(BagError, match=r"tf frames 'map' \(tf_parent\) and 'camera' "
                       r"\(tf_child\) are not connected in the bag's /tf tree \('map' is in "
                       r"the tree of 'map', 'camera' in that of 'world'; frames: map, marker, "
                       r"world, camera\)"):
        FrameReader(tmp_path / "two", tf_parent="map", tf_child="camera")
    with pytest.raises(BagError, match=r"tf frames 'odom' \(tf_parent\) and 'cam' "
                       r"\(tf_child\) are not in"):
        FrameReader(tmp_path / "two", tf_parent="odom", tf_child="cam")
    # without poses (they are to be estimated) the tf frames are not looked at
    assert len(FrameReader(tmp_path / "two", tf_parent="odom", tf_child="cam",
                           with_poses=False)) == 2
    assert_same(frames, list(FrameReader(tmp_path / "two", tf_parent="world",
                                         tf_child="camera")))


def test_tf_tree_order_and_roots():
    parent = {"camera_link": "base_link", "base_link": "odom", "imu": "base_link",
              "optical": "camera_link", "odom": "map", "a": "b", "b": "a"}
    assert bag.tf_frames_in_tree_order(parent) == ["map", "odom", "base_link", "camera_link",
                                                   "optical", "imu", "a", "b"]
    assert tf_root(parent, "optical") == "map" and tf_root(parent, "map") == "map"
    assert tf_root(parent, "b") == tf_root(parent, "a") == "a"
    assert tf_chain(parent, "optical") == ["optical", "camera_link", "base_link", "odom", "map"]
    # A loop (a malformed /tf) is walked once, and a frame hanging from it has its root.
    assert tf_chain(parent, "b") == ["b", "a"]
    assert tf_root({**parent, "c": "b"}, "c") == "a"


def _items_without(frames, tp, drop):
    """All bag items of ``frames`` except those for which drop(index, topic) is true."""
    out = []
    for i, f in enumerate(frames):
        out += [it for it in bag.frame_messages(f, tp) if not drop(i, it[0])]
    return out


def test_missing_pose_is_reported(tmp_path):
    frames, tp = make_frames(4), Topics()
    bag.write_messages(tmp_path / "b", _items_without(frames, tp,
                                                      lambda i, t: i == 2 and t == tp.pose))
    reader = FrameReader(tmp_path / "b")
    got = list(reader)
    assert [f.stamp_ns for f in got] == [frames[i].stamp_ns for i in (0, 1, 3)]
    assert len(reader.dropped) == 1
    stamp, reason = reader.dropped[0]
    assert stamp == frames[2].stamp_ns and reason.startswith("missing pose")
    assert "1 dropped" in reader.summary() and "missing pose: 1" in reader.summary()


def test_missing_depth_and_camera_info_latest_before(tmp_path):
    frames, tp = make_frames(4), Topics()
    items = _items_without(frames, tp, lambda i, t: (i == 1 and t == tp.depth)
                           or (i > 0 and t == tp.camera_info))
    bag.write_messages(tmp_path / "b", items)
    reader = FrameReader(tmp_path / "b")
    got = list(reader)
    assert [f.stamp_ns for f in got] == [frames[i].stamp_ns for i in (0, 2, 3)]
    assert all(f.intrinsics == frames[0].intrinsics for f in got)  # info of frame 0 reused
    assert reader.dropped[0][0] == frames[1].stamp_ns
    assert reader.dropped[0][1].startswith("missing depth")


def test_nearest_stamp_within_skew(tmp_path):
    frames, tp = make_frames(3), Topics()
    items = []
    for i, f in enumerate(frames):
        shift = (3_000_000 if i < 2 else 30_000_000)  # 3 ms skew matches, 30 ms does not
        for topic, typ, s, msg in bag.frame_messages(f, tp):
            if topic == tp.depth:
                g = Frame(s + shift, f.rgb, f.depth, f.pose, f.intrinsics)
                msg = bag.frame_messages(g, tp)[1][3]
                s += shift
            items.append((topic, typ, s, msg))
    bag.write_messages(tmp_path / "b", items)
    reader = FrameReader(tmp_path / "b", max_stamp_skew_ns=10_000_000)
    got = list(reader)
    assert_same(frames[:2], got)
    assert reader.dropped == [(frames[2].stamp_ns, reader.dropped[0][1])]
    assert "missing depth" in reader.dropped[0][1]
    exact = FrameReader(tmp_path / "b", max_stamp_skew_ns=0)
    assert len(exact) == 0 and len(exact.dropped) == 3


def test_size_mismatch_and_non_finite_pose_reported(tmp_path):
    frames, tp = make_frames(3), Topics()
    small = make_frames(1, w=20, h=10, seed=5)[0]
    items = []
    for i, f in enumerate(frames):
        for topic, typ, s, msg in bag.frame_messages(f, tp):
            if i == 0 and topic == tp.depth:
                g = Frame(s, small.rgb, small.depth, small.pose, small.intrinsics)
                msg = bag.frame_messages(g, tp)[1][3]
            if i == 2 and topic == tp.pose:
                msg.pose.position.x = float("nan")
            items.append((topic, typ, s, msg))
    bag.write_messages(tmp_path / "b", items)
    reader = FrameReader(tmp_path / "b")
    got = list(reader)
    assert [f.stamp_ns for f in got] == [frames[1].stamp_ns]
    reasons = dict(reader.dropped)
    assert "size mismatch" in reasons[frames[0].stamp_ns]
    assert "40x30" in reasons[frames[0].stamp_ns] and "20x10" in reasons[frames[0].stamp_ns]
    assert "non-finite" in reasons[frames[2].stamp_ns]


def test_iter_raw_gives_cdr_in_bag_order(tmp_path):
    frames, tp = make_frames(2), Topics()
    bag.write_bag(tmp_path / "b", frames)
    raw = list(bag.iter_raw(tmp_path / "b"))
    assert len(raw) == 2 * 6
    assert [r[2] for r in raw] == sorted(r[2] for r in raw)
    colour = [r for r in raw if r[0] == tp.color]
    assert [r[1] for r in colour] == [bag.IMAGE] * 2
    msg = bag.typestore().deserialize_cdr(colour[1][3], bag.IMAGE)
    assert (msg.height, msg.width, msg.encoding) == (30, 40, "rgb8")
    np.testing.assert_array_equal(msg.data.reshape(30, 40, 3), frames[1].rgb)
    assert bag.image_stamp_and_size(colour[1][3]) == (frames[1].stamp_ns, 30, 40)
    only = list(bag.iter_raw(tmp_path / "b", [tp.pose, "/absent"]))
    assert [r[0] for r in only] == [tp.pose] * 2
    with pytest.raises(BagError, match="none of the topics"):
        list(bag.iter_raw(tmp_path / "b", ["/absent"]))


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_truncated_bag_raises_naming_file(tmp_path, storage):
    bag.write_bag(tmp_path / "b", make_frames(6), storage=storage)
    f = bag_file(tmp_path / "b")
    os.truncate(f, f.stat().st_size * 2 // 3)
    with pytest.raises(BagError, match=str(tmp_path / "b")) as info:
        FrameReader(tmp_path / "b")
    assert f.name in str(info.value)
    # what to do about it: the recording was cut off, and the tool that saves the rest
    assert ("the recording was cut off" if storage == "mcap" else "truncated or damaged") \
        in str(info.value)
    assert "neurncd recover" in str(info.value)
    with pytest.raises(BagError, match=str(f)):
        FrameReader(f)
    with pytest.raises(BagError, match="bag"):
        list(bag.iter_raw(tmp_path / "b"))


def _zstd_copy(plain: Path, out: Path) -> None:
    """The bag ``plain`` rewritten with MCAP's zstd chunks (storage preset zstd_fast)."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, Writer

    w = Writer(out, version=9, storage_plugin=bag._storage_plugin("mcap"))
    w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    w.open()
    with Reader(plain) as r:
        conns = {c.id: w.add_connection(c.topic, c.msgtype, typestore=bag.typestore())
                 for c in r.connections}
        for c, t, raw in r.messages():
            w.write(conns[c.id], t, raw)
    w.close()


@pytest.mark.parametrize("zstd", [False, True])
def test_a_cut_off_mcap_is_recovered_up_to_its_cut(tmp_path, zstd, capsys):
    """A recording cut off (recorder killed, disk full) is refused with the command that
    saves it; `neurncd recover` copies the whole chunks before the cut, and they read
    as the frames that were recorded. A cut in the summary keeps every frame."""
    from neurncd_ros.cli import main

    frames = make_frames(8, w=320, h=240)  # 0.7 MB a frame: rosbags closes chunks at 1 MiB
    bag.write_bag(tmp_path / "b", frames)
    if zstd:
        _zstd_copy(tmp_path / "b", tmp_path / "z")
    folder = tmp_path / ("z" if zstd else "b")
    src = bag_file(folder)
    whole = src.read_bytes()
    src.write_bytes(whole[: len(whole) * 2 // 3])  # in place: the bag folder is cut off
    with pytest.raises(BagError, match="neurncd recover"):
        FrameReader(folder)
    kept = recover_mcap(folder, tmp_path / "fixed.mcap")
    got = list(FrameReader(tmp_path / "fixed.mcap"))
    assert kept["chunks"] >= 2 and 0 < len(got) < len(frames), (kept, len(got))
    assert_same(frames[: len(got)], got)

    cut = tmp_path / "summary_cut.mcap"  # the data whole, the summary and footer not
    cut.write_bytes(whole[:-30])
    assert main(["recover", str(cut), "--out", str(tmp_path / "all.mcap")]) == 0
    assert "recovered" in capsys.readouterr().out
    assert_same(frames, list(FrameReader(tmp_path / "all.mcap")))
    assert main(["recover", str(cut), "--out", str(tmp_path / "all.mcap")]) == 1
    assert "exists (--overwrite replaces it)" in capsys.readouterr().err
    # The recording itself as --out (a hard link too) is refused, whatever --overwrite.
    os.link(cut, tmp_path / "link.mcap")
    for same in (cut, tmp_path / "link.mcap"):
        assert main(["recover", str(cut), "--out", str(same)]) == 1
        assert "must not replace the recording" in capsys.readouterr().err
    assert main(["recover", str(cut), "--out", str(cut), "--overwrite"]) == 1
    assert "must not replace the recording" in capsys.readouterr().err
    assert cut.read_bytes() == whole[:-30]

    (tmp_path / "whole.mcap").write_bytes(whole)
    with pytest.raises(BagError, match="complete.*nothing to recover"):
        recover_mcap(tmp_path / "whole.mcap", tmp_path / "x.mcap")
    (tmp_path / "stub.mcap").write_bytes(whole[:200])
    with pytest.raises(BagError, match="nothing to recover"):
        recover_mcap(tmp_path / "stub.mcap", tmp_path / "x.mcap")
    with pytest.raises(BagError, match="not an MCAP"):
        recover_mcap(tmp_path / "b" / "metadata.yaml", tmp_path / "x.mcap")
    assert not (tmp_path / "x.mcap").exists()


def test_recover_reads_the_recording_chunk_by_chunk(tmp_path):
    """A recording cut off by a full disk can be tens of GB: recover streams it (one
    chunk in memory at a time), it does not read the whole file into memory."""
    import tracemalloc

    bag.write_bag(tmp_path / "b", make_frames(16, w=320, h=240))  # 11 MB, 1 MiB chunks
    src = bag_file(tmp_path / "b")
    os.truncate(src, src.stat().st_size * 2 // 3)
    tracemalloc.start()
    try:
        kept = recover_mcap(src, tmp_path / "fixed.mcap")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert kept["chunks"] >= 5 and peak < kept["size"] / 4, (kept, peak)
    assert len(list(FrameReader(tmp_path / "fixed.mcap"))) >= 8


def _recover_cut(tmp_path: Path) -> tuple[bytes, Any]:
    """The MCAP file of a recording of 8 frames, and a function that recovers given
    bytes written as a file: (counts, frames read back)."""
    frames = make_frames(8, w=320, h=240)
    bag.write_bag(tmp_path / "b", frames)
    whole = bag_file(tmp_path / "b").read_bytes()
    f, out = tmp_path / "cut.mcap", tmp_path / "fixed.mcap"

    def recovered(data: bytes) -> tuple[dict, list]:
        f.write_bytes(data)
        out.unlink(missing_ok=True)
        kept = recover_mcap(f, out)
        return kept, list(FrameReader(out))

    return whole, recovered


def test_recover_takes_a_cut_ending_in_the_magic_bytes_for_a_cut(tmp_path):
    """A cut that happens to end in the bytes of the MCAP magic (a message carrying
    them) is still cut off: a closed file ends with a footer record, then the magic."""
    whole, recovered = _recover_cut(tmp_path)
    cut = whole[: len(whole) // 2]
    kept, got = recovered(cut)
    assert 0 < len(got) < 8
    assert recovered(cut[:-8] + b"\x89MCAP0\r\n")[0]["bytes"] == kept["bytes"]


def test_recover_stops_at_a_zero_filled_tail_or_a_damaged_chunk(tmp_path):
    """A crash can leave the file's length but not its data (zeros after the cut), and
    rosbags writes uncompressed chunks without a checksum: a chunk whose records do not
    fill it exactly, a record of no MCAP data-section kind (opcode 0) or a chunk header
    too short for its fields ends the copy. The output reads, no Python error escapes,
    and no partial output stays."""
    import struct

    whole, recovered = _recover_cut(tmp_path)
    kept, got = recovered(whole[: len(whole) // 2])
    good = whole[: kept["bytes"]]
    for tail in (whole[len(good): len(good) + 100] + bytes(len(whole)),  # a chunk's
                 bytes(1000),                      # start, then zeros; zeros after the
                 b"\x06" + struct.pack("<Q", 10) + bytes(10)):  # last whole record;
        counts, frames = recovered(good + tail)     # a damaged chunk header
        assert counts["bytes"] == kept["bytes"] and len(frames) == len(got), counts
    assert not (tmp_path / "fixed.mcap.part").exists()


def _sqlite_recording(tmp_path: Path) -> tuple[list[Frame], Path, bytes]:
    """12 frames written as an SQLite bag: the frames, its .db3 file and its bytes."""
    frames = make_frames(12, 80, 60, seed=5)
    bag.write_bag(tmp_path / "rec", frames, storage="sqlite3")
    f = bag_file(tmp_path / "rec")
    return frames, f, f.read_bytes()


def test_a_cut_off_sqlite_recording_is_recovered_up_to_its_cut(tmp_path, capsys):
    """An SQLite bag cut at 60 % (an interrupted copy, a full disk) is refused whole, as
    SQLite refuses a file shorter than its header says; `neurncd recover` copies every
    message before the cut into a .db3 file that reads on its own, frame for frame
    equal to the recording's first frames, and leaves the recording as it was."""
    from neurncd_ros.cli import main

    frames, f, whole = _sqlite_recording(tmp_path)
    cut = tmp_path / "cut" / "cut.db3"
    cut.parent.mkdir()
    cut.write_bytes(whole[: len(whole) * 6 // 10])
    with pytest.raises(BagError, match="neurncd recover"):
        FrameReader(cut)
    kept = recover_sqlite(cut, tmp_path / "fixed.db3")
    assert cut.read_bytes() == whole[: len(whole) * 6 // 10]  # the recording untouched
    assert (kept["first_id"], kept["missing"], kept["last_id"]) == (1, 0, kept["messages"])
    got = list(FrameReader(tmp_path / "fixed.db3"))
    assert 5 <= len(got) <= 8, len(got)
    assert_same(frames[: len(got)], got, gt=False)
    # the ground truth too, where the cut left it (the last frame may lose its instances)
    assert_same(frames[: len(got) - 1], got[:-1])
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".fixed")]  # no staging
    # The command, on the bag folder: it finds the .db3 inside and says what it kept.
    shutil.copytree(tmp_path / "rec", tmp_path / "folder")
    (tmp_path / "folder" / f.name).write_bytes(whole[: len(whole) * 6 // 10])
    assert main(["recover", str(tmp_path / "folder"), "--out",
                 str(tmp_path / "cli.db3")]) == 0
    out = capsys.readouterr().out
    assert f"recovered {kept['messages']} messages on 6 topics" in out
    assert f"messages 1-{kept['messages']}, none missing between them" in out


def test_a_recovered_sqlite_copy_opens_as_rosbag2_opens_it(tmp_path):
    """`ros2 bag info` / `play` on the copy: rosbag2's SQLite plugin (Jazzy,
    sqlite_storage.cpp) reads the schema version, then, from version 3 on, selects from
    the `metadata` table, and the open fails when the table is missing. The copy keeps
    the table, empty (a row would name the recording's files, which rosbag2 then opens
    without a metadata.yaml), and every query rosbag2 runs on opening and reading gives
    the copy's messages, in time order."""
    frames, f, whole = _sqlite_recording(tmp_path)
    with sqlite3.connect(f) as con:  # the recording itself closed with a metadata row
        assert con.execute("SELECT count(*) FROM metadata").fetchone() == (1,)
    cut = tmp_path / "cut.db3"
    cut.write_bytes(whole[: len(whole) * 6 // 10])
    kept = recover_sqlite(cut, tmp_path / "fixed.db3")
    con = sqlite3.connect(f"file:{tmp_path / 'fixed.db3'}?mode=ro", uri=True)
    try:
        (version,), = con.execute("SELECT schema_version FROM schema").fetchall()
        assert version >= 3
        assert con.execute("SELECT metadata_version, metadata FROM metadata ORDER BY id"
                           ).fetchall() == []
        topics = con.execute("SELECT id, name, type, serialization_format, "
                             "offered_qos_profiles, type_description_hash FROM topics "
                             "ORDER BY id").fetchall()
        assert len(topics) == 6
        counted = con.execute(
            "SELECT messages.topic_id, name, type, serialization_format, "
            "COUNT(messages.id), MIN(messages.timestamp), MAX(messages.timestamp), "
            "offered_qos_profiles, type_description_hash FROM messages JOIN topics on "
            "topics.id = messages.topic_id GROUP BY topics.name").fetchall()
        assert sum(row[4] for row in counted) == kept["messages"]
        assert con.execute("SELECT topic_type, encoding, encoded_message_definition, "
                           "type_description_hash FROM message_definitions ORDER BY id"
                           ).fetchall()
        assert con.execute("SELECT ros_distro from schema").fetchall()
        read = con.execute("SELECT data, timestamp, topics.name, messages.id FROM messages "
                           "JOIN topics ON messages.topic_id = topics.id WHERE "
                           "(((timestamp = 0) AND (messages.id >= 0)) OR (timestamp > 0)) "
                           "ORDER BY messages.timestamp ASC, messages.id ASC").fetchall()
        assert len(read) == kept["messages"]
        assert [r[1] for r in read] == sorted(r[1] for r in read)
        indexes = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE "
                                             "type = 'index'")}
        assert "timestamp_idx" in indexes  # rosbag2 reads in time order through it
    finally:
        con.close()


def test_a_recovered_copy_keeps_a_definitions_table_whose_rows_are_lost(tmp_path):
    """A torn page under message_definitions: its rows are gone, but rosbags and rosbag2
    query the table on every schema-4 file; the copy holds it empty and reads."""
    frames, f, whole = _sqlite_recording(tmp_path)
    with sqlite3.connect(f) as con:
        (root,), = con.execute("SELECT rootpage FROM sqlite_master WHERE "
                               "name = 'message_definitions'").fetchall()
        (size,), = con.execute("PRAGMA page_size").fetchall()
    torn = bytearray(whole[: len(whole) * 6 // 10])
    torn[(root - 1) * size: root * size] = b"\xff" * size
    cut = tmp_path / "cut.db3"
    cut.write_bytes(bytes(torn))
    kept = recover_sqlite(cut, tmp_path / "fixed.db3")
    with sqlite3.connect(tmp_path / "fixed.db3") as con:
        assert con.execute("SELECT count(*) FROM message_definitions").fetchone() == (0,)
    got = list(FrameReader(tmp_path / "fixed.db3"))
    assert len(got) >= 5 and kept["messages"] > 0
    assert_same(frames[: len(got)], got, gt=False)


def test_sqlite_recover_skips_a_damaged_range_and_keeps_what_follows(tmp_path):
    """Pages zeroed in the middle (a torn write) lose the messages on them; the messages
    after them are read again, and every frame that comes back is exact."""
    frames, f, whole = _sqlite_recording(tmp_path)
    page = 4096
    mid = len(whole) // 2 // page * page
    torn = tmp_path / "torn.db3"
    torn.write_bytes(whole[:mid] + bytes(3 * page) + whole[mid + 3 * page:])
    cut = tmp_path / "cut.db3"
    cut.write_bytes(whole[:mid])
    kept = recover_sqlite(torn, tmp_path / "fixed.db3")
    upto = recover_sqlite(cut, tmp_path / "upto.db3")
    assert kept["missing"] >= 1 and kept["last_id"] == 12 * 6  # the last message is kept
    assert kept["messages"] > upto["messages"] + 12  # what follows the damage is kept
    got = list(FrameReader(tmp_path / "fixed.db3"))
    by_stamp = {fr.stamp_ns: fr for fr in frames}
    assert len(got) > len(list(FrameReader(tmp_path / "upto.db3")))
    assert_same([by_stamp[g.stamp_ns] for g in got], got, gt=False)


def _commit_to_log_and_die(db: Path, statement: str, setup: str = "") -> None:
    """In another process: ``setup`` (Python on connection ``c``), then the database in
    WAL mode with no automatic checkpoint, ``statement`` committed to the log, and the
    process killed before it closes the database (the log stays beside it)."""
    import subprocess
    import sys

    script = ("import os, sqlite3, sys\n"
              "c = sqlite3.connect(sys.argv[1])\n" + setup +
              "c.execute('PRAGMA journal_mode=WAL'); c.execute('PRAGMA wal_autocheckpoint=0')\n"
              f"{statement}\n"
              "c.commit(); os._exit(0)\n")
    subprocess.run([sys.executable, "-c", script, str(db)], check=True)


def test_sqlite_recover_reads_the_write_ahead_log_beside_the_recording(tmp_path):
    """rosbag2's resilient preset writes in WAL mode: messages committed to the -wal file
    but not yet to the database are there too (the log is read with the copy, never
    written into the recording)."""
    import sqlite3

    frames, f, whole = _sqlite_recording(tmp_path)
    rec = tmp_path / "wal" / "w.db3"
    rec.parent.mkdir()
    rec.write_bytes(whole)
    # Six more messages committed to the log, then the writer dies before a checkpoint.
    _commit_to_log_and_die(rec, "c.executemany('INSERT INTO messages (topic_id, timestamp, "
                           "data) VALUES (?, ? + 10000000000, ?)', c.execute('SELECT "
                           "topic_id, timestamp, data FROM messages WHERE id <= 6')"
                           ".fetchall())")
    wal = rec.with_name("w.db3-wal")
    assert wal.stat().st_size > 0
    os.truncate(rec, len(whole) * 6 // 10)
    log = wal.read_bytes()
    kept = recover_sqlite(rec, tmp_path / "fixed.db3")
    assert wal.read_bytes() == log and rec.stat().st_size == len(whole) * 6 // 10
    cut = tmp_path / "cut.db3"
    cut.write_bytes(whole[: len(whole) * 6 // 10])
    upto = recover_sqlite(cut, tmp_path / "upto.db3")
    # (the log also holds the pages the inserts rewrote: a row beyond the cut may return)
    assert kept["messages"] >= upto["messages"] + 6 and kept["last_id"] == 12 * 6 + 6
    con = sqlite3.connect(tmp_path / "fixed.db3")
    late = con.execute("SELECT count(*) FROM messages WHERE timestamp > ?",
                       (STAMP0 + 5 * 10**9,)).fetchone()[0]  # the log's, 10 s later
    con.close()
    assert late == 6


def _small_messages_db(tmp_path: Path, ids) -> tuple[Path, bytes]:
    """An SQLite bag (the package's own tables) of 100-byte messages with these ids, so
    that a page holds a few dozen of them: the file and its bytes."""
    import sqlite3

    _, f, _ = _sqlite_recording(tmp_path)
    src = sqlite3.connect(f)
    path = tmp_path / "small.db3"
    dst = sqlite3.connect(path)
    for (sql,) in src.execute("SELECT sql FROM sqlite_master WHERE sql IS NOT NULL"):
        dst.execute(sql)
    topics = src.execute("SELECT * FROM topics").fetchall()
    dst.executemany(f"INSERT INTO topics VALUES ({', '.join('?' * len(topics[0]))})", topics)
    rng = np.random.default_rng(0)
    dst.executemany("INSERT INTO messages VALUES (?, ?, ?, ?)",
                    [(i, topics[0][0], STAMP0 + i, rng.bytes(100)) for i in ids])
    dst.commit()
    dst.close()
    src.close()
    return path, path.read_bytes()


def _readable_ids(path: Path, ids) -> set[int]:
    """The ids SQLite itself still returns one by one from a damaged file (its B-tree's
    interior pages intact): what a recovery must keep at least."""
    import sqlite3

    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    ok = set()
    for i in ids:
        try:
            if con.execute("SELECT id FROM messages WHERE id = ?", (i,)).fetchone():
                ok.add(i)
        except sqlite3.DatabaseError:
            pass
    con.close()
    return ok


@pytest.mark.parametrize("ids,zeroed", [
    (range(1, 3001), [(104, 108)]),             # a long damaged range, then a short tail
    (range(1, 3001), [(60, 63), (66, 70)]),     # two damaged ranges, rows between them
    (range(1000, 3_000_001, 1000), [(40, 43)]),  # ids with gaps
])
def test_sqlite_recover_keeps_every_row_off_the_damaged_pages(tmp_path, ids, zeroed):
    """Message rows are read off every page of the file, not through the B-tree: what
    lies between or after damaged pages comes back whatever the ids, each row exact."""
    import sqlite3

    path, whole = _small_messages_db(tmp_path, ids)
    page = 4096
    buf = bytearray(whole)
    for a, b in zeroed:  # pages a..b-1 (1-based) torn to zeros
        buf[(a - 1) * page:(b - 1) * page] = bytes((b - a) * page)
    torn = tmp_path / "torn.db3"
    torn.write_bytes(bytes(buf))
    must = _readable_ids(torn, ids)
    assert 0 < len(must) < len(ids)
    kept = recover_sqlite(torn, tmp_path / "fixed.db3")
    con = sqlite3.connect(tmp_path / "fixed.db3")
    got = dict(((i, d) for i, d in con.execute("SELECT id, data FROM messages")))
    con.close()
    assert must <= set(got), sorted(must - set(got))[:5]
    assert kept["messages"] == len(got) and kept["last_id"] == max(ids)
    orig = sqlite3.connect(path)
    for i, data in orig.execute("SELECT id, data FROM messages"):
        assert got.get(i, data) == data  # every row kept is the row written
    orig.close()


def test_sqlite_recover_leaves_deleted_rows_deleted(tmp_path):
    """Rows deleted from a recording (a user's edit: rosbag2 never deletes) stay deleted:
    pages on the freelist, which still hold them, are not read, nor pages past the end a
    write-ahead log's last commit gives the database."""
    import sqlite3

    path, _ = _small_messages_db(tmp_path, range(1, 3001))
    con = sqlite3.connect(path)
    con.execute("PRAGMA secure_delete=off")  # freed pages keep their old rows
    con.execute("DELETE FROM messages WHERE id BETWEEN 1000 AND 1999")
    con.commit()
    assert con.execute("PRAGMA freelist_count").fetchone()[0] > 0
    con.close()
    whole = path.read_bytes()
    cut = tmp_path / "cut.db3"
    cut.write_bytes(whole[: len(whole) * 9 // 10])
    kept = recover_sqlite(cut, tmp_path / "fixed.db3")
    con = sqlite3.connect(tmp_path / "fixed.db3")
    ids = {i for (i,) in con.execute("SELECT id FROM messages")}
    con.close()
    assert not ids & set(range(1000, 2000)) and kept["messages"] == len(ids) > 1000
    # The same delete committed only to a write-ahead log, with auto-vacuum: the log's
    # last commit ends the database before pages that still hold the deleted rows.
    rec = tmp_path / "wal" / "w.db3"
    rec.parent.mkdir()
    setup = ("c.execute('PRAGMA auto_vacuum=FULL')\n"
             "c.execute('CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, "
             "type TEXT NOT NULL, serialization_format TEXT NOT NULL, "
             "offered_qos_profiles TEXT NOT NULL)')\n"
             "c.execute('CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER "
             "NOT NULL, timestamp INTEGER NOT NULL, data BLOB NOT NULL)')\n"
             "c.execute(\"INSERT INTO topics VALUES (1, '/t', 'std_msgs/msg/String', "
             "'cdr', '')\")\n"
             "c.executemany('INSERT INTO messages VALUES (?, 1, ?, ?)', "
             "[(i, i, os.urandom(100)) for i in range(1, 3001)])\n"
             "c.commit()\n")
    _commit_to_log_and_die(rec, "c.execute('DELETE FROM messages WHERE id > 1000')",
                           setup=setup)
    kept = recover_sqlite(rec, tmp_path / "walfixed.db3")
    assert (kept["messages"], kept["last_id"]) == (1000, 1000)


def test_sqlite_recover_applies_a_log_holding_page_one_to_a_cut_file(tmp_path):
    """A log frame of page 1 (any committed change writes it) must not bring back the
    page count of the whole file into a cut copy: the rows on the pages that are there
    come back, as without the log."""

    path, whole = _small_messages_db(tmp_path, range(1, 3001))
    rec = tmp_path / "wal" / "w.db3"
    rec.parent.mkdir()
    rec.write_bytes(whole)
    _commit_to_log_and_die(rec, "c.execute('PRAGMA user_version=7')")
    os.truncate(rec, len(whole) // 2)
    cut = tmp_path / "cut.db3"
    cut.write_bytes(whole[: len(whole) // 2])
    with_log = recover_sqlite(rec, tmp_path / "a.db3")
    without = recover_sqlite(cut, tmp_path / "b.db3")
    assert with_log["messages"] == without["messages"] > 1000


def test_sqlite_recover_refuses_what_it_cannot_or_need_not_recover(tmp_path):
    frames, f, whole = _sqlite_recording(tmp_path)
    with pytest.raises(BagError, match="nothing wrong with it: nothing to recover"):
        recover_sqlite(f, tmp_path / "x.db3")
    cut = tmp_path / "cut.db3"
    cut.write_bytes(whole[: len(whole) // 2])
    with pytest.raises(BagError, match=r"is a \.db3 file: name it x\.db3"):
        recover_sqlite(cut, tmp_path / "x.mcap")
    with pytest.raises(BagError, match="must not replace the recording"):
        recover_sqlite(cut, cut)
    (tmp_path / "stub.db3").write_bytes(whole[:3000])
    with pytest.raises(BagError, match="first page: nothing to recover"):
        recover_sqlite(tmp_path / "stub.db3", tmp_path / "x.db3")
    (tmp_path / "junk.db3").write_bytes(b"not a database at all" * 10)
    with pytest.raises(BagError, match="not an SQLite file"):
        recover_sqlite(tmp_path / "junk.db3", tmp_path / "x.db3")
    bad = bytearray(whole[: len(whole) // 2])
    bad[16:18] = b"\x00\x00"  # a page size of 0
    (tmp_path / "ps0.db3").write_bytes(bytes(bad))
    with pytest.raises(BagError, match="header is damaged"):
        recover_sqlite(tmp_path / "ps0.db3", tmp_path / "new" / "deeper" / "x.db3")
    assert not (tmp_path / "new").exists()  # the folders it made for the output are gone
    (tmp_path / "folder.db3").mkdir()
    with pytest.raises(BagError, match="is a folder"):
        recover_sqlite(cut, tmp_path / "folder.db3")
    (tmp_path / "empty").mkdir()  # a folder holding neither kind of recording
    for recover, out in ((recover_sqlite, "x.db3"), (recover_mcap, "x.mcap")):
        with pytest.raises(BagError, match=r"no recording in it \(no \.mcap or \.db3"):
            recover(tmp_path / "empty", tmp_path / out)
    (tmp_path / "empty" / "rosbag2_0.db3.zstd").write_bytes(b"(\xb5/\xfd")
    with pytest.raises(BagError, match=r"is compressed \(rosbag2_0\.db3\.zstd\).*zstd -d"):
        recover_sqlite(tmp_path / "empty", tmp_path / "x.db3")
    shutil.rmtree(tmp_path / "empty")
    assert not (tmp_path / "x.db3").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging
    # A path with URI characters in it is a path, not a URI (# is no fragment).
    odd = tmp_path / "run#2?x" / "cut.db3"
    odd.parent.mkdir()
    odd.write_bytes(whole[: len(whole) // 2])
    assert recover_sqlite(odd, tmp_path / "odd.db3")["messages"] > 0
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("run")) == \
        ["run#2?x"]


def test_a_bag_folder_without_metadata_names_its_file_and_reindex(tmp_path):
    """rosbag2 writes metadata.yaml when a recording ends: a folder without it got rosbags'
    "Expected metadata file ... does not exist" alone. The error names the storage file,
    which reads on its own, and `ros2 bag reindex`."""
    bag.write_bag(tmp_path / "b", make_frames(3))
    (tmp_path / "b" / "metadata.yaml").unlink()
    f = bag_file(tmp_path / "b")
    with pytest.raises(BagError, match="no metadata.yaml") as info:
        FrameReader(tmp_path / "b")
    assert f"give the storage file itself ({f})" in str(info.value)
    assert f"ros2 bag reindex {tmp_path / 'b'}" in str(info.value)
    assert len(list(FrameReader(f))) == 3


def test_bogus_and_missing_bags(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not a bag " * 50)
    with pytest.raises(BagError, match="junk.mcap"):
        FrameReader(junk)
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    with pytest.raises(BagError, match="notes.txt"):
        FrameReader(text)
    with pytest.raises(BagError, match="no such bag"):
        FrameReader(tmp_path / "absent")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match="empty"):
        FrameReader(tmp_path / "empty")
    assert issubclass(BagError, ValueError)


def test_writer_rejects_bad_arguments(tmp_path):
    frames = make_frames(1)
    with pytest.raises(BagError, match="storage"):
        bag.write_bag(tmp_path / "a", frames, storage="rosbag1")
    with pytest.raises(BagError, match="depth_encoding"):
        bag.write_bag(tmp_path / "b", frames, depth_encoding="mono8")
    bag.write_bag(tmp_path / "c", frames)
    with pytest.raises(BagError, match="exists"):
        bag.write_bag(tmp_path / "c", frames)
    assert bag.write_bag(tmp_path / "c", make_frames(2), overwrite=True) == 2
    far = make_frames(1)[0]
    far.depth[0, 0] = 70.0  # beyond 16UC1 range
    with pytest.raises(BagError, match="65.535"):
        bag.write_bag(tmp_path / "d", [far])
    with pytest.raises(BagError, match="tf_parent"):
        FrameReader(tmp_path / "c", tf_parent="world")


def test_storage_follows_the_suffix(tmp_path):
    """``--out scene.db3`` without a storage made an mcap file in a folder called .db3: the
    suffix now chooses, and a storage that contradicts it is refused."""
    frames = make_frames(1)
    bag.write_bag(tmp_path / "s.db3", frames)
    bag.write_bag(tmp_path / "m.mcap", frames)
    bag.write_bag(tmp_path / "plain", frames, storage="sqlite3")
    # the storage file is named after the folder without doubling its suffix
    assert sorted(p.name for p in (tmp_path / "s.db3").iterdir()) == ["metadata.yaml", "s.db3"]
    assert sorted(p.name for p in (tmp_path / "m.mcap").iterdir()) == ["m.mcap",
                                                                       "metadata.yaml"]
    assert len(list(FrameReader(tmp_path / "s.db3"))) == 1
    assert (tmp_path / "plain" / "plain.db3").is_file()
    with pytest.raises(BagError, match=r"suffix \.db3 says sqlite3.*name it x\.mcap"):
        bag.write_bag(tmp_path / "x.db3", frames, storage="mcap")
    assert not (tmp_path / "x.db3").exists()


@pytest.mark.slow
def test_write_and_read_300_frames(tmp_path):
    """A full-size sequence round-trips through both storages (its speed is
    bench/synth.py's figure, not a test's)."""
    frames = make_frames(300, w=320, h=240)
    for storage in ("mcap", "sqlite3"):
        bag.write_bag(tmp_path / storage, frames, storage=storage)
        back = list(FrameReader(tmp_path / storage))
        assert len(back) == 300
        assert np.array_equal(back[-1].depth, frames[-1].depth)
    shutil.rmtree(tmp_path)


def test_missing_pose_interpolated_when_allowed(tmp_path):
    from neurncd_ros.core.camera import pose_distance
    frames, tp = make_frames(4), Topics()
    bag.write_messages(tmp_path / "b", _items_without(frames, tp,
                                                      lambda i, t: i == 2 and t == tp.pose))
    reader = FrameReader(tmp_path / "b", max_pose_gap_ns=2 * PERIOD + 1)
    got = list(reader)
    assert reader.dropped == [] and len(got) == 4
    assert_same([frames[i] for i in (0, 1, 3)], [got[i] for i in (0, 1, 3)])
    p1, p3, mid = frames[1].pose, frames[3].pose, got[2].pose
    np.testing.assert_allclose(mid[:3, 3], (p1[:3, 3] + p3[:3, 3]) / 2, atol=1e-9)
    _, ang = pose_distance(p1, p3)
    assert pose_distance(p1, mid)[1] == pytest.approx(ang / 2, abs=1e-6)
    assert pose_distance(mid, p3)[1] == pytest.approx(ang / 2, abs=1e-6)
    # a gap limit below the 2-frame spacing keeps the drop
    assert len(FrameReader(tmp_path / "b", max_pose_gap_ns=PERIOD).dropped) == 1


def test_unsupported_encodings_are_dropped_with_reason(tmp_path):
    from neurncd_ros.core.msgconv import image_fields
    frames, tp = make_frames(3), Topics()
    items = []
    for i, f in enumerate(frames):
        for topic, typ, s, msg in bag.frame_messages(f, tp):
            if i == 0 and topic == tp.depth:  # 8-bit depth is not a depth encoding
                msg = bag.image_msg(s, "camera", image_fields(f.rgb[:, :, 0], "mono8"))
            if i == 1 and topic == tp.color:  # grey colour image
                msg = bag.image_msg(s, "camera", image_fields(f.rgb[:, :, 0], "mono8"))
            items.append((topic, typ, s, msg))
    bag.write_messages(tmp_path / "b", items, storage="sqlite3")
    reader = FrameReader(tmp_path / "b")
    got = list(reader)
    assert_same(frames[2:], got)
    reasons = dict(reader.dropped)
    assert reasons[frames[0].stamp_ns].startswith("bad depth") and "mono8" in \
        reasons[frames[0].stamp_ns]
    assert reasons[frames[1].stamp_ns].startswith("bad color")
    assert "bad depth: 1" in reader.summary() and "bad color: 1" in reader.summary()


def _distorted_bag(path: Path) -> tuple[list[Frame], Topics]:
    """Three frames whose camera info has a RealSense-like small distortion."""
    frames, tp = make_frames(3), Topics()
    items = []
    for f in frames:
        for topic, kind, stamp, msg in bag.frame_messages(f, tp):
            if topic == tp.camera_info:
                msg.d = np.array([0.12, -0.25, 0.001, 0.0, 0.1])
            items.append((topic, kind, stamp, msg))
    bag.write_messages(path, items)
    return frames, tp


def test_distorted_camera_info_is_refused_or_taken_as_its_k(tmp_path):
    """A RealSense-like camera info with small distortion coefficients: every frame is
    dropped with the reason naming topics.distortion, or with 'ignore' read with K."""
    import dataclasses

    frames, tp = _distorted_bag(tmp_path / "b")
    refused = FrameReader(tmp_path / "b")
    assert list(refused) == []
    assert all("topics.distortion" in reason for _, reason in refused.dropped)
    ignored = FrameReader(tmp_path / "b", dataclasses.replace(tp, distortion="ignore"))
    got = list(ignored)
    assert [f.stamp_ns for f in got] == [f.stamp_ns for f in frames]
    assert all(g.intrinsics == f.intrinsics for g, f in zip(got, frames))


def test_a_bag_whose_frames_are_all_dropped_says_why(tmp_path):
    """info names the first reason of each kind in full; run and convert refuse such a
    bag with it instead of 'no frames to run on' or an empty output bag."""
    from neurncd_ros import config
    from neurncd_ros.core.data import formats
    from neurncd_ros.core.engine.offline import run_bag

    _distorted_bag(tmp_path / "b")
    text = FrameReader(tmp_path / "b").summary()
    assert "3 dropped (bad camera_info: 3)" in text
    assert "first bad camera_info: " in text and "topics.distortion to 'ignore'" in text
    with pytest.raises(ValueError, match="no frames to run on: .*topics.distortion"):
        run_bag(tmp_path / "b", config.default(), tmp_path / "run")
    with pytest.raises(formats.FormatError, match="no frames to convert: .*topics.distortion"):
        formats.convert(tmp_path / "b", tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists()


# ---------------------------------------------------------------- compressed images

def _compressed(stamp: int, fmt: str, data: bytes):
    """A rosbags sensor_msgs/CompressedImage, built here by hand (cv2 encodes)."""
    return bag._t(bag.COMPRESSED_IMAGE)(header=bag.header_msg(stamp, "camera"), format=fmt,
                                        data=np.frombuffer(data, np.uint8))


def _png(img: np.ndarray) -> bytes:
    import cv2
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def _compressed_bag(path: Path, frames: list[Frame], colour: str = "png",
                    depth: str = "16UC1", rvl: bool = False) -> Topics:
    """The frames as image_transport records them: colour on .../compressed (PNG or JPEG,
    BGR inside), depth on .../compressedDepth (12-byte header, then a PNG of millimetres,
    or for 32FC1 of the quantised inverse depth), ground truth as 16-bit PNGs."""
    import struct

    import cv2
    raw = Topics()
    tp = Topics(color=raw.color + "/compressed", depth=raw.depth + "/compressedDepth",
                semantic=raw.semantic + "/compressed", instance=raw.instance + "/compressed")
    items = []
    for f in frames:
        s = f.stamp_ns
        for topic, typ, stamp, msg in bag.frame_messages(f, raw):
            if topic == raw.color:
                if colour == "png":
                    msg = _compressed(s, "rgb8; png compressed bgr8", _png(f.rgb[:, :, ::-1]))
                else:
                    ok, buf = cv2.imencode(".jpg", f.rgb[:, :, ::-1],
                                           [cv2.IMWRITE_JPEG_QUALITY, 95])
                    msg = _compressed(s, "rgb8; jpeg compressed bgr8", buf.tobytes())
                topic, typ = tp.color, bag.COMPRESSED_IMAGE
            elif topic == raw.depth:
                if depth == "16UC1":
                    mm = np.round(f.depth * 1000).astype(np.uint16)
                    head, img = struct.pack("<iff", 0, 0.0, 0.0), mm
                else:  # compressed_depth_image_transport's inverse-depth quantisation
                    z0, zmax = 100.0, 10.0
                    a = z0 * (z0 + 1.0)
                    b = 1.0 - a / zmax
                    with np.errstate(divide="ignore"):
                        q = np.where(f.depth > 0, a / f.depth + b, 0)
                    head, img = struct.pack("<iff", 0, a, b), q.astype(np.uint16)
                body = _png(img) if not rvl else struct.pack("<II", 64, 48) + bytes(99)
                codec = "rvl" if rvl else "png"
                msg = _compressed(s, f"{depth}; compressedDepth {codec}", head + body)
                topic, typ = tp.depth, bag.COMPRESSED_IMAGE
            elif topic in (raw.semantic, raw.instance):
                img = f.semantic if topic == raw.semantic else f.instance
                topic = tp.semantic if topic == raw.semantic else tp.instance
                msg, typ = _compressed(s, "mono16; png compressed", _png(img)), \
                    bag.COMPRESSED_IMAGE
            items.append((topic, typ, stamp, msg))
    bag.write_messages(path, items)
    return tp


def test_compressed_colour_depth_and_ground_truth_read_exactly(tmp_path):
    frames = make_frames(3, w=64, h=48)
    tp = _compressed_bag(tmp_path / "b", frames)
    assert bag.bag_topics(tmp_path / "b")[tp.color] == (bag.COMPRESSED_IMAGE, 3)
    reader = FrameReader(tmp_path / "b", topics=tp)
    assert len(reader) == 3 and reader.gt_roles == ["semantic", "instance"]
    assert_same(frames, list(reader))  # PNG is lossless: every pixel and depth as written
    assert reader.dropped == []


def test_jpeg_colour_and_quantised_inverse_depth(tmp_path):
    frames = make_frames(2, w=64, h=48, gt=False)
    v, u = np.mgrid[0:48, 0:64]
    for i, f in enumerate(frames):  # smooth colour, as a camera sees (JPEG halves chroma)
        f.rgb = np.stack([u * 4, v * 5, 255 - u * 2 - v - 40 * i], -1).astype(np.uint8)
    tp = _compressed_bag(tmp_path / "b", frames, colour="jpeg", depth="32FC1")
    got = list(FrameReader(tmp_path / "b", topics=tp))
    assert len(got) == 2
    for f, g in zip(frames, got):
        assert g.rgb.shape == f.rgb.shape and g.depth.dtype == np.float32
        # JPEG at quality 95: close, not exact, and still RGB (not BGR).
        err = np.abs(g.rgb.astype(int) - f.rgb.astype(int))
        assert err.mean() < 3, err.mean()
        assert err.mean() < np.abs(g.rgb.astype(int) - f.rgb[:, :, ::-1].astype(int)).mean()
        # No depth stays no depth (not NaN); the rest within the quantisation's step.
        np.testing.assert_array_equal(g.depth == 0, f.depth == 0)
        ok = f.depth > 0
        assert np.abs(g.depth[ok] - f.depth[ok]).max() < 0.01 * f.depth[ok].max() ** 2


def test_compressed_bag_problems_are_named(tmp_path):
    frames = make_frames(2, w=64, h=48, gt=False)
    tp = _compressed_bag(tmp_path / "rvl", frames, rvl=True)
    reader = FrameReader(tmp_path / "rvl", topics=tp)
    assert len(reader) == 0 and len(reader.dropped) == 2
    assert all(r.startswith("bad depth: /camera/depth/image_raw/compressedDepth: "
                            "compressedDepth with the RVL codec is not supported")
               for _, r in reader.dropped), reader.dropped
    assert "bad depth: 2" in reader.summary()
    # The raw topic names of a compressed bag are not in it: the error names the topic to set.
    with pytest.raises(BagError, match="no color topic '/camera/color/image_raw'; .*; it has "
                                       "'/camera/color/image_raw/compressed' "
                                       r"\(sensor_msgs/msg/CompressedImage\): set topics.color"):
        FrameReader(tmp_path / "rvl")
    # A topic of another type is refused, naming the types it may have.
    with pytest.raises(BagError, match="has type sensor_msgs/msg/CameraInfo, expected "
                                       "sensor_msgs/msg/Image or sensor_msgs/msg/CompressedImage"):
        FrameReader(tmp_path / "rvl", topics=Topics(color=tp.camera_info, depth=tp.depth))
    # One colour message whose data is no image: that frame is dropped, naming why.
    frames = make_frames(3, w=64, h=48, gt=False)
    tp = _compressed_bag(tmp_path / "ok", frames)
    s0 = frames[0].stamp_ns
    items = []
    for f in frames:
        for topic, typ, stamp, msg in bag.frame_messages(f):
            if topic == Topics().color:
                data = b"not a jpeg" if stamp == s0 else _png(f.rgb[:, :, ::-1])
                topic, typ, msg = tp.color, bag.COMPRESSED_IMAGE, _compressed(stamp, "jpeg", data)
            items.append((topic, typ, stamp, msg))
    bag.write_messages(tmp_path / "bad", items)
    reader = FrameReader(tmp_path / "bad", topics=Topics(color=tp.color))
    assert_same(frames[1:], list(reader), gt=False)
    assert reader.dropped == [(s0, "bad color: /camera/color/image_raw/compressed: compressed "
                                   "image (format 'jpeg') cannot be decoded (10 bytes)")]


def test_encoded_size_reads_png_and_jpeg_headers():
    import cv2
    img = np.zeros((37, 53, 3), np.uint8)
    assert bag.encoded_size(_png(img)) == (37, 53)
    ok, jpg = cv2.imencode(".jpg", img)
    assert bag.encoded_size(jpg.tobytes()) == (37, 53)
    assert bag.encoded_size(b"not an image") is None
    assert bag.encoded_size(jpg.tobytes()[:20]) is None  # cut before its SOF segment
