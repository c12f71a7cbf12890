"""Datasets: synthetic scene generator, real-format readers, ROS 2 bag I/O."""
