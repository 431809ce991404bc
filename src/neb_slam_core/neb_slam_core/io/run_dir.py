"""The run directory of ``neb-slam run``: every file a run leaves, written from the engine's state.

::

    <run>/
        config.yaml        the resolved configuration (loadable again with ``--config <run>/config.yaml``)
        intrinsics.json    the camera: fx, fy, cx, cy, width, height
        trajectory.txt     TUM format: the processed input frames' stamps and corrected poses (T_world_cam)
        groundtruth.txt    the input's ground-truth poses at those stamps (frames without one are skipped)
        timings.csv        one row per processed frame, columns :data:`TIMINGS_COLUMNS`
        map.pt             block-map checkpoint (:func:`~neb_slam_core.scene.persistence.save_map`); its
                           ``extra`` holds the keyframe poses and frame indices (see :func:`map_extra`)
        mesh.ply           the reconstruction, world frame, vertex colours
        metrics.json       the run's figures (:func:`run_metrics`), with ground truth ATE / RPE (the
                           figures of ``neb-slam eval``), with a ground-truth mesh the reconstruction metrics
        loops.json         every loop detected (:func:`loop_log`): frames, score, whether it was applied
                           and why not, the size of the correction
        trajectory.png, ate_over_time.png    with ground truth (as ``neb-slam eval`` draws them; loops
                           marked on the trajectory)
        blocks.png         the block allocation, top view (:func:`~neb_slam_core.eval.plots.plot_block_allocation`)

:func:`write_run` writes them all from a :class:`~neb_slam_core.slam.Slam` and the :class:`RunLog` the
loop kept; it is called at the end of a run and also after an interruption or a crash, with whatever
the engine holds then, so every file describes the same processed frames. Cheap, important files go
first (trajectory, timings, metrics), the slow ones last (mesh, reconstruction metrics), so an
interruption of the writing itself loses as little as possible. Files are written under a temporary
name and renamed, so none is ever left half-written.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from ..config import MeshConfig, SlamConfig
from ..errors import DatasetError
from ..types import Intrinsics, RgbdFrame, StepResult
from .trajectory import Trajectory, write_tum_trajectory

if TYPE_CHECKING:  # the engine pulls torch; only needed for type hints here
    from ..slam import Slam

log = logging.getLogger(__name__)

CONFIG_FILE = "config.yaml"
INTRINSICS_FILE = "intrinsics.json"
TRAJECTORY_FILE = "trajectory.txt"
GROUNDTRUTH_FILE = "groundtruth.txt"
TIMINGS_FILE = "timings.csv"
MAP_FILE = "map.pt"
MESH_FILE = "mesh.ply"
METRICS_FILE = "metrics.json"
LOOPS_FILE = "loops.json"
BLOCKS_PLOT_FILE = "blocks.png"

#: columns of timings.csv: the input frame index, its stamp (integer ns), the engine's per-stage times
#: (ms), whether it became a keyframe, the id of the block it allocated (empty: none), whether tracking
#: succeeded, then the allocation ratio tau, the blocks in the map after it and the failure reason.
TIMINGS_COLUMNS = ("index", "stamp_ns", "track_ms", "allocate_ms", "map_ms", "loop_ms", "total_ms", "keyframe", "new_block",
                   "tracking_ok", "tau", "n_blocks", "failure_reason")

#: how a run ended, as stored in metrics.json ``status``
STATUSES = ("complete", "interrupted", "crashed")


@dataclass
class FrameLog:
    """One input frame handed to the engine.

    Attributes:
        index: the frame's position in the input dataset.
        stamp_ns: its stamp.
        T_world_cam_gt: its ground-truth pose ``(4, 4)`` float64, or None.
        result: what the engine did with it; None when processing did not finish.
    """

    index: int
    stamp_ns: int
    T_world_cam_gt: np.ndarray | None
    result: StepResult | None = None


@dataclass
class RunLog:
    """What the run loop handed to the engine and got back, in order."""

    frames: list[FrameLog] = field(default_factory=list)

    def begin(self, frame: RgbdFrame) -> None:
        """Call before ``slam.process(frame)``."""
        gt = None if frame.T_world_cam is None else np.array(frame.T_world_cam, dtype=np.float64)
        self.frames.append(FrameLog(int(frame.index), int(frame.stamp_ns), gt))

    def end(self, result: StepResult) -> None:
        """Call with what ``slam.process`` returned for the frame of the last :meth:`begin`."""
        if not self.frames or self.frames[-1].result is not None:
            raise RuntimeError("RunLog.end without a matching begin")
        self.frames[-1].result = result

    @property
    def completed(self) -> list[FrameLog]:
        """The frames the engine finished (their ``result`` is set)."""
        return [f for f in self.frames if f.result is not None]

    def groundtruth(self, n_frames: int) -> Trajectory:
        """Ground-truth poses of the first ``n_frames`` frames, skipping frames that have none."""
        with_gt = [f for f in self.frames[:n_frames] if f.T_world_cam_gt is not None]
        if not with_gt:
            return Trajectory(np.zeros(0, np.int64), np.zeros((0, 4, 4)))
        return Trajectory(np.array([f.stamp_ns for f in with_gt]), np.stack([f.T_world_cam_gt for f in with_gt]))


@dataclass(frozen=True)
class RunOutputOptions:
    """What :func:`write_run` writes beyond the always-written files.

    Attributes:
        mesh: extract and save the mesh (and, with a ground-truth mesh, the reconstruction metrics).
        mesh_cfg: the mesh extraction settings.
        gt_mesh: ground-truth mesh for accuracy / completion; None: no reconstruction metrics.
        first_pose_from_gt: the run started from the first frame's ground-truth pose, so the estimate
            (and the mesh) are in the ground truth's frame; otherwise the mesh is mapped there by the
            ATE alignment before it is compared.
        recon_points: points sampled per mesh; ``depth_views``: virtual views for Depth L1 (0: skip);
        cull_stride: cull the meshes with every k-th ground-truth pose (``neb-slam eval --cull-stride``).
        progress: show progress bars (mesh extraction, culling).
    """

    mesh: bool = True
    mesh_cfg: MeshConfig = MeshConfig()
    gt_mesh: Path | None = None
    first_pose_from_gt: bool = True
    recon_points: int = 200_000
    depth_views: int = 1000
    cull_stride: int = 5
    progress: bool = True


@dataclass
class RunSummary:
    """What :func:`write_run` did: the run's figures and the files it wrote."""

    run_dir: Path
    status: str
    n_frames: int
    metrics: dict
    written: list[Path] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    mesh: object = None  #: the mesh written to mesh.ply (a trimesh.Trimesh), None when none was


