"""Shared fixtures. Real TUM data lives beside the repo in ../shared/data and is used in place."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("NEB_SLAM_SHARED_DATA", REPO.parent / "shared" / "data"))
TUM_300 = SHARED_DATA / "tum_fr1_xyz_300"


@pytest.fixture(scope="session")
def tum_dir() -> Path:
    """The 300-frame TUM fr1_xyz excerpt; skips the test when ../shared/data is absent."""
    if not (TUM_300 / "rgb.txt").is_file():
        pytest.skip(f"real TUM data not found at {TUM_300} (set NEB_SLAM_SHARED_DATA to its parent folder)")
    return TUM_300


@pytest.fixture(scope="session")
def small_scene(tmp_path_factory) -> Path:
    """The 'small' synthetic preset (one furnished room, 96x72, 60 frames), generated once per session."""
    from neb_slam_core.synth.generate import generate

    return generate("small", tmp_path_factory.mktemp("synth") / "small", progress=False)
