"""ROS 2 bag I/O (rosbags, no rclpy): write Frames, read synchronised Frames, raw replay.

- :func:`write_bag` writes colour, depth, camera info, pose (topic and/or /tf)
  and optional semantic / instance ground truth, stamped with ``frame.stamp_ns``;
- :class:`FrameReader` re-assembles Frames from a bag by header stamp (exact
  or nearest within ``max_stamp_skew_ns``; poses optionally interpolated; colour,
  depth and ground truth as sensor_msgs/Image or CompressedImage, as robots record
  them through image_transport),
  taking the pose from the pose topic or from /tf (+ /tf_static) chains (a
  tf frame pair the bag's tree cannot connect is refused, naming its frames), and
  lists what it had to drop;
- :func:`iter_raw` yields raw CDR messages for the replay node;
  :func:`write_messages` writes arbitrary (topic, type, stamp, msg) items.

All message <-> numpy conversion goes through :mod:`neurncd_ros.core.msgconv`.
Every failure to read a bag (missing, truncated, corrupt) raises
:class:`BagError` naming the file. Writer, reader and raw replay stay in one
module (over 500 lines) because they share the bag's topic/type table, its QoS
records and the error handling that names the file. A cut-off MCAP recording is
recovered by :mod:`mcap_recover`.
"""

from __future__ import annotations

import collections
import dataclasses
import struct
from pathlib import Path
from typing import Any, Iterable, Iterator

import numpy as np

from ..msgconv import (MessageError, camera_info_fields, camera_info_to_intrinsics,
                        decode_compressed, is_compressed,
                        depth_fields, depth_from_image, image_fields, image_to_array,
                        matrix_to_pose_fields, ns_to_stamp, pose_to_matrix, rgb_from_image,
                        stamp_to_ns)
from ..camera import Intrinsics, check_pose
from ..frame import Frame
from ..params import param
from ..sync import TfBuffer, nearest, pose_at, tf_root
from ..topics import Topics, compressed_alternatives

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STORAGES = ("mcap", "sqlite3")


class BagError(ValueError):
    """A bag cannot be read or written; the text names the file and the problem."""


@dataclasses.dataclass(frozen=True)
class SyncConfig:
    """How :class:`FrameReader` matches messages into frames."""

    max_stamp_skew_ns: int = param(10_000_000, "largest header-stamp difference between "
                                   "colour and depth / pose / ground truth / tf matched into "
                                   "one frame (nearest wins)", lo=0, unit="ns")
    max_pose_gap_ns: int = param(0, "interpolate the pose (pose topic or each /tf edge) between "
                                 "samples at most this far apart; 0 = exact or nearest only",
                                 lo=0, unit="ns")
    with_ground_truth: bool = param(True, "attach semantic / instance images when present")
    tf_parent: str = param("", "with tf_child: take the pose from /tf as parent->child "
                           "(e.g. world->camera) instead of the pose topic")
    tf_child: str = param("", "child frame of the tf pose lookup (the camera optical frame)")


# ---------------------------------------------------------------- typestore, messages

_TYPESTORE = None


def typestore() -> Any:
    """The ROS 2 Jazzy typestore (made once)."""
    global _TYPESTORE
    if _TYPESTORE is None:
        from rosbags.typesys import Stores, get_typestore
        _TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
    return _TYPESTORE


def _t(name: str) -> Any:
    return typestore().types[name]


def header_msg(stamp_ns: int, frame_id: str) -> Any:
    sec, nsec = ns_to_stamp(stamp_ns)
    return _t("std_msgs/msg/Header")(stamp=_t("builtin_interfaces/msg/Time")(sec=sec,
                                                                              nanosec=nsec),
                                     frame_id=frame_id)


def image_msg(stamp_ns: int, frame_id: str, fields: dict[str, Any]) -> Any:
    """sensor_msgs/Image from :func:`msgconv.image_fields` output."""
    return _t(IMAGE)(header=header_msg(stamp_ns, frame_id), **fields)


def camera_info_msg(stamp_ns: int, frame_id: str, intr: Intrinsics) -> Any:
    f = camera_info_fields(intr)
    roi = _t("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0,
                                                  do_rectify=False)
    return _t(CAMERA_INFO)(
        header=header_msg(stamp_ns, frame_id), height=int(f["height"]),
        width=int(f["width"]), distortion_model=f["distortion_model"],
        d=np.asarray(f["d"], np.float64), k=np.asarray(f["k"], np.float64),
        r=np.asarray(f["r"], np.float64), p=np.asarray(f["p"], np.float64),
        binning_x=0, binning_y=0, roi=roi)


def _quat(q: tuple) -> Any:
    return _t("geometry_msgs/msg/Quaternion")(x=q[0], y=q[1], z=q[2], w=q[3])


def pose_msg(stamp_ns: int, frame_id: str, T: np.ndarray) -> Any:
    f = matrix_to_pose_fields(T)
    pos = _t("geometry_msgs/msg/Point")(x=f["position"][0], y=f["position"][1],
                                        z=f["position"][2])
    pose = _t("geometry_msgs/msg/Pose")(position=pos, orientation=_quat(f["orientation"]))
    return _t(POSE_STAMPED)(header=header_msg(stamp_ns, frame_id), pose=pose)


