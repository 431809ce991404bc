"""Procedural surface materials: albedo as a deterministic function of a surface point.

Every surface of a synthetic scene is axis-aligned, so a point on it has natural 2D texture
coordinates ``uv`` in metres: the two world coordinates that vary along the surface (see
:func:`surface_uv`). A :class:`Material` maps ``uv`` to an RGB albedo in [0, 1]; it never looks at
the camera, so a place looks the same every time it is revisited (what place recognition needs).

The patterns are chosen to give images many corners (ORB/FAST) and blobs: bricks, wooden planks,
mosaic tiles, checkerboards, wallpaper stripes, noise blobs, polka dots and posters with random
shapes. Nothing is read from image files; all of it is computed here.

Randomness inside a pattern (a tile's colour, a plank's tint) comes from an integer hash of the
lattice cell and the material's seed, so it is reproducible bit for bit on every machine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: the material kinds :func:`albedo` knows
KINDS = ("paint", "blobs", "brick", "wood", "tiles", "checker", "stripes", "dots", "poster")

Color = tuple[float, float, float]


@dataclass(frozen=True)
class PosterShape:
    """One shape of a poster, in the poster's ``uv`` coordinates (metres).

    ``kind`` is ``'rect'`` (half sizes ``rx``, ``ry``), ``'ellipse'`` (radii) or ``'ring'`` (an ellipse
    outline of relative thickness 0.3).
    """

    kind: str
    cu: float
    cv: float
    ru: float
    rv: float
    color: Color


@dataclass(frozen=True)
class Material:
    """A procedural texture.

    Attributes:
        kind: one of :data:`KINDS`.
        colors: the palette, RGB in [0, 1]; ``colors[0]`` is the base colour (at least 3 entries).
        scale_m: the pattern's characteristic size in metres (brick height, tile edge, ...).
        seed: drives the hash-based randomness inside the pattern.
        shapes: posters only: the shapes, drawn in order over ``colors[0]``.
        uv_box: posters only: ``(u0, v0, u1, v1)``, the poster's extent; a 3 cm frame is drawn inside it.
    """

    kind: str
    colors: tuple[Color, ...]
    scale_m: float = 0.25
    seed: int = 0
    shapes: tuple[PosterShape, ...] = ()
    uv_box: tuple[float, float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"Material.kind must be one of {KINDS}, got {self.kind!r}")
        if len(self.colors) < 3:
            raise ValueError(f"Material.colors needs at least 3 colours, got {len(self.colors)}")


# ----------------------------------------------------------------------------------------------
# hashing and noise (written here: they must be exact integer functions of the lattice cell so that
# the textures are bitwise reproducible, which library noise generators do not promise)

_M2 = np.uint64(0xBF58476D1CE4E5B9)
_M3 = np.uint64(0x94D049BB133111EB)
_P1 = np.uint64(0xD6E8FEB86659FD93)
_P2 = np.uint64(0xA0761D6478BD642F)


def hash_cells(i: np.ndarray, j: np.ndarray, seed: int) -> np.ndarray:
    """A uniform float64 in [0, 1) per integer cell ``(i, j)`` (arrays of equal shape) and ``seed``.

    A splitmix64 finaliser over a linear combination of the inputs (uint64 arithmetic wraps).
    """
    x = (
        np.asarray(i, dtype=np.int64).astype(np.uint64) * _P1
        + np.asarray(j, dtype=np.int64).astype(np.uint64) * _P2
        + np.uint64(((seed & 0xFFFFFFFF) * 0x9E3779B97F4A7C15) % (1 << 64))
    )
    x = (x ^ (x >> np.uint64(30))) * _M2
    x = (x ^ (x >> np.uint64(27))) * _M3
    x = x ^ (x >> np.uint64(31))
    return (x >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def value_noise(u: np.ndarray, v: np.ndarray, seed: int) -> np.ndarray:
    """Smooth value noise in [0, 1) with unit lattice spacing (smoothstep-interpolated hashes)."""
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = u - iu, v - iv
    iu, iv = iu.astype(np.int64), iv.astype(np.int64)
    su, sv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    a = hash_cells(iu, iv, seed)
    b = hash_cells(iu + 1, iv, seed)
    c = hash_cells(iu, iv + 1, seed)
    d = hash_cells(iu + 1, iv + 1, seed)
    return (a + (b - a) * su) + ((c + (d - c) * su) - (a + (b - a) * su)) * sv


def fbm(u: np.ndarray, v: np.ndarray, seed: int, octaves: int = 3) -> np.ndarray:
    """Fractal sum of :func:`value_noise` octaves, normalised to [0, 1)."""
    total = np.zeros(np.shape(u))
    amp, norm = 1.0, 0.0
    for k in range(octaves):
        f = 2.0**k
        total += amp * value_noise(u * f + 17.3 * k, v * f - 5.1 * k, seed + 101 * k)
        norm += amp
        amp *= 0.5
    return total / norm


# ----------------------------------------------------------------------------------------------
# texture coordinates


def surface_uv(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``(N, 3)`` world points on axis-aligned surfaces with ``(N, 3)`` normals -> ``(N, 2)`` uv (m).

    Floors and ceilings (normal along z) use ``(x, y)``; walls facing x use ``(y, z)``; walls facing y
    use ``(x, z)``. ``v`` is height on walls, so wall patterns stand upright.
    """
    axis = np.argmax(np.abs(normals), axis=1)
    uv = np.empty((len(points), 2))
    uv[:, 0] = np.where(axis == 0, points[:, 1], points[:, 0])
    uv[:, 1] = np.where(axis == 2, points[:, 1], points[:, 2])
    return uv


