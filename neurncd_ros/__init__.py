"""neurncd_ros: online novel class discovery from RGB-D with an Embedding-NeRF (ROS 2)."""

__version__ = "0.1.0"
