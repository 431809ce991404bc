"""Write a synthetic RGB-D sequence to disk in the TUM RGB-D layout.

Output folder::

    rgb/<stamp>.png       8-bit RGB colour
    depth/<stamp>.png     16-bit depth, value = z metres * 5000 (0 = no measurement)
    rgb.txt, depth.txt    'timestamp filename' indexes (identical stamps)
    groundtruth.txt       TUM trajectory 'timestamp tx ty tz qx qy qz qw' (T_world_cam), same stamps
    intrinsics.json       fx fy cx cy width height (read by the TUM loader)
    mesh.ply              the ground-truth mesh with vertex colours (shaded albedo)
    scene.json            seed, every option, scene bounds and trajectory figures; written last, so
                          it marks a complete folder (while a run writes the folder it holds only the
                          options and "complete": false, so an interrupted run is regenerated next time)

The folder opens with :func:`neb_slam_core.datasets.open_dataset`. The output is a function of the
options alone: the same options give the same bytes.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import trimesh
from tqdm import tqdm

from ..datasets.tum import DEPTH_SCALE, INTRINSICS_FILE, write_intrinsics_json
from ..errors import ConfigError, DatasetError
from ..io.trajectory import Trajectory, stamp_ns_to_text, write_tum_trajectory
from .noise import apply_depth_noise
from .presets import get_preset, with_overrides
from .render import Renderer
from .scene import SceneSpec, SyntheticScene, build_scene
from .trajectory import RouteCurve, make_trajectory, route_curve

log = logging.getLogger(__name__)

FORMAT_NAME = "neb-slam synth"
FORMAT_VERSION = 1
SCENE_FILE = "scene.json"
MESH_FILE = "mesh.ply"
#: edge length the exported mesh is subdivided to, so that vertex colours show the textures
MESH_EXPORT_EDGE_M = 0.2
_OUTPUT_FILES = ("rgb.txt", "depth.txt", "groundtruth.txt", INTRINSICS_FILE, MESH_FILE, SCENE_FILE)


@dataclass
class SyntheticSequence:
    """A scene and the camera trajectory through it (everything except the images)."""

    scene: SyntheticScene
    curve: RouteCurve
    trajectory: Trajectory

    @property
    def spec(self) -> SceneSpec:
        return self.scene.spec


def resolve_spec(
    preset_or_spec: SceneSpec | str = "default",
    *,
    n_frames: int | None = None,
    size: tuple[int, int] | None = None,
    seed: int | None = None,
    noise: bool | None = None,
) -> SceneSpec:
    """A preset name or spec with the given overrides applied."""
    spec = get_preset(preset_or_spec) if isinstance(preset_or_spec, str) else preset_or_spec
    spec = with_overrides(spec, n_frames=n_frames, size=size, seed=seed, noise=noise)
    spec.camera.validate()
    spec.trajectory.validate()
    spec.noise.validate()
    return spec


def build_sequence(spec: SceneSpec) -> SyntheticSequence:
    """Build the scene and its trajectory and check the trajectory's clearance from every surface."""
    scene = build_scene(spec)
    curve = route_curve(scene.plan.route_xy, scene.plan.route_closed)
    traj = make_trajectory(curve, spec.trajectory, fixed_yaw_deg=scene.plan.fixed_yaw_deg)
    clearance = camera_clearance(scene, traj.positions)
    if clearance.min() < spec.trajectory.min_clearance_m:
        i = int(np.argmin(clearance))
        raise ConfigError(
            f"synthetic scene {spec.name!r} seed {spec.seed}: frame {i} is {clearance[i]:.3f} m from a "
            f"surface, less than the required {spec.trajectory.min_clearance_m} m (layout too tight)"
        )
    return SyntheticSequence(scene, curve, traj)


def camera_clearance(scene: SyntheticScene, positions: np.ndarray) -> np.ndarray:
    """Distance ``(N,)`` in metres from each camera centre ``(N, 3)`` to the nearest surface of the scene."""
    _, dist, _ = trimesh.proximity.closest_point(scene.mesh, np.asarray(positions, dtype=np.float64))
    return np.asarray(dist)


def trajectory_stats(traj: Trajectory) -> dict:
    """Per-frame motion figures of a trajectory (translation in m, rotation in degrees)."""
    p = traj.poses
    step = np.linalg.norm(np.diff(p[:, :3, 3], axis=0), axis=1)
    rel = np.einsum("nji,njk->nik", p[:-1, :3, :3], p[1:, :3, :3])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rot = np.degrees(np.arccos(cos))
    dt_s = float(np.diff(traj.stamps_ns).mean()) * 1e-9 if len(traj) > 1 else 0.0
    return {
        "length_m": round(float(step.sum()), 4),
        "step_m_mean": round(float(step.mean()), 5),
        "step_m_max": round(float(step.max()), 5),
        "rotation_deg_per_frame_max": round(float(rot.max()), 4),
        "speed_mps": round(float(step.mean() / dt_s), 4) if dt_s > 0 else 0.0,
    }


