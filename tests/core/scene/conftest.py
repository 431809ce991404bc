"""Fixtures shared by the scene tests."""

from __future__ import annotations

import pytest

from neb_slam_core.scene import _ext


@pytest.fixture(scope="session")
def fast_ext():
    """The map's C++ kernels (``_ext.load_map_kernels``). Fails, never skips, when they are unavailable:
    the fast path is part of the product."""
    reason = _ext.unavailable_reason()
    if reason is not None:
        pytest.fail(f"the map's C++ kernels are unavailable: {reason}")
    return _ext.load_map_kernels()
