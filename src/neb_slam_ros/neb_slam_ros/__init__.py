"""NeB-SLAM ROS 2 nodes: thin rclpy wrappers over ``neb_slam_core`` (the contract: docs/topics.md).

One node class per module (``tracker``, ``mapper``, ``loop_closer``, ``bag_replay``, ``slam``), each with a
``main()`` that ``ros2 run neb_slam_ros <node>`` executes. Importing this package does not import rclpy.
"""

#: namespace of every node, so relative topic names resolve under it (``pose`` -> ``/neb_slam/pose``);
#: a user moves the suite elsewhere with ``--ros-args -r __ns:=/other``.
NAMESPACE = "neb_slam"