# ----------------------------------------------------------------------------------------------
# the patterns; each takes uv (N, 2) metres and returns (N, 3) float albedo


def _palette(m: Material) -> np.ndarray:
    return np.asarray(m.colors, dtype=np.float64)


def _pick(palette: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Palette entry chosen by a uniform ``r`` in [0, 1) -> ``(N, 3)``."""
    return palette[np.minimum((r * len(palette)).astype(np.int64), len(palette) - 1)]


def _paint(m: Material, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    mottle = 0.94 + 0.12 * fbm(u / 0.4, v / 0.4, m.seed)
    return _palette(m)[0] * mottle[:, None]


def _blobs(m: Material, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    pal = _palette(m)
    n1 = fbm(u / m.scale_m, v / m.scale_m, m.seed)
    n2 = fbm(u / m.scale_m + 31.7, v / m.scale_m - 11.3, m.seed + 7)
    out = np.repeat(pal[0][None], len(u), axis=0) * (0.9 + 0.2 * n2)[:, None]
    out[n1 > 0.62] = pal[1]
    out[(n2 > 0.66) & (n1 <= 0.62)] = pal[2]
    return out


def _brick(m: Material, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    pal = _palette(m)
    h = m.scale_m
    w = 2.2 * h
    row = np.floor(v / h)
    uu = u / w + 0.5 * (row % 2)
    col = np.floor(uu)
    fu, fv = uu - col, v / h - row
    mortar = 0.012
    is_mortar = (fu * w < mortar) | (fv * h < mortar)
    r = hash_cells(col.astype(np.int64), row.astype(np.int64), m.seed)
    brick = pal[0] * (0.75 + 0.5 * r)[:, None]
    brick[r > 0.85] = pal[1]
    return np.where(is_mortar[:, None], pal[2], brick)


def _wood(m: Material, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    pal = _palette(m)
    plank_w = m.scale_m
    plank_l = 6.0 * plank_w
    lane = np.floor(v / plank_w)
    offset = hash_cells(lane.astype(np.int64), np.zeros_like(lane, dtype=np.int64), m.seed) * plank_l
    along = (u + offset) / plank_l
    piece = np.floor(along)
    tint = hash_cells(lane.astype(np.int64), piece.astype(np.int64), m.seed + 1)
    grain_phase = (v / plank_w - lane) * 9.0 + 1.5 * fbm(u / 0.35, v / 0.05, m.seed + 2)
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * grain_phase)
    base = pal[0] * (1 - 0.35 * grain)[:, None] + pal[1] * (0.35 * grain)[:, None]
    base *= (0.8 + 0.4 * tint)[:, None]
    seam = ((v / plank_w - lane) * plank_w < 0.008) | ((along - piece) * plank_l < 0.008)
    return np.where(seam[:, None], pal[2], base)


def _tiles(m: Material, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    pal = _palette(m)
    s = m.scale_m
    iu, iv = np.floor(u / s), np.floor(v / s)
    fu, fv = u / s - iu, v / s - iv
    grout = 0.01 / s
    r = hash_cells(iu.astype(np.int64), iv.astype(np.int64), m.seed)
    tile = _pick(pal[:-1], r) * (0.85 + 0.3 * hash_cells(iu.astype(np.int64), iv.astype(np.int64), m.seed + 3))[:, None]
    is_grout = (fu < grout) | (fv < grout)
    return np.where(is_grout[:, None], pal[-1], tile)


def _checker(m: Material, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    pal = _palette(m)
    s = m.scale_m
    parity = (np.floor(u / s) + np.floor(v / s)) % 2
    shade = 0.92 + 0.16 * fbm(u / 0.5, v / 0.5, m.seed)
    return np.where(parity[:, None] > 0, pal[0], pal[1]) * shade[:, None]


def _stripes(m: Material, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    pal = _palette(m)
    s = m.scale_m
    lane = np.floor(u / s)
    r = hash_cells(lane.astype(np.int64), np.zeros_like(lane, dtype=np.int64), m.seed)
    out = _pick(pal, r)
    # a column of small diamonds in every stripe (one per 0.4 m of height) gives the stripes corners
    du_m = (u / s - lane - 0.5) * s
    dv_m = (v / 0.4 - np.floor(v / 0.4) - 0.5) * 0.4
    diamond = np.abs(du_m) + np.abs(dv_m) < 0.35 * s
    out = np.where(diamond[:, None], pal[0] * 0.35, out)
    return out * (0.95 + 0.1 * fbm(u / 0.3, v / 0.3, m.seed + 5))[:, None]


def _dots(m: Material, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    pal = _palette(m)
    s = m.scale_m
    iu, iv = np.floor(u / s), np.floor(v / s)
    ii, jj = iu.astype(np.int64), iv.astype(np.int64)
    cu = 0.5 + 0.3 * (hash_cells(ii, jj, m.seed) - 0.5)
    cv = 0.5 + 0.3 * (hash_cells(ii, jj, m.seed + 1) - 0.5)
    rad = 0.15 + 0.2 * hash_cells(ii, jj, m.seed + 2)
    inside = (u / s - iu - cu) ** 2 + (v / s - iv - cv) ** 2 < rad**2
    dot = _pick(pal[1:], hash_cells(ii, jj, m.seed + 3))
    return np.where(inside[:, None], dot, pal[0])


def _poster(m: Material, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    pal = _palette(m)
    out = np.repeat(pal[0][None], len(u), axis=0)
    for sh in m.shapes:
        du, dv = (u - sh.cu) / sh.ru, (v - sh.cv) / sh.rv
        if sh.kind == "rect":
            inside = (np.abs(du) <= 1.0) & (np.abs(dv) <= 1.0)
        elif sh.kind == "ellipse":
            inside = du * du + dv * dv <= 1.0
        else:  # ring
            r2 = du * du + dv * dv
            inside = (r2 <= 1.0) & (r2 >= 0.49)
        out[inside] = sh.color
    if m.uv_box is not None:
        u0, v0, u1, v1 = m.uv_box
        frame = 0.03
        border = (u - u0 < frame) | (u1 - u < frame) | (v - v0 < frame) | (v1 - v < frame)
        out[border] = pal[1]
    return out


_PATTERNS = {
    "paint": _paint,
    "blobs": _blobs,
    "brick": _brick,
    "wood": _wood,
    "tiles": _tiles,
    "checker": _checker,
    "stripes": _stripes,
    "dots": _dots,
    "poster": _poster,
}


def albedo(material: Material, uv: np.ndarray) -> np.ndarray:
    """Albedo of ``material`` at texture coordinates ``uv`` ``(N, 2)`` metres -> ``(N, 3)`` float64 in [0, 1]."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return np.zeros((0, 3))
    out = _PATTERNS[material.kind](material, uv[:, 0], uv[:, 1])
    return np.clip(out, 0.0, 1.0)


# ----------------------------------------------------------------------------------------------
# random materials for the scene builder


def random_color(
    rng: np.random.Generator, saturation: tuple[float, float] = (0.3, 0.9), value: tuple[float, float] = (0.35, 0.95)
) -> Color:
    """A random colour drawn uniformly in HSV (hue, and the given saturation and value ranges)."""
    h = rng.uniform(0.0, 1.0)
    s = rng.uniform(*saturation)
    v = rng.uniform(*value)
    i = int(h * 6.0) % 6
    f = h * 6.0 - int(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    rgb = [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]
    return (round(rgb[0], 4), round(rgb[1], 4), round(rgb[2], 4))


def random_material(rng: np.random.Generator, kind: str, seed: int) -> Material:
    """A material of ``kind`` with a random palette and scale suited to the kind.

    Palettes mix dark and light colours so that the patterns keep their contrast in grey (what
    corner detectors see), not only in hue.
    """
    dark = lambda: random_color(rng, (0.3, 0.9), (0.12, 0.45))  # noqa: E731
    light = lambda: random_color(rng, (0.1, 0.6), (0.65, 0.95))  # noqa: E731
    any_ = lambda: random_color(rng)  # noqa: E731
    if kind == "paint":
        return Material(kind, (random_color(rng, (0.05, 0.4), (0.6, 0.95)), any_(), any_()), 1.0, seed)
    if kind == "brick":
        return Material(
            kind,
            (random_color(rng, (0.4, 0.9), (0.35, 0.7)), dark(), random_color(rng, (0.0, 0.15), (0.75, 0.95))),
            float(rng.uniform(0.07, 0.12)),
            seed,
        )
    if kind == "wood":
        base = random_color(rng, (0.4, 0.7), (0.45, 0.8))
        return Material(
            kind, (base, tuple(x * 0.55 for x in base), (0.12, 0.08, 0.05)), float(rng.uniform(0.12, 0.22)), seed
        )
    if kind == "tiles":
        return Material(
            kind,
            (dark(), light(), any_(), random_color(rng, (0.0, 0.1), (0.2, 0.9))),
            float(rng.uniform(0.15, 0.35)),
            seed,
        )
    if kind == "checker":
        return Material(
            kind,
            (random_color(rng, (0.0, 0.3), (0.8, 0.95)), random_color(rng, (0.3, 0.9), (0.15, 0.45)), any_()),
            float(rng.uniform(0.15, 0.4)),
            seed,
        )
    if kind == "stripes":
        return Material(kind, (dark(), light(), any_(), light()), float(rng.uniform(0.08, 0.2)), seed)
    if kind == "dots":
        return Material(kind, (light(), dark(), dark(), any_()), float(rng.uniform(0.12, 0.3)), seed)
    if kind == "blobs":
        return Material(kind, (any_(), dark(), light()), float(rng.uniform(0.2, 0.5)), seed)
    raise ValueError(f"random_material: unsupported kind {kind!r} (posters are made by random_poster)")


def random_poster(rng: np.random.Generator, uv_box: tuple[float, float, float, float], seed: int) -> Material:
    """A poster filling ``uv_box`` = (u0, v0, u1, v1) metres with 4-9 random rectangles, ellipses and rings."""
    u0, v0, u1, v1 = uv_box
    shapes = []
    for _ in range(int(rng.integers(4, 10))):
        kind = ("rect", "ellipse", "ring")[int(rng.integers(0, 3))]
        ru = float(rng.uniform(0.08, 0.3) * (u1 - u0))
        rv = float(rng.uniform(0.08, 0.3) * (v1 - v0))
        if kind != "rect":
            ru = rv = min(ru, rv) * float(rng.uniform(1.0, 1.6))
        shapes.append(
            PosterShape(
                kind,
                float(rng.uniform(u0, u1)),
                float(rng.uniform(v0, v1)),
                ru,
                rv,
                random_color(rng, (0.5, 1.0), (0.2, 1.0)),
            )
        )
    colors = (random_color(rng, (0.0, 0.5), (0.5, 1.0)), random_color(rng, (0.0, 0.3), (0.05, 0.3)), (0.0, 0.0, 0.0))
    return Material("poster", colors, 1.0, seed, tuple(shapes), tuple(float(x) for x in uv_box))