def tf_msg(stamp_ns: int, transforms: list[tuple[str, str, np.ndarray]]) -> Any:
    """tf2_msgs/TFMessage of (parent, child, T_parent_child) transforms."""
    out = []
    for parent, child, T in transforms:
        f = matrix_to_pose_fields(T)
        tr = _t("geometry_msgs/msg/Vector3")(x=f["position"][0], y=f["position"][1],
                                             z=f["position"][2])
        out.append(_t("geometry_msgs/msg/TransformStamped")(
            header=header_msg(stamp_ns, parent), child_frame_id=child,
            transform=_t("geometry_msgs/msg/Transform")(translation=tr,
                                                        rotation=_quat(f["orientation"]))))
    return _t(TF_MESSAGE)(transforms=out)


# ---------------------------------------------------------------- writing

_SUFFIX_STORAGE = {".mcap": "mcap", ".db3": "sqlite3"}


def storage_for(path: str | Path, storage: str | None = None) -> str:
    """The storage a bag at ``path`` is written in: ``storage``, or else the one its suffix
    names (``.db3`` sqlite3, otherwise mcap).

    A suffix naming the other storage is an error: ``--out scene.db3 --format mcap`` would
    make a folder that says sqlite3 and holds an mcap file."""
    named = _SUFFIX_STORAGE.get(Path(path).suffix.lower())
    if storage is None:
        return named or "mcap"
    if storage not in STORAGES:
        raise BagError(f"storage must be one of {', '.join(STORAGES)}, got {storage!r}")
    if named is not None and named != storage:
        raise BagError(f"{path}: its suffix {Path(path).suffix} says {named}, but the bag is "
                       f"to be written as {storage}: name it {Path(path).stem}"
                       f"{'.mcap' if storage == 'mcap' else '.db3'}, or leave the storage to "
                       "the suffix")
    return storage


def _storage_plugin(storage: str) -> Any:
    from rosbags.rosbag2 import StoragePlugin
    return StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3


def _latched_qos() -> list:
    """Transient-local QoS so replayed /tf_static reaches late subscribers."""
    from rosbags.interfaces import (Qos, QosDurability, QosHistory, QosLiveliness,
                                    QosReliability, QosTime)
    inf = QosTime(sec=0, nsec=0)
    return [Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE,
                QosDurability.TRANSIENT_LOCAL, inf, inf, QosLiveliness.AUTOMATIC, inf, False)]


class _BagWriter:
    """rosbags Writer with connections made on first use.

    The bag is written beside its path and moved there once complete
    (:func:`.folder_common.replacing_output`): an existing bag is refused without
    ``overwrite`` and replaced only by a complete one, and a write that fails (a frame the
    source cannot read, a bad message) leaves no bag and the old one as it was."""

    def __init__(self, path: str | Path, storage: str | None, overwrite: bool) -> None:
        self.path = Path(path)
        self.storage = storage_for(path, storage)
        self.plugin = _storage_plugin(self.storage)
        self.overwrite = overwrite
        self.conns: dict[str, Any] = {}
        self.count = 0

    def _stem(self) -> str:
        """The storage file's name without its extension: ``scene.db3`` holds
        ``scene.db3`` and ``scene.mcap`` holds ``scene.mcap`` (rosbags names the file after
        its folder, which would double the suffix)."""
        name = self.path.name
        suffix = self.path.suffix.lower()
        return name[:-len(suffix)] if suffix in _SUFFIX_STORAGE and len(name) > len(suffix) \
            else name

    def __enter__(self) -> "_BagWriter":
        from rosbags.rosbag2 import Writer

        from .folder_common import replacing_output

        self._out = replacing_output(self.path, self.overwrite,
                                     lambda p: (p / "metadata.yaml").is_file(), "bag folder",
                                     BagError, staged_name=self._stem())
        target = self._out.__enter__()
        try:
            self.writer = Writer(target, version=9, storage_plugin=self.plugin)
            self.writer.open()
        except Exception as err:
            self._out.__exit__(type(err), err, err.__traceback__)
            raise BagError(f"{self.path}: cannot create bag ({err})") from err
        return self

    def __exit__(self, *exc: Any) -> None:
        try:
            self.writer.__exit__(*exc)
        except Exception as err:
            if exc[0] is None:
                self._out.__exit__(type(err), err, err.__traceback__)
                raise
        self._out.__exit__(*exc)

    def write(self, topic: str, msgtype: str, stamp_ns: int, msg: Any) -> None:
        conn = self.conns.get(topic)
        if conn is None:
            qos = _latched_qos() if topic.endswith("tf_static") else ()
            conn = self.writer.add_connection(topic, msgtype, typestore=typestore(),
                                              offered_qos_profiles=qos)
            self.conns[topic] = conn
        elif conn.msgtype != msgtype:
            raise BagError(f"{self.path}: topic {topic} written as {conn.msgtype} and as "
                           f"{msgtype}")
        data = msg if isinstance(msg, (bytes, bytearray, memoryview)) else \
            typestore().serialize_cdr(msg, msgtype)
        self.writer.write(conn, int(stamp_ns), data)
        self.count += 1


