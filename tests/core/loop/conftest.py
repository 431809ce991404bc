"""Shared fixtures of the loop-closure tests: the shipped vocabulary and views of the synthetic loop."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))  # for `from loop_scene import ...`

from loop_scene import render_loop_views

from neb_slam_core.loop.vocabulary import Vocabulary


@pytest.fixture(scope="session")
def vocabulary() -> Vocabulary:
    return Vocabulary.load("")


@pytest.fixture(scope="session")
def loop_views():
    """``({frame: (rendered view, T_world_cam)}, intrinsics)`` of the synthetic loop's keyframes."""
    return render_loop_views()
