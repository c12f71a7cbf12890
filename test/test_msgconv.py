"""Message conversion: every encoding of the topic contract, padding, endianness, errors."""

from types import SimpleNamespace as NS

import numpy as np
import pytest

from neurncd_ros.core import msgconv
from neurncd_ros.core.camera import Intrinsics, look_at
from neurncd_ros.core.msgconv import MessageError


def image(arr, encoding, pad=0, big=False):
    """Build an Image-like message by hand (independently of image_fields)."""
    dtype, ch = msgconv.encoding_layout(encoding)
    a = np.asarray(arr).astype(dtype.newbyteorder(">" if big else "<"))
    h, w = a.shape[:2]
    row = a.reshape(h, -1).view(np.uint8).reshape(h, -1)
    data = np.concatenate([row, np.full((h, pad), 0xAB, np.uint8)], axis=1)
    return NS(height=h, width=w, encoding=encoding, is_bigendian=int(big),
              step=row.shape[1] + pad, data=data.tobytes())


RNG = np.random.default_rng(0)
CASES = {
    "rgb8": RNG.integers(0, 256, (5, 7, 3)).astype(np.uint8),
    "bgr8": RNG.integers(0, 256, (5, 7, 3)).astype(np.uint8),
    "rgba8": RNG.integers(0, 256, (5, 7, 4)).astype(np.uint8),
    "bgra8": RNG.integers(0, 256, (5, 7, 4)).astype(np.uint8),
    "mono8": RNG.integers(0, 256, (5, 7)).astype(np.uint8),
    "mono16": RNG.integers(0, 65536, (5, 7)).astype(np.uint16),
    "16UC1": RNG.integers(0, 65536, (5, 7)).astype(np.uint16),
    "32FC1": RNG.normal(size=(5, 7)).astype(np.float32),
    "32FC9": RNG.normal(size=(5, 7, 9)).astype(np.float32),
    "32FC37": RNG.normal(size=(4, 6, 37)).astype(np.float32),
}


@pytest.mark.parametrize("encoding", sorted(CASES))
@pytest.mark.parametrize("pad", [0, 3])
@pytest.mark.parametrize("big", [False, True])
def test_image_to_array_every_encoding(encoding, pad, big):
    arr = CASES[encoding]
    out = msgconv.image_to_array(image(arr, encoding, pad, big), "/t")
    assert out.dtype == arr.dtype and out.dtype.isnative
    np.testing.assert_array_equal(out, arr)


@pytest.mark.parametrize("encoding", sorted(CASES))
def test_image_fields_round_trip(encoding):
    arr = CASES[encoding]
    f = msgconv.image_fields(arr, encoding)
    msg = NS(**{**f, "data": f["data"].tobytes()})
    assert f["step"] == arr.shape[1] * arr.itemsize * (arr.shape[2] if arr.ndim == 3 else 1)
    np.testing.assert_array_equal(msgconv.image_to_array(msg), arr)


def test_bgr_becomes_rgb():
    bgr = CASES["bgr8"]
    rgb = msgconv.rgb_from_image(image(bgr, "bgr8"), "/c")
    np.testing.assert_array_equal(rgb, bgr[:, :, ::-1])
    np.testing.assert_array_equal(msgconv.rgb_from_image(image(bgr, "rgb8")), bgr)


@pytest.mark.parametrize("pad", [0, 4])
def test_colour_with_alpha_loses_it(pad):
    """rgba8 and bgra8 (the colour of the ZED and Azure Kinect drivers) were refused ("must
    be rgb8 or bgr8") where the same image compressed as a BGRA PNG was taken: the alpha is
    left out, the channels put in RGB order."""
    bgra = CASES["bgra8"]
    rgb = msgconv.rgb_from_image(image(bgra, "bgra8", pad), "/c")
    assert rgb.shape == bgra.shape[:2] + (3,) and rgb.flags.c_contiguous
    np.testing.assert_array_equal(rgb, bgra[:, :, 2::-1])
    rgba = CASES["rgba8"]
    rgb = msgconv.rgb_from_image(image(rgba, "rgba8", pad), "/c")
    assert rgb.shape == rgba.shape[:2] + (3,) and rgb.flags.c_contiguous
    np.testing.assert_array_equal(rgb, rgba[:, :, :3])


def test_depth_units():
    mm = np.array([[0, 1000, 2500]], np.uint16)
    np.testing.assert_allclose(msgconv.depth_from_image(image(mm, "16UC1")), [[0, 1.0, 2.5]])
    m = np.array([[np.nan, 1.25, -1.0, np.inf]], np.float32)
    np.testing.assert_allclose(msgconv.depth_from_image(image(m, "32FC1")), [[0, 1.25, 0, 0]])
    f = msgconv.depth_fields(np.array([[0.0, 1.2344, np.nan]], np.float32), "16UC1")
    np.testing.assert_array_equal(f["data"].view("<u2"), [0, 1234, 0])


