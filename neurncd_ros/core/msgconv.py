"""The one message-conversion module: ROS messages <-> numpy.

Duck-typed on purpose: the same functions read rclpy messages (live topics)
and rosbags messages (offline bags), so neither rclpy nor rosbags is imported
here and the conversion is tested once. Building a message is left to the
caller, who passes the dict of fields returned here to its own message type.

Colour and depth may also come as sensor_msgs/CompressedImage, as robots record them
through image_transport (``<base>/compressed``: JPEG or PNG; ``<base>/compressedDepth``:
PNG behind a 12-byte header, 16UC1 millimetres or 32FC1 quantised inverse depth):
:func:`rgb_from_image` and :func:`depth_from_image` take either message.
"""

from __future__ import annotations

import math
import re
import struct
from typing import Any

import numpy as np

from .camera import Intrinsics, check_pose, matrix_to_quat, quat_to_matrix


class MessageError(ValueError):
    """A message cannot be converted; the text names the topic and the problem."""


_FIXED = {
    "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "mono8": (np.uint8, 1),
    "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
    "8UC1": (np.uint8, 1), "8UC3": (np.uint8, 3),
    "mono16": (np.uint16, 1), "16UC1": (np.uint16, 1),
}
_FLOAT_RE = re.compile(r"^32FC(\d+)$")

SUPPORTED_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8UC1", "8UC3", "mono16",
                       "16UC1", "32FC<S>")
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8")
"""What a colour image may come in: rgba8 and bgra8 (the ZED and Azure Kinect drivers' colour)
lose their alpha, as a compressed BGRA image does."""


QUATERNION_TOLERANCE = 0.01
"""How far |q|^2 of a pose's orientation may be from 1 (tf2's QUATERNION_NORMALIZATION_TOLERANCE);
within it the quaternion is normalised."""


def _where(topic: str) -> str:
    return f"{topic}: " if topic else ""


def encoding_layout(encoding: str, topic: str = "") -> tuple[np.dtype, int]:
    """(dtype, channels) of a supported image encoding."""
    if encoding in _FIXED:
        dt, ch = _FIXED[encoding]
        return np.dtype(dt), ch
    m = _FLOAT_RE.match(encoding or "")
    if m and int(m.group(1)) >= 1:
        return np.dtype(np.float32), int(m.group(1))
    raise MessageError(f"{_where(topic)}unsupported image encoding {encoding!r}; supported: "
                       + ", ".join(SUPPORTED_ENCODINGS))


def _as_bytes(data: Any) -> np.ndarray:
    if isinstance(data, np.ndarray):
        return data.view(np.uint8).reshape(-1)
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    # rclpy exposes uint8[] as array.array('B') or a list.
    return np.frombuffer(bytes(data), dtype=np.uint8) if not hasattr(data, "tobytes") \
        else np.frombuffer(data.tobytes(), dtype=np.uint8)


def image_to_array(msg: Any, topic: str = "") -> np.ndarray:
    """sensor_msgs/Image to an array: (H, W), (H, W, 3) or (H, W, S), native byte order.

    Honours row padding (``step``) and ``is_bigendian``. The result owns its
    memory (safe to keep after the message is gone).
    """
    h, w, enc, step = int(msg.height), int(msg.width), str(msg.encoding), int(msg.step)
    dtype, ch = encoding_layout(enc, topic)
    if h <= 0 or w <= 0:
        raise MessageError(f"{_where(topic)}image has empty size {w}x{h}")
    row = w * ch * dtype.itemsize
    if step < row:
        raise MessageError(f"{_where(topic)}step {step} is smaller than width*channels*bytes "
                           f"= {row} for {w}x{h} {enc}")
    raw = _as_bytes(msg.data)
    if raw.size != step * h:
        raise MessageError(f"{_where(topic)}data has {raw.size} bytes, expected step*height = "
                           f"{step}*{h} = {step * h} for {enc}")
    rows = raw.reshape(h, step)[:, :row]
    big = bool(msg.is_bigendian)
    dt = dtype.newbyteorder(">" if big else "<") if dtype.itemsize > 1 else dtype
    arr = np.ascontiguousarray(rows).view(dt).reshape(h, w, ch)
    arr = arr.astype(dtype, copy=True)  # native order, owned copy
    return arr[:, :, 0] if ch == 1 else arr


