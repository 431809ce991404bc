"""Floor plans, scene meshes and presets."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from neb_slam_core.errors import ConfigError
from neb_slam_core.synth.layout import LayoutSpec, Rect, build_floor_plan
from neb_slam_core.synth.presets import PRESETS, get_preset
from neb_slam_core.synth.scene import build_scene


def _point_in_spaces(plan, xy, margin=1e-9):
    return any(
        s.rect.x0 - margin <= xy[0] <= s.rect.x1 + margin and s.rect.y0 - margin <= xy[1] <= s.rect.y1 + margin
        for s in plan.spaces
    )


def test_rect_distance_is_euclidean_outside_and_zero_inside():
    r = Rect(0.0, 0.0, 2.0, 1.0)
    d = r.distance(np.array([[1.0, 0.5], [3.0, 0.5], [3.0, 2.0], [-1.0, -1.0]]))
    assert np.allclose(d, [0.0, 1.0, np.sqrt(2.0), np.sqrt(2.0)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rooms_plan_spaces_are_disjoint_and_doors_join_two_spaces(seed):
    plan = build_floor_plan(LayoutSpec(kind="rooms"), np.random.default_rng(seed))
    spaces = plan.spaces
    for a in range(len(spaces)):
        for b in range(a + 1, len(spaces)):
            assert not spaces[a].rect.overlaps(spaces[b].rect), (spaces[a].name, spaces[b].name)
    for door in plan.spaces_of("door"):
        touching = [s.name for s in spaces if s is not door and s.rect.overlaps(door.rect, margin=1e-6)]
        assert len(touching) == 2, (door.name, touching)
        assert min(door.rect.size) == pytest.approx(0.15) and max(door.rect.size) >= 1.3 - 1e-9
    # every route waypoint lies in the free space
    assert all(_point_in_spaces(plan, p) for p in plan.route_xy)
    assert plan.route_closed


def test_layout_spec_rejects_bad_values():
    with pytest.raises(ConfigError, match="kind"):
        build_floor_plan(LayoutSpec(kind="castle"), np.random.default_rng(0))
    with pytest.raises(ConfigError, match="loop_columns"):
        build_floor_plan(LayoutSpec(loop_columns=4, n_columns=3), np.random.default_rng(0))
    with pytest.raises(ConfigError, match="door_width"):
        build_floor_plan(LayoutSpec(door_width_m=(0.8, 0.9)), np.random.default_rng(0))


@pytest.mark.parametrize("name", ["default", "large"])
def test_multi_room_presets_are_at_least_12_by_8_m(name):
    scene = build_scene(get_preset(name))
    size = scene.bounds[1] - scene.bounds[0]
    assert size[0] >= 12.0 and size[1] >= 8.0 and 2.5 <= size[2] <= 3.0
    assert len(scene.plan.spaces_of("room")) == 6 and len(scene.plan.spaces_of("corridor")) == 1


def test_corridor_and_small_presets_have_their_shapes():
    corridor = build_scene(get_preset("corridor"))
    c = corridor.plan.spaces_of("corridor")[0].rect
    assert c.size[0] >= 25.0
    assert not corridor.plan.route_closed
    small = build_scene(get_preset("small"))
    size = small.bounds[1] - small.bounds[0]
    assert np.allclose(size, [4.0, 4.0, 2.6], atol=0.11)
    # furnished: boxes rise from the floor (faces facing up between the floor and the ceiling)
    up = (
        (small.mesh.face_normals[:, 2] > 0.99)
        & (small.mesh.triangles_center[:, 2] > 0.2)
        & (small.mesh.triangles_center[:, 2] < 2.5)
    )
    assert up.sum() >= 2 * 3


def test_scene_is_deterministic_in_the_seed():
    spec = get_preset("default")
    a, b = build_scene(spec), build_scene(spec)
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices) and np.array_equal(a.mesh.faces, b.mesh.faces)
    assert np.array_equal(a.face_material, b.face_material) and a.materials == b.materials
    c = build_scene(replace(spec, seed=1))
    assert c.mesh.vertices.shape != a.mesh.vertices.shape or not np.array_equal(c.mesh.vertices, a.mesh.vertices)


def test_mesh_faces_carry_materials_and_face_into_free_space():
    scene = build_scene(get_preset("small"))
    mesh = scene.mesh
    assert scene.face_material.shape == (len(mesh.faces),)
    assert scene.face_material.min() >= 0 and scene.face_material.max() < len(scene.materials)
    room = scene.plan.spaces[0].rect
    H = scene.plan.wall_height_m
    # a point 1 cm along the normal from any face centre is inside the room (furniture stands 2 cm
    # off the walls, so even the backs of cabinets face into the room's air)
    c = mesh.triangles_center + 0.01 * mesh.face_normals
    inside = (
        (c[:, 0] > room.x0)
        & (c[:, 0] < room.x1)
        & (c[:, 1] > room.y0)
        & (c[:, 1] < room.y1)
        & (c[:, 2] > 0)
        & (c[:, 2] < H)
    )
    assert inside.all()


def test_presets_registry_names_and_error():
    assert set(PRESETS) == {"default", "large", "small", "corridor"}
    with pytest.raises(ConfigError, match="default, large, small, corridor"):
        get_preset("huge")