@pytest.mark.parametrize("msg, match", [
    (NS(height=2, width=2, encoding="yuv422", is_bigendian=0, step=4, data=b"\0" * 8),
     "unsupported image encoding 'yuv422'"),
    (NS(height=2, width=3, encoding="mono16", is_bigendian=0, step=4, data=b"\0" * 8),
     "step 4 is smaller"),
    (NS(height=2, width=2, encoding="mono16", is_bigendian=0, step=4, data=b"\0" * 7),
     "data has 7 bytes"),
    (NS(height=0, width=2, encoding="mono16", is_bigendian=0, step=4, data=b""),
     "empty size"),
])
def test_image_errors_name_topic(msg, match):
    with pytest.raises(MessageError, match=match) as err:
        msgconv.image_to_array(msg, "/camera/depth/image_raw")
    assert "/camera/depth/image_raw" in str(err.value)


def test_wrong_encoding_for_role():
    with pytest.raises(MessageError, match="rgb8, bgr8, rgba8 or bgra8, got 'mono8'"):
        msgconv.rgb_from_image(image(CASES["mono8"], "mono8"), "/c")
    with pytest.raises(MessageError, match="16UC1 .mm. or 32FC1"):
        msgconv.depth_from_image(image(CASES["mono8"], "mono8"), "/d")
    with pytest.raises(MessageError, match="does not fit encoding"):
        msgconv.image_fields(CASES["rgb8"], "32FC9")


def test_camera_info():
    info = NS(width=320, height=240, k=[160, 0, 159.5, 0, 161, 119.5, 0, 0, 1], d=[0] * 5)
    intr = msgconv.camera_info_to_intrinsics(info, "/ci")
    assert intr == Intrinsics(160, 161, 159.5, 119.5, 320, 240)
    f = msgconv.camera_info_fields(intr)
    assert msgconv.camera_info_to_intrinsics(NS(**f)) == intr
    distorted = NS(**{**info.__dict__, "d": [0.1, -0.2, 0, 0, 0]})
    with pytest.raises(MessageError, match="/ci: distortion .*topics.distortion to 'ignore'"):
        msgconv.camera_info_to_intrinsics(distorted, "/ci")
    # A RealSense-like colour camera with small coefficients, taken as its K alone.
    assert msgconv.camera_info_to_intrinsics(distorted, "/ci", "ignore") == intr
    with pytest.raises(MessageError, match="/ci: .*non-zero"):
        msgconv.camera_info_to_intrinsics(NS(**{**info.__dict__, "k": [0] * 9}), "/ci")
    with pytest.raises(MessageError, match="9"):
        msgconv.camera_info_to_intrinsics(NS(**{**info.__dict__, "k": [1, 2]}), "/ci")


def pose_msg(t, q):
    return NS(header=None, pose=NS(position=NS(x=t[0], y=t[1], z=t[2]),
                                   orientation=NS(x=q[0], y=q[1], z=q[2], w=q[3])))


def test_pose_round_trip_and_transform():
    T = look_at([1.0, -2.0, 1.5], [3.0, 1.0, 0.7])
    f = msgconv.matrix_to_pose_fields(T)
    np.testing.assert_allclose(msgconv.pose_to_matrix(pose_msg(f["position"], f["orientation"])),
                               T, atol=1e-12)
    tf = NS(transform=NS(translation=NS(x=1.0, y=-2.0, z=1.5),
                         rotation=NS(**dict(zip("xyzw", f["orientation"])))))
    np.testing.assert_allclose(msgconv.pose_to_matrix(tf), T, atol=1e-12)


def test_pose_errors():
    with pytest.raises(MessageError, match="/camera/pose: pose has non-finite"):
        msgconv.pose_to_matrix(pose_msg([np.nan, 0, 0], [0, 0, 0, 1]), "/camera/pose")
    with pytest.raises(MessageError, match="norm"):
        msgconv.pose_to_matrix(pose_msg([0, 0, 0], [0, 0, 0, 0]), "/camera/pose")
    with pytest.raises(MessageError, match="norm 1.010000"):
        msgconv.pose_to_matrix(pose_msg([0, 0, 0], [0, 0, 0, 1.01]), "/camera/pose")
    # what tf2 takes is taken, normalised (a driver's float32 quaternion of norm 1.002)
    np.testing.assert_allclose(msgconv.pose_to_matrix(pose_msg([0, 0, 0], [0, 0, 0, 1.002])),
                               np.eye(4), atol=1e-12)
    bad = np.eye(4)
    bad[0, 3] = np.inf
    with pytest.raises(MessageError, match="/p: pose has non-finite"):
        msgconv.matrix_to_pose_fields(bad, "/p")