def image_fields(arr: np.ndarray, encoding: str, topic: str = "") -> dict[str, Any]:
    """Fields of a sensor_msgs/Image holding ``arr`` (little endian, no padding)."""
    dtype, ch = encoding_layout(encoding, topic)
    arr = np.asarray(arr)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[2] != ch:
        raise MessageError(f"{_where(topic)}array of shape {arr.shape} does not fit encoding "
                           f"{encoding} ({ch} channel(s))")
    if arr.dtype != dtype:
        if dtype.kind != "f" and arr.dtype.kind == "f":
            raise MessageError(f"{_where(topic)}refusing to cast float array to {encoding}")
        arr = arr.astype(dtype)
    h, w = arr.shape[:2]
    data = np.ascontiguousarray(arr.astype(dtype.newbyteorder("<"), copy=False))
    return {"height": h, "width": w, "encoding": encoding, "is_bigendian": 0,
            "step": w * ch * dtype.itemsize, "data": data.view(np.uint8).reshape(-1)}


def is_compressed(msg: Any) -> bool:
    """Whether ``msg`` is a sensor_msgs/CompressedImage (a ``format``, no ``encoding``)."""
    return hasattr(msg, "format") and not hasattr(msg, "encoding")


# compressed_depth_image_transport's header before the PNG: int32 format, then the two
# float32 parameters of the inverse-depth quantisation (little endian, as written on x86).
_DEPTH_HEADER = struct.Struct("<iff")


def _imdecode(data: np.ndarray, topic: str, what: str) -> np.ndarray:
    import cv2  # only compressed images need it

    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise MessageError(f"{_where(topic)}{what} cannot be decoded ({data.size} bytes)")
    return img


def decode_compressed(msg: Any, topic: str = "") -> tuple[np.ndarray, str]:
    """sensor_msgs/CompressedImage to (array, encoding), the encoding as an Image would
    carry it: ``bgr8`` or ``rgb8`` for colour, ``mono8``, ``16UC1`` (millimetres) or
    ``32FC1`` (metres, NaN where nothing was measured). The colour order is
    compressed_image_transport's: the decoded buffer is BGR unless the format names
    ``compressed rgb...`` (the publisher gave the codec RGB data), as its subscriber
    reads it.

    ``format`` is image_transport's: ``"<encoding>; jpeg compressed bgr8"``,
    ``"<encoding>; png compressed"``, or just ``"jpeg"`` / ``"png"`` (compressed), and
    ``"<encoding>; compressedDepth png"`` (compressedDepth: a 12-byte header, then a PNG of
    millimetres for 16UC1, or of the quantised inverse depth q for 32FC1, depth = a / (q - b)
    with a, b from the header and q = 0 for no depth). The RVL codec of compressedDepth is
    refused: record with ``png``, or republish raw."""
    fmt = str(msg.format).strip()
    head, _, rest = fmt.partition(";")
    encoding = head.strip() if rest else ""
    data = _as_bytes(msg.data)
    if "compresseddepth" in fmt.lower():
        if "rvl" in rest.lower():
            raise MessageError(f"{_where(topic)}compressedDepth with the RVL codec is not "
                               "supported; record depth with the png codec (the "
                               "compressedDepth default) or as raw sensor_msgs/Image")
        if data.size <= _DEPTH_HEADER.size:
            raise MessageError(f"{_where(topic)}compressedDepth message of {data.size} bytes "
                               "has no image after its header")
        _, quant_a, quant_b = _DEPTH_HEADER.unpack_from(data.tobytes()[:_DEPTH_HEADER.size])
        img = _imdecode(data[_DEPTH_HEADER.size:], topic, "compressedDepth PNG")
        if img.ndim != 2 or img.dtype != np.uint16:
            raise MessageError(f"{_where(topic)}compressedDepth PNG holds {img.dtype} "
                               f"with shape {img.shape}, expected one 16-bit channel")
        if encoding == "32FC1":
            q = img.astype(np.float32)
            with np.errstate(divide="ignore", invalid="ignore"):
                depth = np.where(img > 0, np.float32(quant_a) / (q - np.float32(quant_b)),
                                 np.float32(np.nan))
            return depth.astype(np.float32), "32FC1"
        if encoding in ("16UC1", "mono16", ""):
            return img, "16UC1"
        raise MessageError(f"{_where(topic)}compressedDepth of encoding {encoding!r}; "
                           "expected 16UC1 or 32FC1")
    img = _imdecode(data, topic, f"compressed image (format {fmt!r})")
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]  # BGRA: the alpha says nothing here
    if img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8:
        return np.ascontiguousarray(img), ("rgb8" if "compressed rgb" in rest.lower()
                                           else "bgr8")
    if img.ndim == 2 and img.dtype == np.uint8:
        return img, "mono8"
    if img.ndim == 2 and img.dtype == np.uint16:
        return img, "16UC1"
    raise MessageError(f"{_where(topic)}compressed image (format {fmt!r}) decodes to "
                       f"{img.dtype} with shape {img.shape}: not a colour, mono or 16-bit image")