def write_messages(path: str | Path, items: Iterable[tuple[str, str, int, Any]],
                   storage: str | None = None, overwrite: bool = False) -> int:
    """Write (topic, msgtype, stamp_ns, message object or CDR bytes) items; returns count.

    ``storage`` None: the one the path's suffix names (:func:`storage_for`)."""
    with _BagWriter(path, storage, overwrite) as w:
        for topic, msgtype, stamp_ns, msg in items:
            w.write(topic, msgtype, stamp_ns, msg)
    return w.count


def frame_messages(fr: Frame, topics: Topics = Topics(), depth_encoding: str = "16UC1",
                   color_encoding: str = "rgb8", pose_mode: str = "topic"
                   ) -> list[tuple[str, str, int, Any]]:
    """The bag items of one Frame (shared by :func:`write_bag` and tests)."""
    if color_encoding not in ("rgb8", "bgr8"):
        raise BagError(f"color_encoding must be rgb8 or bgr8, got {color_encoding!r}")
    if depth_encoding not in ("16UC1", "32FC1"):
        raise BagError(f"depth_encoding must be 16UC1 or 32FC1, got {depth_encoding!r}")
    if pose_mode not in ("topic", "tf", "both", "none"):
        raise BagError(f"pose_mode must be topic, tf, both or none, got {pose_mode!r}")
    fr.validate()
    if fr.intrinsics.fx < 0 or fr.intrinsics.fy < 0:
        # The contract's camera is OpenCV's (x right, y down): a negative focal length
        # (ICL-NUIM's y-up camera) needs its pose converted too, not just the sign.
        raise BagError(f"frame {fr.stamp_ns}: camera fx {fr.intrinsics.fx}, fy "
                       f"{fr.intrinsics.fy}; the topic contract needs OpenCV axes (fx, fy > "
                       "0): convert camera and pose with core.data.formats.opencv_axes (the "
                       "dataset readers do)")
    if fr.pose is None and pose_mode != "none":
        raise BagError(f"frame {fr.stamp_ns} has no pose (estimate poses with "
                       "`neurncd convert --poses odometry`)")
    s, cam = int(fr.stamp_ns), topics.camera_frame
    rgb = fr.rgb if color_encoding == "rgb8" else fr.rgb[:, :, ::-1]
    out = [
        (topics.color, IMAGE, s,
         image_msg(s, cam, image_fields(rgb, color_encoding, topics.color))),
        (topics.depth, IMAGE, s,
         image_msg(s, cam, depth_fields(fr.depth, depth_encoding, topics.depth))),
        (topics.camera_info, CAMERA_INFO, s, camera_info_msg(s, cam, fr.intrinsics)),
    ]
    if pose_mode in ("topic", "both"):
        out.append((topics.pose, POSE_STAMPED, s, pose_msg(s, topics.world_frame, fr.pose)))
    if pose_mode in ("tf", "both"):
        out.append((topics.tf, TF_MESSAGE, s,
                    tf_msg(s, [(topics.world_frame, cam, fr.pose)])))
    for topic, img in ((topics.semantic, fr.semantic), (topics.instance, fr.instance)):
        if img is not None:
            out.append((topic, IMAGE, s, image_msg(s, cam, image_fields(img, "mono16", topic))))
    return out


def write_bag(path: str | Path, frames: Iterable[Frame], storage: str | None = None,
              topics: Topics = Topics(), depth_encoding: str = "16UC1",
              color_encoding: str = "rgb8", progress: bool = False, pose_mode: str = "topic",
              overwrite: bool = False) -> int:
    """Write Frames to a rosbag2 folder; returns the number of frames written.

    Header stamps and bag times are ``frame.stamp_ns``; images use frame_id
    ``topics.camera_frame``, the pose ``topics.world_frame``. ``pose_mode``
    writes the pose on the pose topic, on /tf (world -> camera), both, or not at all
    (``none``: a bag like a camera's without localisation). ``storage`` None: the one the
    path's suffix names (``.db3`` sqlite3, otherwise mcap; :func:`storage_for`).
    """
    from tqdm import tqdm

    n = 0
    # The bar starts once the output is open (a refused output is one clean line) and is
    # closed on any error, so the error starts a line of its own.
    with _BagWriter(path, storage, overwrite) as w, tqdm(
            frames, desc=f"write {Path(path).name}", unit="frame",
            disable=not progress) as it:
        for fr in it:
            try:
                items = frame_messages(fr, topics, depth_encoding, color_encoding, pose_mode)
            except ValueError as err:
                raise BagError(f"{path}: frame {n} (stamp {fr.stamp_ns}): {err}") from None
            for item in items:
                w.write(*item)
            n += 1
    return n


# ---------------------------------------------------------------- reading: low level

def _open(path: Path) -> Any:
    from rosbags.rosbag2 import Reader
    if not path.exists():
        raise BagError(f"{path}: no such bag (file or folder not found)")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as err:
        raise BagError(f"{_where(path)}: not a readable rosbag2 bag ({type(err).__name__}: "
                       f"{err}){_unreadable_hint(path, err)}") from None
    return reader


