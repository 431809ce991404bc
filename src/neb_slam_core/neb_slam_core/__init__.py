"""NeB-SLAM core: neural-block RGB-D SLAM engine, datasets, evaluation and the offline CLI.

The core does no ROS work and imports no rclpy; the ROS 2 nodes in ``neb_slam_ros`` wrap it.
"""

__version__ = "0.1.0"
