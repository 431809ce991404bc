"""The process preparation every engine process runs before its first frame."""

import sys

from neb_slam_core.engine_process import SWITCH_INTERVAL_S, prepare_engine_process


def test_prepare_shortens_the_gil_turns_and_can_run_twice():
    before = sys.getswitchinterval()
    try:
        assert prepare_engine_process("reference") >= 0.0
        assert sys.getswitchinterval() == SWITCH_INTERVAL_S
        assert prepare_engine_process("auto") >= 0.0
        assert sys.getswitchinterval() == SWITCH_INTERVAL_S
    finally:
        sys.setswitchinterval(before)