class RunDirectory:
    """The folder of one run and its writers (one method per file)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    @classmethod
    def create(cls, path: str | Path) -> "RunDirectory":
        """Make a new, empty run folder (parents too); an existing non-empty folder is an error."""
        path = Path(path)
        if path.exists():
            if not path.is_dir():
                raise DatasetError(path, "output path exists and is not a folder")
            if any(path.iterdir()):
                raise DatasetError(path, "output folder is not empty (it may hold another run); "
                                         "choose another --out or remove it")
        path.mkdir(parents=True, exist_ok=True)
        return cls(path)

    def file(self, name: str) -> Path:
        return self.path / name

    def _write_atomic(self, name: str, write: Callable[[Path], object]) -> Path:
        """Write file ``name`` through ``write(tmp_path)`` then rename, so a crash never leaves half a file."""
        path = self.file(name)
        tmp = path.with_name(path.name + ".tmp")
        write(tmp)
        tmp.replace(path)
        return path

    def _write_text(self, name: str, text: str) -> Path:
        return self._write_atomic(name, lambda tmp: tmp.write_text(text))

    def write_config(self, cfg: SlamConfig) -> Path:
        from ..config_io import dump_config

        return self._write_atomic(CONFIG_FILE, lambda tmp: dump_config(cfg, tmp))

    def write_intrinsics(self, intrinsics: Intrinsics) -> Path:
        from ..datasets.tum import write_intrinsics_json

        return self._write_atomic(INTRINSICS_FILE, lambda tmp: write_intrinsics_json(tmp, intrinsics))

    def write_trajectory(self, traj: Trajectory, name: str = TRAJECTORY_FILE, header: str | None = None) -> Path:
        return self._write_atomic(name, lambda tmp: write_tum_trajectory(tmp, traj, header))

    def write_timings(self, frames: list[FrameLog]) -> Path:
        """timings.csv: one row per finished frame (columns :data:`TIMINGS_COLUMNS`)."""
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(TIMINGS_COLUMNS)
        for f in frames:
            r = f.result
            if r is None:
                continue
            t = r.timings
            writer.writerow([f.index, f.stamp_ns, f"{t.track_ms:.3f}", f"{t.allocate_ms:.3f}", f"{t.map_ms:.3f}",
                             f"{t.loop_ms:.3f}", f"{t.total_ms:.3f}", int(r.is_keyframe), "" if r.new_block_id is None else r.new_block_id,
                             int(r.tracking_ok), f"{r.tau:.4f}", r.n_blocks, r.failure_reason])
        return self._write_text(TIMINGS_FILE, buf.getvalue())

    def write_loops(self, loops: list[dict]) -> Path:
        return self._write_text(LOOPS_FILE, json.dumps(_json_safe(loops), indent=2) + "\n")

    def write_metrics(self, metrics: dict) -> Path:
        return self._write_text(METRICS_FILE, json.dumps(_json_safe(metrics), indent=2, sort_keys=True) + "\n")

    def write_map(self, slam: "Slam", frames: list[FrameLog]) -> Path:
        from ..scene.persistence import save_map

        return save_map(slam.block_map, self.file(MAP_FILE), extra=map_extra(slam, frames),
                        block_keyframes=slam.keyframes.block_keyframes())

    def write_mesh(self, mesh) -> Path:
        from ..mesh import save_mesh

        return self._write_atomic(MESH_FILE, lambda tmp: save_mesh(mesh, tmp))


def read_timings(path: str | Path) -> list[dict[str, str]]:
    """The rows of a timings.csv as dicts keyed by :data:`TIMINGS_COLUMNS` (values as text)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "timings file not found")
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        if tuple(reader.fieldnames or ()) != TIMINGS_COLUMNS:
            raise DatasetError(path, f"expected the columns {', '.join(TIMINGS_COLUMNS)}, got {reader.fieldnames}")
        return list(reader)