def _unreadable_hint(path: Path, err: Exception) -> str:
    """What a user can do about a bag rosbags cannot open: a recording cut off (an MCAP
    file without its end: the recorder was killed, the disk filled, a copy stopped), a
    folder without metadata.yaml, a dataset folder given as a bag."""
    text = str(err)
    if "end magic" in text or "MCAP footer" in text:
        return ("; the file ends before its MCAP footer: the recording was cut off (recorder "
                "killed, disk full, an interrupted copy). `neurncd recover <file> --out "
                "fixed.mcap` copies the part that was written (as the MCAP CLI's `mcap "
                "recover` does); then give fixed.mcap here")
    if "malformed" in text or "not a database" in text:
        return ("; the SQLite file is truncated or damaged (recorder killed, interrupted "
                "copy, full disk). `neurncd recover <file> --out fixed.db3` copies the "
                "messages that can still be read; then give fixed.db3 here")
    if path.is_dir() and not (path / "metadata.yaml").is_file():
        files = _storage_files(path)
        if files:
            return (f"; the folder has no metadata.yaml (rosbag2 writes it when a recording "
                    f"ends): give the storage file itself ({path / files[0]}) or run "
                    f"`ros2 bag reindex {path}`")
    return _dataset_hint(path)


def _dataset_hint(path: Path) -> str:
    """For a dataset folder (or NYUv2 .mat) given where a bag belongs: how to make it one."""
    from .folder_common import detect_kind

    if path.is_file() and path.suffix.lower() == ".mat":
        kind = "NYUv2 labelled"
    elif path.is_dir() and not (path / "metadata.yaml").is_file():
        try:
            kind = detect_kind(path)
        except Exception:  # not a dataset layout either: nothing to add
            return ""
    else:
        return ""
    return (f"; it looks like a {kind} dataset: convert it into a bag first (neurncd convert "
            f"{path} --out scene.mcap)")


def _storage_files(folder: Path) -> list[str]:
    """The names of a bag folder's storage files (.mcap, .db3), sorted."""
    return sorted(p.name for p in folder.iterdir() if p.suffix in (".mcap", ".db3"))


def recording_file(src: Path, out: Path, suffix: str) -> Path:
    """The storage file (``suffix``) a recovery reads: ``src``, or the one file of that
    kind in the bag folder ``src``. Refuses a missing file, and an ``out`` that is the
    recording itself (or a hard link to it): a recovery writes a new file."""
    if src.is_dir():
        stored = _storage_files(src)
        if not stored:
            packed = sorted(p.name for p in src.glob("*.zstd"))
            if packed:  # rosbag2's file compression (ros2 bag record --compression-mode file)
                raise BagError(f"{src}: its recording is compressed ({', '.join(packed)}): "
                               f"recover reads the storage file itself; decompress it "
                               f"first (zstd -d {src / packed[0]})")
            raise BagError(f"{src}: a folder with no recording in it (no .mcap or .db3 "
                           "file)")
        files = [f for f in stored if f.endswith(suffix)]
        if len(files) != 1:
            raise BagError(f"{_where(src)}: recover needs one {suffix} file, the folder "
                           f"holds {len(files)}")
        src = src / files[0]
    if not src.is_file():
        raise BagError(f"{src}: no such file")
    if out.resolve() == src.resolve() or (out.exists() and out.samefile(src)):
        raise BagError(f"{out}: the recovered copy must not replace the recording")
    return src


def _where(path: Path) -> str:
    """The bag path, with its storage files when it is a folder (to name the bad file)."""
    files = _storage_files(path) if path.is_dir() else []
    return f"{path} ({', '.join(files)})" if files else str(path)


def _messages(path: Path, reader: Any, topics: Iterable[str]
              ) -> Iterator[tuple[Any, int, bytes]]:
    """(connection, bag time, raw) of the given topics; read errors become BagError."""
    wanted = set(topics)
    conns = [c for c in reader.connections if c.topic in wanted]
    if not conns:
        return
    try:
        for conn, t, raw in reader.messages(connections=conns):
            yield conn, t, raw
    except BagError:
        raise
    except Exception as err:
        raise BagError(f"{_where(path)}: bag is truncated or corrupt ({type(err).__name__}: "
                       f"{err})") from None


def bag_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """Topic -> (message type, message count) of a bag."""
    path = Path(path)
    reader = _open(path)
    try:
        return {name: (info.msgtype or "", info.msgcount) for name, info in
                reader.topics.items()}
    finally:
        reader.close()


