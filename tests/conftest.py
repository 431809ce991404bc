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
    """A block map fitted with ground-truth poses to every other frame of the 'small' scene."""

    block_map: object  # neb_slam_core.scene.block_map.BlockMap
    train: list
    held_out: list
    history: list
    scene: Path
    render: object  # neb_slam_core.config.RenderConfig used for fitting


@pytest.fixture(scope="session")
def fitted_small_map(small_scene) -> FittedMap:
    """200 iterations of 2048 rays from random parameters (about 30 s on two cores); shared by the
    map-fitting and the tracking tests, which must not change it."""
    import numpy as np
    import torch

    from neb_slam_core.config import BlockConfig, RenderConfig, SamplingConfig
    from neb_slam_core.datasets import open_dataset
    from neb_slam_core.mapping.fit import FitConfig, FrameRayPool, allocate_blocks, fit_map
    from neb_slam_core.scene.block_map import BlockMap

    render = RenderConfig(truncation_m=0.05, sampling=SamplingConfig(far_m=5.0))
    torch.manual_seed(0)
    ds = open_dataset(small_scene)
    frames = [ds[i] for i in range(len(ds))]
    train, held_out = frames[::2], frames[1::6]
    poses = [f.T_world_cam for f in train]
    block_map = BlockMap(BlockConfig(), seed=0)
    allocate_blocks(block_map, train, poses, render.sampling.near_m, render.sampling.far_m, np.random.default_rng(0))
    history = fit_map(block_map, FrameRayPool(train, poses), render, FitConfig(iterations=200, rays_per_iteration=2048))
    return FittedMap(block_map, train, held_out, history, small_scene, render)
