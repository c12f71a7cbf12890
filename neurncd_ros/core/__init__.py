"""ROS-free science core: numpy/torch only, importable without rclpy."""