def test_stamps():
    assert msgconv.stamp_to_ns(NS(sec=3, nanosec=5)) == 3_000_000_005
    assert msgconv.ns_to_stamp(3_000_000_005) == (3, 5)


def _png(img) -> bytes:
    import cv2
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def test_compressed_images_decode_to_rgb_and_metres():
    import struct
    bgr = CASES["bgr8"]
    png = NS(format="bgr8; png compressed bgr8", data=_png(bgr))
    assert msgconv.is_compressed(png) and not msgconv.is_compressed(image(bgr, "bgr8"))
    np.testing.assert_array_equal(msgconv.rgb_from_image(png, "/c"), bgr[:, :, ::-1])
    # "compressed rgb8": the publisher gave the codec RGB data, so the decoded buffer is
    # already RGB (compressed_image_transport's subscriber reads it so).
    rgb_data = NS(format="rgb8; png compressed rgb8", data=_png(bgr))
    np.testing.assert_array_equal(msgconv.rgb_from_image(rgb_data, "/c"), bgr)
    bgra = np.dstack([bgr, np.full(bgr.shape[:2], 7, np.uint8)])  # alpha dropped
    np.testing.assert_array_equal(
        msgconv.rgb_from_image(NS(format="png", data=_png(bgra))), bgr[:, :, ::-1])
    mm = np.array([[0, 1000, 2500]], np.uint16)
    for fmt, data in (("16UC1; png compressed", _png(mm)),  # image_transport's compressed
                      ("16UC1; compressedDepth png", struct.pack("<iff", 0, 0, 0) + _png(mm)),
                      ("16UC1; compressedDepth", struct.pack("<iff", 0, 0, 0) + _png(mm))):
        np.testing.assert_allclose(msgconv.depth_from_image(NS(format=fmt, data=data)),
                                   [[0, 1.0, 2.5]])
    # 32FC1: quantised inverse depth q, depth = a / (q - b); q = 0 is no depth (0, not NaN).
    q = np.array([[0, 200, 1000]], np.uint16)
    d = msgconv.depth_from_image(NS(format="32FC1; compressedDepth png",
                                    data=struct.pack("<iff", 0, 500.0, 100.0) + _png(q)))
    np.testing.assert_allclose(d, [[0, 5.0, 500 / 900]], rtol=1e-6)


@pytest.mark.parametrize("fmt, data, call, match", [
    ("png", _png(CASES["mono8"]), "rgb", "colour image must have 3 channels.*decodes to mono8"),
    ("bgr8; png compressed bgr8", _png(CASES["bgr8"]), "depth",
     "depth image must be 16-bit millimetres or 32FC1 metres.*decodes to bgr8"),
    ("jpeg", b"\xff\xd8 broken", "rgb", r"compressed image \(format 'jpeg'\) cannot be decoded"),
    ("16UC1; compressedDepth png", b"\0" * 12, "depth", "has no image after its header"),
    ("16UC1; compressedDepth rvl", b"\0" * 40, "depth", "RVL codec is not supported"),
    ("8UC1; compressedDepth png", b"\0" * 12 + _png(CASES["16UC1"]), "depth",
     "compressedDepth of encoding '8UC1'"),
    ("16UC1; compressedDepth png", b"\0" * 12 + _png(CASES["mono8"]), "depth",
     "holds uint8 with shape"),
])
def test_bad_compressed_images_are_named(fmt, data, call, match):
    conv = msgconv.rgb_from_image if call == "rgb" else msgconv.depth_from_image
    with pytest.raises(MessageError, match="^/t: .*" + match):
        conv(NS(format=fmt, data=data), "/t")


def test_class_table_carries_its_label_images_header():
    """/neurncd/classes is a String: its JSON carries the label image's header, so a
    subscriber pairs a table with its image by stamp (it could only go by arrival order)."""
    import json

    table = {3: {"name": "chair", "kind": "known", "pixels": 120},
             101: {"name": "novel_101", "kind": "novel", "pixels": 0}}
    text = msgconv.class_table_text(1_700_000_000_123_456_789, "camera", table)
    d = json.loads(text)
    assert d["header"] == {"stamp": {"sec": 1_700_000_000, "nanosec": 123_456_789},
                           "frame_id": "camera"}
    assert set(d["classes"]) == {"3", "101"}  # JSON keys are strings
    assert msgconv.class_table_from_text(text) == (1_700_000_000_123_456_789, "camera", table)
    with pytest.raises(msgconv.MessageError, match="/neurncd/classes: not a class table"):
        msgconv.class_table_from_text('{"3": {"name": "chair"}}', "/neurncd/classes")
