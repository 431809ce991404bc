"""Mesh extraction on maps whose SDF is known in closed form (a plane), to check seams, culling and the
extraction block by block."""

import numpy as np
import torch

from neb_slam_core.config import BlockConfig, HashGridConfig, MeshConfig
from neb_slam_core.mesh import affected_blocks, extract_block_meshes, extract_mesh, split_by_block
from neb_slam_core.scene.block_map import BlockMap, MapSample

PLANE_Z = 0.311
GRID = HashGridConfig(n_levels=2, n_features_per_level=2, log2_hashmap_size=10, base_resolution=4, max_resolution=8)


class PlaneMap(BlockMap):
    """A block map whose SDF is the plane z = PLANE_Z (positive above), coloured by x."""

    def query(self, points_world, block_ids=None, with_colour=True):
        valid = self.contains(points_world, block_ids).any(dim=1)
        sdf = torch.where(valid, (points_world[:, 2] - PLANE_Z) / 0.1, torch.zeros_like(points_world[:, 0]))
        rgb = torch.stack([points_world[:, 0].clamp(0, 1)] * 3, dim=1) * valid[:, None]
        return MapSample(sdf, rgb, valid)


def plane_map(centres) -> PlaneMap:
    m = PlaneMap(BlockConfig(edge_m=2.0, grid=GRID), grid_backend="reference")
    for c in centres:
        m.add_block(c)
    return m


def observed_rectangle(x0, x1, y0, y1, step=0.01):
    xs, ys = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step))
    return np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, PLANE_Z)], axis=1)


def test_plane_across_overlapping_blocks_has_no_cracks_and_no_doubled_faces():
    v = 0.05
    m = plane_map([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0]])  # overlap x in [0.5, 1.0]
    obs = observed_rectangle(-0.8, 2.3, -0.5, 0.5)
    mesh = extract_mesh(m, MeshConfig(voxel_size_m=v, cull_distance_m=0.1), obs)
    assert len(mesh.faces) > 0
    assert np.abs(mesh.vertices[:, 2] - PLANE_Z).max() < 1e-5
    # every lattice cell the plane crosses gives exactly two triangles: a doubled wall would give four
    cells = np.floor(mesh.triangles_center[:, :2] / v).astype(int)
    _, counts = np.unique(cells, axis=0, return_counts=True)
    assert counts.max() == 2 and counts.min() == 2
    assert abs(mesh.area - len(counts) * v * v) < 1e-6
    # no cracks: edges used by a single triangle only lie on the outer border of the meshed region
    edges = mesh.edges_sorted
    uniq, n = np.unique(edges, axis=0, return_counts=True)
    border = uniq[n == 1]
    mid = mesh.vertices[border].mean(axis=1)
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    on_outer = (
        np.isclose(mid[:, 0], lo[0])
        | np.isclose(mid[:, 0], hi[0])
        | np.isclose(mid[:, 1], lo[1])
        | np.isclose(mid[:, 1], hi[1])
    )
    assert on_outer.all(), f"interior open edges at {mid[~on_outer][:5]}"
    # the seam region is covered
    assert lo[0] < 0.5 and hi[0] > 1.0


def test_unobserved_surface_is_culled():
    v = 0.05
    m = plane_map([[0.0, 0.0, 0.0]])
    obs = observed_rectangle(-0.5, 0.0, -0.5, 0.5)
    mesh = extract_mesh(m, MeshConfig(voxel_size_m=v, cull_distance_m=0.1), obs)
    x = mesh.vertices[:, 0]
    assert x.min() < -0.4
    # nothing farther than the culling distance (+ one voxel of lattice slack) from the observations
    assert x.max() <= 0.0 + 0.1 + 2 * v
    full = extract_mesh(m, MeshConfig(voxel_size_m=v, cull_distance_m=0.1), None)
    assert full.vertices[:, 0].max() > 0.9  # without observations the whole block is meshed


def test_vertex_colours_come_from_the_colour_decoder():
    m = plane_map([[0.0, 0.0, 0.0]])
    mesh = extract_mesh(m, MeshConfig(voxel_size_m=0.1), observed_rectangle(0.0, 0.9, -0.5, 0.5))
    expected = np.round(np.clip(mesh.vertices[:, 0], 0, 1) * 255)
    assert np.abs(mesh.visual.vertex_colors[:, 0].astype(float) - expected).max() <= 1


def _rows(verts, faces, colours) -> np.ndarray:
    """Triangles as rows of corners and corner colours, in a canonical order (rounded to sort: vertices
    on a seam are computed by two blocks)."""
    r = np.concatenate([verts[faces].reshape(len(faces), -1), colours[faces][..., :3].reshape(len(faces), -1)], axis=1)
    return r[np.lexsort(np.round(r, 6).T[::-1])]


def test_the_blocks_parts_are_the_mesh_split_by_owner():
    cfg = MeshConfig(voxel_size_m=0.05, cull_distance_m=0.1)
    m = plane_map([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [5.0, 0.0, 0.0]])  # 0 and 1 overlap; 2 on its own
    obs = observed_rectangle(-0.8, 5.9, -0.5, 0.5)
    mesh = extract_mesh(m, cfg, obs)
    parts = extract_block_meshes(m, cfg, obs, [2, 0, 1])
    assert sorted(parts) == [0, 1, 2] and all(len(p[1]) > 0 for p in parts.values())
    colours = np.asarray(mesh.visual.vertex_colors)[:, :3]
    whole = _rows(np.asarray(mesh.vertices), np.asarray(mesh.faces), colours)
    together = np.concatenate([_rows(*p) for p in parts.values()])
    together = together[np.lexsort(np.round(together, 6).T[::-1])]
    assert whole.shape == together.shape
    np.testing.assert_allclose(together, whole, rtol=0, atol=1e-9)
    split = split_by_block(mesh, m)
    for b, part in parts.items():
        np.testing.assert_allclose(_rows(*split[b]), _rows(*part), rtol=0, atol=1e-9)
    # a block the observations do not reach has no triangles
    empty = extract_block_meshes(m, cfg, observed_rectangle(-0.8, 0.0, -0.5, 0.5), [2])[2]
    assert empty[0].shape == (0, 3) and empty[1].shape == (0, 3)


def test_a_changed_block_affects_the_blocks_within_its_reach():
    cfg = MeshConfig(voxel_size_m=0.05)
    m = plane_map([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [3.6, 0.0, 0.0], [6.0, 0.0, 0.0]])
    # edge 2 m: 1 overlaps 0, 2 is 0.1 m (two voxels) past 1's face, 3 is 0.4 m past 2's
    assert affected_blocks(m, cfg, [0]) == {0, 1}
    assert affected_blocks(m, cfg, [1]) == {0, 1, 2}
    assert affected_blocks(m, cfg, {3}) == {3}
    assert affected_blocks(m, cfg, []) == set()


def test_observed_voxels_are_the_distinct_voxels_of_the_points():
    from neb_slam_core.mesh import _voxels

    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-30, 30, size=(5000, 3)), rng.uniform(-0.1, 0.1, size=(5000, 3))])
    expected = np.unique(np.floor(points / 0.02).astype(np.int64), axis=0)
    np.testing.assert_array_equal(_voxels(points, 0.02), expected)
    assert _voxels(np.zeros((0, 3)), 0.02).shape == (0, 3)
