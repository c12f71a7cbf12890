"""Thin rclpy adapters around the core: parameters in, messages converted, core called."""
