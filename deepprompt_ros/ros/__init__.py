"""Thin rclpy nodes of deepprompt_ros; message <-> array conversions live in :mod:`.conversions`."""
