"""A synthetic indoor scene: :class:`SceneSpec` -> floor plan, materials and a triangle mesh.

:func:`build_scene` samples, from the spec's seed only:

1. a floor plan (:mod:`.layout`): rooms, corridor, doorways, wall height, the camera route;
2. walls: every boundary between free and solid cells of the rasterised plan becomes a vertical
   quad facing the free side (merged along straight runs); doorways get jambs up to the door height
   and a lintel above; floors and ceilings are one quad per space;
3. furniture: cabinets, tables (top and four legs), low boxes (beds, sofas) and crate stacks, placed
   against the walls or free-standing, never closer to the route than ``route_clearance_m`` and never
   in front of a doorway;
4. posters: thin rectangles 1 cm in front of the walls with random shapes;
5. materials (:mod:`.textures`): one floor, wall and ceiling material per space, one per piece of
   furniture, one per poster.

The mesh is a :class:`trimesh.Trimesh` whose faces are ordered as built (``process=False``); the
array ``face_material`` gives each face's index into ``materials``. Every face's winding makes its
normal point into the free space it is seen from. World frame: z up, metres.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
import trimesh

from ..errors import ConfigError
from .layout import GRID_M, FloorPlan, LayoutSpec, Rect, Space, build_floor_plan
from .noise import DepthNoiseSpec
from .render import CameraSpec
from .textures import Material, random_material, random_poster
from .trajectory import TrajectorySpec, route_curve

FLOOR_KINDS = ("wood", "tiles", "checker")
WALL_KINDS = ("brick", "stripes", "blobs", "dots", "tiles")
FURNITURE_KINDS = ("wood", "checker", "tiles", "dots", "blobs", "stripes", "brick")


@dataclass(frozen=True)
class SceneSpec:
    """Everything that determines a synthetic sequence (with the seed, the output is fixed).

    Attributes:
        name: the preset name (informative).
        seed: drives every random choice: layout, furniture, materials, noise.
        layout: the floor plan family and its ranges.
        camera: image size, field of view, depth range, colour supersampling.
        trajectory: frame count, rate, camera height and the gentle yaw/pitch variation.
        noise: the depth noise model (off unless ``noise.enabled``).
        furniture_per_room: ``(low, high)`` pieces attempted per room (inclusive).
        posters_per_room: ``(low, high)`` posters attempted per room or corridor.
        route_clearance_m: furniture keeps at least this 2D distance from the route.
    """

    name: str = "custom"
    seed: int = 0
    layout: LayoutSpec = field(default_factory=LayoutSpec)
    camera: CameraSpec = field(default_factory=CameraSpec)
    trajectory: TrajectorySpec = field(default_factory=TrajectorySpec)
    noise: DepthNoiseSpec = field(default_factory=DepthNoiseSpec)
    furniture_per_room: tuple[int, int] = (3, 6)
    posters_per_room: tuple[int, int] = (3, 6)
    route_clearance_m: float = 0.6

    def to_dict(self) -> dict:
        """A JSON-ready dict of every option (tuples become lists)."""
        return _jsonable(asdict(self))


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


@dataclass
class SyntheticScene:
    """A built scene.

    Attributes:
        spec: what it was built from.
        plan: the floor plan (spaces, heights, route waypoints).
        mesh: ``(V, 3)`` vertices, ``(F, 3)`` faces; normals face the free space.
        face_material: ``(F,)`` int32 index into ``materials``.
        materials: the procedural materials.
        route_xy: ``(K, 2)`` dense points along the route (what furniture keeps clear of).
    """

    spec: SceneSpec
    plan: FloorPlan
    mesh: trimesh.Trimesh
    face_material: np.ndarray
    materials: list[Material]
    route_xy: np.ndarray

    @property
    def bounds(self) -> np.ndarray:
        """``(2, 3)`` min and max corner of the mesh, metres."""
        return np.asarray(self.mesh.bounds, dtype=np.float64)


# ----------------------------------------------------------------------------------------------
# mesh assembly


class _MeshBuilder:
    """Collects quads (4 corners, counter-clockwise seen from the side the normal points to)."""

    def __init__(self) -> None:
        self.quads: list[np.ndarray] = []
        self.quad_material: list[int] = []
        self.materials: list[Material] = []

    def material(self, m: Material) -> int:
        self.materials.append(m)
        return len(self.materials) - 1

    def quad(self, corners, material: int) -> None:
        self.quads.append(np.asarray(corners, dtype=np.float64))
        self.quad_material.append(material)

    def wall_quad(
        self, axis: int, coord: float, lo: float, hi: float, z0: float, z1: float, normal_sign: int, material: int
    ) -> None:
        """A vertical quad in the plane ``x = coord`` (axis 0) or ``y = coord`` (axis 1), spanning
        ``[lo, hi]`` along the other horizontal axis and ``[z0, z1]`` in height, facing ``normal_sign``."""
        if axis == 0:
            c = [(coord, lo, z0), (coord, hi, z0), (coord, hi, z1), (coord, lo, z1)]
            # (0, +y, 0) x (0, 0, +z) = +x: this order faces +x
            if normal_sign < 0:
                c = c[::-1]
        else:
            c = [(hi, coord, z0), (lo, coord, z0), (lo, coord, z1), (hi, coord, z1)]
            # (-x) x (+z) = +y: this order faces +y
            if normal_sign < 0:
                c = c[::-1]
        self.quad(c, material)

    def horizontal_quad(self, r: Rect, z: float, up: bool, material: int) -> None:
        c = [(r.x0, r.y0, z), (r.x1, r.y0, z), (r.x1, r.y1, z), (r.x0, r.y1, z)]
        self.quad(c if up else c[::-1], material)

    def box(self, r: Rect, z0: float, z1: float, material: int, bottom: bool = False, top: bool = True) -> None:
        """An axis-aligned box over ``r`` from ``z0`` to ``z1`` with outward normals."""
        if top:
            self.horizontal_quad(r, z1, True, material)
        if bottom:
            self.horizontal_quad(r, z0, False, material)
        self.wall_quad(0, r.x1, r.y0, r.y1, z0, z1, +1, material)
        self.wall_quad(0, r.x0, r.y0, r.y1, z0, z1, -1, material)
        self.wall_quad(1, r.y1, r.x0, r.x1, z0, z1, +1, material)
        self.wall_quad(1, r.y0, r.x0, r.x1, z0, z1, -1, material)

    def build(self) -> tuple[trimesh.Trimesh, np.ndarray]:
        q = np.stack(self.quads)  # (Q, 4, 3)
        vertices = q.reshape(-1, 3)
        base = np.arange(len(q)) * 4
        faces = np.concatenate(
            [np.stack([base, base + 1, base + 2], 1), np.stack([base, base + 2, base + 3], 1)], axis=1
        ).reshape(-1, 3)
        mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
        face_material = np.repeat(np.asarray(self.quad_material, dtype=np.int32), 2)
        return mesh, face_material


@dataclass
class _WallRun:
    """A merged straight wall: plane ``axis``-coordinate ``coord``, extent ``[lo, hi]``, facing
    ``normal_sign`` into the free space ``space``."""

    axis: int
    coord: float
    lo: float
    hi: float
    normal_sign: int
    space: int


def _wall_runs(plan: FloorPlan) -> list[_WallRun]:
    """Boundaries between free and solid cells of the rasterised plan, merged into straight runs."""
    b = plan.bounds_xy
    ox, oy = b.x0 - GRID_M, b.y0 - GRID_M  # one solid cell of margin on each side
    nx = int(round((b.x1 - b.x0) / GRID_M)) + 2
    ny = int(round((b.y1 - b.y0) / GRID_M)) + 2
    label = np.full((nx, ny), -1, dtype=np.int64)
    for k, s in enumerate(plan.spaces):
        i0, i1 = int(round((s.rect.x0 - ox) / GRID_M)), int(round((s.rect.x1 - ox) / GRID_M))
        j0, j1 = int(round((s.rect.y0 - oy) / GRID_M)), int(round((s.rect.y1 - oy) / GRID_M))
        label[i0:i1, j0:j1] = np.where(label[i0:i1, j0:j1] < 0, k, label[i0:i1, j0:j1])

    runs: list[_WallRun] = []
    for axis in (0, 1):
        lab = label if axis == 0 else label.T  # rows step along `axis`
        origin_along, origin_across = (ox, oy) if axis == 0 else (oy, ox)
        a, c = lab[:-1], lab[1:]  # neighbours across the line index i+1
        for i in range(a.shape[0]):
            coord = origin_along + (i + 1) * GRID_M
            # free side and its direction: +1 when the free cell is beyond the line
            free = np.where((a[i] < 0) & (c[i] >= 0), c[i], np.where((a[i] >= 0) & (c[i] < 0), a[i], -1))
            sign = np.where((a[i] < 0) & (c[i] >= 0), 1, -1)
            key = np.where(free >= 0, free * 2 + (sign > 0), -1)
            j = 0
            n = len(key)
            while j < n:
                if key[j] < 0:
                    j += 1
                    continue
                j_end = j
                while j_end + 1 < n and key[j_end + 1] == key[j]:
                    j_end += 1
                runs.append(
                    _WallRun(
                        axis,
                        round(coord, 6),
                        round(origin_across + j * GRID_M, 6),
                        round(origin_across + (j_end + 1) * GRID_M, 6),
                        int(sign[j]),
                        int(free[j]),
                    )
                )
                j = j_end + 1
    return runs


# ----------------------------------------------------------------------------------------------


def build_scene(spec: SceneSpec) -> SyntheticScene:
    """Build the scene of ``spec`` (deterministic in ``spec``)."""
    _validate(spec)
    rng = np.random.default_rng([spec.seed, 0x5CE4E])
    plan = build_floor_plan(spec.layout, rng)
    curve = route_curve(plan.route_xy, plan.route_closed)
    route_xy = curve.sample(max(200, int(curve.length / 0.05)))[0]

    mb = _MeshBuilder()
    seed_counter = iter(range(1, 1_000_000))
    H = plan.wall_height_m

    # per-space materials
    space_walls: dict[int, int] = {}
    for k, s in enumerate(plan.spaces):
        if s.kind == "door":
            continue
        floor = mb.material(random_material(rng, FLOOR_KINDS[int(rng.integers(len(FLOOR_KINDS)))], next(seed_counter)))
        wall = mb.material(random_material(rng, WALL_KINDS[int(rng.integers(len(WALL_KINDS)))], next(seed_counter)))
        ceiling = mb.material(random_material(rng, "paint" if rng.uniform() < 0.5 else "tiles", next(seed_counter)))
        space_walls[k] = wall
        mb.horizontal_quad(s.rect, 0.0, True, floor)
        mb.horizontal_quad(s.rect, H, False, ceiling)
    door_paint = mb.material(random_material(rng, "paint", next(seed_counter)))
    threshold = mb.material(random_material(rng, "wood", next(seed_counter)))
    for s in plan.spaces_of("door"):
        mb.horizontal_quad(s.rect, 0.0, True, threshold)

    # walls and doorways
    runs = _wall_runs(plan)
    for r in runs:
        s = plan.spaces[r.space]
        top = plan.door_height_m if s.kind == "door" else H
        mb.wall_quad(
            r.axis,
            r.coord,
            r.lo,
            r.hi,
            0.0,
            top,
            r.normal_sign,
            door_paint if s.kind == "door" else space_walls[r.space],
        )
    for s in plan.spaces_of("door"):
        _lintel(mb, s, plan, door_paint)

    # posters on the walls of rooms and corridors (runs long enough to hold one)
    taken: list[tuple[_WallRun, float, float, float, float]] = []
    poster_runs = [r for r in runs if plan.spaces[r.space].kind != "door" and r.hi - r.lo >= 1.0]
    for k, s in enumerate(plan.spaces):
        if s.kind == "door":
            continue
        mine = [r for r in poster_runs if r.space == k]
        if not mine:
            continue
        for _ in range(int(rng.integers(spec.posters_per_room[0], spec.posters_per_room[1] + 1))):
            _place_poster(mb, rng, mine, taken, H, next(seed_counter))

    # furniture
    furniture: list[Rect] = []
    doors = [s.rect for s in plan.spaces_of("door")]
    for s in plan.spaces:
        if s.kind == "door":
            continue
        n = int(rng.integers(spec.furniture_per_room[0], spec.furniture_per_room[1] + 1))
        if s.kind == "corridor":
            n = max(1, n // 2)
        for _ in range(n):
            _place_furniture(
                mb,
                rng,
                s,
                furniture,
                doors,
                route_xy,
                spec.route_clearance_m,
                next(seed_counter),
                corridor=s.kind == "corridor",
            )

    mesh, face_material = mb.build()
    return SyntheticScene(spec, plan, mesh, face_material, mb.materials, route_xy)


def _validate(spec: SceneSpec) -> None:
    for name in ("furniture_per_room", "posters_per_room"):
        lo, hi = getattr(spec, name)
        if not 0 <= lo <= hi:
            raise ConfigError(f"SceneSpec.{name}: expected 0 <= low <= high, got {(lo, hi)}")
    if spec.route_clearance_m < spec.trajectory.min_clearance_m:
        raise ConfigError("SceneSpec.route_clearance_m must be at least trajectory.min_clearance_m")


def _lintel(mb: _MeshBuilder, door: Space, plan: FloorPlan, material: int) -> None:
    """The wall above a doorway: two faces in the planes of the walls it joins, and its underside."""
    r, zd, H = door.rect, plan.door_height_m, plan.wall_height_m
    w, d = r.size
    if d <= w:  # the doorway passes along y (a wall parallel to x)
        mb.wall_quad(1, r.y0, r.x0, r.x1, zd, H, -1, material)
        mb.wall_quad(1, r.y1, r.x0, r.x1, zd, H, +1, material)
    else:  # passes along x
        mb.wall_quad(0, r.x0, r.y0, r.y1, zd, H, -1, material)
        mb.wall_quad(0, r.x1, r.y0, r.y1, zd, H, +1, material)
    mb.horizontal_quad(r, zd, False, material)


def _place_poster(
    mb: _MeshBuilder, rng: np.random.Generator, runs: list[_WallRun], taken: list, H: float, seed: int
) -> None:
    """Try a few random spots for one poster; skip it when none is free."""
    for _ in range(10):
        r = runs[int(rng.integers(len(runs)))]
        w = float(rng.uniform(0.45, min(1.3, r.hi - r.lo - 0.3)))
        h = float(rng.uniform(0.4, 0.95))
        z0 = float(rng.uniform(0.85, min(1.5, H - 0.25 - h)))
        a0 = float(rng.uniform(r.lo + 0.15, r.hi - 0.15 - w))
        if any(t[0] is r and a0 < t[2] + 0.1 and t[1] < a0 + w + 0.1 and z0 < t[4] and t[3] < z0 + h for t in taken):
            continue
        taken.append((r, a0, a0 + w, z0, z0 + h))
        coord = r.coord + 0.01 * r.normal_sign
        # uv of a wall point: u is y for x-facing walls (axis 0) and x for y-facing walls; v is z
        m = mb.material(random_poster(rng, (a0, z0, a0 + w, z0 + h), seed))
        mb.wall_quad(r.axis, coord, a0, a0 + w, z0, z0 + h, r.normal_sign, m)
        return


def _place_furniture(
    mb: _MeshBuilder,
    rng: np.random.Generator,
    space: Space,
    placed: list[Rect],
    doors: list[Rect],
    route_xy: np.ndarray,
    clearance: float,
    seed: int,
    corridor: bool,
) -> None:
    """Try random placements of one random piece; skip it when none fits."""
    room = space.rect
    kinds = ("cabinet", "crates") if corridor else ("cabinet", "table", "low", "crates", "cabinet")
    kind = kinds[int(rng.integers(len(kinds)))]
    material = None
    for _ in range(40):
        if kind == "cabinet":
            w, d, h = rng.uniform(0.6, 1.6), rng.uniform(0.35, 0.55 if not corridor else 0.4), rng.uniform(0.8, 2.0)
        elif kind == "table":
            w, d, h = rng.uniform(0.8, 1.6), rng.uniform(0.6, 0.9), rng.uniform(0.72, 0.78)
        elif kind == "low":
            w, d, h = rng.uniform(1.4, 2.0), rng.uniform(0.8, 1.0), rng.uniform(0.4, 0.6)
        else:
            w, d, h = rng.uniform(0.35, 0.6), rng.uniform(0.35, 0.6), rng.uniform(0.3, 0.6)
        against_wall = kind != "table" or rng.uniform() < 0.5
        if against_wall:
            side = int(rng.integers(4))
            gap = 0.02
            if side in (0, 1):  # south / north wall: width along x
                x0 = rng.uniform(room.x0 + gap, room.x1 - gap - w)
                y0 = room.y0 + gap if side == 0 else room.y1 - gap - d
                fp = Rect(x0, y0, x0 + w, y0 + d)
            else:  # west / east wall: width along y
                y0 = rng.uniform(room.y0 + gap, room.y1 - gap - w)
                x0 = room.x0 + gap if side == 2 else room.x1 - gap - d
                fp = Rect(x0, y0, x0 + d, y0 + w)
        else:
            x0 = rng.uniform(room.x0 + 0.3, room.x1 - 0.3 - w)
            y0 = rng.uniform(room.y0 + 0.3, room.y1 - 0.3 - d)
            fp = Rect(x0, y0, x0 + w, y0 + d)
        fp = Rect(*(round(float(v), 4) for v in (fp.x0, fp.y0, fp.x1, fp.y1)))
        if fp.x0 < room.x0 or fp.x1 > room.x1 or fp.y0 < room.y0 or fp.y1 > room.y1:
            continue
        if fp.distance(route_xy).min() < clearance:
            continue
        if any(fp.overlaps(o, margin=0.1) for o in placed) or any(fp.overlaps(dr, margin=0.5) for dr in doors):
            continue
        placed.append(fp)
        if material is None:
            material = mb.material(random_material(rng, FURNITURE_KINDS[int(rng.integers(len(FURNITURE_KINDS)))], seed))
        h = round(float(h), 4)
        if kind == "table":
            top = 0.04
            mb.box(fp, h - top, h, material, bottom=True)
            leg = 0.05
            for lx, ly in ((fp.x0, fp.y0), (fp.x1 - leg, fp.y0), (fp.x0, fp.y1 - leg), (fp.x1 - leg, fp.y1 - leg)):
                mb.box(Rect(lx, ly, lx + leg, ly + leg), 0.0, h - top, material, top=False)
        elif kind == "crates":
            mb.box(fp, 0.0, h, material)
            if rng.uniform() < 0.6:  # a smaller crate on top
                cx, cy = fp.center
                s = 0.35 * min(fp.size)
                mb.box(
                    Rect(round(cx - s, 4), round(cy - s, 4), round(cx + s, 4), round(cy + s, 4)),
                    h,
                    round(h + 2 * s, 4),
                    material,
                )
        else:
            mb.box(fp, 0.0, h, material)
        return
