"""Ray-cast rendering: pixel convention, depth against the mesh, Embree backend, textured images."""

from __future__ import annotations

import logging
import sys

import cv2
import numpy as np
import pytest
import trimesh

from neb_slam_core.synth import generate as gen
from neb_slam_core.synth import render as render_mod
from neb_slam_core.synth.presets import get_preset
from neb_slam_core.synth.render import CameraSpec, Renderer
from neb_slam_core.synth.textures import Material
from neb_slam_core.types import Intrinsics

GREY = Material("paint", ((0.5, 0.5, 0.5), (0, 0, 0), (0, 0, 0)))


def _plane_renderer(corners, intr, **kw):
    mesh = trimesh.Trimesh(vertices=np.asarray(corners, float), faces=[[0, 1, 2], [0, 2, 3]], process=False)
    return Renderer(mesh, np.zeros(2, int), [GREY], intr, **kw)


def test_camera_spec_intrinsics_centre_the_principal_point():
    k = CameraSpec(width=160, height=120, fov_h_deg=60.0).intrinsics()
    assert (k.cx, k.cy) == (79.5, 59.5)
    assert k.fx == k.fy == pytest.approx(80.0 / np.tan(np.radians(30.0)))


def test_depth_of_a_tilted_plane_follows_the_pixel_centre_convention():
    # camera at the origin looking along +z (identity pose); plane x + z = 3.
    # Pixel (u, v) has ray (a, b, 1) with a = (u - cx) / fx, so the hit has z = 3 / (1 + a).
    intr = Intrinsics(10.0, 10.0, 3.5, 2.5, 8, 6)
    r = _plane_renderer([[-7, -9, 10], [7, -9, -4], [7, 9, -4], [-7, 9, 10]], intr)
    view = r.render(np.eye(4))
    u = np.arange(8)
    expected = 3.0 / (1.0 + (u - 3.5) / 10.0)
    assert np.allclose(view.depth_m, np.tile(expected, (6, 1)).astype(np.float32), rtol=0, atol=1e-6)
    # cos incidence: normal (1, 0, 1)/sqrt2 against ray (a, b, 1)/|.|
    a, b = np.meshgrid((u - 3.5) / 10.0, (np.arange(6) - 2.5) / 10.0)
    assert np.allclose(view.cos_incidence, (a + 1) / np.sqrt(2) / np.sqrt(a * a + b * b + 1), atol=1e-6)


def test_depth_range_and_misses_read_zero():
    intr = Intrinsics(10.0, 10.0, 3.5, 2.5, 8, 6)
    far = _plane_renderer([[-50, -50, 12], [50, -50, 12], [50, 50, 12], [-50, 50, 12]], intr)
    assert (far.render(np.eye(4)).depth_m == 0).all()  # 12 m > max_depth_m 10
    near = _plane_renderer([[-5, -5, 0.05], [5, -5, 0.05], [5, 5, 0.05], [-5, 5, 0.05]], intr)
    assert (near.render(np.eye(4)).depth_m == 0).all()  # 5 cm < min_depth_m 0.1
    behind = np.diag([1.0, -1.0, -1.0, 1.0])  # looking along -z: no surface
    view = near.render(behind)
    assert (view.depth_m == 0).all() and (view.face_index == -1).all() and (view.rgb == 0).all()


def test_lambertian_shading_of_a_grey_plane():
    intr = Intrinsics(10.0, 10.0, 3.5, 2.5, 8, 6)
    # plane z = 2 seen from the origin: its normal faces the camera, (0, 0, -1); light (0, 0, -1) -> full
    r = _plane_renderer([[-9, -9, 2], [9, -9, 2], [9, 9, 2], [-9, 9, 2]], intr, light_dir=(0, 0, -1), ambient=0.4)
    rgb = r.render(np.eye(4)).rgb
    mottle = 0.94 + 0.12 * np.array([0.0, 1.0])  # paint's brightness variation range
    assert rgb.min() >= np.floor(0.5 * mottle[0] * 255) and rgb.max() <= np.ceil(0.5 * mottle[1] * 255)
    # light from the side (perpendicular to the normal): ambient only
    r2 = _plane_renderer([[-9, -9, 2], [9, -9, 2], [9, 9, 2], [-9, 9, 2]], intr, light_dir=(1, 0, 0), ambient=0.4)
    rgb2 = r2.render(np.eye(4)).rgb.astype(float)
    assert np.allclose(rgb2, 0.4 * r.render(np.eye(4)).rgb.astype(float), atol=1.0)


