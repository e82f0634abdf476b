"""packml_ros2: PackML (ISA-TR88.00.02) units, equipment modules and cells on ROS 2.

``packml_ros2.core`` is the pure engine (no rclpy); the node modules translate between ROS 2 and it.
"""

__version__ = "0.1.0"
