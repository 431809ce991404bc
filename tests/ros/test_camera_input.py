"""The camera input's frame queue as the live engine uses it: which frames a choice keeps, drops and
counts, and the bound (the oldest dropped, or for a live engine the frames kept spread over a wait). The
queue is exercised directly (``_enqueue`` is what the image callbacks call), on a stand-in node that only
records the subscriptions."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np
import pytest

pytestmark = pytest.mark.ros


class _Node:
    def __init__(self):
        self.warned: list[str] = []

    def get_logger(self):
        return SimpleNamespace(warning=self.warned.append, info=lambda *_: None)

    def get_name(self):
        return "test"

    def resolve_topic_name(self, name):
        return "/" + name

    def create_subscription(self, *args, **kwargs):
        return None


def _input(frame_queue: int = 30):
    from neb_slam_ros.camera_input import CameraInput, InputOptions

    return CameraInput(_Node(), InputOptions(frame_queue=frame_queue, warn_period_s=0.0), threading.Condition())


def _frame(stamp_ns: int):
    from neb_slam_core.types import Intrinsics, RgbdFrame

    cam = Intrinsics(fx=2.0, fy=2.0, cx=2.0, cy=1.5, width=4, height=3)
    return RgbdFrame(np.zeros((3, 4, 3), np.uint8), np.ones((3, 4), np.float32), cam, stamp_ns)


def test_pop_chosen_drops_the_older_frames_and_keeps_the_newer():
    inp = _input()
    for s in (10, 20, 30, 40):
        inp._enqueue(_frame(s))
    seen = []

    def choose(stamps):
        seen.append(list(stamps))
        return 1

    frame = inp.pop_chosen(choose)
    assert frame.stamp_ns == 20 and seen == [[10, 20, 30, 40]]
    assert inp.n_dropped == 1  # the frame of stamp 10
    assert [f.stamp_ns for f in inp._queue] == [30, 40]  # newer frames stay for the next choice
    inp.push_front(frame)
    assert inp.pop_newest().stamp_ns == 40 and inp.n_dropped == 3 and not inp.has_frame
    assert inp.pop_chosen(choose) is None and len(seen) == 1  # nothing queued: not asked
    inp._enqueue(_frame(50))
    with pytest.raises(IndexError, match="outside the 1 queued"):
        inp.pop_chosen(lambda stamps: 1)


def test_a_full_queue_drops_its_oldest_frame_with_a_warning():
    inp = _input(frame_queue=2)
    for s in (10, 20, 30):
        inp._enqueue(_frame(s))
    assert [f.stamp_ns for f in inp._queue] == [20, 30] and inp.n_dropped == 1
    assert inp.node.warned and "behind the input" in inp.node.warned[0]
    assert inp.drop_queued() == 2 and inp.n_dropped == 3


def test_a_live_queue_keeps_its_frames_spread_over_a_wait():
    """A live engine's queue while frames arrive every 10 ns after the engine took the frame of stamp 0:
    each overflow drops the frame whose neighbours lie closest (the oldest of equals, never the newest).
    Hand-worked with a queue of 3 for arrivals 10..80 (gap left by each candidate, the drop):
    [10,20,30,40] gaps 20,20,20 -> 10; [20,30,40,50] 30,20,20 -> 30; [20,40,50,60] 40,30,20 -> 50;
    [20,40,60,70] 40,40,30 -> 60; [20,40,70,80] 40,50,40 -> 20; leaving [40, 70, 80]."""
    inp = _input(frame_queue=3)
    inp.thin = True
    inp._enqueue(_frame(0))
    assert inp.pop().stamp_ns == 0
    for s in range(10, 81, 10):
        inp._enqueue(_frame(s))
    assert [f.stamp_ns for f in inp._queue] == [40, 70, 80]
    assert inp.n_dropped == 5 and "spread" in inp.node.warned[1]  # the second drop, of 30
    # a long wait: the engine catches up from 0 in steps of at most 60 where the oldest-first queue of 5
    # would keep only 160..200 and jump by 160
    inp = _input(frame_queue=5)
    inp.thin = True
    inp._enqueue(_frame(0))
    inp.pop()
    for s in range(10, 201, 10):
        inp._enqueue(_frame(s))
    stamps = [f.stamp_ns for f in inp._queue]
    assert len(stamps) == 5 and stamps[-1] == 200 and max(np.diff([0, *stamps])) <= 60, stamps


def test_a_pair_takes_the_depth_stamp_or_the_colour_stamp():
    from neb_slam_ros.sync import StampPairer

    for frame_stamp, expected in (("depth", [1_005, 1_040]), ("colour", [1_000, 1_033])):
        pairer = StampPairer(slop_ns=20, frame_stamp=frame_stamp)
        # colour at 1000 and 1033 ns, depth at 1005 and 1040: each pairs with the nearest within 20
        assert pairer.push("rgb", 1_000, "c0") == ([], "")
        (pair,), _ = pairer.push("depth", 1_005, "d0")
        assert pairer.push("rgb", 1_033, "c1") == ([], "")
        (second,), _ = pairer.push("depth", 1_040, "d1")
        assert [pair.stamp_ns, second.stamp_ns] == expected
        assert (pair.rgb, pair.depth, second.rgb, second.depth) == ("c0", "d0", "c1", "d1")


def test_frame_stamp_parameter_is_checked():
    from neb_slam_ros.camera_input import InputOptions
    from neb_slam_ros.params import ParameterError

    with pytest.raises(ParameterError, match="frame_stamp"):
        InputOptions(frame_stamp="rgb").check()


def test_a_frame_takes_its_depth_image_stamp_and_keeps_both():
    from neb_slam_core.types import COLOUR_STAMP, DEPTH_STAMP, Intrinsics
    from neb_slam_ros import conversions

    cam = (Intrinsics(fx=2.0, fy=2.0, cx=2.0, cy=1.5, width=4, height=3), (0.0,) * 5)
    rgb = conversions.rgb_msg(np.zeros((3, 4, 3), np.uint8), 1_000, "cam")
    depth = conversions.depth_msg(np.ones((3, 4), np.float32), 1_007, "cam")
    topics = ("rgb/image", "depth/image", "rgb/camera_info")
    for frame_stamp, expected in (("depth", 1_007), ("colour", 1_000)):
        frame, _ = conversions.frame_from_msgs(rgb, depth, cam, 0.001, topics, frame_stamp=frame_stamp)
        assert frame.stamp_ns == expected
        assert (frame.extras[COLOUR_STAMP], frame.extras[DEPTH_STAMP]) == (1_000, 1_007)
