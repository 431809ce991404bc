"""Named synthetic scenes: the registry behind ``neb-slam synth --preset NAME``.

- ``default``: the demo: three rooms on each side of a corridor (about 14 x 9.5 m, several neural
  blocks), 160x120, 300 frames on a loop through four rooms and twice across the corridor.
- ``large``: the same family with the loop through all six rooms, 320x240 (``--size 640x480`` for
  full size), 600 frames; for accuracy benchmarks.
- ``small``: one furnished room (about 4 x 4 x 2.6 m), 96x72, 60 frames on a small loop looking
  into the room; for fast tests (fitting the map, end to end).
- ``corridor``: a corridor of about 28 m with rooms on both sides; the camera moves along it once
  (no loop); for block-scaling benchmarks.
"""

from __future__ import annotations

from dataclasses import replace

from ..errors import ConfigError
from .layout import LayoutSpec
from .render import CameraSpec
from .scene import SceneSpec
from .trajectory import TrajectorySpec

PRESETS: dict[str, SceneSpec] = {
    "default": SceneSpec(
        name="default",
        layout=LayoutSpec(kind="rooms", n_columns=3, loop_columns=2),
        camera=CameraSpec(width=160, height=120),
        trajectory=TrajectorySpec(n_frames=300),
    ),
    "large": SceneSpec(
        name="large",
        layout=LayoutSpec(kind="rooms", n_columns=3, loop_columns=3),
        camera=CameraSpec(width=320, height=240),
        trajectory=TrajectorySpec(n_frames=600),
    ),
    "small": SceneSpec(
        name="small",
        layout=LayoutSpec(kind="room", room_width_m=(3.9, 4.1), room_depth_m=(3.9, 4.1), wall_height_m=(2.6, 2.6)),
        camera=CameraSpec(width=96, height=72),
        trajectory=TrajectorySpec(
            n_frames=60, yaw_amplitude_deg=25.0, pitch_amplitude_deg=4.0, height_amplitude_m=0.05
        ),
        furniture_per_room=(5, 7),
        posters_per_room=(4, 7),
    ),
    "corridor": SceneSpec(
        name="corridor",
        layout=LayoutSpec(kind="corridor", n_columns=6, corridor_width_m=(2.3, 2.5)),
        camera=CameraSpec(width=160, height=120),
        trajectory=TrajectorySpec(n_frames=500, yaw_amplitude_deg=20.0, wave_length_m=7.0),
    ),
}


def preset_names() -> list[str]:
    return list(PRESETS)


def get_preset(name: str) -> SceneSpec:
    """The spec registered as ``name``; :class:`ConfigError` listing the choices otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown synthetic scene preset {name!r}; choose one of: {', '.join(PRESETS)}") from None


def with_overrides(
    spec: SceneSpec,
    *,
    n_frames: int | None = None,
    size: tuple[int, int] | None = None,
    seed: int | None = None,
    noise: bool | None = None,
) -> SceneSpec:
    """``spec`` with the command-line options applied (None keeps the spec's value)."""
    if n_frames is not None:
        spec = replace(spec, trajectory=replace(spec.trajectory, n_frames=int(n_frames)))
    if size is not None:
        spec = replace(spec, camera=replace(spec.camera, width=int(size[0]), height=int(size[1])))
    if seed is not None:
        spec = replace(spec, seed=int(seed))
    if noise is not None:
        spec = replace(spec, noise=replace(spec.noise, enabled=bool(noise)))
    return spec
