"""bag_replay's looped passes: stamps that run forward, and reversed passes with the recording's gaps."""

from types import SimpleNamespace

import numpy as np
import pytest

pytestmark = pytest.mark.ros


def _passes(stamps: list[int], reverse: bool, n: int) -> list[tuple[list[int], list[int]]]:
    from neb_slam_ros.bag_replay import BagReplayNode

    fake = SimpleNamespace(
        indices=range(len(stamps)),
        dataset=SimpleNamespace(stamps_ns=np.array(stamps, dtype=np.int64)),
        opt=SimpleNamespace(loop_reverse=reverse),
        _passes=0,
        _last_stamp_ns=0,
    )
    out = []
    for _ in range(n):
        indices, published = BagReplayNode._pass_stamps(fake)
        out.append((list(indices), published))
    return out


def test_each_pass_is_stamped_one_frame_period_after_the_last():
    # frames at 100, 130, 170 ns: period (170 - 100) / 2 = 35
    passes = _passes([100, 130, 170], reverse=False, n=3)
    assert passes[0] == ([0, 1, 2], [100, 130, 170])
    assert passes[1] == ([0, 1, 2], [205, 235, 275])
    assert passes[2] == ([0, 1, 2], [310, 340, 380])


def test_reversed_passes_play_backwards_with_the_recording_s_gaps():
    passes = _passes([100, 130, 170], reverse=True, n=3)
    assert passes[0] == ([0, 1, 2], [100, 130, 170])
    # backwards: frame 2, then 1 (40 ns earlier in the recording), then 0 (30 ns)
    assert passes[1] == ([2, 1, 0], [205, 245, 275])
    assert passes[2] == ([0, 1, 2], [310, 340, 380])
