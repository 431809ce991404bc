"""The nodes' shared base: a worker thread that publishes after the context was shut down (elsewhere in
the process, while a mapping step or loop re-optimisation still runs), or a ``close()`` that publishes
the final mesh and waits for its acknowledgement then, is not killed by rclpy's error."""

from __future__ import annotations

import os

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.filterwarnings("ignore::DeprecationWarning:lark.*")]


def test_publishing_after_shutdown_is_dropped_not_raised(ros_env, monkeypatch):
    rclpy = pytest.importorskip("rclpy")
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    from neb_slam_ros._node_main import RCLError, WorkerNode

    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setitem(os.environ, key, ros_env[key])
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)  # leave pytest's own
    plain = Node("plain", context=context)
    ours = WorkerNode("ours", context=context)
    pub_plain = plain.create_publisher(String, "chatter", 1)
    pub_ours = ours.create_publisher(String, "chatter", 1)
    from rclpy.duration import Duration

    pub_ours.publish(String(data="while up"))  # a working publisher
    assert pub_ours.wait_for_all_acked(Duration(seconds=1.0)) is True  # no subscriber: nothing to wait for
    assert pub_ours.get_subscription_count() == 0 and pub_ours.topic_name == "/chatter"
    rclpy.shutdown(context=context)
    with pytest.raises(RCLError):
        pub_plain.publish(String(data="after shutdown"))  # what killed the mapper's worker
    pub_ours.publish(String(data="after shutdown"))       # dropped quietly
    assert pub_ours.wait_for_all_acked(Duration(seconds=1.0)) is False  # close()'s wait for the final mesh
