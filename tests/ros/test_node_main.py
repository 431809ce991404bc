"""The nodes' shared base (:class:`neb_slam_ros.node.NebNode`): a worker thread that publishes after the
context was shut down (elsewhere in the process, while a mapping step or loop re-optimisation still
runs), or a ``close()`` that publishes the final mesh and waits for its acknowledgement then, is not
killed by rclpy's error; work and requests run in the worker, in order, and ``close()`` ends with
``finish()``."""

from __future__ import annotations

import os

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.filterwarnings("ignore::DeprecationWarning:lark.*")]


def test_publishing_after_shutdown_is_dropped_not_raised(ros_env, monkeypatch):
    rclpy = pytest.importorskip("rclpy")
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    from neb_slam_ros.node import NebNode, RCLError

    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setitem(os.environ, key, ros_env[key])
    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)  # leave pytest's own
    plain = Node("plain", context=context)
    ours = NebNode("ours", with_config=False, namespace="/", context=context)
    pub_plain = plain.create_publisher(String, "chatter", 1)
    pub_ours = ours.create_publisher(String, "chatter", 1)
    from rclpy.duration import Duration

    pub_ours.publish(String(data="while up"))  # a working publisher
    assert pub_ours.wait_for_all_acked(Duration(seconds=1.0)) is True  # no subscriber: nothing to wait for
    assert pub_ours.get_subscription_count() == 0 and pub_ours.topic_name == "/chatter"
    rclpy.shutdown(context=context)
    with pytest.raises(RCLError):
        pub_plain.publish(String(data="after shutdown"))  # what killed the mapper's worker
    pub_ours.publish(String(data="after shutdown"))  # dropped quietly
    assert pub_ours.wait_for_all_acked(Duration(seconds=1.0)) is False  # close()'s wait for the final mesh


def test_work_and_requests_run_in_the_worker_in_order(ros_env, monkeypatch):
    rclpy = pytest.importorskip("rclpy")
    import threading

    from rclpy.signals import SignalHandlerOptions

    from neb_slam_ros.node import NebNode

    for key in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE"):
        monkeypatch.setitem(os.environ, key, ros_env[key])

    class Counter(NebNode):
        def __init__(self, context):
            super().__init__("counter", with_config=False, namespace="/", context=context)
            self.queue: list[int] = []
            self.log: list[tuple[str, object, str]] = []
            self.start_worker()

        def has_work(self):
            return bool(self.queue)

        def take_work(self):
            taken, self.queue = self.queue, []
            return taken

        def do_work(self, work):
            if work:
                self.log.append(("work", tuple(work), threading.current_thread().name))

        def finish(self):
            self.log.append(("finish", None, threading.current_thread().name))

    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = Counter(context)
    try:
        gate, entered = threading.Event(), threading.Event()

        def hold():  # holds the worker until released
            entered.set()
            return str(gate.wait(5.0))

        blocker = node.submit(hold, "block")
        assert entered.wait(5.0)
        with node.cond:
            node.queue += [1, 2]
            node.cond.notify_all()
        # two periodic-style requests while one is pending: the second is dropped
        first = node.submit(lambda: "mesh", "publish_mesh", coalesce=True)
        second = node.submit(lambda: "mesh again", "publish_mesh", coalesce=True)
        failing = node.submit(lambda: 1 / 0, "broken")
        assert second.done.is_set() and second.reply == []
        gate.set()
        for request in (blocker, first, failing):
            assert request.done.wait(5.0)
        assert blocker.reply == [(True, "True")] and first.reply == [(True, "mesh")]
        assert failing.reply[0][0] is False and "ZeroDivisionError" in failing.reply[0][1]
        assert node.log[0] == ("work", (1, 2), "counter-worker")
        node.close()
        assert node.log[-1] == ("finish", None, threading.current_thread().name)
        assert not node._worker.is_alive()
        late = node.submit(lambda: "too late", "late")
        assert not late.done.wait(0.2)  # nobody serves requests after close()
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)
