"""The map alone, fitted by the engine's mapping at ground-truth poses (issue: neural block map).

From random parameters, the mapping steps of the ``fitted_small_map`` fixture on every other frame of
the 'small' scene (noise-free synthetic depth) must give rendered depth on held-out frames within a
quarter of the finest grid cell of the measured depth, a mesh whose accuracy and completion are within
one and a half mesh voxels, and depth that stays continuous where the surface crosses a block boundary.
The finest grid cell is the block edge over the finest resolution (5 m / 250 = 2 cm); the mesh voxel is
2 cm.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from neb_slam_core.config import MeshConfig, RenderConfig, SamplingConfig
from neb_slam_core.eval.recon import DepthL1Config, ReconConfig, evaluate_reconstruction
from neb_slam_core.eval.seams import seam_step_errors
from neb_slam_core.geometry.rays import backproject_depth
from neb_slam_core.mesh import extract_mesh
from neb_slam_core.render.images import render_depth_image

RENDER = RenderConfig(truncation_m=0.05, sampling=SamplingConfig(far_m=5.0))
MESH_VOXEL_M = 0.02


def finest_cell_m(block_map) -> float:
    """The finest hash-grid cell: the block edge over the finest resolution."""
    return block_map.block_cfg.edge_m / block_map.block_cfg.grid.max_resolution


@pytest.fixture(scope="module")
def fitted(fitted_small_map):
    f = fitted_small_map
    assert f.render == RENDER
    return f.block_map, f.train, f.held_out, f.history, f.scene


def test_loss_decreases_and_map_spans_blocks(fitted):
    block_map, _, _, history, _ = fitted
    assert np.mean(history[-20:]) < 0.05 * np.mean(history[:5])
    assert len(block_map) >= 2  # the room is not centred on the first view: a second block is allocated


def test_held_out_depth_within_a_quarter_of_the_finest_cell(fitted):
    block_map, _, held_out, _, _ = fitted
    errors = []
    for f in held_out:
        depth, rgb = render_depth_image(block_map, f, f.T_world_cam, RENDER)
        ok = (f.depth_m > 0) & (depth > 0)
        assert ok.mean() > 0.95
        errors.append(np.abs(depth[ok] - f.depth_m[ok]).mean())
    assert np.mean(errors) < 0.25 * finest_cell_m(block_map), errors


def test_mesh_accuracy_and_completion_within_one_and_a_half_voxels(fitted):
    block_map, train, _, _, scene = fitted
    observed = np.concatenate([backproject_depth(f.depth_m, f.intrinsics, f.T_world_cam, stride=2) for f in train])
    mesh = extract_mesh(block_map, MeshConfig(voxel_size_m=MESH_VOXEL_M), observed)
    gt = trimesh.load(scene / "mesh.ply", process=False)
    poses = np.stack([f.T_world_cam for f in train])
    r = evaluate_reconstruction(
        mesh,
        gt,
        ReconConfig(n_points=50_000, depth_l1=DepthL1Config(n_views=0)),
        poses,
        train[0].intrinsics,
        progress=False,
    )
    limit_cm = 1.5 * 100 * MESH_VOXEL_M
    assert r.accuracy_cm < limit_cm and r.completion_cm < limit_cm, r
    assert r.completion_ratio_pct > 90.0, r


def test_depth_is_continuous_across_block_seams(fitted):
    """Where the observed surface crosses a block face inside another block, the rendered depth step
    matches the ground-truth step within half the finest grid cell (see neb_slam_core.eval.seams)."""
    block_map, _, held_out, _, _ = fitted
    centres = block_map.centres().numpy().astype(np.float64)
    seam, elsewhere = [], []
    for f in held_out:
        depth, _ = render_depth_image(block_map, f, f.T_world_cam, RENDER)
        steps = seam_step_errors(depth, f.depth_m, f.T_world_cam, f.intrinsics, centres, block_map.block_cfg.edge_m)
        seam.append(steps.seam)
        elsewhere.append(steps.elsewhere)
    seam = np.concatenate(seam)
    assert seam.size >= 10, "the held-out views must see surfaces crossing a block boundary"
    assert seam.max() <= 0.5 * finest_cell_m(block_map), seam.max()
    # and seams are no worse than the rest of the surface
    assert np.percentile(seam, 99) <= np.percentile(np.concatenate(elsewhere), 99) + 0.002


def test_known_pose_mapping_takes_the_mappers_own_steps(small_scene):
    """:class:`KnownPoseMapping` stores every frame as a keyframe of the blocks it sees, and its steps
    are the backend mapper's: step by step, bit for bit what one mapper call of as many steps does."""
    import torch

    from neb_slam_core.config_io import load_config
    from neb_slam_core.datasets import open_dataset
    from neb_slam_core.slam import KnownPoseMapping

    ds = open_dataset(small_scene)
    frames = [ds[i] for i in (0, 4, 8)]
    cfg = load_config("ci")
    stepwise, at_once = KnownPoseMapping(cfg), KnownPoseMapping(cfg)
    for f in frames:
        stepwise.add(f)
        at_once.add(f)
    assert len(stepwise.keyframes) == 3
    assert stepwise.keyframes.keyframes_of_block(0) == [0, 1, 2]
    losses = stepwise.optimise(3)
    result = at_once.backend.mapper.optimise(3, optimise_poses=False)
    assert len(losses) == 3 and losses[-1] == result.loss
    for (name, a), (_, b) in zip(stepwise.block_map.state_dict().items(), at_once.block_map.state_dict().items()):
        assert torch.equal(a, b), name
    np.testing.assert_array_equal(stepwise.keyframes.poses(), np.stack([f.T_world_cam for f in frames]))