def iter_raw(path: str | Path, topics: list[str] | None = None
             ) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, msgtype, bag time ns, raw CDR bytes) in bag order, for replay."""
    path = Path(path)
    reader = _open(path)
    try:
        present = {c.topic for c in reader.connections}
        wanted = present if topics is None else set(topics)
        if topics is not None and not (wanted & present):
            raise BagError(f"{path}: none of the topics {sorted(wanted)} is in the bag; it has "
                           f"{sorted(present)}")
        for conn, t, raw in _messages(path, reader, wanted):
            yield conn.topic, conn.msgtype, int(t), bytes(raw)
    finally:
        reader.close()


def deserialize(raw: bytes, msgtype: str, path: Path, topic: str) -> Any:
    try:
        return typestore().deserialize_cdr(raw, msgtype)
    except Exception as err:
        raise BagError(f"{path}: {topic}: cannot decode {msgtype} ({type(err).__name__}: "
                       f"{err})") from None


_U32 = {True: struct.Struct("<I"), False: struct.Struct(">I")}
_STAMP = {True: struct.Struct("<iI"), False: struct.Struct(">iI")}


def header_stamp(raw: bytes) -> int:
    """Header stamp (ns) of a CDR message that starts with a std_msgs/Header."""
    little = raw[1] & 1 == 1
    sec, nsec = _STAMP[little].unpack_from(raw, 4)
    return sec * 1_000_000_000 + nsec


def image_stamp_and_size(raw: bytes) -> tuple[int, int, int]:
    """Header stamp (ns), height and width of a CDR sensor_msgs/Image without decoding data.

    CDR body (after the 4-byte encapsulation header): stamp sec, nanosec,
    frame_id (uint32 length + bytes), padding to 4, height, width.
    """
    little = raw[1] & 1 == 1
    (n,) = _U32[little].unpack_from(raw, 12)
    off = (12 + n + 3) & ~3
    (h,) = _U32[little].unpack_from(raw, 4 + off)
    (w,) = _U32[little].unpack_from(raw, 4 + off + 4)
    return header_stamp(raw), h, w


def _cdr_string_end(raw: bytes, off: int, little: bool) -> tuple[int, bytes]:
    """(offset after, bytes without the NUL) of the CDR string at body offset ``off``
    (aligned to 4 first; the body starts after the 4-byte encapsulation header)."""
    off = (off + 3) & ~3
    (n,) = _U32[little].unpack_from(raw, 4 + off)
    return off + 4 + n, bytes(raw[4 + off + 4: 4 + off + 4 + max(n - 1, 0)])


_PNG = b"\x89PNG\r\n\x1a\n"
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def encoded_size(data: bytes) -> tuple[int, int] | None:
    """(height, width) of a PNG or JPEG from its header alone (PNG IHDR, JPEG SOF
    segment), or None when neither is found."""
    if data[:8] == _PNG and len(data) >= 24:
        w, h = struct.unpack_from(">II", data, 16)
        return int(h), int(w)
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in _JPEG_SOF:
            h, w = struct.unpack_from(">HH", data, i + 5)
            return int(h), int(w)
        if marker in (0x01, *range(0xD0, 0xD9)):  # markers without a length
            i += 2
            continue
        (n,) = struct.unpack_from(">H", data, i + 2)
        i += 2 + n
    return None


def compressed_stamp_and_size(raw: bytes) -> tuple[int, int, int]:
    """Header stamp (ns), height and width of a CDR sensor_msgs/CompressedImage from the
    PNG or JPEG header of its data (after the 12-byte header of compressedDepth); height
    and width are 0 when the header does not say (the caller then decodes the image).

    CDR body: stamp sec, nanosec, frame_id (string), format (string), data (uint32
    length + bytes), strings and the length aligned to 4."""
    little = raw[1] & 1 == 1
    off, _ = _cdr_string_end(raw, 8, little)
    off, fmt = _cdr_string_end(raw, off, little)
    off = (off + 3) & ~3
    (n,) = _U32[little].unpack_from(raw, 4 + off)
    start = 4 + off + 4 + (12 if b"compresseddepth" in fmt.lower() else 0)
    size = encoded_size(bytes(raw[start: min(start + 65536, 4 + off + 4 + n)]))
    return (header_stamp(raw), *(size or (0, 0)))


# ---------------------------------------------------------------- /tf tree

def tf_frames_in_tree_order(parent: dict[str, str]) -> list[str]:
    """Every frame of a child -> parent map, each tree from its root down (depth first).

    The order a person reads a tf tree in (odom, base_link, camera_link, ...), which
    a sorted list is not; roots and siblings are sorted, frames on a loop come last."""
    children: dict[str, list[str]] = collections.defaultdict(list)
    for child, par in parent.items():
        children[par].append(child)
    roots = sorted({p for p in parent.values() if p not in parent})
    out: list[str] = []
    stack = roots[::-1]
    while stack:
        frame = stack.pop()
        if frame in out:
            continue
        out.append(frame)
        stack.extend(sorted(children[frame], reverse=True))
    return out + sorted(set(parent) - set(out))


def check_tf_pair(tfbuf: TfBuffer, tf_parent: str, tf_child: str, path: str | Path,
                  tf_topic: str = "/tf") -> None:
    """Raise :class:`BagError` when no pose tf_parent -> tf_child can come out of ``tfbuf``.

    A frame missing from the tree, or two frames in different trees, would drop every
    frame as "missing pose" one by one; one line naming the bag's frames says why
    (a wrong frame name: ``map`` for ``odom``). The tree is the bag's whole /tf and
    /tf_static (a frame keeps its first parent, as :meth:`TfBuffer.lookup` sees it)."""
    parent = tfbuf.parent
    frames = tf_frames_in_tree_order(parent)
    listed = f"frames: {', '.join(frames) if frames else 'none'}"
    missing = [(name, role) for name, role in ((tf_parent, "tf_parent"),
                                               (tf_child, "tf_child"))
               if name not in frames]
    if missing:
        names = " and ".join(f"{name!r} ({role})" for name, role in missing)
        verb = "is" if len(missing) == 1 else "are"
        raise BagError(f"{path}: tf frame{'s' * (len(missing) > 1)} {names} {verb} not in "
                       f"the bag's {tf_topic} tree ({listed})")
    root_p, root_c = tf_root(parent, tf_parent), tf_root(parent, tf_child)
    if root_p != root_c:
        raise BagError(f"{path}: tf frames {tf_parent!r} (tf_parent) and {tf_child!r} "
                       f"(tf_child) are not connected in the bag's {tf_topic} tree "
                       f"({tf_parent!r} is in the tree of {root_p!r}, {tf_child!r} in that "
                       f"of {root_c!r}; {listed})")


# ---------------------------------------------------------------- FrameReader

@dataclasses.dataclass
class _Planned:
    stamp: int
    keys: dict[str, tuple[str, int]]       # role -> (topic, stamp)
    intr: Intrinsics
    pose: np.ndarray


class FrameReader:
    """Frames of a bag, synchronised by header stamp.

    Construction reads the small topics and the image headers (so a bad bag
    fails here, with :class:`BagError`) and plans the frames; iterating decodes
    images in one pass. ``dropped`` lists ``(stamp_ns, reason)`` of colour
    frames that could not be assembled.
    """

    def __init__(self, path: str | Path, topics: Topics = Topics(),
                 with_ground_truth: bool = SyncConfig.with_ground_truth,
                 max_stamp_skew_ns: int = SyncConfig.max_stamp_skew_ns,
                 tf_parent: str | None = None, tf_child: str | None = None,
                 max_pose_gap_ns: int = SyncConfig.max_pose_gap_ns,
                 with_poses: bool = True) -> None:
        self.path = Path(path)
        self.with_poses = with_poses
        self.topics = topics
        self.with_ground_truth = with_ground_truth
        self.skew = int(max_stamp_skew_ns)
        self.max_gap = int(max_pose_gap_ns)
        if self.skew < 0 or self.max_gap < 0:
            raise BagError(f"max_stamp_skew_ns and max_pose_gap_ns must be >= 0, got "
                           f"{max_stamp_skew_ns} and {max_pose_gap_ns}")
        if bool(tf_parent) != bool(tf_child):
            raise BagError("give both tf_parent and tf_child (or neither)")
        # tf2 names frames without a leading slash (TfBuffer strips it from the bag's).
        self.tf_pair = (tf_parent.lstrip("/"), tf_child.lstrip("/")) if tf_parent else None
        self._plan_dropped: list[tuple[int, str]] = []
        self._bad_images: dict[tuple[str, int], str] = {}
        self.dropped: list[tuple[int, str]] = []
        self.n_color = 0
        self.missing_gt = 0
        self._plan: list[_Planned] = []
        self._make_plan()
        self.dropped = list(self._plan_dropped)

    @classmethod
    def from_config(cls, path: str | Path, topics: Topics, sync: SyncConfig,
                    with_poses: bool = True) -> "FrameReader":
        return cls(path, topics, sync.with_ground_truth, sync.max_stamp_skew_ns,
                   sync.tf_parent or None, sync.tf_child or None, sync.max_pose_gap_ns,
                   with_poses=with_poses)

    def __len__(self) -> int:
        return len(self._plan)

    # -- pass 1: headers and small messages
    def _make_plan(self) -> None:
        tp, path = self.topics, self.path
        reader = _open(path)
        try:
            types = {c.topic: c.msgtype for c in reader.connections}
            for role in ("color", "depth", "camera_info"):
                if getattr(tp, role) not in types:
                    hint = "".join(f"; it has {t!r} ({types[t]}): set topics.{role} to it"
                                   for t in compressed_alternatives(getattr(tp, role), types))
                    raise BagError(f"{path}: no {role} topic {getattr(tp, role)!r}; topics in "
                                   f"the bag: {sorted(types)}{hint}")
            for topic, want in ((tp.color, IMAGE_TYPES), (tp.depth, IMAGE_TYPES),
                                (tp.camera_info, (CAMERA_INFO,))):
                if types[topic] not in want:
                    raise BagError(f"{path}: {topic} has type {types[topic]}, expected "
                                   + " or ".join(want))
            self._types = types
            if not self.with_poses:
                self.pose_source = "none (to be estimated)"
            elif self.tf_pair is None:
                if tp.pose not in types:
                    raise BagError(f"{path}: no pose topic {tp.pose!r} (topics: "
                                   f"{sorted(types)}); for a /tf pose pass tf_parent and "
                                   "tf_child; a bag without poses gets them from "
                                   "`neurncd convert --poses odometry`")
                self.pose_source = tp.pose
            else:
                if tp.tf not in types and tp.tf_static not in types:
                    raise BagError(f"{path}: tf pose asked but neither {tp.tf} nor "
                                   f"{tp.tf_static} is in the bag")
                self.pose_source = f"tf {self.tf_pair[0]}->{self.tf_pair[1]}"
            gt_roles = [r for r in ("semantic", "instance")
                        if self.with_ground_truth and types.get(getattr(tp, r)) in IMAGE_TYPES]
            self.gt_roles = gt_roles
            image_roles = {tp.color: "color", tp.depth: "depth"}
            image_roles.update({getattr(tp, r): r for r in gt_roles})
            small = [tp.camera_info] + ([] if not self.with_poses else
                                        [tp.pose] if self.tf_pair is None else
                                        [t for t in (tp.tf, tp.tf_static) if t in types])
            heads: dict[str, list[tuple[int, int, int]]] = collections.defaultdict(list)
            infos: list[tuple[int, Intrinsics | str]] = []
            poses: list[tuple[int, np.ndarray | str]] = []
            tfbuf = TfBuffer()
            for conn, _, raw in _messages(path, reader, list(image_roles) + small):
                topic = conn.topic
                if topic in image_roles:
                    role = image_roles[topic]
                    stamp, h, w = self._stamp_and_size(raw, conn.msgtype, topic)
                    if isinstance(h, str):  # a compressed image that cannot be decoded
                        self._bad_images[(role, stamp)] = h
                        h = w = 0
                    heads[role].append((stamp, h, w))
                    continue
                msg = deserialize(raw, conn.msgtype, path, topic)
                if topic == tp.camera_info:
                    try:
                        infos.append((stamp_to_ns(msg.header.stamp),
                                      camera_info_to_intrinsics(msg, topic,
                                                                tp.distortion)))
                    except MessageError as err:
                        infos.append((stamp_to_ns(msg.header.stamp), str(err)))
                elif self.tf_pair is None:
                    try:
                        poses.append((stamp_to_ns(msg.header.stamp),
                                      check_pose(pose_to_matrix(msg, topic), f"{topic} pose")))
                    except ValueError as err:
                        poses.append((stamp_to_ns(msg.header.stamp), str(err)))
                else:
                    tfbuf.add(msg, static=topic == tp.tf_static)
        finally:
            reader.close()
        if self.with_poses and self.tf_pair is not None:
            check_tf_pair(tfbuf, *self.tf_pair, path, tf_topic=tp.tf)
        self._plan_frames(heads, infos, poses, tfbuf)

    def _stamp_and_size(self, raw: bytes, msgtype: str, topic: str
                        ) -> tuple[int, int | str, int]:
        """Stamp, height and width of an image message without decoding its pixels (a
        compressed image whose PNG or JPEG header does not say is decoded: if it cannot
        be, the height is the reason, and its frame is dropped with it)."""
        try:
            if msgtype == IMAGE:
                return image_stamp_and_size(raw)
            stamp, h, w = compressed_stamp_and_size(raw)
        except (struct.error, IndexError):
            raise BagError(f"{self.path}: {topic}: corrupt image message") from None
        if h and w:
            return stamp, h, w
        try:
            arr, _ = decode_compressed(deserialize(raw, msgtype, self.path, topic), topic)
        except MessageError as err:
            return stamp, str(err), 0
        return stamp, arr.shape[0], arr.shape[1]

    def _plan_frames(self, heads: dict, infos: list, poses: list, tfbuf: TfBuffer) -> None:
        infos.sort(key=lambda x: x[0])
        poses.sort(key=lambda x: x[0])
        info_t = np.array([s for s, _ in infos], dtype=np.int64)
        pose_t = np.array([s for s, _ in poses], dtype=np.int64)
        pose_vals = [p for _, p in poses]
        table = {}
        for role, items in heads.items():
            first: dict[int, tuple[int, int]] = {}
            for s, h, w in items:
                first.setdefault(s, (h, w))
            table[role] = (np.array(sorted(first), dtype=np.int64), first)
        colors = heads.get("color", [])
        self.n_color = len(colors)
        seen: set[int] = set()
        for s, h, w in sorted(colors):
            if s in seen:
                self._plan_dropped.append((s, "duplicate: another colour image has this stamp"))
                continue
            seen.add(s)
            reason, planned = self._plan_one(s, (h, w), table, infos, info_t, pose_vals,
                                             pose_t, tfbuf)
            if reason:
                self._plan_dropped.append((s, reason))
            else:
                self._plan.append(planned)

    def _match(self, table: dict, role: str, s: int) -> tuple[int, tuple[int, int]] | None:
        if role not in table:
            return None
        times, sizes = table[role]
        if times.size == 0:
            return None
        k, d = nearest(times, s)
        if d > self.skew:
            return None
        t = int(times[k])
        return t, sizes[t]

    def _plan_one(self, s: int, size: tuple[int, int], table: dict, infos: list,
                  info_t: np.ndarray, pose_vals: list, pose_t: np.ndarray, tfbuf: TfBuffer
                  ) -> tuple[str, _Planned | None]:
        tp, ms = self.topics, self.skew / 1e6
        if ("color", s) in self._bad_images:
            return f"bad color: {self._bad_images[('color', s)]}", None
        dep = self._match(table, "depth", s)
        if dep is None:
            return f"missing depth: no {tp.depth} within {ms:g} ms", None
        if ("depth", dep[0]) in self._bad_images:
            return f"bad depth: {self._bad_images[('depth', dep[0])]}", None
        if dep[1] != size:
            return (f"size mismatch: colour is {size[1]}x{size[0]} but depth is "
                    f"{dep[1][1]}x{dep[1][0]}"), None
        k = int(np.searchsorted(info_t, s + self.skew, side="right")) - 1
        if k < 0:
            return f"missing camera_info: no {tp.camera_info} at or before this stamp", None
        intr = infos[k][1]
        if isinstance(intr, str):
            return f"bad camera_info: {intr}", None
        if intr.shape != size:
            return (f"size mismatch: camera_info is {intr.width}x{intr.height} but colour is "
                    f"{size[1]}x{size[0]}"), None
        source = tp.pose if self.tf_pair is None else "tf {}->{}".format(*self.tf_pair)
        if not self.with_poses:
            pose = None
        else:
            try:
                if self.tf_pair is None:
                    pose = pose_at(pose_t, pose_vals, s, self.skew, self.max_gap)
                else:
                    pose = tfbuf.lookup(self.tf_pair[0], self.tf_pair[1], s, self.skew,
                                        self.max_gap)
                pose = check_pose(pose, f"{source} pose")
            except LookupError as err:
                text = str(err.args[0]) if err.args else repr(err)
                kind = "bad pose" if text.startswith("invalid sample") else "missing pose"
                if "no sample within" in text and not self.max_gap:
                    text += " (set sync.max_pose_gap_ns to interpolate between samples)"
                return f"{kind}: {source}: {text}", None
            except ValueError as err:
                return f"bad pose: {err}", None
        keys = {"color": (tp.color, s), "depth": (tp.depth, dep[0])}
        for role in self.gt_roles:
            m = self._match(table, role, s)
            if m is None or m[1] != size:
                self.missing_gt += 1
                continue
            keys[role] = (getattr(tp, role), m[0])
        return "", _Planned(s, keys, intr, pose)

    # -- pass 2: decode images in bag order, emit frames in stamp order
    def __iter__(self) -> Iterator[Frame]:
        self.dropped = list(self._plan_dropped)
        need: dict[tuple[str, int], int] = collections.Counter()
        for p in self._plan:
            for key in p.keys.values():
                need[key] += 1
        if not self._plan:
            return
        have: dict[tuple[str, int], Any] = {}
        head = 0
        reader = _open(self.path)
        try:
            topics = sorted({k[0] for k in need})
            for conn, _, raw in _messages(self.path, reader, topics):
                s = header_stamp(raw)
                key = (conn.topic, s)
                if need.get(key, 0) <= 0 or key in have:
                    continue
                have[key] = self._decode(raw, conn.topic)
                while head < len(self._plan) and all(k in have for k in
                                                     self._plan[head].keys.values()):
                    fr = self._assemble(self._plan[head], have)
                    for k in self._plan[head].keys.values():
                        need[k] -= 1
                        if need[k] == 0:
                            del have[k]
                    head += 1
                    if fr is not None:
                        yield fr
        finally:
            reader.close()
        for p in self._plan[head:]:
            self.dropped.append((p.stamp, "incomplete: images listed but not read back"))

    def _decode(self, raw: bytes, topic: str) -> np.ndarray | str:
        msg = deserialize(raw, self._types[topic], self.path, topic)
        tp = self.topics
        try:
            if topic == tp.color:
                return rgb_from_image(msg, topic)
            if topic == tp.depth:
                return depth_from_image(msg, topic)
            arr = (decode_compressed(msg, topic)[0] if is_compressed(msg)
                   else image_to_array(msg, topic))
            if arr.ndim != 2:
                raise MessageError(f"{topic}: label image must have one channel")
            return arr.astype(np.uint16)
        except MessageError as err:
            return str(err)

    def _assemble(self, p: _Planned, have: dict) -> Frame | None:
        parts = {role: have[key] for role, key in p.keys.items()}
        for role, v in parts.items():
            if isinstance(v, str):
                self.dropped.append((p.stamp, f"bad {role}: {v}"))
                return None
        try:
            return Frame(p.stamp, parts["color"], parts["depth"], p.pose, p.intr,
                         parts.get("semantic"), parts.get("instance")).validate()
        except ValueError as err:
            self.dropped.append((p.stamp, f"invalid frame: {err}"))
            return None

    def summary(self) -> str:
        """One paragraph: frames planned, dropped (by reason), pose and ground truth source."""
        reasons = collections.Counter(r.split(":", 1)[0] for _, r in self.dropped)
        text = (f"{self.path}: {self.n_color} colour images, {len(self._plan)} frames "
                f"synchronised (skew <= {self.skew / 1e6:g} ms), {len(self.dropped)} dropped")
        if reasons:
            text += " (" + ", ".join(f"{k}: {v}" for k, v in sorted(reasons.items())) + ")"
            # One full reason per kind: the kind alone ("bad camera_info") does not say
            # what to change (a distortion to refuse or ignore, topics.distortion).
            first = {}
            for _, r in self.dropped:
                first.setdefault(r.split(":", 1)[0], r)
            text += "".join(f"; first {k}: {first[k].split(':', 1)[1].strip()}"
                            for k in sorted(first) if ":" in first[k])
        text += f"; pose from {self.pose_source}; ground truth: "
        text += ", ".join(self.gt_roles) if self.gt_roles else "none"
        if self.missing_gt:
            text += f" ({self.missing_gt} frame(s) without matching ground truth)"
        return text
