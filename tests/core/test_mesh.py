"""Mesh extraction on maps whose SDF is known in closed form (a plane), to check seams and culling."""

import numpy as np
import torch

from neb_slam_core.config import BlockConfig, HashGridConfig, MeshConfig
from neb_slam_core.mesh import extract_mesh
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