def rgb_from_image(msg: Any, topic: str = "") -> np.ndarray:
    """Colour image message (rgb8, bgr8, rgba8 or bgra8, the alpha left out, or a
    compressed colour image) to (H, W, 3) uint8 RGB."""
    if is_compressed(msg):
        arr, enc = decode_compressed(msg, topic)
        if enc not in ("bgr8", "rgb8"):
            raise MessageError(f"{_where(topic)}colour image must have 3 channels; the "
                               f"compressed image (format {msg.format!r}) decodes to {enc}")
    else:
        enc = msg.encoding
        if enc not in COLOUR_ENCODINGS:
            raise MessageError(f"{_where(topic)}colour image must be "
                               f"{', '.join(COLOUR_ENCODINGS[:-1])} or {COLOUR_ENCODINGS[-1]}, "
                               f"got {enc!r}")
        arr = image_to_array(msg, topic)
    if enc in ("bgr8", "bgra8"):
        return np.ascontiguousarray(arr[:, :, 2::-1])
    return np.ascontiguousarray(arr[:, :, :3]) if enc == "rgba8" else arr


def depth_from_image(msg: Any, topic: str = "") -> np.ndarray:
    """Depth message (16UC1/mono16 millimetres or 32FC1 metres) to float32 metres.

    Non-finite and negative values become 0 (no measurement), as in the
    16-bit convention, so downstream code has one invalid marker. A compressed depth
    image (compressedDepth, or a 16-bit PNG) is decoded first (:func:`decode_compressed`).
    """
    if is_compressed(msg):
        d, enc = decode_compressed(msg, topic)
        if enc not in ("16UC1", "32FC1"):
            raise MessageError(f"{_where(topic)}depth image must be 16-bit millimetres or "
                               f"32FC1 metres; the compressed image (format {msg.format!r}) "
                               f"decodes to {enc}")
    else:
        enc = msg.encoding
        if enc not in ("16UC1", "mono16", "32FC1"):
            raise MessageError(f"{_where(topic)}depth image must be 16UC1 (mm) or 32FC1 (m), "
                               f"got {enc!r}")
        d = image_to_array(msg, topic)
    if enc != "32FC1":
        return d.astype(np.float32) / np.float32(1000.0)
    bad = ~np.isfinite(d) | (d < 0)
    if bad.any():
        d = d.copy()
        d[bad] = 0.0
    return d


def depth_fields(depth_m: np.ndarray, encoding: str = "16UC1", topic: str = ""
                 ) -> dict[str, Any]:
    """Image fields for a metric depth array, as 16UC1 millimetres or 32FC1 metres."""
    depth_m = np.asarray(depth_m, dtype=np.float32)
    if encoding == "16UC1":
        mm = np.where(np.isfinite(depth_m) & (depth_m > 0), np.round(depth_m * 1000.0), 0)
        if mm.max(initial=0) > 65535:
            raise MessageError(f"{_where(topic)}depth above 65.535 m does not fit 16UC1")
        return image_fields(mm.astype(np.uint16), "16UC1", topic)
    if encoding == "32FC1":
        return image_fields(depth_m, "32FC1", topic)
    raise MessageError(f"{_where(topic)}depth encoding must be 16UC1 or 32FC1, got "
                       f"{encoding!r}")


def camera_info_to_intrinsics(msg: Any, topic: str = "", distortion: str = "refuse"
                              ) -> Intrinsics:
    """sensor_msgs/CameraInfo to Intrinsics (uses K). Non-zero distortion coefficients are
    refused, or with ``distortion`` 'ignore' (``topics.distortion``) left out: K alone."""
    k = np.asarray(msg.k, dtype=np.float64).reshape(-1)
    if k.size != 9:
        raise MessageError(f"{_where(topic)}camera info K has {k.size} values, expected 9")
    d = np.asarray(getattr(msg, "d", []), dtype=np.float64)
    if distortion != "ignore" and d.size and np.any(np.abs(d) > 1e-9):
        raise MessageError(f"{_where(topic)}distortion {d.tolist()} is not supported: "
                           "rectify the images first, or set topics.distortion to 'ignore' "
                           "to use K alone")
    try:
        return Intrinsics(float(k[0]), float(k[4]), float(k[2]), float(k[5]),
                          int(msg.width), int(msg.height))
    except ValueError as err:
        raise MessageError(f"{_where(topic)}{err}") from None