def generate(
    preset_or_spec: SceneSpec | str = "default",
    out_dir: str | Path = "synth",
    *,
    n_frames: int | None = None,
    size: tuple[int, int] | None = None,
    seed: int | None = None,
    noise: bool | None = None,
    force: bool = False,
    progress: bool = True,
) -> Path:
    """Render a synthetic sequence into ``out_dir`` (TUM layout, see the module docstring).

    When ``out_dir`` already holds a complete sequence made with the same options, nothing is done
    unless ``force``. A non-empty folder that is not a synthetic sequence is refused unless ``force``
    (then only the files this function writes are replaced).

    Returns:
        ``out_dir`` as a :class:`~pathlib.Path`.
    """
    spec = resolve_spec(preset_or_spec, n_frames=n_frames, size=size, seed=seed, noise=noise)
    out = Path(out_dir)
    if not force and is_complete(out, spec):
        log.info("%s already holds this synthetic scene (%s, seed %d); nothing to do", out, spec.name, spec.seed)
        return out
    _prepare_folder(out, force)
    # Marks the folder as ours while it is written: an interrupted run (Ctrl-C, a crash) leaves a folder
    # the next run recognises, regenerates and never takes for complete (is_complete wants the full
    # summary written last), instead of refusing it as someone else's non-empty folder.
    (out / SCENE_FILE).write_text(
        json.dumps(
            {"format": FORMAT_NAME, "version": FORMAT_VERSION, "complete": False, "options": spec.to_dict()}, indent=2
        )
        + "\n"
    )

    seq = build_sequence(spec)
    intr = spec.camera.intrinsics()
    renderer = Renderer.for_scene(seq.scene, intr)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    names = []
    stamps = seq.trajectory.stamps_ns
    for i in tqdm(range(len(stamps)), desc=f"synth {spec.name}", unit="frame", disable=not progress):
        view = renderer.render(seq.trajectory.poses[i])
        depth = view.depth_m
        if spec.noise.enabled:
            depth = apply_depth_noise(
                depth, view.cos_incidence, spec.noise, np.random.default_rng([spec.seed, i, 0xD3])
            )
        name = stamp_ns_to_text(int(stamps[i]))
        _write_png(out / "rgb" / f"{name}.png", cv2.cvtColor(view.rgb, cv2.COLOR_RGB2BGR))
        _write_png(out / "depth" / f"{name}.png", depth_to_png16(depth))
        names.append(name)

    header = f"# {FORMAT_NAME} scene '{spec.name}' seed {spec.seed}\n"
    (out / "rgb.txt").write_text(header + "# timestamp filename\n" + "".join(f"{n} rgb/{n}.png\n" for n in names))
    (out / "depth.txt").write_text(header + "# timestamp filename\n" + "".join(f"{n} depth/{n}.png\n" for n in names))
    write_tum_trajectory(
        out / "groundtruth.txt",
        seq.trajectory,
        header=f"{FORMAT_NAME} scene '{spec.name}' seed {spec.seed}: T_world_cam, OpenCV camera axes, z-up world",
    )
    write_intrinsics_json(out / INTRINSICS_FILE, intr)
    export_mesh(seq.scene, out / MESH_FILE, renderer)
    (out / SCENE_FILE).write_text(json.dumps(scene_summary(seq), indent=2) + "\n")
    return out


