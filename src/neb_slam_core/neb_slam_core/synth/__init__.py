"""Procedural synthetic RGB-D scenes with ground truth (``neb-slam synth``).

Indoor scenes built from a seed (rooms, corridor, furniture, posters, procedural textures), rendered
by ray casting along a smooth camera trajectory, written in the TUM RGB-D layout with the ground-truth
trajectory, intrinsics and mesh. Modules: :mod:`.layout` (floor plans and routes), :mod:`.textures`
(materials), :mod:`.scene` (spec and mesh), :mod:`.trajectory`, :mod:`.render`, :mod:`.noise` (depth
noise model), :mod:`.presets` (named scenes), :mod:`.generate` (writing a sequence: call
``neb_slam_core.synth.generate.generate(...)``; the module is not shadowed by the function here).
"""

from . import generate
from .generate import build_sequence, resolve_spec
from .noise import DepthNoiseSpec, apply_depth_noise
from .presets import PRESETS, get_preset, preset_names
from .render import CameraSpec, RenderedView, Renderer
from .scene import SceneSpec, SyntheticScene, build_scene
from .trajectory import TrajectorySpec, make_trajectory

__all__ = [
    "CameraSpec",
    "DepthNoiseSpec",
    "PRESETS",
    "RenderedView",
    "Renderer",
    "SceneSpec",
    "SyntheticScene",
    "TrajectorySpec",
    "apply_depth_noise",
    "build_scene",
    "build_sequence",
    "generate",
    "get_preset",
    "make_trajectory",
    "preset_names",
    "resolve_spec",
]