def test_embree_is_used():
    scene = gen.build_scene(get_preset("small"))
    assert Renderer.for_scene(scene).backend == "embree"


def test_fallback_intersector_warns_once_and_agrees(monkeypatch, caplog):
    scene = gen.build_scene(get_preset("small"))
    seq = gen.build_sequence(gen.resolve_spec("small", n_frames=4))
    intr = CameraSpec(width=24, height=18).intrinsics()
    ref = Renderer.for_scene(scene, intr, supersample=1).render(seq.trajectory.poses[1])
    monkeypatch.setitem(sys.modules, "trimesh.ray.ray_pyembree", None)  # import now raises ImportError
    monkeypatch.setattr(render_mod, "_warned_fallback", False)
    with caplog.at_level(logging.WARNING, logger="neb_slam_core.synth.render"):
        slow = Renderer.for_scene(scene, intr, supersample=1)
        Renderer.for_scene(scene, intr, supersample=1)
    assert slow.backend == "trimesh"
    assert len([r for r in caplog.records if "Embree" in r.getMessage()]) == 1
    view = slow.render(seq.trajectory.poses[1])
    same = np.isclose(view.depth_m, ref.depth_m, atol=1e-5)
    assert same.mean() > 0.99
    assert np.abs(view.rgb.astype(int) - ref.rgb.astype(int))[same].max() <= 1


def _backproject(view, intr, T_world_cam):
    v, u = np.nonzero(view.depth_m > 0)
    z = view.depth_m[v, u].astype(np.float64)
    x_cam = np.stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z], axis=1)
    return x_cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]


@pytest.mark.parametrize("name", ["small", "default"])
def test_backprojected_depth_lies_on_the_mesh(name, small_sequence, default_sequence):
    seq = small_sequence if name == "small" else default_sequence
    intr = CameraSpec(width=64, height=48).intrinsics()
    r = Renderer.for_scene(seq.scene, intr)
    for i in np.linspace(0, len(seq.trajectory) - 1, 3).astype(int):
        T = seq.trajectory.poses[i]
        view = r.render(T)
        assert (view.depth_m > 0).mean() > 0.95
        pts = _backproject(view, intr, T)
        _, dist, _ = trimesh.proximity.closest_point(seq.scene.mesh, pts)
        assert dist.max() < 1e-3, (i, dist.max())


def test_every_visible_face_is_seen_from_its_front(default_sequence):
    seq = default_sequence
    r = Renderer.for_scene(seq.scene, CameraSpec(width=48, height=36).intrinsics(), supersample=1)
    for i in range(0, 300, 30):
        tri, _, _, dirs = r.cast(seq.trajectory.poses[i], r._rays_cam)
        hit = tri >= 0
        facing = np.einsum("ij,ij->i", seq.scene.mesh.face_normals[tri[hit]], dirs[hit])
        assert (facing < 0).all(), i


def test_colour_does_not_depend_on_the_viewpoint(small_sequence):
    r = Renderer.for_scene(small_sequence.scene, CameraSpec(width=16, height=12).intrinsics(), supersample=1)
    floor = int(np.flatnonzero(small_sequence.scene.mesh.face_normals[:, 2] > 0.99)[0])
    p = small_sequence.scene.mesh.triangles_center[[floor]]
    a = r.shade(np.array([floor]), p, np.array([[0.3, 0.2, -1.0]]))
    b = r.shade(np.array([floor]), p, np.array([[-0.6, 0.5, -0.4]]))
    assert np.array_equal(a, b) and a.max() > 0


def test_frames_are_textured_for_orb(default_sequence):
    # a 320x240 view of the demo scene: many ORB corners and strong colour variation
    r = Renderer.for_scene(default_sequence.scene, CameraSpec(width=320, height=240).intrinsics())
    orb = cv2.ORB_create(nfeatures=1000)
    for i in (0, 150):
        rgb = r.render(default_sequence.trajectory.poses[i]).rgb
        keypoints = orb.detect(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), None)
        assert len(keypoints) >= 100, (i, len(keypoints))
        assert rgb.reshape(-1, 3).std(axis=0).mean() > 30.0