def scene_summary(seq: SyntheticSequence) -> dict:
    """The contents of ``scene.json``."""
    spec, scene = seq.spec, seq.scene
    intr = spec.camera.intrinsics()
    b = scene.bounds
    return {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "preset": spec.name,
        "seed": spec.seed,
        "options": spec.to_dict(),
        "bounds_m": {
            "min": [round(float(x), 6) for x in b[0]],
            "max": [round(float(x), 6) for x in b[1]],
            "size": [round(float(x), 6) for x in b[1] - b[0]],
        },
        "n_frames": len(seq.trajectory),
        "image_size": [intr.width, intr.height],
        "intrinsics": {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy},
        "conventions": {
            "world": "z up, floor at z = 0, metres",
            "poses": "groundtruth.txt holds T_world_cam with OpenCV camera axes (x right, y down, z forward)",
            "pixels": "integer (u, v) are pixel centres; the ray of a pixel is K^-1 [u, v, 1]",
            "depth": f"z along the optical axis, PNG value = metres * {DEPTH_SCALE:g}, 0 = none, "
            f"valid range {spec.camera.min_depth_m}..{spec.camera.max_depth_m} m",
        },
        "trajectory": {
            "loop": bool(scene.plan.route_closed),
            **trajectory_stats(seq.trajectory),
            "min_clearance_m": round(float(camera_clearance(scene, seq.trajectory.positions).min()), 4),
        },
        "mesh": {
            "file": MESH_FILE,
            "render_faces": int(len(scene.mesh.faces)),
            "materials": len(scene.materials),
            "spaces": [
                {"name": s.name, "kind": s.kind, "rect_xy": [s.rect.x0, s.rect.y0, s.rect.x1, s.rect.y1]}
                for s in scene.plan.spaces
            ],
            "wall_height_m": scene.plan.wall_height_m,
        },
    }


def is_complete(out: Path, spec: SceneSpec) -> bool:
    """True when ``out`` holds a complete sequence generated with exactly ``spec``'s options."""
    try:
        meta = json.loads((out / SCENE_FILE).read_text())
    except (OSError, ValueError):
        return False
    if meta.get("format") != FORMAT_NAME or meta.get("version") != FORMAT_VERSION or meta.get("complete") is False:
        return False
    if meta.get("options") != json.loads(json.dumps(spec.to_dict())):
        return False
    if not all((out / f).is_file() for f in _OUTPUT_FILES):
        return False
    for index in ("rgb.txt", "depth.txt"):
        lines = [ln.split() for ln in (out / index).read_text().splitlines() if ln and not ln.startswith("#")]
        if len(lines) != spec.trajectory.n_frames or not all(len(p) == 2 and (out / p[1]).is_file() for p in lines):
            return False
    return True


def _prepare_folder(out: Path, force: bool) -> None:
    """Make ``out`` ready: create it, or clear the files a previous run wrote."""
    if out.exists() and not out.is_dir():
        raise DatasetError(out, "exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    ours = (out / SCENE_FILE).is_file()
    if any(out.iterdir()) and not ours and not force:
        raise DatasetError(
            out,
            "folder is not empty and holds no synthetic scene (scene.json); "
            "choose an empty or new folder, or pass --force to overwrite its TUM files",
        )
    # scene.json first: an interrupted rewrite must not look complete
    for f in (SCENE_FILE,) + _OUTPUT_FILES:
        (out / f).unlink(missing_ok=True)
    for sub in ("rgb", "depth"):
        if (out / sub).is_dir():
            for png in (out / sub).glob("*.png"):
                png.unlink()


def depth_to_png16(depth_m: np.ndarray) -> np.ndarray:
    """Float metres -> uint16 PNG values (metres * 5000, rounded; 0 stays 0)."""
    return np.clip(np.round(np.asarray(depth_m, dtype=np.float64) * DEPTH_SCALE), 0, 65535).astype(np.uint16)


def _write_png(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image):
        raise DatasetError(path, "could not write the image")


def export_mesh(scene: SyntheticScene, path: Path, renderer: Renderer) -> None:
    """Write the scene mesh as binary PLY with vertex colours.

    The render mesh (large quads) is subdivided to edges of at most :data:`MESH_EXPORT_EDGE_M` so the
    colours show the textures; a vertex's colour is its surface's colour there, shaded as the camera
    sees it (view-independent). Quads of different surfaces share no vertices, so colours do not
    bleed across surfaces. The geometry is exactly the render mesh's surface.
    """
    v, f, idx = trimesh.remesh.subdivide_to_size(
        scene.mesh.vertices, scene.mesh.faces, MESH_EXPORT_EDGE_M, max_iter=12, return_index=True
    )
    v, f = np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)
    vertex_face = np.zeros(len(v), dtype=np.int64)  # the source face of each vertex
    vertex_face[f.ravel()] = np.repeat(np.asarray(idx, dtype=np.int64), 3)
    normals = np.asarray(scene.mesh.face_normals)[vertex_face]
    color = renderer.shade(vertex_face, v, -normals)  # seen from the side the normal points to
    rgba = np.concatenate([np.clip(np.round(color * 255), 0, 255), np.full((len(v), 1), 255)], axis=1).astype(np.uint8)
    out = trimesh.Trimesh(vertices=v, faces=f, vertex_colors=rgba, process=False)
    path.write_bytes(out.export(file_type="ply"))
