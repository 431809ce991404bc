"""The report of a run: its figures, plots, mesh and the mesh's evaluation, written into its run directory.

:func:`write_run` writes every file of a run directory (the layout of :mod:`neb_slam_core.io.run_dir`,
through its :class:`~neb_slam_core.io.run_dir.RunDirectory` writers) from a
:class:`~neb_slam_core.slam.Slam` and the :class:`~neb_slam_core.io.run_dir.RunLog` the loop kept. It is
called at the end of a run and also after an interruption or a crash, with whatever the engine holds
then, so every file describes the same processed frames. Cheap, important files go first (trajectory,
timings, metrics), the slow ones last (mesh, reconstruction metrics), so an interruption of the writing
itself loses as little as possible.

Shared by ``neb-slam run`` and the ROS ``slam`` node.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..config import MeshConfig
from ..errors import DatasetError
from ..io.run_dir import (
    BLOCKS_PLOT_FILE,
    GROUNDTRUTH_FILE,
    INTRINSICS_FILE,
    MESH_FILE,
    STATUSES,
    TRAJECTORY_FILE,
    FrameLog,
    RunDirectory,
    RunLog,
    loop_log,
)
from ..io.trajectory import Trajectory

if TYPE_CHECKING:  # the engine pulls torch; only needed for type hints here
    from ..slam import Slam

log = logging.getLogger(__name__)


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


def run_metrics(slam: Slam, frames: list[FrameLog], wall_s: float, status: str) -> dict:
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


def block_allocations(slam: Slam, frames: list[FrameLog], traj: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """For each block of the map, the input index of the frame that allocated it (-1: unknown) and that
    frame's current camera centre ``(M, 3)`` (NaN where unknown)."""
    n_blocks = len(slam.block_map)
    alloc_index = np.full(n_blocks, -1, dtype=np.int64)
    alloc_xyz = np.full((n_blocks, 3), np.nan)
    for pos, f in enumerate(frames[: len(traj)]):
        if f.result is not None and f.result.new_block_id is not None and f.result.new_block_id < n_blocks:
            alloc_index[f.result.new_block_id] = f.index
            alloc_xyz[f.result.new_block_id] = traj.poses[pos, :3, 3]
    return alloc_index, alloc_xyz


def write_run(
    run_dir: RunDirectory,
    slam: Slam,
    run_log: RunLog,
    options: RunOutputOptions,
    status: str = "complete",
    wall_s: float = 0.0,
    extra_metrics: dict | None = None,
) -> RunSummary:
    """Write every file of the run directory from the engine's current state (see the module docstring).

    ``extra_metrics`` are figures the caller knows and the engine does not (``neb-slam run``: the frames
    it could not read, the live figures); they go into metrics.json with the rest.

    Steps that cannot be done (ATE with fewer than 3 ground-truth poses, a mesh from an empty map) are
    skipped with a warning and listed in ``RunSummary.skipped``.
    """
    from .plots import plot_block_allocation, save_figure
    from .report import trajectory_metrics, write_trajectory_plots

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
    metrics.update(extra_metrics or {})
    ate = None
    if len(gt):
        try:
            ate_metrics, ate = trajectory_metrics(
                traj, gt, est_source=run_dir.file(TRAJECTORY_FILE), gt_source=run_dir.file(GROUNDTRUTH_FILE)
            )
            metrics.update(ate_metrics)
        except DatasetError as exc:
            skip("ATE", str(exc))
    summary.metrics = metrics
    summary.written.append(run_dir.write_metrics(metrics))

    if ate is not None:
        marks = [(e["stamp_ns"], s, e["applied"]) for e in loops for s in e["loop_stamps_ns"]]
        summary.written += write_trajectory_plots(ate, run_dir.path, marks)
    alloc_index, alloc_xyz = block_allocations(slam, frames, traj)
    fig = plot_block_allocation(
        traj.positions,
        slam.block_map.centres().detach().cpu().double().numpy().reshape(-1, 3),
        slam.block_map.block_cfg.edge_m,
        alloc_index,
        alloc_xyz,
    )
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
    from ..datasets.tum import read_intrinsics_json
    from .report import evaluate_mesh_files, recon_metrics

    cull_poses = intrinsics = T_gt_rec = None
    if len(gt):
        cull_poses = gt.poses[:: options.cull_stride]
        intr_path = run_dir.file(INTRINSICS_FILE)
        intrinsics = read_intrinsics_json(intr_path) if intr_path.is_file() else None
    if not options.first_pose_from_gt:
        if ate is None:
            skip(
                "reconstruction metrics",
                "the run did not start from a ground-truth pose and has no ATE "
                "alignment to bring the mesh into the ground truth's frame",
            )
            return {}
        T_gt_rec = ate.T_gt_est
    if cull_poses is None or intrinsics is None:
        log.warning(
            "%s: no ground-truth poses or intrinsics: the reconstruction is compared without culling", run_dir.path
        )
    try:
        recon = evaluate_mesh_files(
            run_dir.file(MESH_FILE),
            options.gt_mesh,
            T_gt_rec=T_gt_rec,
            cull_poses=cull_poses,
            intrinsics=intrinsics,
            n_points=options.recon_points,
            depth_views=options.depth_views,
        )
    except DatasetError as exc:
        skip("reconstruction metrics", str(exc))
        return {}
    out = recon_metrics(recon)
    out["gt_mesh"] = str(options.gt_mesh)
    return out