def map_extra(slam: "Slam", frames: list[FrameLog]) -> dict:
    """What map.pt stores beside the map (plain tensors and lists, loadable with ``weights_only``).

    ``keyframe_poses``: ``(K, 4, 4)`` float64 tensor of the keyframes' current ``T_world_cam``;
    ``keyframe_frame_indices`` / ``keyframe_stamps_ns``: each keyframe's input frame index and stamp;
    ``frame_indices`` / ``stamps_ns``: those of every processed frame.
    """
    import torch

    kfs = slam.keyframes.keyframes
    poses = slam.keyframes.poses() if kfs else np.zeros((0, 4, 4))
    n = slam.n_frames
    return {
        "keyframe_poses": torch.from_numpy(np.ascontiguousarray(poses, dtype=np.float64)),
        "keyframe_frame_indices": [frames[kf.frame_index].index for kf in kfs],
        "keyframe_stamps_ns": [int(kf.stamp_ns) for kf in kfs],
        "frame_indices": [f.index for f in frames[:n]],
        "stamps_ns": [f.stamp_ns for f in frames[:n]],
    }


def loop_log(slam: "Slam", frames: list[FrameLog]) -> list[dict]:
    """Every loop the engine detected, in order: :meth:`~neb_slam_core.types.LoopEvent.as_dict` plus the
    input frame index and stamp of the query keyframe (``frame``, ``stamp_ns``) and of its loop
    keyframes (``loop_frames``, ``loop_stamps_ns``)."""
    kfs = slam.keyframes.keyframes

    def frame_of(keyframe_id: int) -> int:
        return frames[kfs[keyframe_id].frame_index].index

    out = []
    for event in slam.loops:
        entry = {"frame": frame_of(event.query_id), "stamp_ns": int(kfs[event.query_id].stamp_ns)}
        entry.update(event.as_dict())
        entry["loop_frames"] = [frame_of(i) for i in event.loop_ids]
        entry["loop_stamps_ns"] = [int(kfs[i].stamp_ns) for i in event.loop_ids]
        out.append(entry)
    return out


