"""The topic contract: every topic and frame name the nodes, the bags and the tools use.

One module, imported by the nodes, by bag I/O and by the offline tools, so a
name is declared once and is a parameter (``topics.*``) everywhere.
"""

from __future__ import annotations

import dataclasses

from .params import param


COMPRESSED_SUFFIXES = ("compressed", "compressedDepth")


def is_compressed_topic(topic: str) -> bool:
    """Whether an input image topic carries sensor_msgs/CompressedImage: image_transport
    publishes them as ``<base>/compressed`` and ``<base>/compressedDepth``, and the nodes
    subscribe with the type the name says (a bag says its types itself)."""
    return topic.rstrip("/").rsplit("/", 1)[-1] in COMPRESSED_SUFFIXES


def compressed_alternatives(topic: str, present) -> list[str]:
    """The image_transport topics of ``topic`` (``<topic>/compressed``,
    ``<topic>/compressedDepth``) among ``present`` when ``topic`` itself is not there:
    the topic a user should set instead."""
    if topic in present:
        return []
    return [t for t in (f"{topic}/{x}" for x in COMPRESSED_SUFFIXES) if t in present]


@dataclasses.dataclass(frozen=True)
class Topics:
    """Topic and frame names of the topic contract (every one overridable)."""

    color: str = param("/camera/color/image_raw", "colour image, sensor_msgs/Image rgb8|bgr8; "
                       "a topic ending in /compressed is a sensor_msgs/CompressedImage (JPEG "
                       "or PNG, image_transport's compressed)")
    depth: str = param("/camera/depth/image_raw", "depth registered to colour, 16UC1 mm or "
                       "32FC1 m; a topic ending in /compressedDepth (or /compressed, a 16-bit "
                       "PNG) is a sensor_msgs/CompressedImage")
    camera_info: str = param("/camera/color/camera_info", "sensor_msgs/CameraInfo of colour")
    pose: str = param("/camera/pose", "geometry_msgs/PoseStamped camera-to-world, OpenCV axes")
    semantic: str = param("/camera/semantic/image_raw", "ground-truth NYU-13 ids, mono16")
    instance: str = param("/camera/instance/image_raw", "ground-truth instance ids, mono16")
    embedding: str = param("/neurncd/embedding", "backbone embedding, 32FC<C> (logits, then "
                           "feature channels), same stamp as the frame")
    embedding_spec: str = param("/neurncd/embedding/spec", "what the embedding channels mean "
                                "(std_msgs/String JSON: channel_to_id, feature_channels, "
                                "backbone), transient local")
    rendered_embedding: str = param("/neurncd/rendered_embedding", "a view's embedding "
                                    "rendered by the field, 32FC<C>, stamp of its frame")
    entropy: str = param("/neurncd/entropy", "a view's entropy of the rendered softmax, "
                         "32FC1")
    view_depth: str = param("/neurncd/view/depth", "the depth of the rendered view (32FC1 "
                            "m): measured, averaged with the keyframes' (mapper_node."
                            "depth_fusion); published with it so discovery always has it")
    view_color: str = param("/neurncd/view/color", "the colour image of the rendered view, "
                            "rgb8")
    view_pose: str = param("/neurncd/view/pose", "camera-to-world pose of the rendered view "
                           "(geometry_msgs/PoseStamped, stamp of its frame), for discovery's "
                           "label fusion")
    view_camera_info: str = param("/neurncd/view/camera_info", "intrinsics of the rendered "
                                  "view's depth and colour")
    rendered_spec: str = param("/neurncd/rendered_embedding/spec", "what the rendered "
                               "embedding channels mean (as embedding_spec), transient local")
    keyframes: str = param("/neurncd/keyframes", "pose of every keyframe the field admits "
                           "(geometry_msgs/PoseStamped, stamp of its frame)")
    diagnostics: str = param("/diagnostics", "node health: rates, drops, state "
                             "(diagnostic_msgs/DiagnosticArray)")
    labels: str = param("/neurncd/labels", "discovered labels, mono16 (novel ids >= 100)")
    labels_color: str = param("/neurncd/labels_color", "labels coloured with the palette, rgb8")
    classes: str = param("/neurncd/classes", "class table as JSON (std_msgs/String)")
    tf: str = param("/tf", "dynamic transforms, tf2_msgs/TFMessage")
    tf_static: str = param("/tf_static", "static transforms, tf2_msgs/TFMessage")
    camera_frame: str = param("camera", "frame_id of images and camera info")
    world_frame: str = param("world", "frame_id of the pose (fixed world frame)")
    distortion: str = param("refuse", "camera info with non-zero distortion coefficients: "
                            "'refuse' it (rectify the images first, e.g. image_proc), or "
                            "'ignore' the coefficients and use K alone: the labels stay "
                            "aligned with the raw image pixel for pixel, and the 3D fusion "
                            "is off by the lens distortion towards the borders (small for "
                            "the few-percent coefficients of a RealSense colour camera)",
                            choices=("refuse", "ignore"))
