"""The occupancy slice (:mod:`neb_slam_core.occupancy`) of a map whose SDF is known in closed form: a
vertical pillar of radius 0.5 m at world (1, 0) in one 2 m block; cells are hand-counted from the rule
(occupied where the distance to the axis is at most 0.5 m plus half a cell)."""

from __future__ import annotations

import numpy as np
import torch

from neb_slam_core.config import BlockConfig, HashGridConfig
from neb_slam_core.occupancy import FREE, OCCUPIED, UNKNOWN, occupancy_slice
from neb_slam_core.scene.block_map import BlockMap, MapSample

TR = 0.1  # truncation: the SDF unit
RES = 0.1


class PillarMap(BlockMap):
    def query(self, points_world, block_ids=None, with_colour=True):
        valid = self.contains(points_world, block_ids).any(dim=1)
        r = torch.linalg.norm(points_world[:, :2] - torch.tensor([1.0, 0.0]), dim=1)
        sdf = (r - 0.5) / TR
        return MapSample(torch.where(valid, sdf, torch.zeros_like(sdf)), points_world.new_zeros(len(r), 3), valid)


def _map() -> PillarMap:
    grid = HashGridConfig(n_levels=2, n_features_per_level=2, log2_hashmap_size=10, base_resolution=4, max_resolution=8)
    m = PillarMap(BlockConfig(edge_m=2.0, grid=grid), grid_backend="reference")
    m.add_block(torch.tensor([1.0, 0.0, 1.0]))  # x 0..2, y -1..1, z 0..2
    m.blocks[0].observed[:] = True
    return m


def _expected(centre_xy, n: int, origin, unknown=lambda x, y: False) -> np.ndarray:
    out = np.zeros((n, n), np.int8)
    for j in range(n):
        for i in range(n):
            x, y = origin[0] + (i + 0.5) * RES, origin[1] + (j + 0.5) * RES
            r = np.hypot(x - centre_xy[0], y - centre_xy[1])
            out[j, i] = UNKNOWN if unknown(x, y) else (OCCUPIED if r - 0.5 <= RES / 2 else FREE)
    return out


def test_a_slice_through_a_pillar_in_the_world_frame():
    s = occupancy_slice(_map(), TR, np.eye(4), height_m=1.0, resolution_m=RES)
    assert s.origin_xy == (0.0, -1.0) and s.cells.shape == (20, 20)
    np.testing.assert_array_equal(s.cells, _expected((1.0, 0.0), 20, (0.0, -1.0)))
    # per quadrant, cell centres (0.05 + 0.1 a, 0.05 + 0.1 b) within 0.55 m: 5 + 5 + 5 + 4 + 3 for a = 0..4
    assert (s.cells == OCCUPIED).sum() == 4 * 22


def test_a_level_frame_turned_and_shifted_against_the_world():
    # level x = world y, level y = -world x, level origin at world (1, 0, 0.5): the pillar's axis is the
    # level frame's z axis, and the slice at level height 0.5 is at world height 1.0
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = [1.0, 0.0, 0.5]
    s = occupancy_slice(_map(), TR, T, height_m=0.5, resolution_m=RES)
    assert s.origin_xy == (-1.0, -1.0) and s.cells.shape == (20, 20)
    np.testing.assert_array_equal(s.cells, _expected((0.0, 0.0), 20, (-1.0, -1.0)))
    # above the block: every cell unknown
    assert (occupancy_slice(_map(), TR, T, height_m=2.0, resolution_m=RES).cells == UNKNOWN).all()


def test_space_no_keyframe_has_seen_is_unknown():
    m = _map()
    m.blocks[0].observed[: m.blocks[0].observed.shape[0] // 4] = False  # world x < 0.5 unseen
    s = occupancy_slice(m, TR, np.eye(4), height_m=1.0, resolution_m=RES)
    np.testing.assert_array_equal(s.cells, _expected((1.0, 0.0), 20, (0.0, -1.0), unknown=lambda x, y: x < 0.5))


def test_an_empty_map_gives_an_empty_grid():
    grid = HashGridConfig(n_levels=2, n_features_per_level=2, log2_hashmap_size=10, base_resolution=4, max_resolution=8)
    s = occupancy_slice(BlockMap(BlockConfig(edge_m=2.0, grid=grid), grid_backend="reference"), TR, np.eye(4), 0.0, RES)
    assert s.cells.shape == (0, 0)