def run_metrics(slam: "Slam", frames: list[FrameLog], wall_s: float, status: str) -> dict:
    """The run's own figures (no ground truth needed).

    ``n_frames``: frames with a pose in trajectory.txt (an interruption inside the engine may leave one
    frame with a pose but no timings); ``s_per_frame``: mean engine time per finished frame (``total_ms``,
    the engine alone);
    ``wall_s_per_frame``: wall-clock time of the loop (reading included) per finished frame;
    ``track_ms_mean``: mean tracking time over the tracked frames (all but the first);
    ``map_ms_mean``: mapping time per frame, i.e. the total (the first frame's initialisation included)
    spread over all finished frames; ``n_tracking_failures``: frames whose tracking failed;
    ``n_loops_detected`` / ``n_loops_applied``: loops found, and corrections applied.
    """
    done = [f.result for f in frames if f.result is not None]
    n = len(done)
    tracked = [r.timings.track_ms for r in done if r.frame_index > 0]

    def mean(values: list[float]) -> float | None:
        return float(np.mean(values)) if values else None

    return {
        "status": status,
        "n_frames": slam.n_frames,
        "n_blocks": len(slam.block_map),
        "param_mb": slam.block_map.param_mb(),
        "n_keyframes": len(slam.keyframes),
        "n_tracking_failures": sum(not r.tracking_ok for r in done),
        "s_per_frame": None if n == 0 else sum(r.timings.total_ms for r in done) / n / 1e3,
        "wall_s_per_frame": None if n == 0 else wall_s / n,
        "track_ms_mean": mean(tracked),
        "allocate_ms_mean": mean([r.timings.allocate_ms for r in done]),
        "map_ms_mean": None if n == 0 else sum(r.timings.map_ms for r in done) / n,
        "n_mapping_steps": sum(r.mapped for r in done),
        "loop_ms_mean": None if n == 0 else sum(r.timings.loop_ms for r in done) / n,
        "n_loops_detected": len(slam.loops),
        "n_loops_applied": sum(e.applied for e in slam.loops),
    }


