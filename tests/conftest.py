"""Shared fixtures. Real TUM data lives beside the repo in ../shared/data and is used in place."""

from __future__ import annotations

import os
from dataclasses import dataclass
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


@dataclass
class FittedMap:
    """A block map fitted by the engine's mapping at the ground-truth poses of every other frame of the
    'small' scene."""

    block_map: object  # neb_slam_core.scene.block_map.BlockMap
    train: list
    held_out: list
    history: list  # the total loss of each mapping step
    scene: Path
    render: object  # neb_slam_core.config.RenderConfig used for fitting


@pytest.fixture(scope="session")
def fitted_small_map(small_scene) -> FittedMap:
    """The engine's allocation and mapping (:class:`~neb_slam_core.slam.KnownPoseMapping`) on every other
    frame of the 'small' scene at its ground-truth pose, each a keyframe keeping all its pixels (96x72:
    the engine's 5 % would leave 345 per frame), then 160 mapping steps of the engine's 2048 + 512 rays
    (as many rays as 200 steps of 2048) with the poses held, from random parameters; shared by the
    map-fitting, rendering and tracking tests, which must not change it."""
    from neb_slam_core.config import KeyframeConfig, RenderConfig, SamplingConfig, SlamConfig
    from neb_slam_core.datasets import open_dataset
    from neb_slam_core.slam import KnownPoseMapping

    render = RenderConfig(truncation_m=0.05, sampling=SamplingConfig(far_m=5.0))
    ds = open_dataset(small_scene)
    frames = [ds[i] for i in range(len(ds))]
    train, held_out = frames[::2], frames[1::6]
    mapping = KnownPoseMapping(SlamConfig(render=render, keyframes=KeyframeConfig(pixel_fraction=1.0)))
    for f in train:
        mapping.add(f)
    history = mapping.optimise(160)
    return FittedMap(mapping.block_map, train, held_out, history, small_scene, render)
