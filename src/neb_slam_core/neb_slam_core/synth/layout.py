"""Procedural floor plans: rooms, corridors and doorways as axis-aligned rectangles, plus the route.

A :class:`FloorPlan` is the free space of a scene: a set of axis-aligned rectangles (rooms, a
corridor, and the doorways that cut through the walls between them), the wall height, and a route:
waypoints in the free space that the camera trajectory interpolates. Everything outside the
rectangles is solid wall; :mod:`.scene` turns the plan into a mesh.

World frame: z up, floor at z = 0, metres. Coordinates are multiples of :data:`GRID_M` so that the
plan rasterises exactly (the wall builder works on that grid).

Layout kinds (:class:`LayoutSpec.kind`):

- ``"rooms"``: a corridor along x with a row of rooms on each side (``n_columns`` per side). Every
  room has a doorway to the corridor; neighbouring rooms on one side are joined by a doorway too. The
  route is a loop: from the corridor into the first south room, east through ``loop_columns`` south
  rooms, across the corridor into the north room of that column, west through the north rooms, and
  back across the corridor to the start.
- ``"room"``: one room with furniture; the route is a small closed ellipse near its centre.
- ``"corridor"``: a long corridor with rooms on both sides; the route runs along the corridor (open).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError

#: the plan's grid; every rectangle edge lies on it
GRID_M = 0.05


def snap(x: float) -> float:
    """Round ``x`` to the plan grid."""
    return round(round(x / GRID_M) * GRID_M, 6)


@dataclass(frozen=True)
class Rect:
    """An axis-aligned rectangle ``[x0, x1] x [y0, y1]`` in metres."""

    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def center(self) -> tuple[float, float]:
        return (0.5 * (self.x0 + self.x1), 0.5 * (self.y0 + self.y1))

    @property
    def size(self) -> tuple[float, float]:
        return (self.x1 - self.x0, self.y1 - self.y0)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Euclidean 2D distance of ``(N, 2)`` points to the rectangle (0 inside) -> ``(N,)``."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        dx = np.maximum(np.maximum(self.x0 - p[:, 0], p[:, 0] - self.x1), 0.0)
        dy = np.maximum(np.maximum(self.y0 - p[:, 1], p[:, 1] - self.y1), 0.0)
        return np.hypot(dx, dy)

    def overlaps(self, other: Rect, margin: float = 0.0) -> bool:
        return not (
            self.x1 + margin <= other.x0
            or other.x1 + margin <= self.x0
            or self.y1 + margin <= other.y0
            or other.y1 + margin <= self.y0
        )


@dataclass(frozen=True)
class Space:
    """One free-space rectangle: ``kind`` is ``'room'``, ``'corridor'`` or ``'door'``."""

    name: str
    kind: str
    rect: Rect


@dataclass
class FloorPlan:
    """The free space of a scene and the camera's route through it.

    Attributes:
        spaces: rooms, corridors and doorways; doorways join two other spaces through a wall.
        wall_height_m: floor-to-ceiling height.
        door_height_m: height of the doorways (a lintel fills the wall above them).
        route_xy: ``(M, 2)`` waypoints of the camera route in metres (for a loop, not repeated at the end).
        route_closed: whether the route is a loop.
        fixed_yaw_deg: when not None the camera keeps this mean heading instead of looking along the
            route (used by the one-room plan, whose small loop would otherwise spin the camera).
    """

    spaces: list[Space]
    wall_height_m: float
    door_height_m: float
    route_xy: np.ndarray
    route_closed: bool
    fixed_yaw_deg: float | None = None

    @property
    def bounds_xy(self) -> Rect:
        """The bounding rectangle of all free space."""
        return Rect(
            min(s.rect.x0 for s in self.spaces),
            min(s.rect.y0 for s in self.spaces),
            max(s.rect.x1 for s in self.spaces),
            max(s.rect.y1 for s in self.spaces),
        )

    def spaces_of(self, kind: str) -> list[Space]:
        return [s for s in self.spaces if s.kind == kind]


@dataclass(frozen=True)
class LayoutSpec:
    """Parameters of a procedural floor plan (see the module docstring for the kinds).

    Ranges are ``(low, high)`` and sampled uniformly from the scene seed.
    """

    kind: str = "rooms"
    n_columns: int = 3
    loop_columns: int = 2
    room_width_m: tuple[float, float] = (4.3, 4.9)
    room_depth_m: tuple[float, float] = (3.5, 4.0)
    corridor_width_m: tuple[float, float] = (2.1, 2.4)
    wall_height_m: tuple[float, float] = (2.6, 2.9)
    wall_thickness_m: float = 0.15
    door_width_m: tuple[float, float] = (1.3, 1.5)
    door_height_m: float = 2.1

    def validate(self) -> None:
        if self.kind not in ("rooms", "room", "corridor"):
            raise ConfigError(f"LayoutSpec.kind: expected 'rooms', 'room' or 'corridor', got {self.kind!r}")
        if self.kind == "rooms" and not 2 <= self.loop_columns <= self.n_columns:
            raise ConfigError(
                f"LayoutSpec.loop_columns: expected 2..n_columns ({self.n_columns}), got {self.loop_columns}"
            )
        if self.n_columns < 1:
            raise ConfigError(f"LayoutSpec.n_columns: expected >= 1, got {self.n_columns}")
        if self.door_width_m[0] < 1.2:
            raise ConfigError(
                "LayoutSpec.door_width_m: doorways narrower than 1.2 m leave the camera "
                "less than 0.4 m from the door frame"
            )
        if self.door_height_m >= self.wall_height_m[0]:
            raise ConfigError("LayoutSpec.door_height_m must be below the lowest wall height")


def build_floor_plan(spec: LayoutSpec, rng: np.random.Generator) -> FloorPlan:
    """Sample a floor plan of ``spec.kind`` from ``rng``."""
    spec.validate()
    if spec.kind == "rooms":
        return _rooms_plan(spec, rng)
    if spec.kind == "room":
        return _single_room_plan(spec, rng)
    return _corridor_plan(spec, rng)


# ----------------------------------------------------------------------------------------------


def _u(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return snap(float(rng.uniform(*lo_hi)))


@dataclass
class _TwoRowPlan:
    """Geometry shared by the 'rooms' and 'corridor' layouts: rooms south and north of a corridor."""

    spaces: list[Space]
    columns: list[tuple[float, float]]  # x extent of each column
    door_x: list[float]  # corridor doorway centre per column (same both sides)
    south_y: tuple[float, float]
    corridor_y: tuple[float, float]
    north_y: tuple[float, float]
    inner_door_y_south: list[float]  # y of the doorway between column i and i+1, south row
    inner_door_y_north: list[float]
    height: float


def _two_rows(spec: LayoutSpec, rng: np.random.Generator, inner_doors: bool) -> _TwoRowPlan:
    t = spec.wall_thickness_m
    height = _u(rng, spec.wall_height_m)
    d_south, d_north = _u(rng, spec.room_depth_m), _u(rng, spec.room_depth_m)
    w_corr = _u(rng, spec.corridor_width_m)
    south_y = (0.0, d_south)
    corridor_y = (snap(d_south + t), snap(d_south + t + w_corr))
    north_y = (snap(corridor_y[1] + t), snap(corridor_y[1] + t + d_north))

    columns, x = [], 0.0
    for _ in range(spec.n_columns):
        w = _u(rng, spec.room_width_m)
        columns.append((x, snap(x + w)))
        x = snap(x + w + t)
    x_end = columns[-1][1]

    spaces = [Space("corridor", "corridor", Rect(0.0, corridor_y[0], x_end, corridor_y[1]))]
    door_x, inner_s, inner_n = [], [], []
    for i, (x0, x1) in enumerate(columns):
        spaces.append(Space(f"room_s{i}", "room", Rect(x0, south_y[0], x1, south_y[1])))
        spaces.append(Space(f"room_n{i}", "room", Rect(x0, north_y[0], x1, north_y[1])))
        dw = _u(rng, spec.door_width_m)
        dx = snap(0.5 * (x0 + x1) + rng.uniform(-0.3, 0.3))
        door_x.append(dx)
        spaces.append(
            Space(f"door_s{i}_corridor", "door", Rect(snap(dx - dw / 2), south_y[1], snap(dx + dw / 2), corridor_y[0]))
        )
        spaces.append(
            Space(f"door_n{i}_corridor", "door", Rect(snap(dx - dw / 2), corridor_y[1], snap(dx + dw / 2), north_y[0]))
        )
        if inner_doors and i + 1 < len(columns):
            for row, (y0, y1), store in (("s", south_y, inner_s), ("n", north_y, inner_n)):
                dw = _u(rng, spec.door_width_m)
                # keep the doorway 1.4..(depth - 1.4) m from the outer wall so the route can turn
                far = y0 if row == "s" else y1
                depth = y1 - y0
                off = float(rng.uniform(1.5, max(1.5, depth - 1.5)))
                dy = snap(far + off if row == "s" else far - off)
                store.append(dy)
                spaces.append(
                    Space(
                        f"door_{row}{i}_{row}{i + 1}",
                        "door",
                        Rect(x1, snap(dy - dw / 2), columns[i + 1][0], snap(dy + dw / 2)),
                    )
                )
    return _TwoRowPlan(spaces, columns, door_x, south_y, corridor_y, north_y, inner_s, inner_n, height)


def _rooms_plan(spec: LayoutSpec, rng: np.random.Generator) -> FloorPlan:
    p = _two_rows(spec, rng, inner_doors=True)
    t = spec.wall_thickness_m
    a = 0.65  # waypoint distance before/after a doorway
    yc = 0.5 * (p.corridor_y[0] + p.corridor_y[1])
    k = spec.loop_columns
    x0, xk = p.door_x[0], p.door_x[k - 1]
    # start: corridor centre in front of the first south room, heading south through its doorway
    pts: list[tuple[float, float]] = [(x0, yc), (x0, p.corridor_y[0] + a), (x0, p.south_y[1] - a)]
    # south rooms, west to east, through the inner doorways (middle rooms: a dip towards the far wall)
    for i in range(k - 1):
        if i > 0:
            pts.append((0.5 * (p.columns[i][0] + p.columns[i][1]), p.south_y[0] + 1.3))
        xe, dy = p.columns[i][1], p.inner_door_y_south[i]
        pts += [(xe - a, dy), (xe + t + a, dy)]
    # last south room of the loop: north through its doorway, across the corridor, into the north room
    pts += [(xk, p.south_y[1] - a), (xk, p.corridor_y[0] + a), (xk, p.corridor_y[1] - a), (xk, p.north_y[0] + a)]
    # north rooms, east to west
    for i in range(k - 2, -1, -1):
        if i < k - 2:
            pts.append((0.5 * (p.columns[i + 1][0] + p.columns[i + 1][1]), p.north_y[1] - 1.3))
        xe, dy = p.columns[i][1], p.inner_door_y_north[i]
        pts += [(xe + t + a, dy), (xe - a, dy)]
    # first north room: south through its doorway back to the start
    pts += [(x0, p.north_y[0] + a), (x0, p.corridor_y[1] - a)]
    return FloorPlan(p.spaces, p.height, spec.door_height_m, np.asarray(pts, dtype=np.float64), True)


def _corridor_plan(spec: LayoutSpec, rng: np.random.Generator) -> FloorPlan:
    p = _two_rows(spec, rng, inner_doors=False)
    yc = 0.5 * (p.corridor_y[0] + p.corridor_y[1])
    x_end = p.columns[-1][1]
    # stop 3 m before the far end wall: the last frames still look down a stretch of corridor
    xs = np.arange(1.2, x_end - 3.0 + 1e-9, 2.0)
    xs[-1] = x_end - 3.0
    weave = 0.25 * np.where(np.arange(len(xs)) % 2 == 0, 1.0, -1.0)
    weave[0] = weave[-1] = 0.0
    route = np.stack([xs, yc + weave], axis=1)
    return FloorPlan(p.spaces, p.height, spec.door_height_m, route, False)


def _single_room_plan(spec: LayoutSpec, rng: np.random.Generator) -> FloorPlan:
    w, d = _u(rng, spec.room_width_m), _u(rng, spec.room_depth_m)
    room = Rect(0.0, 0.0, w, d)
    cx, cy = room.center
    # a small ellipse, slightly towards the south wall, looking north (at the far wall and furniture)
    n = 8
    ang = np.arange(n) * (2 * np.pi / n)
    route = np.stack([cx + 0.55 * np.cos(ang), cy - 0.35 + 0.35 * np.sin(ang)], axis=1)
    return FloorPlan(
        [Space("room_s0", "room", room)],
        _u(rng, spec.wall_height_m),
        spec.door_height_m,
        route,
        True,
        fixed_yaw_deg=90.0,
    )