def block_allocations(slam: "Slam", frames: list[FrameLog], traj: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """For each block of the map, the input index of the frame that allocated it (-1: unknown) and that
    frame's current camera centre ``(M, 3)`` (NaN where unknown)."""
    n_blocks = len(slam.block_map)
    alloc_index = np.full(n_blocks, -1, dtype=np.int64)
    alloc_xyz = np.full((n_blocks, 3), np.nan)
    for pos, f in enumerate(frames[:len(traj)]):
        if f.result is not None and f.result.new_block_id is not None and f.result.new_block_id < n_blocks:
            alloc_index[f.result.new_block_id] = f.index
            alloc_xyz[f.result.new_block_id] = traj.poses[pos, :3, 3]
    return alloc_index, alloc_xyz


def write_run(run_dir: RunDirectory, slam: "Slam", run_log: RunLog, options: RunOutputOptions,
              status: str = "complete", wall_s: float = 0.0) -> RunSummary:
    """Write every file of the run directory from the engine's current state (see the module docstring).

    Steps that cannot be done (ATE with fewer than 3 ground-truth poses, a mesh from an empty map) are
    skipped with a warning and listed in ``RunSummary.skipped``.
    """
    from ..eval.report import trajectory_metrics, write_trajectory_plots
    from ..eval.plots import plot_block_allocation, save_figure

    if status not in STATUSES:
        raise ValueError(f"status must be one of {STATUSES}, got {status!r}")
    traj = slam.trajectory()
    frames = run_log.frames
    if len(traj) > len(frames) or any(int(s) != f.stamp_ns for s, f in zip(traj.stamps_ns, frames)):
        raise RuntimeError("the run log does not match the engine's processed frames")
    summary = RunSummary(run_dir.path, status, len(traj), {})

    def skip(what: str, why: str) -> None:
        log.warning("%s: %s skipped: %s", run_dir.path, what, why)
        summary.skipped.append(f"{what}: {why}")

    header = f"neb-slam run ({status}): {len(traj)} frames, T_world_cam"
    summary.written.append(run_dir.write_trajectory(traj, TRAJECTORY_FILE, header))
    gt = run_log.groundtruth(len(traj))
    if len(gt):
        summary.written.append(run_dir.write_trajectory(gt, GROUNDTRUTH_FILE, "ground truth of the processed frames"))
    summary.written.append(run_dir.write_timings(frames))
    loops = loop_log(slam, frames)
    summary.written.append(run_dir.write_loops(loops))

    metrics = run_metrics(slam, frames, wall_s, status)
    ate = None
    if len(gt):
        try:
            ate_metrics, ate = trajectory_metrics(traj, gt, est_source=run_dir.file(TRAJECTORY_FILE),
                                                  gt_source=run_dir.file(GROUNDTRUTH_FILE))
            metrics.update(ate_metrics)
        except DatasetError as exc:
            skip("ATE", str(exc))
    summary.metrics = metrics
    summary.written.append(run_dir.write_metrics(metrics))

    if ate is not None:
        marks = [(e["stamp_ns"], s, e["applied"]) for e in loops for s in e["loop_stamps_ns"]]
        summary.written += write_trajectory_plots(ate, run_dir.path, marks)
    alloc_index, alloc_xyz = block_allocations(slam, frames, traj)
    fig = plot_block_allocation(traj.positions, slam.block_map.centres().detach().cpu().double().numpy().reshape(-1, 3),
                                slam.block_map.block_cfg.edge_m, alloc_index, alloc_xyz)
    summary.written.append(save_figure(fig, run_dir.file(BLOCKS_PLOT_FILE)))

    if len(slam.block_map) == 0:
        skip("map and mesh", "the map has no blocks")
        return summary
    summary.written.append(run_dir.write_map(slam, frames))
    if not options.mesh:
        return summary
    from ..mesh import extract_mesh

    mesh = extract_mesh(slam.block_map, options.mesh_cfg, slam.observed_points(), progress=options.progress)
    if len(mesh.faces) == 0:
        skip("mesh", "the map's SDF has no surface near the observed points")
        return summary
    summary.written.append(run_dir.write_mesh(mesh))
    summary.mesh = mesh

    if options.gt_mesh is not None:
        metrics.update(_recon_metrics(run_dir, gt, ate, options, skip))
        summary.written.append(run_dir.write_metrics(metrics))
    return summary


def _recon_metrics(run_dir: RunDirectory, gt: Trajectory, ate, options: RunOutputOptions, skip) -> dict:
    """Accuracy / completion (/ Depth L1) of the run's mesh against ``options.gt_mesh``, culled to the
    ground-truth camera poses (every ``cull_stride``-th) with the run's intrinsics."""
    from ..eval.report import evaluate_mesh_files, recon_metrics
    from ..datasets.tum import read_intrinsics_json

    cull_poses = intrinsics = T_gt_rec = None
    if len(gt):
        cull_poses = gt.poses[:: options.cull_stride]
        intr_path = run_dir.file(INTRINSICS_FILE)
        intrinsics = read_intrinsics_json(intr_path) if intr_path.is_file() else None
    if not options.first_pose_from_gt:
        if ate is None:
            skip("reconstruction metrics", "the run did not start from a ground-truth pose and has no ATE "
                                           "alignment to bring the mesh into the ground truth's frame")
            return {}
        T_gt_rec = ate.T_gt_est
    if cull_poses is None or intrinsics is None:
        log.warning("%s: no ground-truth poses or intrinsics: the reconstruction is compared without culling", run_dir.path)
    try:
        recon = evaluate_mesh_files(run_dir.file(MESH_FILE), options.gt_mesh, T_gt_rec=T_gt_rec, cull_poses=cull_poses,
                                    intrinsics=intrinsics, n_points=options.recon_points,
                                    depth_views=options.depth_views)
    except DatasetError as exc:
        skip("reconstruction metrics", str(exc))
        return {}
    out = recon_metrics(recon)
    out["gt_mesh"] = str(options.gt_mesh)
    return out


def _json_safe(value):
    """Metrics -> JSON: numpy scalars to Python numbers, non-finite floats to None (JSON has no NaN)."""
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
