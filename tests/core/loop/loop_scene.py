"""The synthetic loop the loop-closure tests share (imported by name: conftest.py puts this folder on
``sys.path``)."""

from __future__ import annotations

import numpy as np

from neb_slam_core.geometry.se3 import invert

#: frames of the 'default' synthetic preset (160x120, 300 frames, the route returns to its start) used
#: as keyframes: the start of the loop, a stretch far from it, and its end, which sees the start again
LOOP_FRAMES = (0, 10, 20, 30, 40, 150, 160, 270, 280, 290)
FRAME_NS = 33_333_333


def pose_error(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (degrees) of ``T_gt^-1 T_est``."""
    E = invert(T_gt) @ T_est
    return (
        float(np.linalg.norm(E[:3, 3])),
        float(np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1)))),
    )


def render_loop_views() -> tuple[dict, object]:
    """Rendered views and ground-truth poses of :data:`LOOP_FRAMES` (about 1.5 s), and the camera."""
    from neb_slam_core.synth.generate import build_sequence, resolve_spec
    from neb_slam_core.synth.render import Renderer

    spec = resolve_spec("default")
    seq = build_sequence(spec)
    intr = spec.camera.intrinsics()
    renderer = Renderer.for_scene(seq.scene, intr)
    poses = seq.trajectory.poses
    return {f: (renderer.render(poses[f]), poses[f]) for f in LOOP_FRAMES}, intr
