"""The process preparation every engine process runs before its first frame."""

import os
import sys
import threading

import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from neb_slam_core.engine_process import SWITCH_INTERVAL_S, lower_thread_priority, prepare_engine_process, usable_cores


def blas_threads() -> list[int]:
    return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]


def test_prepare_shortens_the_gil_turns_limits_blas_and_can_run_twice():
    before = sys.getswitchinterval()
    with threadpool_limits(2, user_api="blas"):  # the pools as a two-core process starts them; restored after
        assert blas_threads() and max(blas_threads()) > 1  # numpy's OpenBLAS is loaded and multi-threaded
        try:
            assert prepare_engine_process("reference") >= 0.0
            assert sys.getswitchinterval() == SWITCH_INTERVAL_S
            assert blas_threads() == [1] * len(blas_threads())
            assert prepare_engine_process("auto") >= 0.0
            assert sys.getswitchinterval() == SWITCH_INTERVAL_S
        finally:
            sys.setswitchinterval(before)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice values are Linux's")
def test_a_background_thread_is_niced_and_no_other():
    main_tid = threading.get_native_id()
    before = os.getpriority(os.PRIO_PROCESS, main_tid)
    seen = {}

    def background():
        tid = threading.get_native_id()
        start = os.getpriority(os.PRIO_PROCESS, tid)
        seen["lowered"] = lower_thread_priority(5)
        seen["delta"] = os.getpriority(os.PRIO_PROCESS, tid) - start
        seen["unchanged"] = lower_thread_priority(0)

    t = threading.Thread(target=background)
    t.start()
    t.join()
    assert seen == {"lowered": True, "delta": min(5, 19 - before), "unchanged": False}
    assert os.getpriority(os.PRIO_PROCESS, main_tid) == before


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="the CPU affinity is a Linux call")
def test_usable_cores_follow_the_affinity():
    """A process pinned to one core has one usable core, whatever the machine has."""
    before = os.sched_getaffinity(0)
    assert usable_cores() == len(before)
    try:
        os.sched_setaffinity(0, {min(before)})
        assert usable_cores() == 1
    finally:
        os.sched_setaffinity(0, before)
