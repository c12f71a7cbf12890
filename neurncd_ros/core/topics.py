"""The topic contract: every topic and frame name the nodes, the bags and the tools use.

One module, imported by the nodes, by bag I/O and by the offline tools, so a
name is declared once and is a parameter (``topics.*``) everywhere.
"""

from __future__ import annotations

import dataclasses

from .params import param


@dataclasses.dataclass(frozen=True)
class Topics:
    """Topic and frame names of the topic contract (every one overridable)."""

    color: str = param("/camera/color/image_raw", "colour image, sensor_msgs/Image rgb8|bgr8")
    depth: str = param("/camera/depth/image_raw", "depth registered to colour, 16UC1 mm or "
                       "32FC1 m")
    camera_info: str = param("/camera/color/camera_info", "sensor_msgs/CameraInfo of colour")
    pose: str = param("/camera/pose", "geometry_msgs/PoseStamped camera-to-world, OpenCV axes")
    semantic: str = param("/camera/semantic/image_raw", "ground-truth NYU-13 ids, mono16")
    instance: str = param("/camera/instance/image_raw", "ground-truth instance ids, mono16")
    embedding: str = param("/neurncd/embedding", "backbone embedding, 32FC<S>")
    rendered_embedding: str = param("/neurncd/rendered_embedding", "embedding rendered by "
                                    "the field, 32FC<S>")
    entropy: str = param("/neurncd/entropy", "rendered entropy, 32FC1")
    labels: str = param("/neurncd/labels", "discovered labels, mono16 (novel ids >= 100)")
    labels_color: str = param("/neurncd/labels_color", "labels coloured with the palette, rgb8")
    classes: str = param("/neurncd/classes", "class table as JSON (std_msgs/String)")
    tf: str = param("/tf", "dynamic transforms, tf2_msgs/TFMessage")
    tf_static: str = param("/tf_static", "static transforms, tf2_msgs/TFMessage")
    camera_frame: str = param("camera", "frame_id of images and camera info")
    world_frame: str = param("world", "frame_id of the pose (fixed world frame)")