def camera_info_fields(intr: Intrinsics) -> dict[str, Any]:
    """Fields of a sensor_msgs/CameraInfo for an undistorted pinhole camera."""
    k = intr.K
    p = np.zeros((3, 4))
    p[:, :3] = k
    return {"height": intr.height, "width": intr.width, "distortion_model": "plumb_bob",
            "d": np.zeros(5), "k": k.reshape(-1), "r": np.eye(3).reshape(-1),
            "p": p.reshape(-1)}


def pose_to_matrix(msg: Any, topic: str = "") -> np.ndarray:
    """PoseStamped, Pose, TransformStamped or Transform to a 4x4 matrix."""
    obj = msg
    for attr in ("pose", "transform"):
        if hasattr(obj, attr):
            obj = getattr(obj, attr)
            break
    if hasattr(obj, "position"):
        t, q = obj.position, obj.orientation
    elif hasattr(obj, "translation"):
        t, q = obj.translation, obj.rotation
    else:
        raise MessageError(f"{_where(topic)}message has no pose or transform")
    vals = [t.x, t.y, t.z, q.x, q.y, q.z, q.w]
    if not all(math.isfinite(v) for v in vals):
        raise MessageError(f"{_where(topic)}pose has non-finite values {vals}")
    # tf2's tolerance (|q|^2 within 0.01 of 1, then normalised): a quaternion tf2 takes is
    # taken (1e-3 on |q| refused a norm of 1.002 that tf2 and rviz accept)
    n2 = q.x ** 2 + q.y ** 2 + q.z ** 2 + q.w ** 2
    if abs(n2 - 1.0) > QUATERNION_TOLERANCE:
        raise MessageError(f"{_where(topic)}orientation quaternion has norm "
                           f"{math.sqrt(n2):.6f}, expected 1 (|q|^2 within "
                           f"{QUATERNION_TOLERANCE} of 1, as tf2 takes it)")
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q.x, q.y, q.z, q.w)
    T[:3, 3] = [t.x, t.y, t.z]
    return T


def matrix_to_pose_fields(T: np.ndarray, topic: str = "") -> dict[str, tuple]:
    """4x4 pose to position (x, y, z) and orientation (x, y, z, w)."""
    try:
        T = check_pose(T)
    except ValueError as err:
        raise MessageError(f"{_where(topic)}{err}") from None
    return {"position": tuple(float(v) for v in T[:3, 3]),
            "orientation": matrix_to_quat(T[:3, :3])}


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time to integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> tuple[int, int]:
    """Integer nanoseconds to (sec, nanosec)."""
    return int(ns) // 1_000_000_000, int(ns) % 1_000_000_000


def class_table_text(stamp_ns: int, frame_id: str, table: dict[int, dict]) -> str:
    """The /neurncd/classes message's JSON (std_msgs/String): ``{"header": {"stamp":
    {"sec", "nanosec"}, "frame_id"}, "classes": {"<id>": {"name", "kind", "pixels"}}}``.

    The header is the label image's, so a subscriber matches a table to its image by
    stamp (a String has no header of its own; a subscriber that fell behind would
    otherwise pair an image with another image's table)."""
    import json

    sec, nanosec = ns_to_stamp(stamp_ns)
    return json.dumps({"header": {"stamp": {"sec": sec, "nanosec": nanosec},
                                  "frame_id": frame_id},
                       "classes": {str(k): v for k, v in table.items()}})


def class_table_from_text(text: str, topic: str = "") -> tuple[int, str, dict[int, dict]]:
    """(stamp in ns, frame_id, {id: {"name", "kind", "pixels"}}) of a /neurncd/classes
    message's JSON (:func:`class_table_text`), for subscribers; MessageError if it is not
    one."""
    import json

    try:
        d = json.loads(text)
        header = d["header"]
        stamp = int(header["stamp"]["sec"]) * 1_000_000_000 + int(header["stamp"]["nanosec"])
        table = {int(k): dict(v) for k, v in d["classes"].items()}
        return stamp, str(header["frame_id"]), table
    except (ValueError, TypeError, KeyError, AttributeError) as err:
        raise MessageError(f"{_where(topic)}not a class table ({type(err).__name__}: "
                           f"{err}): {text[:120]!r}") from None
