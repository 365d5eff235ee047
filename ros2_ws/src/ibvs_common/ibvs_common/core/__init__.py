"""ROS-free core: numpy/OpenCV only, dataclasses in and out, no rclpy or message types."""
