"""Procedural materials: exact hashing, value ranges, texture coordinates, posters."""

from __future__ import annotations

import numpy as np
import pytest

from neb_slam_core.synth.textures import (
    KINDS,
    Material,
    PosterShape,
    albedo,
    hash_cells,
    random_material,
    random_poster,
    surface_uv,
    value_noise,
)


def test_hash_is_deterministic_uniform_and_seeded():
    i, j = np.meshgrid(np.arange(-150, 150), np.arange(-150, 150))
    h = hash_cells(i, j, 7)
    assert np.array_equal(h, hash_cells(i, j, 7))
    assert h.min() >= 0.0 and h.max() < 1.0
    # 90,000 uniform draws: mean 0.5 +- 0.001 (std of the mean 0.00096 -> 5 sigma = 0.005)
    assert abs(h.mean() - 0.5) < 0.005
    assert abs(h.var() - 1 / 12) < 0.002
    assert not np.array_equal(h, hash_cells(i, j, 8))
    assert not np.array_equal(h, hash_cells(j, i, 7))  # not symmetric in (i, j)


def test_value_noise_interpolates_the_lattice_hashes():
    # at integer points value noise equals the hash of that lattice cell; it stays within [0, 1)
    i, j = np.array([0, 3, -2]), np.array([0, -5, 4])
    assert np.allclose(value_noise(i.astype(float), j.astype(float), 3), hash_cells(i, j, 3))
    u = np.linspace(-3, 3, 1000)
    n = value_noise(u, 0.37 * u, 3)
    assert n.min() >= 0.0 and n.max() < 1.0
    # continuity: neighbouring samples 6 mm apart differ little
    assert np.abs(np.diff(n)).max() < 0.05


def test_surface_uv_uses_the_two_in_plane_coordinates():
    p = np.array([[1.0, 2.0, 3.0]] * 3)
    n = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    uv = surface_uv(p, n)
    assert uv.tolist() == [[1.0, 2.0], [2.0, 3.0], [1.0, 3.0]]  # floor (x, y); x-wall (y, z); y-wall (x, z)


@pytest.mark.parametrize("kind", [k for k in KINDS if k != "poster"])
def test_every_material_is_a_deterministic_function_in_range(kind):
    rng = np.random.default_rng(0)
    m = random_material(rng, kind, seed=11)
    uv = np.random.default_rng(1).uniform(-5, 5, size=(5000, 2))
    c = albedo(m, uv)
    assert c.shape == (5000, 3) and c.min() >= 0.0 and c.max() <= 1.0
    assert np.array_equal(c, albedo(m, uv))  # same place, same colour
    assert np.array_equal(c[100:200], albedo(m, uv[100:200]))  # independent of what else is evaluated
    if kind != "paint":
        assert c.std(axis=0).max() > 0.04  # patterned, not flat


def test_checkerboard_alternates_by_cell():
    m = Material("checker", ((1.0, 1.0, 1.0), (0.0, 0.0, 0.0), (0.5, 0.5, 0.5)), scale_m=0.5)
    c = albedo(m, np.array([[0.25, 0.25], [0.75, 0.25], [0.75, 0.75], [-0.25, 0.25]]))
    bright = c.mean(axis=1) > 0.5
    # cell (0,0) even -> colours[1] (dark); (1,0) odd -> colours[0]; (1,1) even; (-1,0) odd
    assert bright.tolist() == [False, True, False, True]


def test_poster_draws_its_shapes_and_frame():
    red, bg, frame = (1.0, 0.0, 0.0), (0.9, 0.9, 0.9), (0.1, 0.1, 0.1)
    m = Material(
        "poster",
        (bg, frame, (0.0, 0.0, 0.0)),
        1.0,
        0,
        (PosterShape("ellipse", 1.0, 1.0, 0.2, 0.2, red),),
        (0.5, 0.5, 1.5, 1.5),
    )
    c = albedo(m, np.array([[1.0, 1.0], [1.15, 1.0], [1.3, 1.3], [0.51, 1.0]]))
    assert np.allclose(c[0], red) and np.allclose(c[1], red)  # inside the circle (r = 0.2)
    assert np.allclose(c[2], bg)  # outside it
    assert np.allclose(c[3], frame)  # within 3 cm of the edge


def test_random_poster_is_reproducible():
    a = random_poster(np.random.default_rng(5), (0.0, 1.0, 1.0, 1.6), seed=3)
    b = random_poster(np.random.default_rng(5), (0.0, 1.0, 1.0, 1.6), seed=3)
    assert a == b and 4 <= len(a.shapes) <= 9


def test_unknown_kind_is_rejected():
    with pytest.raises(ValueError, match="kind"):
        Material("marble", ((0, 0, 0),) * 3)
